"""The traversal loop shared by one-level and two-level trees: one ray, one bounded stack.

:mod:`jaxbvh.rays.traversal` (binary and wide BVHs) and :mod:`jaxbvh.twolevel.traversal`
(instances below a top level) walk a tree the same way; only what a *node reference* and
a *primitive slot* mean differs, and that is what the two hooks say:

* ``primitive(slot, tag) -> (t, u, v, prim)``: test the primitive in ``prim_index`` slot
  ``slot`` of the open leaf (``tag``: what the leaf was opened with) and name it;
* ``node(ref, tag, entry, t_far) -> Node``: look at the popped node ``ref`` (entered at
  ``entry``; ``tag`` pushed with it) and test the boxes of its children against the ray
  interval ``[t_min, t_far]``.

The one-level hooks read the tree and call the primitive intersector; the two-level ones
map the ray into an instance's frame below a top-level leaf and tag every stack entry
with its instance. Everything else lives here once: the loop state (:class:`Walk`), the
primitive step and its hit rules per mode, the node step (visit test, leaf opening,
counters, visiting order, push with overflow flag), the step bound and the
:class:`Hits` record. The rules themselves (counters, order, ties, bounds) are written in
:mod:`jaxbvh.rays.traversal`'s docstring.

Every loop step does one of two things, a primitive step while a leaf is open, else a
node step; both are computed and the other one masked out (a ``vmap``-ed loop runs both
branches anyway). The loop stops when the stack is empty and no leaf is open, at the
first hit in any-hit mode, or after ``step_limit`` steps; a ray still working at the
bound reports ``step_limit``, a push that does not fit reports ``stack_overflow``.
"""

from __future__ import annotations

import dataclasses
from typing import Any, Callable, NamedTuple

import jax
import jax.numpy as jnp

I32 = jnp.int32


@jax.tree_util.register_dataclass
@dataclasses.dataclass(frozen=True)
class Hits:
    """Per-ray results, every array [R].

    ``t`` float (``inf`` for a miss; in any-hit mode the first hit found), ``prim``
    int32 (-1 for a miss), ``u``, ``v`` barycentrics of the hit; counters int32
    ``box_tests``, ``prim_tests``, ``nodes_visited``, ``leaves_visited``;
    ``stack_overflow`` and ``step_limit`` bool (:mod:`jaxbvh.rays.traversal`). All-hits
    mode adds ``hit_count`` int32 [R], ``hit_prims`` int32 [R, H] (-1 past the end),
    ``hit_t`` float [R, H] and ``hits_overflow`` bool [R]; the other modes leave them None.
    Hits are distinct primitives: in a tree with references a triangle reached again
    from another leaf is not counted again (exact while the list holds every hit, i.e.
    without ``hits_overflow``).
    """

    t: Any
    prim: Any
    u: Any
    v: Any
    box_tests: Any
    prim_tests: Any
    nodes_visited: Any
    leaves_visited: Any
    stack_overflow: Any
    step_limit: Any
    hit_count: Any = None
    hit_prims: Any = None
    hit_t: Any = None
    hits_overflow: Any = None


class Node(NamedTuple):
    """What the ``node`` hook reports about one popped node (``k`` child slots).

    The walk uses the leaf fields only when ``is_leaf`` and the child fields only when
    not; both are computed either way.
    """

    is_leaf: Any     # bool []: the node is a leaf (open its run of primitives)
    leaf_start: Any  # int32 []: first prim_index slot of the leaf's run
    leaf_count: Any  # int32 []: primitives in the run
    leaf_tag: Any    # int32 [] or None: handed to ``primitive`` for the run (two-level: instance)
    assumed: Any     # bool [] or None: the node's box was assumed hit (skip flag), so its visit is not counted
    kids: Any        # int32 [k]: node references to push (garbage where ``kid_hit`` is False)
    kid_tags: Any    # int32 [] or [k] or None: tags pushed with the children
    kid_hit: Any     # bool [k]: real child whose box the ray enters within [t_min, t_far]
    kid_entry: Any   # float [k]: where the ray enters each child's box
    tested: Any      # bool [k]: child boxes actually tested (counted as box tests)
    split: Any       # int32 [] split axis (-1: none) or None: order by entry distance only
    direction: Any   # float [3]: the ray direction in the node's frame (axis order)


