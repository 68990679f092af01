"""Goldsmith–Salmon insertion build: objects put into a tree one at a time (jitted).

Goldsmith & Salmon (1987), as Ng & Trifonov (2003, §4) use it to price an insertion
order. The tree is not binary: an interior node has 2 to ``max_children`` children.

Sources. The 1987 paper itself was not at hand; the algorithm below follows Ng and
Trifonov's description ("searched top down without backtracking, every time choosing a
subtree ... that will have a minimal increase in cost ... [which] depends on the
surface area, increase in surface area in case of addition, and number of children, for
the node and its ancestors"), Ericson's account (*Real-Time Collision Detection* §6.2.3.1:
an object becomes a new child of a node, ``d = k (A' - A) + A'``; or is paired with a
node under a new parent, ``d = 2 A'``; or goes lower, ``d = k (A' - A)``; the least
expensive option wins; ties by the nearest centre or at random) and Haines's 1988
summary (Ray Tracing News). Where they leave room we chose: pairing is offered with the
leaf the walk ends at (not with interior nodes on the way), the child to descend into is
the one whose own cost term grows least (``rise`` below), and Haines's later
improvement (trying both options at every child) is not used.

Cost
====
A ray that hits a node's box tests all of the node's children, and it hits a box with
probability proportional to the box's surface area, so Goldsmith and Salmon price a
tree as ``sum over interior nodes of area x number of children`` (divided by the root's
area: :func:`jaxbvh.goldsmith_salmon_cost`). Areas here are half-areas of extents
scaled by the power of two that brings the scene's largest extent into [0.5, 1)
(:mod:`jaxbvh.tree.cost`), and the insertion costs below are the exact changes of the
unnormalised sum (the root's box is the same whichever candidate wins, so the
normalisation does not change the choice).

Insertion
=========
The first object of the order becomes the root (a leaf). Each later object ``b`` walks
down from the root without backtracking. Write ``A(x)`` for the area of node ``x``'s
box, ``A(x+b)`` for the area of that box grown to hold ``b``, ``dA(x) = A(x+b) - A(x)``
(exactly 0 when the box already holds ``b``) and ``k(x)`` for the number of children.
``I`` is the *inherited* cost: how much the terms of the nodes above the current one
grow, ``sum k(a) dA(a)`` over them (0 at the root). At the current node ``x``:

* leaf: the candidate *pair* — a new interior node in ``x``'s place with children
  ``x`` and ``b`` — costs ``I + 2 A(x+b)``, and the walk ends;
* interior node with fewer than ``max_children`` children: the candidate *child* — ``b``
  as one more child of ``x`` — costs ``(I + k(x) dA(x)) + A(x+b)``;
* then the walk goes on into the child ``c`` whose term grows least if ``b`` goes into
  it: ``rise(c) = k(c) dA(c)`` for an interior child, ``2 A(c+b)`` for a leaf (which
  would become a pair), with ``I <- I + k(x) dA(x)``.

Every candidate met is compared with the cheapest so far; the cheapest wins and ``b``
is inserted there. Deeper candidates never cost less than the inherited cost ``I``
(costs only add non-negative terms), so the walk stops early once ``I`` reaches the
cheapest candidate; the result is the same as walking on to a leaf. After the insertion
the boxes from the insertion point up grow to hold ``b``, stopping at the first box
that already holds it (all boxes above it hold it too).

Tie rules (the NumPy reference :mod:`jaxbvh.builders.insertion_reference` keeps the same ones).
Costs count as equal when they differ by at most a relative ``TIE_TOLERANCE`` (2^-20,
as in :mod:`jaxbvh.builders.topdown`: XLA on CPU fuses multiply-adds, so a cost can come out one
ulp apart here and in NumPy):

* a deeper candidate replaces the cheapest so far only when ``cost * (1 + tol) <
  cheapest``, so among equal costs the shallowest wins, and the walk stops once
  ``I * (1 + tol) >= cheapest``;
* among children of equal ``rise`` (typically several boxes that already hold ``b``,
  all rising by 0) the walk takes the one whose box centre is nearest to ``b``'s in the
  L1 norm (Goldsmith and Salmon's suggestion; computed as ``|sum of corners of c - sum
  of corners of b|`` summed over x, y, z in that order, no multiplications, so exact
  ties are real), then the lowest child slot.

Layout of the result (a :class:`~jaxbvh.tree.layout.WideBVH`, child ``[N, max_children]``)
=====================================================================================
Leaf ``p`` is node ``p`` and holds primitive ``p`` (``prim_start = p``, ``prim_count =
1``, ``prim_index[p] = p``); the ``j``-th interior node made is node ``n + j``, so real
nodes are ``0 .. 2n - 2`` and everything above is inert padding (``N = 2 * capacity``,
``capacity = capacity_bucket(n)``). Children sit in the order they arrived: a pair is
``[old node, b]`` in the slot the old node had, a new child takes the next free slot.
A node holding ``max_children`` children takes no more (the candidate *child* is not
offered there); ``max_children`` is the only departure from the 1987 algorithm, which
has no limit. Default 8. Four random orders of each shared mesh, mean G&S cost by
``max_children`` (the walk down prices every child slot, so time grows with it: 1.6x
from 8 to 16 on a population of 50):

==========  =======  ==================  ==================  =================
mesh        n        4 (nodes full)      8 (nodes full)      16 / 64
==========  =======  ==================  ==================  =================
spot        5,856    49.010 (25%)        48.928 (0.01%)      48.928 / 48.928
teapot      6,320    48.135 (36%)        47.917 (0.67%)      47.914 / 47.914
legocar     10,992   60.993 (38%)        56.213 (1.6%)       56.067 / 56.067
drone       32,720   26.536 (42%)        24.944 (2.8%)       24.885 / 24.883
bunny       69,451   69.495 (26%)        69.405 (0%)         69.405 / 69.405
==========  =======  ==================  ==================  =================

(legocar and the drone mix large and tiny triangles: their widest nodes reach ~50
children without a limit.)

Loops and batches. The build is one ``while_loop`` step per insertion; inside it the
walk down and the walk up are ``while_loop`` s bounded by the node count. One call
builds a batch of orders at once (:func:`build_batch`, :func:`insert_batch`): the
trees live in one flat table, every loop step advances every tree that is not done,
and each tree's result is exactly what it would be alone. This is how
:mod:`jaxbvh.stochastic.evolve` prices a population.
"""

