"""One frozen Config per builder: its knobs, their defaults, their checks.

:func:`jaxbvh.build` takes one of these (``jaxbvh.build(lo, hi, BinnedConfig(bins=8))``);
:data:`BUILDERS` maps every method to its class: :data:`BOX_BUILDERS` those that build
from boxes alone, :data:`TRIANGLE_BUILDERS` those that need the triangles (``"sbvh"``).
The defaults here are the only
ones: :func:`jaxbvh.build`'s keyword form, the command line's options and their
``--help`` all read them from these classes (:mod:`jaxbvh.configs` says how).

=================  ===============  =====================================================
class              method           knobs beyond ``max_leaf, ct, ci, pad, dtype``
=================  ===============  =====================================================
:class:`SweepConfig`   ``"sweep"``      none
:class:`BinnedConfig`  ``"binned"``     ``bins``
:class:`MedianConfig`  ``"median"``     none (``ct``, ``ci`` unused: it never prices a split)
:class:`LBVHConfig`    ``"lbvh"``       ``morton_bits``
:class:`PLOCConfig`    ``"ploc"``       ``morton_bits``, ``radius``
:class:`SBVHConfig`    ``"sbvh"``       ``bins``, ``spatial_bins``, ``alpha``,
                                        ``reference_capacity`` (needs the triangles, not
                                        only their boxes)
=================  ===============  =====================================================
"""

from __future__ import annotations

import dataclasses
from collections import OrderedDict
from typing import Any, ClassVar

from jaxbvh.builders.morton import CODE_BITS, check_code_bits
from jaxbvh.configs import Checked, ci_knob, ct_knob, integer, knob, max_leaf_knob, real


def _code_bits(name, value):
    return check_code_bits(value)  # the Morton module's rule, whose message names morton_bits


@dataclasses.dataclass(frozen=True)
class BuilderConfig(Checked):
    """Knobs every builder has (a base class; build with one of its subclasses).

    ``max_leaf``: the largest leaf (default :data:`jaxbvh.configs.DEFAULT_MAX_LEAF`); 1
    splits down to single primitives, larger leaves are made where the SAH says a leaf
    costs no more than its best split (the median
    builder makes every node of at most ``max_leaf`` primitives a leaf).
    ``ct``, ``ci``: the SAH's traversal and intersection costs, used only by that leaf
    test. ``pad``: pad the arrays to a capacity bucket (fewer compiles) or size them
    exactly. ``dtype``: float32 (None, the default) or float64 (needs x64); the boxes
    are cast to it.
    """

    method: ClassVar[str] = ""  # the name in BUILDERS and on the command line

    max_leaf: int = max_leaf_knob()
    ct: float = ct_knob()
    ci: float = ci_knob()
    pad: bool = knob(True, help="pad arrays to a capacity bucket (fewer recompiles)")
    dtype: Any = knob(None, help="float32 (None) or float64 (needs x64)")


@dataclasses.dataclass(frozen=True)
class SweepConfig(BuilderConfig):
    """Full-sweep SAH (Müller & Fellner 1999, as Ng & Trifonov 2003 describe it): every
    split position of every axis is priced; :mod:`jaxbvh.builders.topdown`."""

    method: ClassVar[str] = "sweep"


@dataclasses.dataclass(frozen=True)
class BinnedConfig(BuilderConfig):
    """Binned SAH (Wald 2007): centres bucketed into ``bins`` equal bins per axis, only the
    planes between bins priced; :mod:`jaxbvh.builders.topdown`."""

    method: ClassVar[str] = "binned"

    bins: int = knob(16, check=integer(2), metavar="B", help="bins per axis")


@dataclasses.dataclass(frozen=True)
class MedianConfig(BuilderConfig):
    """Object median (Kay & Kajiya 1986): the longest axis, half the primitives each side;
    :mod:`jaxbvh.builders.topdown`."""

    method: ClassVar[str] = "median"


@dataclasses.dataclass(frozen=True)
class _MortonConfig(BuilderConfig):
    """Knobs of the builders that start from Morton order (:mod:`jaxbvh.builders.morton`)."""

    morton_bits: int = knob(30, check=_code_bits, choices=CODE_BITS, help="Morton code length")


@dataclasses.dataclass(frozen=True)
class LBVHConfig(_MortonConfig):
    """LBVH (Lauterbach et al. 2009) as Karras' radix tree (2012), bottom-up from Morton
    order; :mod:`jaxbvh.builders.lbvh`."""

    method: ClassVar[str] = "lbvh"


