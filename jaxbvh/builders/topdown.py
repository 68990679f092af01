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

from jaxbvh.builders.configs import BuilderConfig
from jaxbvh.draws import split_uniforms
from jaxbvh.numerics import TIE_TOLERANCE, half_area, on_device
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.layout import BVH, capacity_bucket


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


def build(lo, hi, n, scale, config: BuilderConfig) -> BVH:
    """The top-down tree of ``config`` (a Sweep, Binned or Median Config) over prepared inputs.

    ``lo``, ``hi``, ``n``, ``scale``: as from :func:`jaxbvh.builders.inputs.prepare`. Returns a
    :class:`~jaxbvh.tree.layout.BVH` of JAX arrays, nodes numbered level by level, root 0.
    """
    if config.method not in RULES:
        raise ValueError(f"the top-down engine builds {', '.join(RULES)}, not {config.method!r}")
    bins = config.bins if config.method == "binned" else 0
    if bins and capacity_bucket(int(n)) * bins >= 2**31:
        raise ValueError(f"binned build of {int(n)} primitives with {bins} bins needs keys past int32; "
                         "use fewer bins")
    dt = lo.dtype
    return engine(lo, hi, n, on_device(config.max_leaf, np.int32), on_device(config.ct, dt),
                  on_device(config.ci, dt), scale, method=config.method, bins=bins)


def randomized_forest(lo, hi, n, scale, splits: RandomSplits, *, rcl: str):
    """Randomized full-sweep forest (module docstring), one primitive per leaf.

    ``lo``, ``hi``, ``n``, ``scale``: as from :func:`jaxbvh.builders.inputs.prepare`; ``scale`` must be
    the whole scene's (areas of every tree on one scale). ``rcl``: ``"axes"`` or
    ``"list"``. Returns ``(forest, tree_of)``: a :class:`BVH` whose nodes ``0 .. G - 1``
    are the roots (``root`` is 0, ``prim_index`` holds slots of ``lo``), and ``tree_of``
    [2 capacity] int32, each node's group (-1 for unused slots). Traceable (jit, vmap).
    """
    if rcl not in SPLIT_CHOICES:
        raise ValueError(f"rcl must be one of {', '.join(SPLIT_CHOICES)}, got {rcl!r}")
    one = jnp.ones((), lo.dtype)
    scene = _Scene(lo, hi, _centres(lo, hi, n), scale, jnp.int32(1), one, one)
    state = _grow(scene, _forest_state(scene, n, splits), method="sweep", bins=0, rcl=rcl, splits=splits)
    return _tree(state, n), state.tree_of


# ----------------------------------------------------------------------------------
# The engine: one while_loop step per level (_level), made of the steps below
# ----------------------------------------------------------------------------------

RULES = ("sweep", "binned", "median")  # the split rules of the engine (module docstring)
SPLIT_CHOICES = ("axes", "list")  # randomized split rules (module docstring)
_NO_CODE = np.iinfo(np.int32).max  # tie-rule code of "no candidate"


class _Scene(NamedTuple):
    """What every level reads and no level changes."""

    lo: Any        # [capacity, 3] primitive boxes (padding: the empty box)
    hi: Any
    centre: Any    # [capacity, 3] box centres (padding: +inf, so it sorts last)
    scale: Any     # the scene's power-of-two area scale
    max_leaf: Any  # int32: nodes of at most this many primitives may become leaves
    ct: Any        # SAH traversal and intersection costs (leaf test only)
    ci: Any


class _State(NamedTuple):
    """The loop state: the tree so far and the runs of the open nodes.

    Node arrays have ``2 capacity`` slots; ``none`` (= that count) is the out-of-range
    node id, so scatters to it are dropped.
    """

    orders: Any      # [3, capacity] int32: per axis, the primitive at each position; runs sorted by centre
    pos_node: Any    # [capacity] int32: the node whose run holds each position (none: padding, or done)
    start: Any       # [nodes] int32: first position of each node's run
    count: Any       # [nodes] int32: primitives in each node's run
    frontier: Any    # [nodes] bool: the open nodes, all on the level being built
    left: Any        # [nodes] int32: children (-1: leaf or unused), parent (-1: a root)
    right: Any
    parent: Any
    axis: Any        # [nodes] int32: the split axis (-1: leaf)
    prim_start: Any  # [nodes] int32: a leaf's run of positions (0, 0 for interior nodes)
    prim_count: Any
    lo: Any          # [nodes, 3] boxes, written when a node is on the frontier
    hi: Any
    next_free: Any   # int32: the first node id not yet used
    tree_of: Any     # [nodes] int32: the tree (group) of each node in a forest, -1 unused; None: one tree