from __future__ import annotations

from functools import partial
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.builders.inputs import prepare
from jaxbvh.configs import integer
from jaxbvh.numerics import TIE_TOLERANCE, half_area
from jaxbvh.program_store import stored_jit
from jaxbvh.tree.cost import goldsmith_salmon_cost
from jaxbvh.tree.layout import WideBVH

DEFAULT_MAX_CHILDREN = 8  # see the table in the module docstring


def check_order(order, n: int) -> np.ndarray:
    """``order`` as int32 [n] after checking that it is a permutation of ``0 .. n-1``."""
    a = np.asarray(order)
    if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"order must be an integer array of shape ({n},), got {a.dtype} {a.shape}")
    if not np.array_equal(np.sort(a), np.arange(n)):
        raise ValueError(f"order must be a permutation of 0 .. {n - 1} (each primitive once)")
    return a.astype(np.int32)



def check_max_children(max_children) -> int:
    """``max_children`` as an int after checking that it is an integer >= 2."""
    return integer(2)("max_children", max_children)


def pad_order(order, capacity: int) -> np.ndarray:
    """``order`` [..., n] padded with its own ids ``n .. capacity-1`` to [..., capacity] (never read)."""
    order = np.asarray(order, np.int32)
    n = order.shape[-1]
    tail = np.broadcast_to(np.arange(n, capacity, dtype=np.int32), order.shape[:-1] + (capacity - n,))
    return np.concatenate([order, tail], axis=-1)


def build(prim_lo, prim_hi, order=None, *, max_children: int = DEFAULT_MAX_CHILDREN,
          pad: bool = True, capacity: int | None = None, dtype=None) -> WideBVH:
    """Goldsmith–Salmon tree over primitive boxes, inserted in ``order``.

    Args:
      prim_lo, prim_hi: [n, 3] primitive boxes (scene-relative coordinates recommended,
        e.g. ``jaxbvh.io.Mesh.local_boxes()``).
      order: permutation of ``0 .. n-1``, the insertion order (default: ``0 .. n-1``).
      max_children: most children of a node (module docstring), >= 2.
      pad: pad to a capacity bucket (fewer recompiles) or size the arrays exactly.
      capacity: pad to exactly this many primitive slots instead (>= n).
      dtype: float32 (default) or float64 (needs x64).

    Returns:
      A :class:`~jaxbvh.tree.layout.WideBVH` of JAX arrays, child [2 * capacity, max_children]
      (layout: module docstring); its cost is :func:`jaxbvh.goldsmith_salmon_cost`.
    """
    k = check_max_children(max_children)
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, capacity=capacity, dtype=dtype)
    count = int(n)
    order = np.arange(count, dtype=np.int32) if order is None else check_order(order, count)
    trees, _ = insert_batch(lo, hi, jnp.asarray(pad_order(order[None], lo.shape[0])), n, scale, max_children=k)
    return tree_at(trees, 0)


