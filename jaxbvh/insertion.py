"""Goldsmith–Salmon insertion build: objects put into a tree one at a time (jitted).

Goldsmith & Salmon (1987), as Ng & Trifonov (2003, §4) use it to price an insertion
order. The tree is not binary: an interior node has 2 to ``max_children`` children.

Cost
====
A ray that hits a node's box tests all of the node's children, and it hits a box with
probability proportional to the box's surface area, so Goldsmith and Salmon price a
tree as ``sum over interior nodes of area x number of children`` (divided by the root's
area: :func:`jaxbvh.goldsmith_salmon_cost`). Areas here are half-areas of extents
scaled by the power of two that brings the scene's largest extent into [0.5, 1)
(:mod:`jaxbvh.cost`), and the insertion costs below are the exact changes of the
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

Tie rules (the NumPy reference :mod:`jaxbvh.reference.insertion` keeps the same ones).
Costs count as equal when they differ by at most a relative ``TIE_TOLERANCE`` (2^-20,
as in :mod:`jaxbvh.build`: XLA on CPU fuses multiply-adds, so a cost can come out one
ulp apart here and in NumPy):

* a deeper candidate replaces the cheapest so far only when ``cost * (1 + tol) <
  cheapest``, so among equal costs the shallowest wins, and the walk stops once
  ``I * (1 + tol) >= cheapest``;
* among children of equal ``rise`` (typically several boxes that already hold ``b``,
  all rising by 0) the walk takes the one whose box centre is nearest to ``b``'s in the
  L1 norm (Goldsmith and Salmon's suggestion; computed as ``|sum of corners of c - sum
  of corners of b|`` summed over x, y, z in that order, no multiplications, so exact
  ties are real), then the lowest child slot.

Layout of the result (a :class:`~jaxbvh.tree.WideBVH`, child ``[N, max_children]``)
=====================================================================================
Leaf ``p`` is node ``p`` and holds primitive ``p`` (``prim_start = p``, ``prim_count =
1``, ``prim_index[p] = p``); the ``j``-th interior node made is node ``n + j``, so real
nodes are ``0 .. 2n - 2`` and everything above is inert padding (``N = 2 * capacity``,
``capacity = capacity_bucket(n)``). Children sit in the order they arrived: a pair is
``[old node, b]`` in the slot the old node had, a new child takes the next free slot.
A node holding ``max_children`` children takes no more (the candidate *child* is not
offered there); ``max_children`` is the only departure from the 1987 algorithm, which
has no limit. Default 16: random orders of the shared meshes give arities of 2–6 in
all but a few nodes (legocar, whose large and tiny triangles mix, reached 50 once).

Loops. The build is one ``while_loop`` step per insertion. Inside it the walk down
and the walk up are ``while_loop`` s bounded by the node count. The whole build can be
``vmap``-ed over orders (:func:`build_batch`), which is how :mod:`jaxbvh.evolve`
prices a population.
"""

from __future__ import annotations

from functools import partial

import jax
import jax.numpy as jnp
import numpy as np

from jaxbvh.build import TIE_TOLERANCE, _working_dtype, check_prim_boxes, scene_scale
from jaxbvh.cost import goldsmith_salmon_cost, half_area
from jaxbvh.tree import WideBVH, capacity_bucket

DEFAULT_MAX_CHILDREN = 16


def check_order(order, n: int) -> np.ndarray:
    """``order`` as int32 [n] after checking that it is a permutation of ``0 .. n-1``."""
    a = np.asarray(order)
    if a.shape != (n,) or not np.issubdtype(a.dtype, np.integer):
        raise ValueError(f"order must be an integer array of shape ({n},), got {a.dtype} {a.shape}")
    if not np.array_equal(np.sort(a), np.arange(n)):
        raise ValueError(f"order must be a permutation of 0 .. {n - 1} (each primitive once)")
    return a.astype(np.int32)


def _check_max_children(max_children) -> int:
    k = int(max_children)
    if k < 2:
        raise ValueError(f"max_children must be >= 2, got {max_children}")
    return k