class Hooks(NamedTuple):
    """The two tree-specific functions of a walk (module docstring)."""

    primitive: Callable  # (slot, tag) -> (t, u, v, prim id) of the primitive in prim_index slot ``slot``
    node: Callable       # (ref, tag, entry, t_far) -> Node


class Found(NamedTuple):
    """The hits found so far (scalars unless noted)."""

    t: Any          # float: interval end; closest / any: the hit found (t_max while none), all: stays t_max
    prim: Any       # int32: id of the closest (any: first) hit, -1 while none
    u: Any          # float: barycentric u of that hit
    v: Any          # float: barycentric v of that hit
    best: Any       # float: all-hits mode only (else None): t of the closest hit so far
    count: Any      # int32: all-hits mode only: hits seen, listed or not
    prims: Any      # int32 [H]: all-hits mode only: ids of the first H hits in visiting order, -1 after
    ts: Any         # float [H]: all-hits mode only: their t, inf after


class Counts(NamedTuple):
    """The counters of :class:`Hits` (int32 scalars)."""

    box_tests: Any       # boxes tested, the root's included
    prim_tests: Any      # primitive tests
    nodes_visited: Any   # popped nodes that passed the entry test (skip-flagged ones excepted)
    leaves_visited: Any  # of those, the leaves


class Walk(NamedTuple):
    """Loop state of one ray."""

    sp: Any              # int32 []: stack entries in use; the top is sp - 1
    stack_node: Any      # int32 [capacity]: node reference of each entry (the hooks' numbering)
    stack_tag: Any       # int32 [capacity] or None: tag of each entry (two-level: instance, -1 top level)
    stack_entry: Any     # float [capacity]: where the ray enters the entry's box
    leaf_pos: Any        # int32 []: next prim_index slot of the open leaf
    leaf_end: Any        # int32 []: end of the open leaf's run (leaf_pos == leaf_end: no leaf open)
    leaf_tag: Any        # int32 [] or None: tag the open leaf was opened with
    found: Found         # hits so far
    counts: Counts       # counters
    stack_overflow: Any  # bool []: a push did not fit (hit and counts then untrustworthy)
    done: Any            # bool []: any-hit mode found its hit
    steps: Any           # int32 []: loop steps taken (bounded by step_limit)


def walk(hooks: Hooks, root, root_hit, root_entry, t_min, t_max, *, mode: str, capacity: int,
         max_hits: int, step_limit, tagged: bool = False) -> Walk:
    """Trace one ray from ``root`` (a node reference) to the end; returns the final :class:`Walk`.

    ``root_hit``, ``root_entry``: the root box test (made by the caller, counted here as
    one box test); ``t_min``, ``t_max``: the open ray interval (float scalars, the walk's
    dtype); ``mode``: "closest", "any" or "all"; ``capacity``: static stack size;
    ``max_hits``: all-hits list length; ``step_limit``: the loop bound (int or int32
    scalar); ``tagged``: entries carry tags (``Node.leaf_tag``, ``Node.kid_tags``).
    """
    state = _start(root, root_hit, root_entry, t_max, mode=mode, capacity=capacity,
                   max_hits=max_hits, tagged=tagged)

    def cond(s):
        return working(s) & (s.steps < step_limit)

    def body(s):
        # decided once, before the primitive step: a leaf that ends in this step must not
        # also pop (its stack may be empty; the top entry would then be stale)
        in_leaf = s.leaf_pos < s.leaf_end
        s = s._replace(steps=s.steps + 1)
        s = _primitive_step(hooks, s, in_leaf, t_min, t_max, mode=mode, max_hits=max_hits)
        return _node_step(hooks, s, ~in_leaf, capacity=capacity)

    return jax.lax.while_loop(cond, body, state)