def build_batch(prim_lo, prim_hi, orders, *, max_children: int = DEFAULT_MAX_CHILDREN,
                pad: bool = True, capacity: int | None = None, dtype=None):
    """One tree per order, all in one call: ``(trees, costs)``.

    ``orders``: [B, n] permutations (B >= 1); other arguments as :func:`build`.
    Returns a :class:`~jaxbvh.tree.layout.WideBVH` whose arrays have a leading batch axis
    [B, ...] (:func:`tree_at` picks one) and the costs [B]
    (:func:`jaxbvh.goldsmith_salmon_cost` of each tree).
    """
    k = check_max_children(max_children)
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, capacity=capacity, dtype=dtype)
    orders = np.asarray(orders)
    if orders.ndim != 2 or orders.shape[0] < 1:
        raise ValueError(f"orders must be [B, n] with B >= 1, got shape {orders.shape}")
    checked = np.stack([check_order(o, int(n)) for o in orders])
    return insert_batch(lo, hi, jnp.asarray(pad_order(checked, lo.shape[0])), n, scale, max_children=k)


def tree_at(trees, i: int) -> WideBVH:
    """Tree ``i`` of a batch made by :func:`build_batch` (fields [B, ...] -> one tree's)."""
    return jax.tree_util.tree_map(lambda a: a[i], trees)


# ----------------------------------------------------------------------------------
# The build (jitted): one while_loop step per insertion, all orders of a batch at once
# ----------------------------------------------------------------------------------
#
# The trees of a batch of B orders live in flat arrays of B * N rows (tree b's node x is
# row b * N + x; the ids stored in ``child`` and ``parent`` are the local x). The walks
# down and up carry only [B]-sized vectors, with a per-tree ``done`` flag: a
# ``jax.vmap`` of a one-tree build would turn each walk into a loop that selects its
# whole carry every step and makes XLA copy the tree arrays at every insertion (3x
# slower on a population of 50).


_UP_LIST = 16  # boxes grown per insertion without a loop that carries the table (speed only)

# Columns of the node table [B * N, 8]: box lo (3), box hi (3), area, child count.
_AREA, _COUNT = 6, 7


def _row(box_lo, box_hi, count, scale):
    """Node table rows [..., 8] for boxes [..., 3] and child counts [...]."""
    area = half_area(box_lo, box_hi, scale)
    return jnp.concatenate([box_lo, box_hi, area[..., None], count[..., None].astype(box_lo.dtype)], axis=-1)


def _holds(box_lo, box_hi, b_lo, b_hi):
    return jnp.all(box_lo <= b_lo, axis=-1) & jnp.all(box_hi >= b_hi, axis=-1)


class _Trees(NamedTuple):
    """The trees of a batch while they are built (the ``fori_loop`` carry)."""

    child: Any    # [B * N, K] int32: children of each row's node, in arrival order (-1: none)
    parent: Any   # [B * N] int32: each node's parent (-1: root or unused)
    table: Any    # [B * N, 8]: box lo, box hi, area, child count (_row)
    root: Any     # [B] int32: each tree's root
    next_id: Any  # [B] int32: the id the next interior node of each tree gets


class _Insertion(NamedTuple):
    """The insertion of one primitive into every tree: what the walks read."""

    p: Any         # [B] int32: the primitive, ``orders[:, t]``
    b_lo: Any      # [B, 3] its box
    b_hi: Any
    b_centre: Any  # [B, 3] lo + hi (twice the centre: no multiplication, exact ties)
    row0: Any      # [B] int32: first row of each tree
    near: Any      # 1 + TIE_TOLERANCE in the boxes' dtype
    scale: Any     # the scene's area scale


class _Walk(NamedTuple):
    """The walk down, per tree [B] (module docstring, Insertion)."""

    x: Any          # the current node
    x_parent: Any   # its parent (-1 at the root) and its slot there
    x_slot: Any
    inherited: Any  # I: how much the terms of the nodes above x grow
    best: Any       # the cheapest candidate so far (inf: none yet)
    m: Any          # that candidate's node, its parent and slot there, its child count
    m_parent: Any
    m_slot: Any
    m_count: Any
    m_area: Any     # A(m + b) and the box m + b
    m_lo: Any
    m_hi: Any
    done: Any       # bool: the walk has ended for this tree
    steps: Any      # int32 scalar: steps taken (bounded by the node count)