class _Runs(NamedTuple):
    """Where each position stands on the current level, all [capacity]."""

    active: Any   # bool: in the run of an open node
    seg: Any      # int32: that node, none when not active (segment ids of the scans)
    start: Any    # int32: the first position of its run
    count: Any    # int32: its run's length
    offset: Any   # int32: position - start
    first: Any    # bool: first / last position of its run
    last: Any


def _centres(lo, hi, n):
    """Box centres [capacity, 3]; padding +inf (sorted last)."""
    return jnp.where((jnp.arange(lo.shape[0]) < n)[:, None], 0.5 * lo + 0.5 * hi, jnp.inf)


def _greedy_state(scene: _Scene, n) -> _State:
    """One tree: every primitive in the root's run."""
    cap = scene.lo.shape[0]
    nodes = 2 * cap
    dtype = scene.lo.dtype
    is_prim = jnp.arange(cap, dtype=jnp.int32) < n
    # one permutation per axis, each run sorted by centre (stable: equal centres by id)
    orders = jnp.argsort(scene.centre.T, axis=1, stable=True).astype(jnp.int32)  # one sort op for all axes
    int_nodes = jnp.full(nodes, -1, jnp.int32)
    return _State(
        orders=orders, pos_node=jnp.where(is_prim, 0, nodes).astype(jnp.int32),
        start=jnp.zeros(nodes, jnp.int32), count=jnp.zeros(nodes, jnp.int32).at[0].set(n),
        frontier=jnp.zeros(nodes, bool).at[0].set(True),
        left=int_nodes, right=int_nodes, parent=int_nodes, axis=int_nodes,
        prim_start=jnp.zeros(nodes, jnp.int32), prim_count=jnp.zeros(nodes, jnp.int32),
        lo=jnp.full((nodes, 3), jnp.inf, dtype), hi=jnp.full((nodes, 3), -jnp.inf, dtype),
        next_free=jnp.int32(1), tree_of=None)


def _forest_state(scene: _Scene, n, splits: RandomSplits) -> _State:
    """A forest: group g's primitives take the run ``[offset_g, offset_g + count_g)`` of
    every axis order, sorted by centre inside it (stable sorts keep ids in order); the
    roots are nodes ``0 .. G - 1``."""
    s = _greedy_state(scene, n)
    cap = scene.lo.shape[0]
    nodes = 2 * cap
    is_prim = jnp.arange(cap, dtype=jnp.int32) < n
    group = jnp.where(is_prim, splits.group, cap)
    orders = jnp.stack([o[jnp.argsort(group[o], stable=True)] for o in s.orders])
    size = jax.ops.segment_sum(is_prim.astype(jnp.int32), group, num_segments=cap + 1)[:cap]
    root = jnp.arange(cap, dtype=jnp.int32)
    return s._replace(
        orders=orders,
        pos_node=jnp.where(is_prim, group[orders[0]], nodes).astype(jnp.int32),
        start=jnp.zeros(nodes, jnp.int32).at[root].set(jnp.cumsum(size) - size),
        count=jnp.zeros(nodes, jnp.int32).at[root].set(size),
        frontier=jnp.zeros(nodes, bool).at[root].set(size > 0),
        next_free=jnp.sum(size > 0, dtype=jnp.int32),
        tree_of=jnp.full(nodes, -1, jnp.int32).at[root].set(jnp.where(size > 0, root, -1)))


def _runs(s: _State) -> _Runs:
    """Each position's node and run on this level."""
    cap = s.pos_node.shape[0]
    none = s.count.shape[0]
    pos = jnp.arange(cap, dtype=jnp.int32)
    # one gather of the node's (open, start, count); padding and done positions read 0s
    at = jnp.stack([s.frontier.astype(jnp.int32), s.start, s.count], axis=1).at[s.pos_node].get(
        mode="fill", fill_value=0)
    active, start, count = at[:, 0] == 1, at[:, 1], at[:, 2]
    offset = pos - start
    return _Runs(active=active, seg=jnp.where(active, s.pos_node, none), start=start, count=count,
                 offset=offset, first=offset == 0, last=offset == count - 1)