def prepare(prim_lo, prim_hi, *, pad: bool = True, dtype=None):
    """Checked, padded device inputs for :func:`insert_all`: ``(lo, hi, n, scale)``.

    ``lo``, ``hi``: [capacity, 3] with empty boxes (``+inf``, ``-inf``) past ``n``;
    ``scale``: the scene's power-of-two area scale (module docstring).
    """
    lo, hi = check_prim_boxes(prim_lo, prim_hi)
    dt = _working_dtype(dtype, lo.dtype)
    lo, hi = lo.astype(dt), hi.astype(dt)
    n = lo.shape[0]
    cap = capacity_bucket(n) if pad else n
    lo_p = np.full((cap, 3), np.inf, dt)
    hi_p = np.full((cap, 3), -np.inf, dt)
    lo_p[:n], hi_p[:n] = lo, hi
    return jnp.asarray(lo_p), jnp.asarray(hi_p), jnp.int32(n), jnp.asarray(scene_scale(lo, hi), dt)


def pad_order(order, capacity: int) -> np.ndarray:
    """``order`` [..., n] padded with its own ids ``n .. capacity-1`` to [..., capacity] (never read)."""
    order = np.asarray(order, np.int32)
    n = order.shape[-1]
    tail = np.broadcast_to(np.arange(n, capacity, dtype=np.int32), order.shape[:-1] + (capacity - n,))
    return np.concatenate([order, tail], axis=-1)


def build(prim_lo, prim_hi, order=None, *, max_children: int = DEFAULT_MAX_CHILDREN,
          pad: bool = True, dtype=None) -> WideBVH:
    """Goldsmith–Salmon tree over primitive boxes, inserted in ``order``.

    Args:
      prim_lo, prim_hi: [n, 3] primitive boxes (scene-relative coordinates recommended,
        e.g. ``jaxbvh.io.Mesh.local_boxes()``).
      order: permutation of ``0 .. n-1``, the insertion order (default: ``0 .. n-1``).
      max_children: most children of a node (module docstring), >= 2.
      pad: pad to a capacity bucket (fewer recompiles) or size the arrays exactly.
      dtype: float32 (default) or float64 (needs x64).

    Returns:
      A :class:`~jaxbvh.tree.WideBVH` of JAX arrays, child [2 * capacity, max_children]
      (layout: module docstring); its cost is :func:`jaxbvh.goldsmith_salmon_cost`.
    """
    k = _check_max_children(max_children)
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, dtype=dtype)
    count = int(n)
    order = np.arange(count, dtype=np.int32) if order is None else check_order(order, count)
    tree, _ = insert_all(lo, hi, jnp.asarray(pad_order(order, lo.shape[0])), n, scale, max_children=k)
    return tree


def build_batch(prim_lo, prim_hi, orders, *, max_children: int = DEFAULT_MAX_CHILDREN,
                pad: bool = True, dtype=None):
    """One tree per order, in one ``vmap``-ed call: ``(trees, costs)``.

    ``orders``: [B, n] permutations. Returns a :class:`~jaxbvh.tree.WideBVH` whose
    arrays have a leading batch axis [B, ...] and the costs [B]
    (:func:`jaxbvh.goldsmith_salmon_cost` of each tree).
    """
    k = _check_max_children(max_children)
    lo, hi, n, scale = prepare(prim_lo, prim_hi, pad=pad, dtype=dtype)
    orders = np.asarray(orders)
    if orders.ndim != 2:
        raise ValueError(f"orders must be [B, n], got shape {orders.shape}")
    checked = np.stack([check_order(o, int(n)) for o in orders]) if orders.shape[0] else orders
    return insert_batch(lo, hi, jnp.asarray(pad_order(checked, lo.shape[0])), n, scale, max_children=k)


def tree_at(trees, i: int) -> WideBVH:
    """Tree ``i`` of a batch made by :func:`build_batch`."""
    return jax.tree_util.tree_map(lambda a: a[i], trees)


