"""Which builder builds a tree: :func:`build` dispatches to the top-down engine
(:mod:`jaxbvh.builders.topdown`: sweep, binned, median) or a bottom-up builder
(:mod:`jaxbvh.builders.lbvh`, :mod:`jaxbvh.builders.ploc`)."""

from __future__ import annotations

import jax.numpy as jnp

from jaxbvh.builders import lbvh, ploc, topdown
from jaxbvh.tree.layout import BVH, capacity_bucket

BUILDERS = ("sweep", "binned", "median", "lbvh", "ploc")


def build(prim_lo, prim_hi, *, method: str = "sweep", max_leaf: int = 1, bins: int = 16,
          ct: float = 1.0, ci: float = 1.0, pad: bool = True, dtype=None, radius: int = 16,
          morton_bits: int = 30) -> BVH:
    """Build a binary BVH over primitive boxes.

    ``"sweep"``, ``"binned"`` and ``"median"`` run the top-down engine below;
    ``"lbvh"`` (:mod:`jaxbvh.builders.lbvh`, Karras' radix tree over Morton codes) and ``"ploc"``
    (:mod:`jaxbvh.builders.ploc`, Meister & Bittner's clustering) build bottom-up, far faster on
    large inputs, at some cost in SAH.

    Args:
      prim_lo, prim_hi: [n, 3] primitive boxes (any frame; pass scene-relative
        coordinates, e.g. ``jaxbvh.io.Mesh.local_boxes()``, for float32 accuracy far
        from the origin).
      method: ``"sweep"`` (full-sweep SAH), ``"binned"``, ``"median"``, ``"lbvh"`` or
        ``"ploc"``.
      max_leaf: largest leaf; 1 (default) splits down to single primitives.
      bins: bins per axis for ``"binned"``.
      ct, ci: SAH traversal and intersection costs (leaf termination only).
      pad: pad arrays to a capacity bucket (fewer recompiles) or size them exactly.
      dtype: float32 (default) or float64 (needs x64); boxes are cast to it, so validate
        the tree against boxes cast the same way.
      radius: neighbours on each side a ``"ploc"`` cluster looks at (effort knob; static).
      morton_bits: 30 or 63, the Morton codes ``"lbvh"`` and ``"ploc"`` sort by.

    Returns:
      A :class:`~jaxbvh.tree.layout.BVH` of JAX arrays with ``2 * capacity`` node slots, root 0
      and the real nodes first: numbered level by level with ``axis`` set to each split's
      axis for the top-down builders; for ``"lbvh"`` and ``"ploc"`` interior nodes first
      (parents before children for ``"ploc"``), then leaves in Morton order, ``axis`` the
      Morton bit's axis (``"lbvh"``) or -1 (``"ploc"``).
    """
    if method not in BUILDERS:
        raise ValueError(f"unknown builder {method!r}; choose one of {', '.join(BUILDERS)}")
    if int(max_leaf) < 1:
        raise ValueError(f"max_leaf must be >= 1, got {max_leaf}")
    if method == "ploc" and int(radius) < 1:
        raise ValueError(f"radius must be >= 1, got {radius}")
    if method in ("lbvh", "ploc") and int(morton_bits) not in (30, 63):
        raise ValueError(f"morton_bits must be 30 or 63, got {morton_bits}")
    if method == "binned" and int(bins) < 2:
        raise ValueError(f"bins must be >= 2, got {bins}")
    lo_p, hi_p, n, scale = topdown.engine_inputs(prim_lo, prim_hi, pad=pad, dtype=dtype)
    if method == "binned" and capacity_bucket(int(n)) * int(bins) >= 2**31:
        raise ValueError(f"binned build of {int(n)} primitives with {bins} bins needs keys past int32; "
                         "use fewer bins")
    if method in ("lbvh", "ploc"):
        options = dict(max_leaf=int(max_leaf), ct=ct, ci=ci, scale=scale, morton_bits=int(morton_bits))
        if method == "lbvh":
            return lbvh.build(lo_p, hi_p, int(n), **options)
        return ploc.build(lo_p, hi_p, int(n), radius=int(radius), **options)
    dt = lo_p.dtype
    return topdown._build(lo_p, hi_p, n, jnp.int32(max_leaf), jnp.asarray(ct, dt), jnp.asarray(ci, dt), scale,
                  method=method, bins=int(bins) if method == "binned" else 0)