def working(s: Walk):
    """The ray has work left (bool []): not done, and a stack entry or an open leaf."""
    return ~s.done & ((s.sp > 0) | (s.leaf_pos < s.leaf_end))


def _start(root, root_hit, root_entry, t_max, *, mode, capacity, max_hits, tagged) -> Walk:
    dtype = t_max.dtype
    all_hits = mode == "all"
    found = Found(t=t_max, prim=I32(-1), u=jnp.zeros((), dtype), v=jnp.zeros((), dtype),
                  best=t_max if all_hits else None,
                  count=I32(0) if all_hits else None,
                  prims=jnp.full(max_hits, -1, I32) if all_hits else None,
                  ts=jnp.full(max_hits, jnp.inf, dtype) if all_hits else None)
    return Walk(
        sp=jnp.where(root_hit, 1, 0).astype(I32),
        stack_node=jnp.zeros(capacity, I32).at[0].set(root),
        stack_tag=jnp.full(capacity, -1, I32) if tagged else None,
        stack_entry=jnp.full(capacity, jnp.inf, dtype).at[0].set(root_entry),
        leaf_pos=I32(0), leaf_end=I32(0), leaf_tag=I32(0) if tagged else None,
        found=found, counts=Counts(box_tests=I32(1), prim_tests=I32(0), nodes_visited=I32(0),
                                   leaves_visited=I32(0)),
        stack_overflow=jnp.zeros((), bool), done=jnp.zeros((), bool), steps=I32(0))


def _primitive_step(hooks, s: Walk, in_leaf, t_min, t_max, *, mode, max_hits) -> Walk:
    """Test the open leaf's next primitive (masked out unless ``in_leaf``)."""
    t, u, v, prim = hooks.primitive(s.leaf_pos, s.leaf_tag)
    valid = in_leaf & (t > t_min) & (t < t_max)
    found = _record(s.found, valid, t, u, v, prim, mode=mode, max_hits=max_hits)
    counts = s.counts._replace(prim_tests=s.counts.prim_tests + in_leaf.astype(I32))
    return s._replace(found=found, counts=counts, leaf_pos=s.leaf_pos + in_leaf.astype(I32),
                      done=valid if mode == "any" else s.done)


def _record(f: Found, valid, t, u, v, prim, *, mode, max_hits) -> Found:
    """Keep a valid hit by the mode's rule: any takes it; closest and all keep the
    smallest ``t`` (equal ``t``: lower id); all also lists it. Closest and any shrink the
    interval (``f.t``); all keeps it whole and tracks the closest in ``f.best``."""
    best = f.best if mode == "all" else f.t
    if mode == "any":
        take = valid
    else:
        take = valid & ((t < best) | ((t == best) & (prim < f.prim)))
    if mode == "all":
        # a tree with references (spatial splits) reaches one triangle from several
        # leaves: a primitive already listed is the same hit, not a new one
        valid = valid & ~jnp.any(f.prims == prim)
        take = take & valid
        slot = jnp.where(valid & (f.count < max_hits), f.count, max_hits)
        f = f._replace(best=jnp.where(take, t, best),
                       prims=f.prims.at[slot].set(prim, mode="drop"),
                       ts=f.ts.at[slot].set(t, mode="drop"),
                       count=f.count + valid.astype(I32))
    else:
        f = f._replace(t=jnp.where(take, t, f.t))
    return f._replace(prim=jnp.where(take, prim, f.prim), u=jnp.where(take, u, f.u),
                      v=jnp.where(take, v, f.v))


