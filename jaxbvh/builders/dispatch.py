"""Which builder builds a tree: :func:`build` takes a Config (:mod:`jaxbvh.builders.configs`)
and hands the checked, padded boxes to the top-down engine (:mod:`jaxbvh.builders.topdown`:
sweep, binned, median), a bottom-up builder (:mod:`jaxbvh.builders.lbvh`,
:mod:`jaxbvh.builders.ploc`) or, with the triangles, the spatial-split builder
(:mod:`jaxbvh.builders.sbvh`)."""

from __future__ import annotations

import warnings

import numpy as np

from jaxbvh.builders import lbvh, ploc, sbvh, topdown
from jaxbvh.builders.configs import BOX_BUILDERS, BUILDERS, DEFAULT_BUILDER, BuilderConfig, make_config
from jaxbvh.builders.inputs import prepare
from jaxbvh.tree.layout import BVH

__all__ = ["BUILDERS", "BOX_BUILDERS", "DEFAULT_BUILDER", "build"]

# method -> its builder on prepared inputs: (lo, hi, n, scale, config) -> BVH
_ON_PREPARED = {"sweep": topdown.build, "binned": topdown.build, "median": topdown.build,
                "lbvh": lbvh.build, "ploc": ploc.build}  # "sbvh" builds from triangles (_build_sbvh)


def build(prim_lo, prim_hi, config: BuilderConfig | str | None = None, *, method: str | None = None,
          capacity: int | None = None, triangles=None, **options) -> BVH:
    """Build a binary BVH over primitive boxes.

    ``jaxbvh.build(lo, hi, BinnedConfig(bins=8))`` builds with a Config; the keyword form
    ``jaxbvh.build(lo, hi, method="binned", bins=8)`` makes that Config first
    (:func:`jaxbvh.builders.configs.make_config`: knobs of other builders are ignored).
    ``"sweep"``, ``"binned"`` and ``"median"`` run the top-down engine; ``"lbvh"``
    (Karras' radix tree over Morton codes) and ``"ploc"`` (Meister & Bittner's
    clustering) build bottom-up, far faster on large inputs, at some cost in SAH.

    Args:
      prim_lo, prim_hi: [n, 3] primitive boxes (any frame; pass scene-relative
        coordinates, e.g. ``jaxbvh.io.Mesh.local_boxes()``, for float32 accuracy far
        from the origin).
      config: a Config of :data:`BUILDERS` (its knobs and defaults are documented
        there), a method name, or None: ``method`` and ``options``.
      method: a name in :data:`BUILDERS` (default :data:`DEFAULT_BUILDER`), with
      options: the Config's knobs (``max_leaf``, ``bins``, ``ct``, ``ci``, ``pad``,
        ``dtype``, ``radius``, ``morton_bits``, ``alpha``, ``reference_capacity``). ``dtype`` float64 needs x64; the boxes
        are cast to it, so validate the tree against boxes cast the same way.
      capacity: primitive slots to pad to (at least ``n``), in place of ``pad``'s
        capacity bucket: inputs of many sizes then share one compiled program (a
        test's random scenes, a batch of small meshes). ``ValueError`` below ``n``.
        For ``"sbvh"``: reference slots, in place of ``reference_capacity``.
      triangles: [n, 3, 3] the triangles of the boxes, in the same frame; needed by
        ``"sbvh"`` (spatial splits clip triangles), which then builds from them
        (``prim_lo``, ``prim_hi`` must be their boxes: only their shape is checked),
        and ignored by the other methods. A triangle may then sit in several leaves
        (check the tree with ``jaxbvh.validate(tree, references=True, ...)``); when
        the reference slots run out, nodes take object splits and a ``UserWarning``
        says so (:func:`jaxbvh.builders.sbvh.build_sbvh` returns that as a flag).

    Returns:
      A :class:`~jaxbvh.tree.layout.BVH` of JAX arrays with ``2 * capacity`` node slots, root 0
      and the real nodes first: numbered level by level with ``axis`` set to each split's
      axis for the top-down builders; for ``"lbvh"`` and ``"ploc"`` interior nodes first
      (parents before children for ``"ploc"``), then leaves in Morton order, ``axis`` the
      Morton bit's axis (``"lbvh"``) or -1 (``"ploc"``).
    """
    if isinstance(config, str):
        if method is not None:
            raise TypeError(f"method given twice: {config!r} and method={method!r}")
        config, method = None, config
    if config is None:
        config = make_config(DEFAULT_BUILDER if method is None else method, **options)
    elif method is not None or options:
        raise TypeError("give a builder Config or method and keyword options, not both "
                        "(config.replace(...) changes a Config)")
    elif not isinstance(config, BuilderConfig) or config.method not in BUILDERS:
        raise TypeError(f"config must be one of {', '.join(c.__name__ for c in BUILDERS.values())}, "
                        f"got {type(config).__name__}")
    if config.method == "sbvh":
        return _build_sbvh(prim_lo, prim_hi, triangles, config, capacity)
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=config.pad, capacity=capacity, dtype=config.dtype)
    return _ON_PREPARED[config.method](lo, hi, n, scale, config)


def _build_sbvh(prim_lo, prim_hi, triangles, config, capacity) -> BVH:
    if triangles is None:
        raise ValueError("method 'sbvh' needs the triangles: build(lo, hi, method='sbvh', triangles=tri)")
    tri = sbvh.check_triangles(triangles)
    if np.shape(prim_lo) != (tri.shape[0], 3) or np.shape(prim_hi) != (tri.shape[0], 3):
        raise ValueError(f"sbvh: lo and hi must be the boxes of the {tri.shape[0]} triangles, shape "
                         f"[{tri.shape[0]}, 3]; got {np.shape(prim_lo)} and {np.shape(prim_hi)}")
    result = sbvh.build_sbvh(tri, config, capacity=capacity)
    if bool(result.out_of_capacity):
        warnings.warn(f"sbvh: the {result.tree.prim_index.shape[0]} reference slots ran out; some nodes took "
                      "object splits (raise reference_capacity)", stacklevel=3)
    return result.tree
