"""A stackless walk over a binary or wide BVH by parent links: its state does not grow with depth.

The walk of one query (Hapala, Davidovič, Wald, Havran and Slusallek 2011, "Efficient
stack-less BVH traversal for ray tracing", generalised to ``k`` children and to any
order key) keeps only the node it stands on and whether it arrived there going down or
coming back up; the tree's ``parent`` array says where to go back to. So one query
carries a few scalars, whatever the tree's height, and a 6,000-deep chain costs per step
what a 20-deep tree does (a stack sized by the height costs ``height`` per step).

Order. The children of a node are visited in increasing *order key*, ties to the lower
child slot. The key must depend only on the query and the child's box, never on what
was found so far (closest point: the box's distance to the point; ray: the entry
distance; box and radius queries: 0, i.e. slot order), so that coming back up from a
child the walk can recompute the order and continue with the next child in it.

Culling. A child is entered only if the query still *keeps* it (closest point: its box
is no farther than the best distance so far; radius: no farther than the radius; box:
its box overlaps). The decision is taken when the walk would enter the child, with the
best result known then, so a closest-point walk prunes as well as a stack walk that
culls at pop time.

Steps. A step tests one primitive of the open leaf, or else makes one node move: down
into the next kept child of the node (a leaf opens its run of primitives at once), or up
to the parent when no kept child is left. Both are computed and one is masked out (a
``vmap``-ed loop runs both anyway). A node move tests the boxes of all ``k`` children of
the node it looks at (``box_tests`` counts them; going up re-tests the parent's, which is
the price of having no stack). In a valid tree a walk goes down into every node at most
once and up out of it at most once and tests every primitive slot at most once, so it is
cut off after ``2 N + P + 2`` steps (node and slot capacities): a broken tree (a cycle, a
wrong parent link) cannot make it run forever, and a query still working at the bound
reports ``step_limit``.

Counters (int32): ``box_tests`` (the root's included), ``prim_tests``, ``nodes_visited``
(nodes entered going down, the root included) and ``leaves_visited`` (of those, leaves).

The twin, written for one query at a time in NumPy, is
:func:`jaxbvh.queries.search_reference.walk`.
"""

from __future__ import annotations

from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.tree.layout import BVH

I32 = jnp.int32


class Counts(NamedTuple):
    """The counters of one walk (int32 scalars; module docstring)."""

    box_tests: Any
    prim_tests: Any
    nodes_visited: Any
    leaves_visited: Any


class Hooks(NamedTuple):
    """What a query says about boxes and primitives (the walk knows neither)."""

    boxes: Callable      # (lo [k, 3], hi [k, 3], found) -> (key [k] float, keep [k] bool)
    primitive: Callable  # (found, prim id int32 [], active bool []) -> found (unchanged unless active)
    stop: Callable | None = None  # found -> bool []: the query is answered (any hit); None: never


class _State(NamedTuple):
    node: Any       # int32 []: the node the walk stands on
    up: Any         # bool []: it came back up out of ``node`` (its subtree is done)
    leaf_pos: Any   # int32 []: next prim_index slot of the open leaf
    leaf_end: Any   # int32 []: end of the open leaf's run (leaf_pos == leaf_end: none open)
    found: Any      # the query's results so far (its own pytree)
    counts: Counts
    done: Any       # bool []
    steps: Any      # int32 []


def children(tree, node):
    """Child ids [k] int32 of ``node`` (-1: no child)."""
    if isinstance(tree, BVH):
        return jnp.stack([tree.left[node], tree.right[node]])
    return tree.child[node]


def step_bound(tree) -> int:
    """Steps one walk may take, ``2 N + P + 2`` (static: from the arrays' shapes)."""
    return 2 * int(tree.prim_count.shape[0]) + int(tree.prim_index.shape[0]) + 2