class _Climb(NamedTuple):
    """The walk up, per tree [B], first part: up to ``_UP_LIST`` grown boxes listed, not written."""

    a: Any        # the node whose box is grown next
    listed: Any   # [B, _UP_LIST] int32: rows grown so far (first loop), ``flat`` when none
    rows: Any     # [B, _UP_LIST, 8]: their grown table rows
    steps: Any    # int32 scalar: steps taken
    active: Any   # bool: a still needs growing


class _Growing(NamedTuple):
    """The walk up past the listed boxes (rare), per tree [B]: it writes as it goes."""

    a: Any       # the node whose box is grown next
    table: Any   # the node table (the carry: written every step)
    steps: Any   # int32 scalar: steps taken (bounded by the node count)
    active: Any  # bool: a still needs growing


def _grow_by(rows, b_lo, b_hi, scale):
    """``(box + b lo, hi, A(x+b), dA(x))`` of table rows [..., 8]; dA is 0 when x holds b."""
    x_lo, x_hi = rows[..., :3], rows[..., 3:6]
    u_lo, u_hi = jnp.minimum(x_lo, b_lo), jnp.maximum(x_hi, b_hi)
    grown = half_area(u_lo, u_hi, scale)
    holds = _holds(x_lo, x_hi, b_lo, b_hi)
    return u_lo, u_hi, grown, jnp.where(holds, jnp.zeros_like(grown), grown - rows[..., _AREA])


def _walk_down(trees: _Trees, ins: _Insertion, max_children, nodes) -> _Walk:
    """The cheapest insertion point of every tree (module docstring); reads only."""
    child, table = trees.child, trees.table
    batch = ins.p.shape[0]
    dtype = table.dtype
    inf = jnp.asarray(jnp.inf, dtype)

    def step(w: _Walk) -> _Walk:
        r = ins.row0 + w.x
        rows = table[r]
        u_lo, u_hi, grown, delta = _grow_by(rows, ins.b_lo, ins.b_hi, ins.scale)
        kf = rows[:, _COUNT]
        k = kf.astype(jnp.int32)
        leaf = k == 0
        own = kf * delta
        # the candidate here: a pair (leaf) or one more child (interior node with room)
        candidate = jnp.where(leaf, w.inherited + 2 * grown, (w.inherited + own) + grown)
        better = ~w.done & (leaf | (k < max_children)) & (candidate * ins.near < w.best)

        def pick(value, kept):
            return jnp.where(better if value.ndim == 1 else better[:, None], value, kept)

        w = w._replace(best=pick(candidate, w.best), m=pick(w.x, w.m), m_parent=pick(w.x_parent, w.m_parent),
                       m_slot=pick(w.x_slot, w.m_slot), m_count=pick(k, w.m_count), m_area=pick(grown, w.m_area),
                       m_lo=pick(u_lo, w.m_lo), m_hi=pick(u_hi, w.m_hi))
        # the child whose term rises least; then the nearest centre; then the lowest slot
        kids = child[r]  # [B, K]
        kid_rows = table[ins.row0[:, None] + jnp.maximum(kids, 0)]  # [B, K, 8]
        _, _, c_grown, c_delta = _grow_by(kid_rows, ins.b_lo[:, None], ins.b_hi[:, None], ins.scale)
        ck = kid_rows[..., _COUNT]
        rise = jnp.where(kids < 0, inf, jnp.where(ck == 0, 2 * c_grown, ck * c_delta))
        tied = rise <= jnp.min(rise, axis=1, keepdims=True) * ins.near
        d = jnp.abs((kid_rows[..., :3] + kid_rows[..., 3:6]) - ins.b_centre[:, None])
        slot = jnp.argmin(jnp.where(tied, (d[..., 0] + d[..., 1]) + d[..., 2], inf), axis=1).astype(jnp.int32)
        inherited = jnp.where(w.done, w.inherited, w.inherited + own)
        go = ~w.done & ~leaf
        return w._replace(x_parent=jnp.where(go, w.x, w.x_parent), x_slot=jnp.where(go, slot, w.x_slot),
                          x=jnp.where(go, jnp.take_along_axis(kids, slot[:, None], axis=1)[:, 0], w.x),
                          inherited=inherited, done=w.done | leaf | (inherited * ins.near >= w.best),
                          steps=w.steps + 1)

    minus = jnp.full(batch, -1, jnp.int32)
    zero_i = jnp.zeros(batch, jnp.int32)
    empty = jnp.zeros((batch, 3), dtype)
    start = _Walk(x=trees.root, x_parent=minus, x_slot=zero_i, inherited=jnp.zeros(batch, dtype),
                  best=jnp.full(batch, jnp.inf, dtype), m=trees.root, m_parent=minus, m_slot=zero_i,
                  m_count=zero_i, m_area=jnp.zeros(batch, dtype), m_lo=empty, m_hi=empty,
                  done=jnp.zeros(batch, bool), steps=jnp.int32(0))
    return jax.lax.while_loop(lambda w: jnp.any(~w.done) & (w.steps < nodes), step, start)


