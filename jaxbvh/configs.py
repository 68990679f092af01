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
(:class:`jaxbvh.cli.options.ConfigOptions`), checks a value by the same rule the
library does. The checks below put the knob's name first in their message, so the
command line can say ``--max-leaf`` where the library says ``max_leaf``.

A knob that several methods share (the SAH constants, the optimizers' margin and
split-axis pass) is made by one function below (:func:`ct_knob`, ...), so its
default, check and help are written once. A knob whose default is itself a Config (the
pipeline's stage configs) is checked by :func:`config_of`, and the command line offers
that Config's knobs too.
"""

from __future__ import annotations

import dataclasses
import math
import numbers
from typing import Any, Callable


def knob(default, *, check: Callable | None = None, help: str = "", metavar: str | None = None,
         choices=None, type: Callable | None = None):
    """A dataclass field with its default, check and command-line metadata (module docstring).

    ``default`` must be immutable (a number, string, tuple, None or a frozen Config):
    every instance shares it.
    """
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


#: the largest integer a knob takes unless its check says less: counts and sizes end up
#: in int32 arrays (ids, leaf sizes, loop counters), so a larger one could only overflow
INT_MAX = 2 ** 31 - 1


def integer(minimum: int | None = None, maximum: int | None = INT_MAX) -> Callable:
    """An integer (``2.0`` counts, ``True`` and ``2.5`` do not) in ``[minimum, maximum]``
    (``maximum``: :data:`INT_MAX` unless given; None: no bound)."""

    def check(name, value):
        whole = isinstance(value, numbers.Real) and not isinstance(value, bool) and _is_whole(value)
        in_range = whole and (minimum is None or value >= minimum) and (maximum is None or value <= maximum)
        if not in_range:
            # the int32 bound is named only to a value that passed it: "an integer >= 1"
            # is what a user who typed 0 needs to read
            shown_max = maximum if maximum != INT_MAX or (whole and value > INT_MAX) else None
            what = _interval("an integer", minimum, shown_max, None, None)
            raise ValueError(f"{name} must be {what}, got {value!r}")
        return int(value)

    return check


def _is_whole(value) -> bool:
    """``value`` (a real number) is a whole number; a Python int of any size is."""
    if isinstance(value, numbers.Integral):
        return True
    try:
        return float(value).is_integer()
    except OverflowError:
        return False


def real(minimum: float | None = None, maximum: float | None = None, *, finite: bool = True,
         below: float | None = None, above: float | None = None) -> Callable:
    """A real number in ``[minimum, maximum]``, ``< below``, ``> above``; finite unless
    ``finite=False`` (never NaN)."""

    def check(name, value):
        number = isinstance(value, numbers.Real) and not isinstance(value, bool)
        ok = number and not math.isnan(value) and (not finite or math.isfinite(value)) \
            and (minimum is None or value >= minimum) and (maximum is None or value <= maximum) \
            and (below is None or value < below) and (above is None or value > above)
        if not ok:
            what = _interval("a finite number" if finite else "a number", minimum, maximum, above, below)
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


def sizes(name, value):
    """A non-empty sequence of integers >= 1 (work sizes), as a tuple (hashable: Configs
    of the optimizers are part of a compiled program's identity)."""
    one = integer(1)
    try:
        items = tuple(one(name, v) for v in value)
    except (TypeError, ValueError):
        items = ()
    if not items:
        raise ValueError(f"{name} must be positive sizes, got {value!r}")
    return items


def config_of(config_class) -> Callable:
    """A nested Config: an instance of ``config_class``, or a dict of its knobs (checked
    by that Config, whose message names the inner knob)."""

    def check(name, value):
        if isinstance(value, dict):
            value = config_class(**value)
        if not isinstance(value, config_class):
            raise ValueError(f"{name} must be a {config_class.__module__}.{config_class.__qualname__} "
                             f"or a dict of its fields, got {type(value).__name__}")
        return value

    return check


def config_or_options(config, options: dict, config_class):
    """A search's settings given either way: ``config`` (a ``config_class``) or keyword
    ``options`` that make one (None and no options: the defaults); ``TypeError`` for both
    at once or for a ``config`` of another type."""
    if config is None:
        return config_class(**options)
    if options:
        raise TypeError(f"give a {config_class.__qualname__} or keyword options, not both "
                        "(config.replace(...) changes one)")
    if not isinstance(config, config_class):
        raise TypeError(f"config must be a {config_class.__module__}.{config_class.__qualname__}, "
                        f"got {type(config).__name__}")
    return config


def _interval(what: str, minimum, maximum, above, below) -> str:
    """``what`` with its bounds: ``in (0, 1]``, ``>= 2``, ``< 1``, ..."""
    shown = lambda x: str(x) if isinstance(x, int) else f"{x:g}"  # noqa: E731 (no 2.14748e+09)
    low = f"[{shown(minimum)}" if minimum is not None else f"({shown(above)}" if above is not None else None
    high = f"{shown(maximum)}]" if maximum is not None else f"{shown(below)})" if below is not None else None
    if low and high:
        return f"{what} in {low}, {high}"
    if low:
        return f"{what} {'>=' if minimum is not None else '>'} {low[1:]}"
    if high:
        return f"{what} {'<=' if maximum is not None else '<'} {high[:-1]}"
    return what


# ----------------------------------------------------------------------------------
# Knobs several methods share: one default, one check, one help each
# ----------------------------------------------------------------------------------


def ct_knob():
    """``ct``: the SAH's cost of a traversal step (1, as every paper here uses it)."""
    return knob(1.0, check=real(0), metavar="CT", help="SAH traversal cost, >= 0")


#: the largest leaf, by default, of every builder (SAH leaf test) and of the pipeline's final
#: leaf merge (jaxbvh.optimize.leaves): the one place this default is set. A cap only: the
#: SAH leaf test decides each leaf. Measured in bench/results/leaves.md (issue 40), sweep
#: build then the pipeline, limits 4 / 8 / 16: the same SAH on spot, cow, teapot, fandisk,
#: rocker-arm and the bunny; 16 lowest on the drone (12.796 / 12.704 / 12.682: 4 left it
#: above tinybvh's Optimize(200), 12.763), legocar (26.677 / 26.650 / 26.650) and the
#: interior (63.588 / 63.583 / 63.583). Leaves of one primitive (1) were 1.5-18% worse.
DEFAULT_MAX_LEAF = 16


def max_leaf_knob():
    """``max_leaf``: the most primitives in a leaf; leaves of several primitives are made
    only where the SAH says they cost less (:data:`DEFAULT_MAX_LEAF`)."""
    return knob(DEFAULT_MAX_LEAF, check=integer(1), metavar="N", help="most primitives per leaf")


def ci_knob():
    """``ci``: the SAH's cost of a primitive test (1)."""
    return knob(1.0, check=real(0), metavar="CI", help="SAH intersection cost, >= 0")


def min_gain_knob():
    """``min_gain``: the relative margin an optimizer's move must beat; None: ``64 * eps``
    of the tree's float type (:func:`jaxbvh.numerics.min_gain`)."""
    return knob(None, check=optional(real(0, finite=False)), type=float, metavar="G",
                help="relative margin a move must beat (none: 64 eps of the tree's float type)")


def split_axes_knob():
    """``split_axes``: Kensler's final pass (:func:`jaxbvh.tree.split_axes.assign_split_axes`)
    on an optimizer's result."""
    return knob(True, help="Kensler's split-axis pass on the result")


@dataclasses.dataclass(frozen=True)
class SAHCosts(Checked):
    """The SAH constants alone: the Config of pricing a tree one did not build (``jaxbvh
    trace``, the stats of a tree file). ``ct``, ``ci``: as every builder's."""

    ct: float = ct_knob()
    ci: float = ci_knob()