# ----------------------------------------------------------------------------------
# The build (jitted): one while_loop step per insertion
# ----------------------------------------------------------------------------------


def _holds(box_lo, box_hi, b_lo, b_hi):
    return jnp.all(box_lo <= b_lo, axis=-1) & jnp.all(box_hi >= b_hi, axis=-1)


def _growth(box_lo, box_hi, b_lo, b_hi, scale):
    """``(A(x+b), dA(x))`` for boxes [..., 3]; ``dA`` is exactly 0 when the box holds ``b``."""
    u_lo, u_hi = jnp.minimum(box_lo, b_lo), jnp.maximum(box_hi, b_hi)
    grown = half_area(u_lo, u_hi, scale)
    same = jnp.all(u_lo == box_lo, axis=-1) & jnp.all(u_hi == box_hi, axis=-1)
    return grown, jnp.where(same, jnp.zeros_like(grown), grown - half_area(box_lo, box_hi, scale))


def _insert_one(t, s, lo, hi, order, scale, max_children):
    """Insert primitive ``order[t]`` into the tree state ``s`` (module docstring)."""
    child, nchild, parent, box_lo, box_hi, root, next_id = s
    nodes = child.shape[0]
    dtype = lo.dtype
    near = jnp.asarray(1 + TIE_TOLERANCE, dtype)
    inf = jnp.asarray(jnp.inf, dtype)
    p = order[t]
    b_lo, b_hi = lo[p], hi[p]
    b_centre = b_lo + b_hi

    # --- walk down: (node, inherited, cheapest, its node, done, steps)
    def down_cond(w):
        return ~w[4] & (w[5] < nodes)

    def down_body(w):
        x, inherited, best, best_node, _, steps = w
        grown, delta = _growth(box_lo[x], box_hi[x], b_lo, b_hi, scale)
        k = nchild[x]
        leaf = k == 0
        own = k.astype(dtype) * delta
        candidate = jnp.where(leaf, inherited + 2 * grown, (inherited + own) + grown)
        offered = leaf | (k < max_children)
        better = offered & (candidate * near < best)
        best = jnp.where(better, candidate, best)
        best_node = jnp.where(better, x, best_node)
        # the child whose term rises least
        kids = child[x]
        real = kids >= 0
        safe = jnp.where(real, kids, 0)
        c_lo, c_hi = box_lo[safe], box_hi[safe]
        c_grown, c_delta = _growth(c_lo, c_hi, b_lo, b_hi, scale)
        ck = nchild[safe]
        rise = jnp.where(ck == 0, 2 * c_grown, ck.astype(dtype) * c_delta)
        rise = jnp.where(real, rise, inf)
        tied = rise <= jnp.min(rise) * near
        d = jnp.abs((c_lo + c_hi) - b_centre)
        distance = jnp.where(tied, (d[:, 0] + d[:, 1]) + d[:, 2], inf)
        slot = jnp.argmax(tied & (distance == jnp.min(distance)))
        inherited = inherited + own
        done = leaf | (inherited * near >= best)
        return kids[slot], inherited, best, best_node, done, steps + 1

    zero = jnp.zeros((), dtype)
    walk = (root, zero, inf, root, jnp.zeros((), bool), jnp.int32(0))
    _, _, _, m, _, _ = jax.lax.while_loop(down_cond, down_body, walk)

    # --- insert at m: a pair (m was a leaf) or one more child of m
    none = nodes  # out-of-range id: scatters to it are dropped
    pair = nchild[m] == 0
    v = next_id
    pm = parent[m]
    has_parent = pm >= 0
    row = child[jnp.maximum(pm, 0)]
    slot_of_m = jnp.argmax(row == m)
    child = child.at[jnp.where(pair, v, none), 0].set(m, mode="drop")
    child = child.at[jnp.where(pair, v, none), 1].set(p, mode="drop")
    child = child.at[jnp.where(pair & has_parent, pm, none), slot_of_m].set(v, mode="drop")
    child = child.at[jnp.where(pair, none, m), nchild[m]].set(p, mode="drop")
    nchild = nchild.at[jnp.where(pair, v, m)].add(jnp.where(pair, 2, 1))
    parent = parent.at[p].set(jnp.where(pair, v, m))
    parent = parent.at[jnp.where(pair, v, none)].set(pm, mode="drop")
    parent = parent.at[jnp.where(pair, m, none)].set(v, mode="drop")
    box_lo = box_lo.at[jnp.where(pair, v, none)].set(jnp.minimum(box_lo[m], b_lo), mode="drop")
    box_hi = box_hi.at[jnp.where(pair, v, none)].set(jnp.maximum(box_hi[m], b_hi), mode="drop")
    root = jnp.where(pair & (m == root), v, root)
    next_id = next_id + pair.astype(jnp.int32)

    # --- walk up: grow boxes until one already holds b
    start = jnp.where(pair, jnp.where(has_parent, pm, -1), m)

    def up_cond(u):
        a, blo, bhi, steps = u
        safe = jnp.maximum(a, 0)
        return (a >= 0) & (steps < nodes) & ~_holds(blo[safe], bhi[safe], b_lo, b_hi)

    def up_body(u):
        a, blo, bhi, steps = u
        blo = blo.at[a].set(jnp.minimum(blo[a], b_lo))
        bhi = bhi.at[a].set(jnp.maximum(bhi[a], b_hi))
        return parent[a], blo, bhi, steps + 1

    _, box_lo, box_hi, _ = jax.lax.while_loop(up_cond, up_body, (start, box_lo, box_hi, jnp.int32(0)))
    return child, nchild, parent, box_lo, box_hi, root, next_id