def _node_step(hooks, s: Walk, pop, *, capacity) -> Walk:
    """Pop the top entry (masked out unless ``pop``); a visited leaf opens, a visited
    interior node pushes the children the ray enters, nearest on top."""
    top = jnp.maximum(s.sp - 1, 0)
    entry = s.stack_entry[top]
    # closest: cull against the best hit; any / all: found.t stays t_max
    visit = pop & (entry <= s.found.t)
    node = hooks.node(s.stack_node[top], None if s.stack_tag is None else s.stack_tag[top],
                      entry, s.found.t)
    counted = visit if node.assumed is None else visit & ~node.assumed
    open_leaf = visit & node.is_leaf
    expand = visit & ~node.is_leaf
    c = s.counts
    counts = c._replace(
        nodes_visited=c.nodes_visited + counted.astype(I32),
        leaves_visited=c.leaves_visited + open_leaf.astype(I32),
        box_tests=c.box_tests + jnp.where(expand, jnp.sum(node.tested), 0).astype(I32))
    s = s._replace(
        counts=counts,
        leaf_pos=jnp.where(open_leaf, node.leaf_start, s.leaf_pos),
        leaf_end=jnp.where(open_leaf, node.leaf_start + node.leaf_count, s.leaf_end),
        leaf_tag=None if s.leaf_tag is None else jnp.where(open_leaf, node.leaf_tag, s.leaf_tag))
    return _push(s, node, node.kid_hit & expand, pop, top, capacity=capacity)


def _visit_key(node: Node):
    """Sort key of the children [k] (smaller first): by slot along the split axis (lower
    child first when the direction is >= 0 there), else by entry distance."""
    if node.split is None:
        return node.kid_entry
    k = node.kid_entry.shape[0]
    slot_ids = jnp.arange(k)
    lower_first = node.direction[jnp.maximum(node.split, 0)] >= 0
    by_axis = jnp.where(lower_first, slot_ids, k - 1 - slot_ids).astype(node.kid_entry.dtype)
    return jnp.where(node.split >= 0, by_axis, node.kid_entry)


def _push(s: Walk, node: Node, kid_hit, pop, top, *, capacity) -> Walk:
    """Replace the popped entry by the children hit, in visiting order, nearest on top;
    children that do not fit are dropped and flagged."""
    key = _visit_key(node)
    slot_ids = jnp.arange(key.shape[0])
    before = (key[:, None] < key[None, :]) | (
        (key[:, None] == key[None, :]) & (slot_ids[:, None] < slot_ids[None, :]))
    rank = jnp.sum(kid_hit[:, None] & before, axis=0)  # visiting position of each kid
    n_push = jnp.sum(kid_hit).astype(I32)
    pos = top + n_push - 1 - rank  # nearest on top
    fits = pos < capacity
    pos = jnp.where(kid_hit & fits, pos, capacity)
    stack_tag = s.stack_tag
    if stack_tag is not None:
        stack_tag = stack_tag.at[pos].set(node.kid_tags, mode="drop")
    return s._replace(
        stack_node=s.stack_node.at[pos].set(node.kids, mode="drop"),
        stack_tag=stack_tag,
        stack_entry=s.stack_entry.at[pos].set(node.kid_entry, mode="drop"),
        stack_overflow=s.stack_overflow | jnp.any(kid_hit & ~fits),
        sp=jnp.where(pop, jnp.minimum(top + n_push, capacity), s.sp))


def finish(s: Walk, *, mode: str, max_hits: int) -> Hits:
    """The :class:`Hits` of one finished walk (scalars; all-hits lists [max_hits])."""
    f, c = s.found, s.counts
    hit = f.prim >= 0
    best = f.best if mode == "all" else f.t
    extra = {}
    if mode == "all":
        extra = dict(hit_count=f.count, hit_prims=f.prims, hit_t=f.ts, hits_overflow=f.count > max_hits)
    return Hits(t=jnp.where(hit, best, jnp.inf), prim=f.prim, u=f.u, v=f.v,
                box_tests=c.box_tests, prim_tests=c.prim_tests, nodes_visited=c.nodes_visited,
                leaves_visited=c.leaves_visited, stack_overflow=s.stack_overflow,
                step_limit=working(s), **extra)