def _node_boxes(scene: _Scene, s: _State, runs: _Runs):
    """Boxes [nodes, 3] of the nodes on this level (others keep theirs)."""
    nodes = s.count.shape[0]
    box_lo, box_hi = _segment_bounds(scene.lo[s.orders[0]], scene.hi[s.orders[0]], runs.seg, nodes)
    return jnp.where(s.frontier[:, None], box_lo, s.lo), jnp.where(s.frontier[:, None], box_hi, s.hi)


def _segment_bounds(lo, hi, seg, nodes):
    """Per-segment min of ``lo`` and max of ``hi`` ([P, 3] each) as [nodes, 3] each.

    One scatter-min of ``(lo, -hi)`` (negation is exact), not a min and a max: every
    scatter is a separately compiled loop on CPU.
    """
    both = jax.ops.segment_min(jnp.concatenate([lo, -hi], axis=1), seg, num_segments=nodes + 1)[:nodes]
    return both[:, :3], -both[:, 3:]


_SCAN_BLOCK = 32  # positions per block of the segmented box scan (run time measured alike for 16 to 64)


def segmented_box_scan(lo, hi, offset, longest):
    """Inclusive running box along axis 1 of [S, P, 3] boxes, each run restarting.

    ``offset``: [S, P] int32, each position's distance from the first of its run;
    ``longest``: int32, no run is longer. One scan serves many sequences at once (all
    axes, forward and backward). The one segmented box scan of the package (the
    two-level top level's sweeps use it too, :mod:`jaxbvh.twolevel.brefs_segments`).

    ``lax.associative_scan`` unrolls ``2 log2 P`` levels of slices, which was most of
    the engine's compile time; this scan has a fixed small program instead: the
    positions in blocks of ``_SCAN_BLOCK``, a sequential ``lax.scan`` within every block
    at once, a doubling (Hillis-Steele) ``while_loop`` over the block ends that stops
    once the longest run is covered, and a pass that gives each position whose run began
    before its block the previous block's end. Min and max are exact, so the boxes are
    the same in any order.
    """
    seqs, cap, _ = lo.shape
    block = _SCAN_BLOCK
    pad = -cap % block
    if pad:  # padding positions are runs of their own (offset 0), cut off at the end
        lo, hi = (jnp.pad(x, ((0, 0), (0, pad), (0, 0))) for x in (lo, hi))
        offset = jnp.pad(offset, ((0, 0), (0, pad)))
    blocks = (cap + pad) // block
    offset = offset.reshape(seqs, blocks, block)

    def by_column(x):  # [S, blocks * block, 3] -> [block, S, blocks, 3]
        return jnp.moveaxis(x.reshape(seqs, blocks, block, 3), 2, 0)

    def within(carry, column):  # one position of every block; the carry: the one before it
        before_lo, before_hi = carry
        column_lo, column_hi, take = column
        column_lo = jnp.where(take, jnp.minimum(before_lo, column_lo), column_lo)
        column_hi = jnp.where(take, jnp.maximum(before_hi, column_hi), column_hi)
        return (column_lo, column_hi), (column_lo, column_hi)

    lo_c, hi_c = by_column(lo), by_column(hi)
    take = jnp.moveaxis(offset >= 1, 2, 0)[..., None]  # column 0 takes only from itself
    _, (lo_c, hi_c) = jax.lax.scan(within, (lo_c[0], hi_c[0]), (lo_c, hi_c, take))
    lo_b, hi_b = jnp.moveaxis(lo_c, 0, 2), jnp.moveaxis(hi_c, 0, 2)  # [S, blocks, block, 3]

    end_offset = offset[:, :, -1]

    def shifted(x, d):  # x[:, j - d], wrapping round (only read where the run reaches back)
        return jax.lax.dynamic_slice_in_dim(jnp.concatenate([x, x], axis=1), blocks - d, blocks, axis=1)

    def over_blocks(state):
        # before: each block end holds the box of its run within the last d blocks; after: 2 d
        d, end_lo, end_hi = state
        reach = (end_offset >= d * block)[..., None]
        end_lo = jnp.where(reach, jnp.minimum(shifted(end_lo, d), end_lo), end_lo)
        end_hi = jnp.where(reach, jnp.maximum(shifted(end_hi, d), end_hi), end_hi)
        return 2 * d, end_lo, end_hi

    _, end_lo, end_hi = jax.lax.while_loop(lambda s: s[0] * block < longest, over_blocks,
                                           (jnp.int32(1), lo_b[:, :, -1], hi_b[:, :, -1]))
    before = (offset > jnp.arange(block, dtype=offset.dtype))[..., None]  # the run began before the block
    prev_lo, prev_hi = shifted(end_lo, 1)[:, :, None], shifted(end_hi, 1)[:, :, None]
    run_lo = jnp.where(before, jnp.minimum(prev_lo, lo_b), lo_b).reshape(seqs, cap + pad, 3)[:, :cap]
    run_hi = jnp.where(before, jnp.maximum(prev_hi, hi_b), hi_b).reshape(seqs, cap + pad, 3)[:, :cap]
    return run_lo, run_hi


