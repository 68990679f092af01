"""Top-down builders, one level at a time over all open nodes (jitted).

Three split rules share one level-synchronous engine:

* ``"sweep"`` — full-sweep SAH (Müller & Fellner, as Ng & Trifonov describe it): every
  split position along every axis, primitives ordered by box centre, the boxes of both
  sides grown by a forward and a backward sweep; the cheapest split is taken.
* ``"binned"`` — binned SAH (Wald 2007): centres bucketed into ``bins`` equal bins of the
  node's centre bounds per axis; only the planes between bins are candidates.
* ``"median"`` — Kay & Kajiya object median: the longest axis of the node's box, the
  lower half of the primitives (by centre) to the left.

The engine keeps the primitives in *positions*: every open node owns a contiguous run of
positions, and for each axis a permutation lists the primitives of each run sorted by
centre. One step of the ``while_loop`` takes every open node of the current level,
scores its splits with segmented scans over the runs, and stably partitions the runs
into the children's, so the work per level is a few passes over all primitives however
many nodes are open. The same code can be vmapped over random trials. Binning needs no
bins in memory here: the runs are already sorted by centre, so bins never decrease along
a run and Wald's candidate planes are the positions where the bin changes; the binned
builder is the sweep restricted to those positions (same partitions as counting into
bins, at the sweep's cost).

Tie rule (the NumPy reference in :mod:`jaxbvh.builders.topdown_reference` keeps the same one).
Centres are ``0.5 * lo + 0.5 * hi``; primitives with equal centres are ordered by id.
Costs count as equal when they differ by at most a relative ``TIE_TOLERANCE``
(2^-20): XLA on CPU fuses multiply-adds, so one cost can come out one ulp apart in two
places (or here and in NumPy), and only a tolerance makes the choice reproducible.

* sweep: least cost ``A_L N_L + A_R N_R``; among equal costs the split closest to the
  middle (``|2 N_L - N|`` least, the smaller ``N_L`` first), then the lowest axis.
* binned: least cost; among equal costs the lowest axis, then the lowest plane. Bin of a
  centre ``c``: ``floor((c - cmin) * B / (cmax - cmin))`` clipped to ``B - 1``; an axis
  with ``cmax == cmin`` has no planes. A node with no plane on any axis (all centres in
  one point) is split into its lower and upper half by primitive id.
* median: the first longest axis; primitives sorted by (centre, id); left gets
  ``N // 2``.

Leaves. A node of one primitive is a leaf. With ``max_leaf > 1`` a node of at most
``max_leaf`` primitives becomes a leaf when ``Ci N <= Ct + Ci (A_L N_L + A_R N_R) / A``
within the tie tolerance (SAH termination: a tie is a leaf, e.g. a point inside its
sibling's box, which costs exactly what the leaf costs; for a zero-area node the right side is ``Ct + Ci N``, so it stays a
leaf); the median builder makes such nodes leaves unconditionally.

Areas are half-areas of extents times a power of two fixed by the scene box, so no
float32 overflow at 1e30 or underflow at 1e-30 (:mod:`jaxbvh.tree.cost`).

Randomized split choice (the hook :mod:`jaxbvh.stochastic.grasp` uses, :func:`randomized_forest`).
With ``rcl`` set, the sweep rule becomes Ng & Trifonov's randomized one: a node first
finds the greedy split above (so ``noise = 0`` is exactly the sweep builder); then, when
its first uniform ``u0 < noise``, it *deviates* to an alternative picked by its second
uniform ``u1``:

* ``rcl="axes"``: the best split of one of the two other axes (per-axis best: least
  cost, ties by the tie rule above restricted to the axis), ``u1 < 1/2`` the next axis
  ``(a + 1) % 3``, else ``(a + 2) % 3``, where ``a`` is the greedy split's axis;
* ``rcl="list"`` with ``k``: the split of rank ``r = 1 + floor(u1 (m - 1))`` (clipped to
  ``m - 1``) of the node's ``m = min(k, 3 (N - 1))`` best, where rank 0 is the greedy
  split and rank ``j`` the greedy split among the candidates left after ranks ``< j``
  (so a tie within ``TIE_TOLERANCE`` ranks by the tie rule); ``k = 1`` never deviates.

A node's two uniforms come from :func:`jaxbvh.draws.split_uniforms` for its trial and its run of
positions ``[start, start + count)`` (root ``[0, n)``, left child ``[start, start +
N_L)``, right ``[start + N_L, start + N)``): a name that does not depend on the order
nodes are visited in, so a recursive builder keeping the same arithmetic draws the same
numbers. The randomized engine builds a *forest*: primitives come in groups ``0 .. G -
1``, each grown into its own tree (roots are nodes ``0 .. G - 1``), with its own trial
number and a ``shift`` added to every run start it names, so that a group can be a
subtree of a trial's tree, named as in the whole tree.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.draws import split_uniforms
from jaxbvh.numerics import TIE_TOLERANCE, half_area, scene_scale, working_dtype
from jaxbvh.tree.layout import BVH, capacity_bucket
from jaxbvh.tree.validate import few_ids


def check_prim_boxes(prim_lo, prim_hi, what: str = "primitive boxes"):
    """Host-side check of ``prim_lo``, ``prim_hi`` [n, 3]; returns them as NumPy arrays.

    Raises ``ValueError`` naming the problem: wrong shape, no primitives, NaN/inf
    (with how many and which), or ``lo > hi``.
    """
    lo = np.asarray(prim_lo)
    hi = np.asarray(prim_hi)
    if lo.ndim != 2 or lo.shape[-1] != 3 or lo.shape != hi.shape:
        raise ValueError(f"{what}: lo and hi must both have shape [n, 3], got {lo.shape} and {hi.shape}")
    if lo.shape[0] == 0:
        raise ValueError(f"{what}: no primitives (n = 0); a BVH needs at least one")
    if not (np.issubdtype(lo.dtype, np.floating) and np.issubdtype(hi.dtype, np.floating)):
        lo, hi = lo.astype(np.float64), hi.astype(np.float64)
    bad = ~(np.isfinite(lo).all(1) & np.isfinite(hi).all(1))
    if bad.any():
        ids = np.flatnonzero(bad)
        raise ValueError(f"{what}: {ids.size} of {lo.shape[0]} have NaN or infinite coordinates "
                         f"(first: {few_ids(ids)})")
    inverted = (lo > hi).any(1)
    if inverted.any():
        ids = np.flatnonzero(inverted)
        raise ValueError(f"{what}: {ids.size} have lo > hi (first: {few_ids(ids)})")
    return lo, hi




class RandomSplits(NamedTuple):
    """Inputs of the randomized split choice (module docstring); a pytree, traced under jit.

    ``key``: the run's ``jax.random`` key. ``group`` [capacity] int32: the tree each
    primitive slot grows into, ``0 .. G - 1``, every one used (padding slots: any).
    ``trial``, ``shift`` [capacity] int32, indexed by group: the trial number of the tree,
    and what to add to its run starts to name its nodes. ``noise``: float32 probability
    of deviating. ``k``: int32 list length (``rcl="list"``).
    """

    key: Any
    group: Any
    trial: Any
    shift: Any
    noise: Any
    k: Any


def randomized_forest(lo, hi, n, scale, splits: RandomSplits, *, rcl: str):
    """Randomized full-sweep forest (module docstring), one primitive per leaf.

    ``lo``, ``hi``, ``n``, ``scale``: as from :func:`engine_inputs`; ``scale`` must be
    the whole scene's (areas of every tree on one scale). ``rcl``: ``"axes"`` or
    ``"list"``. Returns ``(forest, tree_of)``: a :class:`BVH` whose nodes ``0 .. G - 1``
    are the roots (``root`` is 0, ``prim_index`` holds slots of ``lo``), and ``tree_of``
    [2 capacity] int32, each node's group (-1 for unused slots). Traceable (jit, vmap).
    """
    if rcl not in SPLIT_CHOICES:
        raise ValueError(f"rcl must be one of {', '.join(SPLIT_CHOICES)}, got {rcl!r}")
    one = jnp.ones((), lo.dtype)
    return _build(lo, hi, n, jnp.int32(1), one, one, scale, splits, method="sweep", bins=0, rcl=rcl)


def engine_inputs(prim_lo, prim_hi, *, pad: bool = True, dtype=None):
    """Checked, cast and padded engine inputs ``(lo, hi, n, scale)`` for ``_build``.

    ``lo``, ``hi``: [capacity, 3] JAX arrays (padding: the empty box); ``n``: int32
    primitive count; ``scale``: the scene's power-of-two area scale. Arguments and errors
    as :func:`build`.
    """
    lo, hi = check_prim_boxes(prim_lo, prim_hi)
    dt = working_dtype(dtype, lo.dtype)
    lo, hi = lo.astype(dt), hi.astype(dt)
    n = lo.shape[0]
    cap = capacity_bucket(n) if pad else n
    lo_p = np.full((cap, 3), np.inf, dt)
    hi_p = np.full((cap, 3), -np.inf, dt)
    lo_p[:n], hi_p[:n] = lo, hi
    return jnp.asarray(lo_p), jnp.asarray(hi_p), jnp.int32(n), jnp.asarray(scene_scale(lo, hi), dt)


# ----------------------------------------------------------------------------------
# the engine
# ----------------------------------------------------------------------------------

_NO_CODE = np.iinfo(np.int32).max  # tie-rule code of "no candidate"
SPLIT_CHOICES = ("axes", "list")  # randomized split rules (module docstring)



def _sweep_split_of(code, count):
    """(axis, N_L) of the sweep split with tie-rule code ``code`` in a node of ``count``."""
    gap, upper = (code // 3) // 2, (code // 3) % 2
    return code % 3, jnp.where(upper == 1, count + gap, count - gap) // 2


def _least_code(cost, code, seg, num_segments):
    """Tie-rule winner per segment: least cost, then least ``code`` within TIE_TOLERANCE.

    ``cost``, ``code``, ``seg``: equal shapes (``inf`` cost = not a candidate). Returns
    the winner's code [num_segments], ``_NO_CODE`` for a segment without candidates.
    """
    best = jax.ops.segment_min(cost.ravel(), seg.ravel(), num_segments=num_segments)
    near = (best * (1 + TIE_TOLERANCE)).at[seg].get(mode="fill", fill_value=jnp.inf)
    ok = (cost <= near) & (cost < jnp.inf)
    return jax.ops.segment_min(jnp.where(ok, code, _NO_CODE).ravel(), seg.ravel(),
                               num_segments=num_segments)


def _randomized_split(rcl, cost3, code3, seg3, greedy_code, count, open_node, uniforms, noise, k):
    """Split (axis, N_L) [nodes] of every node under the randomized rule (module docstring).

    ``cost3``, ``code3``, ``seg3``: [3, P] candidate costs (inf: none), tie-rule codes and
    node ids (``nodes`` = none); ``greedy_code``: [nodes] the greedy split's code;
    ``open_node``: [nodes] nodes split on this level; ``uniforms``: [nodes, 2].
    """
    nodes = count.shape[0]
    greedy_axis, greedy_left = _sweep_split_of(greedy_code, count)
    deviate = open_node & (count >= 2) & (uniforms[:, 0] < noise)
    u1 = uniforms[:, 1]
    if rcl == "axes":
        axis_seg = seg3 + (nodes + 1) * jnp.arange(3, dtype=jnp.int32)[:, None]
        per_axis = _least_code(cost3, code3, axis_seg, 3 * (nodes + 1)).reshape(3, nodes + 1)[:, :nodes]
        alt_axis = (greedy_axis + jnp.where(u1 < 0.5, 1, 2)) % 3
        alt_code = jnp.take_along_axis(per_axis, alt_axis[None, :], axis=0)[0]
    else:
        size = jnp.minimum(k, 3 * (count - 1))  # the list: the node's best min(k, 3 (N - 1))
        others = jnp.maximum(size - 1, 0)
        pick = jnp.minimum(jnp.floor(u1 * others.astype(jnp.float32)).astype(jnp.int32), others - 1)
        rank = jnp.where(deviate & (others > 0), 1 + pick, 0)
        deviate = rank > 0

        def next_rank(state):  # rank j: the greedy split among those not yet ranked
            j, taken, chosen = state
            code_j = _least_code(jnp.where(taken, jnp.inf, cost3), code3, seg3, nodes + 1)[:nodes]
            taken = taken | (code3 == code_j.at[seg3].get(mode="fill", fill_value=_NO_CODE))
            return j + 1, taken, jnp.where(rank == j, code_j, chosen)

        taken = code3 == greedy_code.at[seg3].get(mode="fill", fill_value=_NO_CODE)
        last = jnp.max(rank)  # at most k - 1: the loop's bound
        _, _, alt_code = jax.lax.while_loop(lambda s: s[0] <= last, next_rank,
                                            (jnp.int32(1), taken, greedy_code))
    alt_axis, alt_left = _sweep_split_of(alt_code, count)
    return jnp.where(deviate, alt_axis, greedy_axis), jnp.where(deviate, alt_left, greedy_left)


def _segmented_box_scan(lo, hi, starts):
    """Inclusive running box along axis 1 of [S, P, 3] boxes, restarting where ``starts``.

    ``starts``: [S, P] bool. One scan serves many sequences at once (all axes, forward
    and backward), which keeps the compiled program small.
    """

    def combine(a, b):
        fa, la, ha = a
        fb, lb, hb = b
        return (fa | fb, jnp.where(fb[..., None], lb, jnp.minimum(la, lb)),
                jnp.where(fb[..., None], hb, jnp.maximum(ha, hb)))

    _, run_lo, run_hi = jax.lax.associative_scan(combine, (starts, lo, hi), axis=1)
    return run_lo, run_hi


def _split_costs(lo_pos, hi_pos, first, last, n_left, n_right, scale):
    """Cost ``A_L N_L + A_R N_R`` of splitting each run after each position.

    ``*_pos``: boxes in position order, one row per axis order [3, P, 3];
    ``first`` / ``last``: [P] run boundaries; ``n_left``/``n_right``: [P] counts of
    the two sides when splitting after the position. Returns [3, P].
    """
    axes = lo_pos.shape[0]
    # forward sweeps (left sides) and backward sweeps (right sides) in one scan
    seq_lo = jnp.concatenate([lo_pos, lo_pos[:, ::-1]])
    seq_hi = jnp.concatenate([hi_pos, hi_pos[:, ::-1]])
    starts = jnp.concatenate([jnp.broadcast_to(first, (axes,) + first.shape),
                              jnp.broadcast_to(last[::-1], (axes,) + last.shape)])
    run_lo, run_hi = _segmented_box_scan(seq_lo, seq_hi, starts)
    fwd_lo, fwd_hi = run_lo[:axes], run_hi[:axes]
    # the right side of a split after p is the backward run starting at p + 1
    empty = jnp.full((axes, 1, 3), jnp.inf, lo_pos.dtype)
    right_lo = jnp.concatenate([run_lo[axes:, ::-1][:, 1:], empty], axis=1)
    right_hi = jnp.concatenate([run_hi[axes:, ::-1][:, 1:], -empty], axis=1)
    dtype = lo_pos.dtype
    return (half_area(fwd_lo, fwd_hi, scale) * n_left.astype(dtype)
            + half_area(right_lo, right_hi, scale) * n_right.astype(dtype))


@partial(jax.jit, static_argnames=("method", "bins", "rcl"))
def _build(lo, hi, n, max_leaf, ct, ci, scale, splits=None, *, method, bins, rcl=None):
    """The engine. ``rcl`` (None: greedy, or one of SPLIT_CHOICES) with ``method="sweep"``
    and ``splits`` (:class:`RandomSplits`) builds the randomized forest and returns
    ``(BVH, tree_of)`` (:func:`randomized_forest`); otherwise one tree, a ``BVH``."""
    cap = lo.shape[0]
    nodes = 2 * cap
    none = nodes  # out-of-range node id: scatters to it are dropped
    dtype = lo.dtype
    pos = jnp.arange(cap, dtype=jnp.int32)
    is_prim = pos < n
    centre = jnp.where(is_prim[:, None], 0.5 * lo + 0.5 * hi, jnp.inf)
    # one permutation per axis, each run sorted by centre (stable: equal centres by id)
    orders = jnp.stack([jnp.argsort(centre[:, a], stable=True).astype(jnp.int32) for a in range(3)])

    int_nodes = jnp.full(nodes, -1, jnp.int32)
    state = dict(
        orders=orders,
        pos_node=jnp.where(is_prim, 0, none).astype(jnp.int32),
        start=jnp.zeros(nodes, jnp.int32),
        count=jnp.zeros(nodes, jnp.int32).at[0].set(n),
        frontier=jnp.zeros(nodes, bool).at[0].set(True),
        left=int_nodes, right=int_nodes, parent=int_nodes, axis=int_nodes,
        prim_start=jnp.zeros(nodes, jnp.int32), prim_count=jnp.zeros(nodes, jnp.int32),
        lo=jnp.full((nodes, 3), jnp.inf, dtype), hi=jnp.full((nodes, 3), -jnp.inf, dtype),
        next_free=jnp.int32(1),
    )
    if rcl is not None:
        # a forest: group g's primitives take the run [offset_g, offset_g + count_g) of
        # every axis order, sorted by centre inside it (stable sorts keep ids in order)
        group = jnp.where(is_prim, splits.group, cap)
        orders = jnp.stack([o[jnp.argsort(group[o], stable=True)] for o in orders])
        size = jax.ops.segment_sum(is_prim.astype(jnp.int32), group, num_segments=cap + 1)[:cap]
        trees = jnp.sum(size > 0, dtype=jnp.int32)
        root = jnp.arange(cap, dtype=jnp.int32)
        state.update(
            orders=orders,
            pos_node=jnp.where(is_prim, group[orders[0]], none).astype(jnp.int32),
            start=jnp.zeros(nodes, jnp.int32).at[root].set(jnp.cumsum(size) - size),
            count=jnp.zeros(nodes, jnp.int32).at[root].set(size),
            frontier=jnp.zeros(nodes, bool).at[root].set(size > 0),
            next_free=trees,
            tree_of=jnp.full(nodes, -1, jnp.int32).at[root].set(jnp.where(size > 0, root, -1)),
        )
    node_ids = jnp.arange(nodes, dtype=jnp.int32)

    def level(s):
        orders, pos_node, frontier = s["orders"], s["pos_node"], s["frontier"]
        active = frontier.at[pos_node].get(mode="fill", fill_value=False)
        seg = jnp.where(active, pos_node, none)
        start_p = s["start"].at[pos_node].get(mode="fill", fill_value=0)
        count_p = s["count"].at[pos_node].get(mode="fill", fill_value=0)
        offset = pos - start_p
        first = offset == 0
        last = offset == count_p - 1
        count = s["count"]

        # boxes of the nodes on this level
        prim0 = orders[0]
        box_lo = jax.ops.segment_min(lo[prim0], seg, num_segments=nodes + 1)[:nodes]
        box_hi = jax.ops.segment_max(hi[prim0], seg, num_segments=nodes + 1)[:nodes]
        node_lo = jnp.where(frontier[:, None], box_lo, s["lo"])
        node_hi = jnp.where(frontier[:, None], box_hi, s["hi"])
        node_area = half_area(node_lo, node_hi, scale)

        n_left_p = offset + 1
        n_right_p = count_p - n_left_p
        if method == "median":
            extent = node_hi - node_lo
            split_axis = jnp.argmax(extent, axis=1).astype(jnp.int32)
            n_left = count // 2
            best = jnp.zeros(nodes, dtype)
            sah_leaf = jnp.ones(nodes, bool)
        elif method == "sweep":
            cost3 = _split_costs(lo[orders], hi[orders], first, last, n_left_p, n_right_p, scale)
            cost3 = jnp.where(active & (n_right_p > 0), cost3, jnp.inf)  # [3, P]
            two_k = 2 * n_left_p
            key3 = (jnp.abs(two_k - count_p) * 2 + (two_k > count_p))[None, :] * 3 + jnp.arange(3, dtype=jnp.int32)[:, None]
            cost3_all, code3 = cost3, key3  # before the greedy choice masks key3
        else:  # binned
            # the per-axis orders are sorted by centre, so bins never decrease along a run:
            # the planes between occupied bins are the positions where the bin changes
            c_pos = centre[prim0]
            cmin = jax.ops.segment_min(c_pos, seg, num_segments=nodes + 1)[:nodes]
            cmax = jax.ops.segment_max(c_pos, seg, num_segments=nodes + 1)[:nodes]
            span = (cmax - cmin).at[pos_node].get(mode="fill", fill_value=0).T  # [3, P]
            low = cmin.at[pos_node].get(mode="fill", fill_value=0).T
            c_sorted = jnp.stack([centre[orders[a], a] for a in range(3)])
            binsf = jnp.asarray(bins, dtype)
            raw = jnp.floor((c_sorted - low) * binsf / jnp.where(span > 0, span, 1))
            bin_sorted = jnp.where(active & (span > 0), jnp.clip(raw, 0, binsf - 1), 0).astype(jnp.int32)
            cost3 = _split_costs(lo[orders], hi[orders], first, last, n_left_p, n_right_p, scale)
            next_bin = jnp.concatenate([bin_sorted[:, 1:], jnp.full((3, 1), -1, jnp.int32)], axis=1)
            cost3 = jnp.where(active & (n_right_p > 0) & (bin_sorted != next_bin), cost3, jnp.inf)
            key3 = jnp.arange(3, dtype=jnp.int32)[:, None] * bins + bin_sorted  # lowest axis, then plane
        if method != "median":
            seg3 = jnp.broadcast_to(seg, (3, cap))
            best = jax.ops.segment_min(cost3.ravel(), seg3.ravel(), num_segments=nodes + 1)[:nodes]
            near = best * (1 + TIE_TOLERANCE)
            is_best = (cost3 <= near.at[seg3].get(mode="fill", fill_value=jnp.inf)) & (cost3 < jnp.inf)
            key3 = jnp.where(is_best, key3, jnp.iinfo(jnp.int32).max)
            best_key = jax.ops.segment_min(key3.ravel(), seg3.ravel(), num_segments=nodes + 1)[:nodes]
            found = best < jnp.inf
            if method == "sweep":
                # the key names the split: |2 N_L - N|, its sign and the axis
                split_axis = best_key % 3
                gap, upper = (best_key // 3) // 2, (best_key // 3) % 2
                n_left = jnp.where(upper == 1, count + gap, count - gap) // 2
                if rcl is not None:
                    tree_p = jnp.maximum(s["tree_of"].at[pos_node].get(mode="fill", fill_value=0), 0)
                    drawn = split_uniforms(splits.key, splits.trial[tree_p], start_p + splits.shift[tree_p],
                                           count_p)
                    at_first = jnp.where(first & active, pos_node, none)
                    uniforms = jnp.zeros((nodes, 2), jnp.float32).at[at_first].set(drawn, mode="drop")
                    split_axis, n_left = _randomized_split(
                        rcl, cost3_all, code3, seg3, best_key, count, s["frontier"] & (count >= 2),
                        uniforms, splits.noise, splits.k)
            else:
                split_axis = jnp.where(found, best_key // bins, 0)
                at_best = is_best & (key3 == best_key.at[seg3].get(mode="fill", fill_value=-1))
                n_left3 = jnp.where(at_best, n_left_p[None, :], 0)
                n_left = jax.ops.segment_max(n_left3.ravel(), seg3.ravel(), num_segments=nodes + 1)[:nodes]
                # no plane on any axis (all centres in one point): halves by id, which
                # is the order of every axis when all centres are equal
                n_left = jnp.where(found, n_left, count // 2)
            count_f = count.astype(dtype)
            split_est = ct + jnp.where(node_area > 0, ci * best / jnp.where(node_area > 0, node_area, 1),
                                       ci * count_f)
            # a leaf when it costs no more than the split, within the tie tolerance (an
            # exact tie, e.g. a point inside its sibling's box, must not hang on rounding)
            sah_leaf = (ci * count_f <= split_est * (1 + TIE_TOLERANCE)) | ~found

        leaf = frontier & ((count <= 1) | ((count <= max_leaf) & sah_leaf))
        split = frontier & ~leaf
        rank = jnp.cumsum(split.astype(jnp.int32)) - split
        left_id = jnp.where(split, s["next_free"] + 2 * rank, none)
        right_id = jnp.where(split, left_id + 1, none)
        n_left = jnp.where(split, n_left, 0)

        # move primitives into the children's runs
        pos_split = active & split.at[pos_node].get(mode="fill", fill_value=False)
        axis_p = split_axis.at[pos_node].get(mode="fill", fill_value=0)
        n_left_at = n_left.at[pos_node].get(mode="fill", fill_value=0)
        prim_at = jnp.take_along_axis(orders, axis_p[None, :], axis=0)[0]
        goes_left = offset < n_left_at
        left_prim = jnp.zeros(cap, bool).at[jnp.where(pos_split, prim_at, cap)].set(goes_left, mode="drop")
        flags = [left_prim[orders[a]] & pos_split for a in range(3)]
        rows = []
        for a in range(3):
            flag = flags[a]
            before = jnp.cumsum(flag.astype(jnp.int32)) - flag
            rank_left = before - before.at[start_p].get(mode="fill", fill_value=0)
            rank_right = offset - rank_left
            target = jnp.where(flag, start_p + rank_left, start_p + n_left_at + rank_right)
            target = jnp.where(pos_split, target, pos)
            rows.append(jnp.zeros(cap, jnp.int32).at[target].set(orders[a]))
        new_orders = jnp.stack(rows)
        # a primitive's new node follows from its new position
        child_of_pos = jnp.where(offset < n_left_at, left_id.at[pos_node].get(mode="fill", fill_value=none),
                                 right_id.at[pos_node].get(mode="fill", fill_value=none))
        new_pos_node = jnp.where(pos_split, child_of_pos, pos_node)

        start, cnt = s["start"], s["count"]
        new_start = start.at[left_id].set(start, mode="drop").at[right_id].set(start + n_left, mode="drop")
        new_count = cnt.at[left_id].set(n_left, mode="drop").at[right_id].set(cnt - n_left, mode="drop")
        parent = s["parent"].at[left_id].set(node_ids, mode="drop").at[right_id].set(node_ids, mode="drop")
        new_frontier = jnp.zeros(nodes, bool).at[left_id].set(True, mode="drop").at[right_id].set(True, mode="drop")
        more = {}
        if rcl is not None:  # children belong to their parent's tree
            tree_of = s["tree_of"]
            more["tree_of"] = tree_of.at[left_id].set(tree_of, mode="drop").at[right_id].set(tree_of, mode="drop")
        return dict(
            **more,
            orders=new_orders, pos_node=new_pos_node, start=new_start, count=new_count,
            frontier=new_frontier,
            left=jnp.where(split, left_id, s["left"]), right=jnp.where(split, right_id, s["right"]),
            parent=parent, axis=jnp.where(split, split_axis, s["axis"]),
            prim_start=jnp.where(leaf, start, s["prim_start"]),
            prim_count=jnp.where(leaf, cnt, s["prim_count"]),
            lo=node_lo, hi=node_hi,
            next_free=s["next_free"] + 2 * jnp.sum(split, dtype=jnp.int32),
        )

    s = jax.lax.while_loop(lambda s: jnp.any(s["frontier"]), level, state)
    tree = BVH(left=s["left"], right=s["right"], parent=s["parent"], lo=s["lo"], hi=s["hi"],
               prim_start=s["prim_start"], prim_count=s["prim_count"], axis=s["axis"],
               prim_index=jnp.where(is_prim, s["orders"][0], -1), root=jnp.int32(0))
    return tree if rcl is None else (tree, s["tree_of"])
