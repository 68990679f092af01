"""What every ``Config`` is made of: frozen dataclass fields with a documented default,
a check, and what the command line needs to offer them.

A method's knobs (a builder's leaf size, GRASP's trials, the genetic algorithm's
population, ...) live in one frozen dataclass per method, after madmann91/bvh's
per-builder ``Config``. Each field is made by :func:`knob`, which stores in the field's
``metadata``:

==========  ===========================================================================
key         what it is
==========  ===========================================================================
``check``   ``check(name, value) -> value``: raises ``ValueError`` naming the knob, or
            returns the value normalised (``2.0`` for an integer knob becomes ``2``)
``help``    one line for ``--help`` (the default is appended by the command line)
``metavar`` the placeholder in ``--help``
``choices`` the allowed values, when they are a short list
``type``    how the command line parses the value, when the default does not say it
            (a default of ``None``)
==========  ===========================================================================

:class:`Checked` runs every field's check in ``__post_init__`` and then the class's own
``_check_together`` for rules between knobs, so a Config that exists is valid, and the
command line, which builds its options and their defaults from these fields
(:func:`jaxbvh.cli.commands._common.add_config_options`), checks a value by the same
rule the library does. The checks below put the knob's name first in their message, so
the command line can say ``--max-leaf`` where the library says ``max_leaf``.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Callable


def knob(default, *, check: Callable | None = None, help: str = "", metavar: str | None = None,
         choices=None, type: Callable | None = None):
    """A dataclass field with its default, check and command-line metadata (module docstring)."""
    metadata = {"check": check, "help": help, "metavar": metavar, "choices": choices, "type": type}
    return dataclasses.field(default=default, metadata={k: v for k, v in metadata.items() if v is not None})


class Checked:
    """Mixin of the frozen Config dataclasses: checks (and normalises) every knob on creation."""

    def __post_init__(self):
        for f in dataclasses.fields(self):
            check = f.metadata.get("check")
            if check is not None:
                # frozen: normalised values go in through object.__setattr__, as dataclasses do
                object.__setattr__(self, f.name, check(f.name, getattr(self, f.name)))
        self._check_together()

    def _check_together(self) -> None:
        """Rules between knobs (none by default); raise ``ValueError`` naming them."""

    def replace(self, **changes):
        """A copy with ``changes``, checked again."""
        return dataclasses.replace(self, **changes)


def names(config_class) -> tuple[str, ...]:
    """The knobs of a Config class, in definition order."""
    return tuple(f.name for f in dataclasses.fields(config_class))


def defaults(config_class) -> dict[str, Any]:
    """``{knob: default}`` of a Config class."""
    return {f.name: f.default for f in dataclasses.fields(config_class)}


# ----------------------------------------------------------------------------------
# Checks: each ``(name, value) -> value``; the message starts with the knob's name
# ----------------------------------------------------------------------------------


def integer(minimum: int | None = None, maximum: int | None = None) -> Callable:
    """An integer (``2.0`` counts, ``True`` and ``2.5`` do not) in ``[minimum, maximum]``."""

    def check(name, value):
        whole = isinstance(value, numbers.Real) and not isinstance(value, bool) and float(value).is_integer()
        in_range = whole and (minimum is None or value >= minimum) and (maximum is None or value <= maximum)
        if not in_range:
            raise ValueError(f"{name} must be {_range('an integer', minimum, maximum)}, got {value!r}")
        return int(value)

    return check


def real(minimum: float | None = None, maximum: float | None = None, *, finite: bool = True,
         below: float | None = None) -> Callable:
    """A real number in ``[minimum, maximum]`` (or ``< below``), finite unless ``finite=False``."""

    def check(name, value):
        number = isinstance(value, numbers.Real) and not isinstance(value, bool)
        ok = number and not math.isnan(value) and (not finite or math.isfinite(value)) \
            and (minimum is None or value >= minimum) and (maximum is None or value <= maximum) \
            and (below is None or value < below)
        if not ok:
            what = _range("a finite number" if finite else "a number", minimum, maximum)
            if below is not None:
                what += f" below {below:g}"
            raise ValueError(f"{name} must be {what}, got {value!r}")
        return float(value)

    return check


def one_of(choices) -> Callable:
    """One of ``choices``."""

    def check(name, value):
        if value not in choices:
            raise ValueError(f"{name} must be one of {', '.join(map(str, choices))}, got {value!r}")
        return value

    return check


def optional(check: Callable) -> Callable:
    """``None`` or what ``check`` accepts."""
    return lambda name, value: None if value is None else check(name, value)


def _range(what: str, minimum, maximum) -> str:
    if minimum is not None and maximum is not None:
        return f"{what} in [{minimum:g}, {maximum:g}]"
    if minimum is not None:
        return f"{what} >= {minimum:g}"
    if maximum is not None:
        return f"{what} <= {maximum:g}"
    return what