def walk(tree, hooks: Hooks, found):
    """Walk ``tree`` (:class:`~jaxbvh.tree.layout.BVH` or :class:`~jaxbvh.tree.layout.WideBVH`,
    JAX arrays) for one query; ``found``: the query's starting results.

    Returns ``(found, counts, step_limit)``: the final results, :class:`Counts` and
    whether the walk was cut off by :func:`step_bound` (results then incomplete).
    """
    root = tree.root.astype(I32)
    n_slots = tree.prim_index.shape[0]
    _, root_keep = hooks.boxes(tree.lo[root][None], tree.hi[root][None], found)
    root_keep = root_keep[0]
    root_leaf = tree.prim_count[root] > 0
    opened = root_keep & root_leaf
    start = tree.prim_start[root]
    state = _State(
        node=root, up=root_leaf, leaf_pos=jnp.where(opened, start, 0).astype(I32),
        leaf_end=jnp.where(opened, start + tree.prim_count[root], 0).astype(I32), found=found,
        counts=Counts(box_tests=I32(1), prim_tests=I32(0), nodes_visited=root_keep.astype(I32),
                      leaves_visited=opened.astype(I32)),
        done=~root_keep, steps=I32(0))
    limit = step_bound(tree)

    def cond(s):
        return ~s.done & (s.steps < limit)

    def body(s):
        in_leaf = s.leaf_pos < s.leaf_end
        # primitive step (masked out unless a leaf is open)
        prim = tree.prim_index[jnp.clip(s.leaf_pos, 0, n_slots - 1)]
        found = hooks.primitive(s.found, prim, in_leaf)
        c = s.counts._replace(prim_tests=s.counts.prim_tests + in_leaf.astype(I32))

        # node move (masked out while a leaf is open)
        finished = s.up & (s.node == root)
        moving = ~in_leaf & ~finished
        here = jnp.where(s.up, tree.parent[s.node], s.node)  # the node whose children we look at
        kids = children(tree, jnp.maximum(here, 0))
        real = kids >= 0
        safe = jnp.maximum(kids, 0)
        key, keep = hooks.boxes(tree.lo[safe], tree.hi[safe], found)
        slots = jnp.arange(kids.shape[0])
        before = real[:, None] & ((key[:, None] < key[None, :]) |
                                  ((key[:, None] == key[None, :]) & (slots[:, None] < slots[None, :])))
        rank = jnp.sum(before, axis=0)  # visiting position of every child
        came_from = jnp.where(s.up, jnp.sum(jnp.where(kids == s.node, rank, 0)), -1)
        candidate = real & keep & (rank > came_from)
        down = moving & jnp.any(candidate)
        nxt = kids[jnp.argmin(jnp.where(candidate, rank, kids.shape[0]))]
        nxt_safe = jnp.maximum(nxt, 0)
        nxt_leaf = tree.prim_count[nxt_safe] > 0
        open_leaf = down & nxt_leaf
        start = tree.prim_start[nxt_safe]
        c = c._replace(box_tests=c.box_tests + jnp.where(moving, jnp.sum(real), 0).astype(I32),
                       nodes_visited=c.nodes_visited + down.astype(I32),
                       leaves_visited=c.leaves_visited + open_leaf.astype(I32))
        done = s.done | (~in_leaf & finished)
        if hooks.stop is not None:
            done = done | hooks.stop(found)
        return _State(
            node=jnp.where(down, nxt, jnp.where(moving, here, s.node)).astype(I32),
            # a leaf is done going down as soon as it opens: after its run the walk goes up
            up=jnp.where(down, nxt_leaf, s.up | moving),
            leaf_pos=jnp.where(open_leaf, start, s.leaf_pos + in_leaf.astype(I32)).astype(I32),
            leaf_end=jnp.where(open_leaf, start + tree.prim_count[nxt_safe], s.leaf_end).astype(I32),
            found=found, counts=c, done=done, steps=s.steps + 1)

    end = jax.lax.while_loop(cond, body, state)
    return end.found, end.counts, ~end.done