def _split_costs(scene: _Scene, orders, runs: _Runs):
    """Cost ``A_L N_L + A_R N_R`` [3, P] of splitting each run after each position, per
    axis order; ``inf`` where that is no split (the last position, or not active)."""
    lo_pos, hi_pos = scene.lo[orders], scene.hi[orders]  # boxes in position order [3, P, 3]
    n_left = runs.offset + 1
    n_right = runs.count - n_left
    axes = lo_pos.shape[0]
    # forward sweeps (left sides) and backward sweeps (right sides) in one scan
    seq_lo = jnp.concatenate([lo_pos, lo_pos[:, ::-1]])
    seq_hi = jnp.concatenate([hi_pos, hi_pos[:, ::-1]])
    from_end = runs.count - 1 - runs.offset  # a position's offset in the backward sweep
    offset = jnp.concatenate([jnp.broadcast_to(runs.offset, (axes,) + runs.offset.shape),
                              jnp.broadcast_to(from_end[::-1], (axes,) + from_end.shape)])
    run_lo, run_hi = segmented_box_scan(seq_lo, seq_hi, offset, jnp.max(jnp.where(runs.active, runs.count, 0)))
    fwd_lo, fwd_hi = run_lo[:axes], run_hi[:axes]
    # the right side of a split after p is the backward run starting at p + 1
    empty = jnp.full((axes, 1, 3), jnp.inf, lo_pos.dtype)
    right_lo = jnp.concatenate([run_lo[axes:, ::-1][:, 1:], empty], axis=1)
    right_hi = jnp.concatenate([run_hi[axes:, ::-1][:, 1:], -empty], axis=1)
    dtype = lo_pos.dtype
    cost = (half_area(fwd_lo, fwd_hi, scene.scale) * n_left.astype(dtype)
            + half_area(right_lo, right_hi, scene.scale) * n_right.astype(dtype))
    return jnp.where(runs.active & (n_right > 0), cost, jnp.inf)


def _sweep_candidates(scene: _Scene, s: _State, runs: _Runs):
    """Every split position of every axis: ``(cost3, code3)`` [3, P], the code ranking
    equal costs by the sweep's tie rule (``|2 N_L - N|``, its sign, the axis)."""
    two_k = 2 * (runs.offset + 1)
    code3 = (jnp.abs(two_k - runs.count) * 2 + (two_k > runs.count))[None, :] * 3 \
        + jnp.arange(3, dtype=jnp.int32)[:, None]
    return _split_costs(scene, s.orders, runs), code3