def _place(trees: _Trees, ins: _Insertion, w: _Walk) -> _Trees:
    """Insert b at the walk's winner m: a pair (m was a leaf) or one more child of m; writes only."""
    child, parent, table = trees.child, trees.parent, trees.table
    flat = table.shape[0]  # out-of-range row: scatters to it are dropped
    m, pm, count, p = w.m, w.m_parent, w.m_count, ins.p
    rm = ins.row0 + m
    pair = count == 0
    v = trees.next_id
    rv = jnp.where(pair, ins.row0 + v, flat)
    child = child.at[rv, 0].set(m, mode="drop")
    child = child.at[rv, 1].set(p, mode="drop")
    child = child.at[jnp.where(pair & (pm >= 0), ins.row0 + pm, flat), w.m_slot].set(v, mode="drop")
    child = child.at[jnp.where(pair, flat, rm), count].set(p, mode="drop")
    parent = parent.at[ins.row0 + p].set(jnp.where(pair, v, m))
    parent = parent.at[rv].set(pm, mode="drop")
    parent = parent.at[jnp.where(pair, rm, flat)].set(v, mode="drop")
    # the new node of a pair gets m's box grown by b; an m that takes b as a child
    # gets one more child (its box grows on the walk up)
    new_count = jnp.where(pair, 2, count + 1).astype(table.dtype)
    table = table.at[jnp.where(pair, rv, rm), _COUNT].set(new_count)
    table = table.at[rv, :_AREA].set(jnp.concatenate([w.m_lo, w.m_hi], axis=1), mode="drop")
    table = table.at[rv, _AREA].set(w.m_area, mode="drop")
    return _Trees(child=child, parent=parent, table=table, root=jnp.where(pair & (m == trees.root), v, trees.root),
                  next_id=trees.next_id + pair.astype(jnp.int32))


def _walk_up(trees: _Trees, ins: _Insertion, start, nodes) -> _Trees:
    """Grow the boxes from ``start`` [B] up until one already holds b.

    The first loop only reads: it lists up to ``_UP_LIST`` grown rows per tree, written
    after it; the second grows any further ones (rare), carrying the table.
    """
    parent, table = trees.parent, trees.table
    batch = ins.p.shape[0]
    flat = table.shape[0]

    def needs_growing(a, table):
        rows = table[ins.row0 + jnp.maximum(a, 0)]
        return (a >= 0) & ~_holds(rows[:, :3], rows[:, 3:6], ins.b_lo, ins.b_hi)

    def grown_rows(a, table):
        rows = table[ins.row0 + jnp.maximum(a, 0)]
        u_lo, u_hi = jnp.minimum(rows[:, :3], ins.b_lo), jnp.maximum(rows[:, 3:6], ins.b_hi)
        return _row(u_lo, u_hi, rows[:, _COUNT], ins.scale)

    def up(a, active):
        return jnp.where(active, parent[ins.row0 + jnp.maximum(a, 0)], a)

    def list_step(c: _Climb) -> _Climb:
        listed = c.listed.at[:, c.steps].set(jnp.where(c.active, ins.row0 + c.a, flat))
        rows = c.rows.at[:, c.steps].set(grown_rows(c.a, table))
        a = up(c.a, c.active)
        return _Climb(a=a, listed=listed, rows=rows, steps=c.steps + 1, active=c.active & needs_growing(a, table))

    climb = _Climb(a=start, listed=jnp.full((batch, _UP_LIST), flat, jnp.int32),
                   rows=jnp.zeros((batch, _UP_LIST, 8), table.dtype), steps=jnp.int32(0),
                   active=needs_growing(start, table))
    climb = jax.lax.while_loop(lambda c: jnp.any(c.active) & (c.steps < _UP_LIST), list_step, climb)
    table = table.at[climb.listed].set(climb.rows, mode="drop")

    def more_step(g: _Growing) -> _Growing:
        table = g.table.at[jnp.where(g.active, ins.row0 + g.a, flat)].set(grown_rows(g.a, g.table), mode="drop")
        a = up(g.a, g.active)
        return _Growing(a=a, table=table, steps=g.steps + 1, active=g.active & needs_growing(a, table))

    more = _Growing(a=climb.a, table=table, steps=jnp.int32(0), active=climb.active)
    more = jax.lax.while_loop(lambda g: jnp.any(g.active) & (g.steps < nodes), more_step, more)
    return trees._replace(table=more.table)


