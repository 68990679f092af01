"""Sequential NumPy twin of :mod:`jaxbvh.builders.lbvh`: the radix tree by recursive splitting.

Keys as in :mod:`jaxbvh.builders.morton` (Python integers, :mod:`jaxbvh.builders.morton_reference`),
sorted; a run of keys ``[a, b]`` with ``a < b`` splits after the last key whose
highest bit where ``key[a]`` and ``key[b]`` differ is 0. Boxes are the unions of the
children's, leaves collapse by :mod:`jaxbvh.builders.bottom_up_reference`.
"""

from __future__ import annotations

import numpy as np

from jaxbvh.builders import morton_reference as morton
from jaxbvh.builders.bottom_up_reference import Node, to_bvh
from jaxbvh.tree.layout import BVH


def radix_tree(keys: list[int], ids: list[int], lo, hi, bits: int) -> Node:
    """The radix tree of sorted distinct ``keys`` (primitive ``ids[p]`` at position p)."""
    n = len(keys)

    def make(a: int, b: int) -> Node:
        if a == b:
            return Node.leaf(ids[a], lo, hi)
        bit = (keys[a] ^ keys[b]).bit_length() - 1
        m = a
        while not (keys[m + 1] >> bit) & 1:
            m += 1
        return Node.merge(make(a, m), make(m + 1, b), morton.split_axis(keys[a], keys[b], n, bits))

    return make(0, n - 1)  # depth <= 64: the keys are 64-bit and distinct


def build(prim_lo, prim_hi, config) -> BVH:
    """Reference LBVH of ``config`` (read for ``max_leaf``, ``ct``, ``ci``, ``morton_bits``);
    boxes used in their dtype. Unpadded NumPy BVH, depth-first."""
    lo, hi = np.asarray(prim_lo), np.asarray(prim_hi)
    keys, ids = morton.sorted_keys(lo, hi, config.morton_bits)
    return to_bvh(radix_tree(keys, ids, lo, hi, config.morton_bits), lo, hi, max_leaf=config.max_leaf,
                  ct=config.ct, ci=config.ci)