def _insert_all(lo, hi, order, n, scale, max_children):
    cap = lo.shape[0]
    nodes = 2 * cap
    dtype = lo.dtype
    ids = jnp.arange(nodes, dtype=jnp.int32)
    is_leaf = ids < n
    box_lo = jnp.full((nodes, 3), jnp.inf, dtype).at[:cap].set(lo)
    box_hi = jnp.full((nodes, 3), -jnp.inf, dtype).at[:cap].set(hi)
    state = (jnp.full((nodes, max_children), -1, jnp.int32), jnp.zeros(nodes, jnp.int32),
             jnp.full(nodes, -1, jnp.int32), box_lo, box_hi, order[0], n)

    def body(t, s):
        return _insert_one(t, s, lo, hi, order, scale, max_children)

    child, _, parent, box_lo, box_hi, root, _ = jax.lax.fori_loop(1, n, body, state)
    prim_ids = jnp.arange(cap, dtype=jnp.int32)
    tree = WideBVH(child=child, parent=parent, lo=box_lo, hi=box_hi,
                   prim_start=jnp.where(is_leaf, ids, 0), prim_count=is_leaf.astype(jnp.int32),
                   prim_index=jnp.where(prim_ids < n, prim_ids, -1), root=root)
    return tree, goldsmith_salmon_cost(tree)


@partial(jax.jit, static_argnames=("max_children",))
def insert_all(lo, hi, order, n, scale, *, max_children: int = DEFAULT_MAX_CHILDREN):
    """The build on prepared inputs (:func:`prepare`, :func:`pad_order`): ``(tree, cost)``.

    ``order`` [capacity] int32 (entries past ``n`` unused); ``n`` int32 scalar.
    """
    return _insert_all(lo, hi, order, n, scale, max_children)


@partial(jax.jit, static_argnames=("max_children",))
def insert_batch(lo, hi, orders, n, scale, *, max_children: int = DEFAULT_MAX_CHILDREN):
    """:func:`insert_all` ``vmap``-ed over ``orders`` [B, capacity]: ``(trees [B, ...], costs [B])``."""
    return jax.vmap(lambda o: _insert_all(lo, hi, o, n, scale, max_children))(orders)