@dataclasses.dataclass(frozen=True)
class PLOCConfig(_MortonConfig):
    """PLOC, parallel locally-ordered clustering (Meister & Bittner 2017): ``radius``
    neighbours on each side in Morton order (the paper uses 8 to 25; static, one compile
    per value); :mod:`jaxbvh.builders.ploc`."""

    method: ClassVar[str] = "ploc"

    radius: int = knob(16, check=integer(1), metavar="R",
                       help="neighbours on each side a cluster looks at")


@dataclasses.dataclass(frozen=True)
class SBVHConfig(BuilderConfig):
    """Spatial-split BVH (Stich, Friedrich & Dietrich 2009): binned object splits, and
    where the children of a node's best object split overlap by more than ``alpha``
    times the root's area, binned spatial splits that clip straddling triangles to the
    plane; a triangle may then sit in several leaves. Needs the triangles
    (``jaxbvh.build(..., triangles=tri)``); :mod:`jaxbvh.builders.sbvh`.

    ``bins``: bins per axis of the object split. ``spatial_bins``: spatial bins per axis
    at most (fewer for nodes of few references). ``alpha``: the paper's overlap
    threshold (1e-5; 0 tries spatial splits at every node, a large value never).
    ``reference_capacity``: slots for references as a multiple of the triangle count
    (at least 1); when they run out, nodes take object splits and the build says so.
    """

    method: ClassVar[str] = "sbvh"

    bins: int = knob(16, check=integer(2), metavar="B", help="bins per axis")
    spatial_bins: int = knob(4, check=integer(2), metavar="S",
                             help="spatial bins per axis at most (fewer for nodes of few references)")
    alpha: float = knob(1e-5, check=real(0.0), metavar="A",
                        help="overlap (fraction of the root's area) above which spatial splits are tried")
    reference_capacity: float = knob(2.0, check=real(1.0, 64.0), metavar="F",
                                     help="reference slots as a multiple of the triangle count")


# method name -> Config class. OrderedDicts: ``method in BUILDERS`` and iterating give
# the names in this order, and hypothesis' sampled_from takes them (it refuses plain dicts)
# the builders that need only the primitives' boxes: what code building from boxes alone
# (two-level objects, tests drawing box sets) can take
BOX_BUILDERS: OrderedDict[str, type[BuilderConfig]] = OrderedDict(
    (c.method, c) for c in (SweepConfig, BinnedConfig, MedianConfig, LBVHConfig, PLOCConfig))
# the builders that need the triangles, not only their boxes (jaxbvh.build(..., triangles=tri))
TRIANGLE_BUILDERS: OrderedDict[str, type[BuilderConfig]] = OrderedDict((c.method, c) for c in (SBVHConfig,))
# every builder: what jaxbvh.build, make_config and the command line's --builder take
BUILDERS: OrderedDict[str, type[BuilderConfig]] = OrderedDict(list(BOX_BUILDERS.items())
                                                               + list(TRIANGLE_BUILDERS.items()))
DEFAULT_BUILDER = "sweep"  # the method of jaxbvh.build(lo, hi) and of the command line
# BUILDERS' name while BUILDERS listed the box builders only (jaxbvh.batch.build still
# imports it): the same mapping
ALL_BUILDERS = BUILDERS

# every builder knob: the keyword form of jaxbvh.build takes any of them for any method
KNOBS = tuple(OrderedDict.fromkeys(f.name for c in BUILDERS.values() for f in dataclasses.fields(c)))


def make_config(method: str = DEFAULT_BUILDER, **options) -> BuilderConfig:
    """The Config of ``method`` from keyword options (the form ``jaxbvh.build`` always took).

    Knobs of other builders are ignored, so one set of options serves every method (as
    the command line and the two-level builder pass them); a name no builder knows is a
    ``TypeError``, a bad value a ``ValueError`` naming the knob.
    """
    if method not in BUILDERS:
        raise ValueError(f"unknown builder {method!r}; choose one of {', '.join(BUILDERS)}")
    unknown = sorted(set(options) - set(KNOBS))
    if unknown:
        raise TypeError(f"unknown builder option(s) {', '.join(unknown)}; builders take {', '.join(KNOBS)}")
    cls = BUILDERS[method]
    own = {f.name for f in dataclasses.fields(cls)}
    return cls(**{k: v for k, v in options.items() if k in own})