def _insert(t, trees: _Trees, lo, hi, orders, scale, max_children, nodes) -> _Trees:
    """Insert primitive ``orders[:, t]`` into every tree of the batch (module docstring).

    XLA updates the tree arrays in place only when every read of an array is ordered
    before every write to it by data dependence; otherwise it copies the arrays at
    every insertion (10x slower). So the walk down only reads (and returns all that
    the insertion needs: the parent and slot of the winning node come from the walk
    itself), the insertion only writes, and the walk up lists the grown boxes before
    they are written.
    """
    batch = orders.shape[0]
    p = orders[:, t]
    b_lo, b_hi = lo[p], hi[p]  # [B, 3]
    ins = _Insertion(p=p, b_lo=b_lo, b_hi=b_hi, b_centre=b_lo + b_hi,
                     row0=jnp.arange(batch, dtype=jnp.int32) * nodes,
                     near=jnp.asarray(1 + TIE_TOLERANCE, lo.dtype), scale=scale)
    w = _walk_down(trees, ins, max_children, nodes)
    placed = _place(trees, ins, w)
    return _walk_up(placed, ins, jnp.where(w.m_count == 0, w.m_parent, w.m), nodes)


@partial(stored_jit, static_argnames=("max_children",))
def insert_batch(lo, hi, orders, n, scale, *, max_children: int = DEFAULT_MAX_CHILDREN):
    """The build on prepared inputs (:func:`prepare`, :func:`pad_order`), one tree per order.

    ``orders`` [B, capacity] int32 (entries past ``n`` unused); ``n`` int32 scalar.
    Returns ``(trees, costs)``: a :class:`~jaxbvh.tree.layout.WideBVH` whose arrays have a
    leading axis [B, ...], and the costs [B] (:func:`jaxbvh.goldsmith_salmon_cost`).
    """
    batch, cap = orders.shape
    nodes = 2 * cap
    dtype = lo.dtype
    one_lo = jnp.full((nodes, 3), jnp.inf, dtype).at[:cap].set(lo)
    one_hi = jnp.full((nodes, 3), -jnp.inf, dtype).at[:cap].set(hi)
    one = _row(one_lo, one_hi, jnp.zeros(nodes, jnp.int32), scale)
    # every tree starts as its first primitive, a leaf; interior nodes get ids from n
    state = _Trees(child=jnp.full((batch * nodes, max_children), -1, jnp.int32),
                   parent=jnp.full(batch * nodes, -1, jnp.int32), table=jnp.tile(one, (batch, 1)),
                   root=orders[:, 0], next_id=jnp.full(batch, n, jnp.int32))

    def body(t, trees):
        return _insert(t, trees, lo, hi, orders, scale, max_children, nodes)

    child, parent, table, root, _ = jax.lax.fori_loop(1, n, body, state)
    ids = jnp.arange(nodes, dtype=jnp.int32)
    is_leaf = ids < n
    prim_ids = jnp.arange(cap, dtype=jnp.int32)

    def per_tree(a):
        return jnp.broadcast_to(a, (batch,) + a.shape)

    table = table.reshape(batch, nodes, 8)
    trees = WideBVH(child=child.reshape(batch, nodes, max_children), parent=parent.reshape(batch, nodes),
                    lo=table[..., :3], hi=table[..., 3:6],
                    prim_start=per_tree(jnp.where(is_leaf, ids, 0)), prim_count=per_tree(is_leaf.astype(jnp.int32)),
                    prim_index=per_tree(jnp.where(prim_ids < n, prim_ids, -1)), root=root)
    return trees, jax.vmap(goldsmith_salmon_cost)(trees)
