"""Sequential NumPy twin of :mod:`jaxbvh.stochastic.grasp`: recursive randomized full-sweep builds.

One node at a time, as Ng & Trifonov describe it: sort the node's primitives along each
axis, sweep forward and backward for every split's cost, find the greedy split, and with
probability ``noise`` deviate to an alternative from the restricted candidate list. The
split rules, tie rule and cost expressions are those of :mod:`jaxbvh.builders.topdown` (and of
:mod:`jaxbvh.builders.topdown_reference`), computed in the boxes' own dtype; a node's two uniforms
come from :func:`jaxbvh.draws.split_uniforms` keyed by its trial and its run ``[start,
start + count)`` (left child ``[start, start + N_L)``, right child the rest), exactly as
the engine keys them, so both give the same tree for the same key and trial. Nodes come out in depth-first
order, root 0, unpadded.
"""

from __future__ import annotations

from functools import lru_cache

import jax
import numpy as np

from jaxbvh.builders.topdown_reference import sweep_candidates, tie_winner
from jaxbvh.draws import split_uniforms
from jaxbvh.numerics import scene_scale
from jaxbvh.tree import cost_reference as cost
from jaxbvh.tree.layout import BVH


@lru_cache(maxsize=1)
def _uniforms_fn():
    return jax.jit(split_uniforms)


def node_uniforms(key, trial: int, start: int, count: int) -> np.ndarray:
    """The node's two float32 uniforms (the engine's, :func:`jaxbvh.draws.split_uniforms`)."""
    return np.asarray(_uniforms_fn()(key, np.int32(trial), np.int32(start), np.int32(count)))


def choose_split(candidates, u0, u1, noise, rcl):
    """The split a node takes: the greedy one, or with ``u0 < noise`` an alternative.

    ``rcl="axes"``: the greedy split among the candidates of axis ``(a + 1) % 3`` when
    ``u1 < 1/2``, else of ``(a + 2) % 3`` (``a`` the greedy axis). ``rcl=k``: rank
    ``1 + min(floor(u1 (m - 1)), m - 2)`` of the ``m = min(k, len(candidates))`` best,
    ranks given by taking the greedy split of what is left, one after another.
    """
    greedy = tie_winner(candidates)
    if not np.float32(u0) < np.float32(noise):
        return greedy
    if rcl == "axes":
        axis = (greedy[2] + (1 if u1 < np.float32(0.5) else 2)) % 3
        return tie_winner([c for c in candidates if c[2] == axis])
    size = min(int(rcl), len(candidates))
    if size < 2:
        return greedy
    rank = 1 + min(int(np.floor(np.float32(u1) * np.float32(size - 1))), size - 2)
    left = [c for c in candidates if c[1] != greedy[1]]
    for _ in range(rank):
        pick = tie_winner(left)
        left = [c for c in left if c[1] != pick[1]]
    return pick


def randomized_build(key, prim_lo, prim_hi, *, trial: int = 0, noise: float, rcl="axes") -> BVH:
    """Reference GRASP trial ``trial`` of the run keyed ``key`` (as :func:`jaxbvh.stochastic.grasp.randomized_build`).

    Boxes are used in their own dtype; returns an unpadded NumPy :class:`~jaxbvh.tree.layout.BVH`
    in depth-first order, one primitive per leaf.
    """
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    dtype = lo.dtype
    n = lo.shape[0]
    scale = dtype.type(scene_scale(lo, hi))
    centre = dtype.type(0.5) * lo + dtype.type(0.5) * hi

    left, right, parent, axis_of = [], [], [], []
    node_lo, node_hi, prim_start, prim_count = [], [], [], []
    prim_index: list[int] = []

    def new_node(par):
        for arr, v in ((left, -1), (right, -1), (parent, par), (axis_of, -1), (prim_start, 0), (prim_count, 0)):
            arr.append(v)
        node_lo.append(None)
        node_hi.append(None)
        return len(left) - 1

    stack = [(new_node(-1), np.arange(n), 0)]  # (node, primitive ids, first position of its run)
    while stack:
        node, ids, start = stack.pop()
        node_lo[node], node_hi[node] = lo[ids].min(0), hi[ids].max(0)
        count = len(ids)
        if count == 1:
            prim_start[node], prim_count[node] = len(prim_index), 1
            prim_index.append(int(ids[0]))
            continue
        u0, u1 = node_uniforms(key, trial, start, count)
        candidates = sweep_candidates(ids, lo, hi, centre, scale)
        _, _, axis, left_ids, right_ids = choose_split(candidates, u0, u1, noise, rcl)
        axis_of[node] = axis
        l_id, r_id = new_node(node), new_node(node)
        left[node], right[node] = l_id, r_id
        stack.append((r_id, right_ids, start + len(left_ids)))
        stack.append((l_id, left_ids, start))

    i32 = lambda a: np.asarray(a, np.int32)  # noqa: E731
    return BVH(left=i32(left), right=i32(right), parent=i32(parent),
               lo=np.stack(node_lo).astype(dtype), hi=np.stack(node_hi).astype(dtype),
               prim_start=i32(prim_start), prim_count=i32(prim_count), axis=i32(axis_of),
               prim_index=i32(prim_index), root=np.int32(0))


def grasp(key, prim_lo, prim_hi, *, trials: int, noise: float, rcl="axes", objective: str = "nt"):
    """Best of ``trials`` reference trials: ``(tree, objectives [trials] float64, best trial)``.

    Every trial built whole; objectives in float64 (:mod:`jaxbvh.tree.cost_reference`); the
    first of equal objectives wins.
    """

    measure = cost.ng_trifonov_cost if objective == "nt" else cost.sah
    trees = [randomized_build(key, prim_lo, prim_hi, trial=t, noise=noise, rcl=rcl) for t in range(trials)]
    values = np.array([measure(t) for t in trees], np.float64)
    best = int(np.argmin(values))
    return trees[best], values, best