def _binned_candidates(scene: _Scene, s: _State, runs: _Runs, bins: int):
    """The planes between bins (Wald's candidates): ``(cost3, code3)`` [3, P], the code
    ranking equal costs by axis, then plane.

    The per-axis orders are sorted by centre, so bins never decrease along a run: the
    planes between occupied bins are the positions where the bin changes.
    """
    nodes = s.count.shape[0]
    dtype = scene.lo.dtype
    c_pos = scene.centre[s.orders[0]]
    cmin, cmax = _segment_bounds(c_pos, c_pos, runs.seg, nodes)
    span = (cmax - cmin).at[s.pos_node].get(mode="fill", fill_value=0).T  # [3, P]
    low = cmin.at[s.pos_node].get(mode="fill", fill_value=0).T
    c_sorted = jnp.take_along_axis(scene.centre.T, s.orders, axis=1)
    binsf = jnp.asarray(bins, dtype)
    raw = jnp.floor((c_sorted - low) * binsf / jnp.where(span > 0, span, 1))
    bin_sorted = jnp.where(runs.active & (span > 0), jnp.clip(raw, 0, binsf - 1), 0).astype(jnp.int32)
    next_bin = jnp.concatenate([bin_sorted[:, 1:], jnp.full((3, 1), -1, jnp.int32)], axis=1)
    cost3 = jnp.where(bin_sorted != next_bin, _split_costs(scene, s.orders, runs), jnp.inf)
    return cost3, jnp.arange(3, dtype=jnp.int32)[:, None] * bins + bin_sorted


def _tie_winner(cost, code, seg, num_segments):
    """Tie-rule winner per segment: least cost, then least ``code`` within TIE_TOLERANCE.

    ``cost``, ``code``, ``seg``: equal shapes (``inf`` cost = not a candidate). Returns
    ``(best, winner, near_best)``: the least cost [num_segments], the winner's code
    [num_segments] (``_NO_CODE`` for a segment without candidates), and which
    candidates are within the tolerance of their segment's least.
    """
    best = jax.ops.segment_min(cost.ravel(), seg.ravel(), num_segments=num_segments)
    near = (best * (1 + TIE_TOLERANCE)).at[seg].get(mode="fill", fill_value=jnp.inf)
    near_best = (cost <= near) & (cost < jnp.inf)
    winner = jax.ops.segment_min(jnp.where(near_best, code, _NO_CODE).ravel(), seg.ravel(),
                                 num_segments=num_segments)
    return best, winner, near_best


def _sweep_split_of(code, count):
    """(axis, N_L) of the sweep split with tie-rule code ``code`` in a node of ``count``."""
    gap, upper = (code // 3) // 2, (code // 3) % 2
    return code % 3, jnp.where(upper == 1, count + gap, count - gap) // 2


def _binned_split_of(code, found, near_best, code3, seg3, runs: _Runs, count, bins: int):
    """(axis, N_L) of the winning plane; a node with no plane on any axis (all centres in
    one point, ``found`` False) is split into halves by id, which is the order of every
    axis then."""
    nodes = count.shape[0]
    at_best = near_best & (code3 == code.at[seg3].get(mode="fill", fill_value=-1))
    n_left3 = jnp.where(at_best, (runs.offset + 1)[None, :], 0)
    n_left = jax.ops.segment_max(n_left3.ravel(), seg3.ravel(), num_segments=nodes + 1)[:nodes]
    return jnp.where(found, code // bins, 0), jnp.where(found, n_left, count // 2)


def _node_uniforms(s: _State, runs: _Runs, splits: RandomSplits):
    """The two uniforms [nodes, 2] of every open node (module docstring: named by the
    node's trial and run, drawn at its run's first position)."""
    nodes = s.count.shape[0]
    tree_p = jnp.maximum(s.tree_of.at[s.pos_node].get(mode="fill", fill_value=0), 0)
    drawn = split_uniforms(splits.key, splits.trial[tree_p], runs.start + splits.shift[tree_p], runs.count)
    at_first = jnp.where(runs.first & runs.active, s.pos_node, nodes)
    return jnp.zeros((nodes, 2), jnp.float32).at[at_first].set(drawn, mode="drop")


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
        _, per_axis, _ = _tie_winner(cost3, code3, axis_seg, 3 * (nodes + 1))
        per_axis = per_axis.reshape(3, nodes + 1)[:, :nodes]
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
            code_j = _tie_winner(jnp.where(taken, jnp.inf, cost3), code3, seg3, nodes + 1)[1][:nodes]
            taken = taken | (code3 == code_j.at[seg3].get(mode="fill", fill_value=_NO_CODE))
            return j + 1, taken, jnp.where(rank == j, code_j, chosen)

        taken = code3 == greedy_code.at[seg3].get(mode="fill", fill_value=_NO_CODE)
        last = jnp.max(rank)  # at most k - 1: the loop's bound
        _, _, alt_code = jax.lax.while_loop(lambda s: s[0] <= last, next_rank,
                                            (jnp.int32(1), taken, greedy_code))
    alt_axis, alt_left = _sweep_split_of(alt_code, count)
    return jnp.where(deviate, alt_axis, greedy_axis), jnp.where(deviate, alt_left, greedy_left)


def _sah_leaf(scene: _Scene, best, node_area, count, found):
    """Whether a node costs no more as a leaf than split at its best, within the tie
    tolerance (an exact tie, e.g. a point inside its sibling's box, must not hang on
    rounding); a node without a candidate split is a leaf too."""
    ct, ci = scene.ct, scene.ci
    count_f = count.astype(scene.lo.dtype)
    split_est = ct + jnp.where(node_area > 0, ci * best / jnp.where(node_area > 0, node_area, 1), ci * count_f)
    return (ci * count_f <= split_est * (1 + TIE_TOLERANCE)) | ~found


def _choose_splits(scene: _Scene, s: _State, runs: _Runs, node_lo, node_hi, *, method, bins, rcl, splits):
    """``(axis, N_L, sah_leaf)`` [nodes] of every node on this level under ``method``."""
    nodes = s.count.shape[0]
    count = s.count
    if method == "median":  # the first longest axis, the lower half (by centre, then id) left
        split_axis = jnp.argmax(node_hi - node_lo, axis=1).astype(jnp.int32)
        return split_axis, count // 2, jnp.ones(nodes, bool)
    if method == "sweep":
        cost3, code3 = _sweep_candidates(scene, s, runs)
    else:
        cost3, code3 = _binned_candidates(scene, s, runs, bins)
    seg3 = jnp.broadcast_to(runs.seg, cost3.shape)
    best, code, near_best = _tie_winner(cost3, code3, seg3, nodes + 1)
    best, code = best[:nodes], code[:nodes]
    found = best < jnp.inf
    if method == "sweep":
        split_axis, n_left = _sweep_split_of(code, count)
        if rcl is not None:
            split_axis, n_left = _randomized_split(
                rcl, cost3, code3, seg3, code, count, s.frontier & (count >= 2),
                _node_uniforms(s, runs, splits), splits.noise, splits.k)
    else:
        split_axis, n_left = _binned_split_of(code, found, near_best, code3, seg3, runs, count, bins)
    return split_axis, n_left, _sah_leaf(scene, best, half_area(node_lo, node_hi, scene.scale), count, found)


def _partition(s: _State, runs: _Runs, split, split_axis, n_left, left_id, right_id):
    """Move the primitives of split nodes into their children's runs, stably in every
    axis order: ``(orders, pos_node)`` of the next level."""
    cap = s.pos_node.shape[0]
    pos = jnp.arange(cap, dtype=jnp.int32)
    # one gather of the node's split, axis, N_L and children; padding and done positions read
    # 0s (only positions of split nodes use the children)
    at = jnp.stack([split.astype(jnp.int32), split_axis, n_left, left_id, right_id], axis=1).at[s.pos_node].get(
        mode="fill", fill_value=0)
    pos_split = runs.active & (at[:, 0] == 1)
    axis_p, n_left_at = at[:, 1], at[:, 2]
    # which primitives go left: the first N_L of the run in the split axis' order
    prim_at = jnp.take_along_axis(s.orders, axis_p[None, :], axis=0)[0]
    goes_left = runs.offset < n_left_at
    left_prim = jnp.zeros(cap, bool).at[jnp.where(pos_split, prim_at, cap)].set(goes_left, mode="drop")
    # all axes at once, [3, P] (one cumsum and one scatter in the program, not three)
    flag = left_prim[s.orders] & pos_split
    before = jnp.cumsum(flag.astype(jnp.int32), axis=1) - flag
    rank_left = before - before.at[:, runs.start].get(mode="fill", fill_value=0)
    rank_right = runs.offset - rank_left
    target = jnp.where(flag, runs.start + rank_left, runs.start + n_left_at + rank_right)
    target = jnp.where(pos_split, target, pos)
    rows = jnp.arange(3, dtype=jnp.int32)[:, None]
    orders = jnp.zeros_like(s.orders).at[jnp.broadcast_to(rows, target.shape), target].set(s.orders)
    # a primitive's new node follows from its new position
    child_of_pos = jnp.where(runs.offset < n_left_at, at[:, 3], at[:, 4])
    return orders, jnp.where(pos_split, child_of_pos, s.pos_node)


def _level(scene: _Scene, s: _State, *, method, bins, rcl, splits) -> _State:
    """Build one level: every open node becomes a leaf or is split, its children open."""
    nodes = s.count.shape[0]
    node_ids = jnp.arange(nodes, dtype=jnp.int32)
    runs = _runs(s)
    node_lo, node_hi = _node_boxes(scene, s, runs)
    split_axis, n_left, sah_leaf = _choose_splits(scene, s, runs, node_lo, node_hi, method=method, bins=bins,
                                                  rcl=rcl, splits=splits)
    count = s.count
    leaf = s.frontier & ((count <= 1) | ((count <= scene.max_leaf) & sah_leaf))
    split = s.frontier & ~leaf
    # children ids: two per split node, in node order, from next_free
    rank = jnp.cumsum(split.astype(jnp.int32)) - split
    left_id = jnp.where(split, s.next_free + 2 * rank, nodes)
    right_id = jnp.where(split, left_id + 1, nodes)
    n_left = jnp.where(split, n_left, 0)
    orders, pos_node = _partition(s, runs, split, split_axis, n_left, left_id, right_id)

    # the children's start, count, parent, open flag (and tree), written by one scatter:
    # rows [nodes, k] of the values now, of the left children and of the right ones
    ones = jnp.ones(nodes, jnp.int32)
    now = [s.start, count, s.parent, jnp.zeros(nodes, jnp.int32)]
    to_left = [s.start, n_left, node_ids, ones]
    to_right = [s.start + n_left, count - n_left, node_ids, ones]
    if s.tree_of is not None:  # a child is in its parent's tree
        now, to_left, to_right = now + [s.tree_of], to_left + [s.tree_of], to_right + [s.tree_of]
    written = jnp.stack(now, axis=1).at[jnp.concatenate([left_id, right_id])].set(
        jnp.concatenate([jnp.stack(to_left, axis=1), jnp.stack(to_right, axis=1)]), mode="drop")
    tree_of = None if s.tree_of is None else written[:, 4]
    return _State(
        orders=orders, pos_node=pos_node,
        start=written[:, 0], count=written[:, 1], frontier=written[:, 3] == 1,
        left=jnp.where(split, left_id, s.left), right=jnp.where(split, right_id, s.right),
        parent=written[:, 2], axis=jnp.where(split, split_axis, s.axis),
        prim_start=jnp.where(leaf, s.start, s.prim_start), prim_count=jnp.where(leaf, count, s.prim_count),
        lo=node_lo, hi=node_hi, next_free=s.next_free + 2 * jnp.sum(split, dtype=jnp.int32), tree_of=tree_of)


def _grow(scene: _Scene, state: _State, *, method, bins, rcl=None, splits=None) -> _State:
    """Levels until no node is open."""
    return jax.lax.while_loop(lambda s: jnp.any(s.frontier),
                              partial(_level, scene, method=method, bins=bins, rcl=rcl, splits=splits), state)


def _tree(s: _State, n) -> BVH:
    is_prim = jnp.arange(s.orders.shape[1], dtype=jnp.int32) < n
    return BVH(left=s.left, right=s.right, parent=s.parent, lo=s.lo, hi=s.hi, prim_start=s.prim_start,
               prim_count=s.prim_count, axis=s.axis, prim_index=jnp.where(is_prim, s.orders[0], -1),
               root=jnp.int32(0))


@partial(stored_jit, static_argnames=("method", "bins"))
def engine(lo, hi, n, max_leaf, ct, ci, scale, *, method: str, bins: int = 0) -> BVH:
    """The greedy engine on prepared inputs (:func:`jaxbvh.builders.inputs.prepare`); jitted, vmappable.

    ``max_leaf``: int32; ``ct``, ``ci``: scalars in the boxes' dtype; ``method``: one of
    :data:`RULES` (static); ``bins``: bins per axis for ``"binned"`` (static, else 0).
    Returns a :class:`~jaxbvh.tree.layout.BVH` (``2 capacity`` node slots, level by level).
    """
    scene = _Scene(lo, hi, _centres(lo, hi, n), scale, max_leaf, ct, ci)
    return _tree(_grow(scene, _greedy_state(scene, n), method=method, bins=bins), n)
