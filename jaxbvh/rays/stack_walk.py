"""The traversal loop shared by one-level and two-level trees: lanes of rays, a short stack each.

:mod:`jaxbvh.rays.traversal` (binary and wide BVHs) and :mod:`jaxbvh.twolevel.traversal`
(instances below a top level) walk a tree the same way; only what a *node reference* and
a *primitive slot* mean differs, and that is what the two hooks say:

* ``primitive(slot, tag) -> (t, u, v, prim)``: test the primitive in ``prim_index`` slot
  ``slot`` of the open leaf (``tag``: what the leaf was opened with) and name it;
* ``node(ref, tag, entry, t_far) -> Node``: look at the popped node ``ref`` (entered at
  ``entry``; ``tag`` pushed with it), test the boxes of its children against the ray
  interval ``[t_min, t_far]``, and say which node is above it (``Node.parent``, for the
  climb below; walks without parent links pass ``climbs=False``: a spill is then an
  overflow).

The one-level hooks read the tree and call the primitive intersector; the two-level ones
map the ray into an instance's frame below a top-level leaf and tag every stack entry
with its instance. Everything else lives here once: the loop state (:class:`Walk`), the
primitive step and its hit rules per mode, the node step (visit test, leaf opening,
counters, visiting order, push with overflow flag), the step bound and the
:class:`Hits` record. The rules themselves (counters, order, ties, bounds) are written in
:mod:`jaxbvh.rays.traversal`'s docstring.

:func:`walk_rays` runs one ``while_loop`` over ``lanes`` rays at once. In every step each
lane does one of two things for its ray, a primitive step while a leaf is open (the next
``leaf_width`` slots), else a node step (a pop); both are computed and the other one
masked out. Climb steps (below) have a pass of their own before it, run only in the
steps where some lane needs one.
A ray ends when its stack is empty and no leaf is open (and it has nothing left to climb),
at the first hit in any-hit mode, or after ``step_limit`` steps (node pops, primitive
tests and climb steps); a ray still working at the bound reports ``step_limit``.

Short stack, parent-link climb. A lane's stack holds ``capacity`` entries (a static
:data:`STACK`, whatever the tree's depth, so the lanes' state does not grow with depth and
one program serves trees of every depth). It is a ring: a push that does not fit
overwrites the *oldest* entries (the bottom), which in a depth-first walk are the last
ones it would visit. When the stack runs empty after such a spill, the work left is
exactly those lost entries, i.e. the nodes after the last popped node in visiting
order; the walk finds them by parent links (Hapala et al. 2011): a *climb step* looks at
the parent of the node it stands on, tests the boxes of its children again, and pushes
the first child after that node in visiting order whose box the ray still enters (then
pops on as usual), or, if none is left, moves up to the parent; at the root the ray ends.
This needs an order that can be recomputed: the visit key of a child depends only on the
ray and the child's box (the entry distance, or the split axis), never on the hits found;
a child assumed hit (skip flags) comes first (key ``-inf``), and in a climb it is entered
at ``t_min``. A child pushed and later dropped passes the same test in the climb
(``entry <= min(far, t_best)`` then is ``entry <= far`` at the push and
``entry <= t_best`` at the pop), so nodes visited, leaves visited, primitive tests, the
hits and the all-hits list are those of an unbounded stack (one exception: a skip-flagged
child that the stack walk would cull, entered where its parent was but beyond the hit
found since, is visited after a climb: visits can only grow); a climb adds its box tests
(the children of the parent, tested again) and a step. Without parent links
(``climbs=False``) a spill sets ``stack_overflow`` (hits and counts then untrustworthy).
Every ``REFILL_EVERY`` steps the lanes whose ray ended write its :class:`Hits` and take
the next rays (a wavefront). The stacks [lanes, capacity] are not part of the per-lane
state that the step maps over: a step gathers each lane's top entry and scatters its
pushes, so its cost does not grow with the capacity.

In one step a lane makes its node step first and then its primitive step, so a leaf
popped in a step is tested in it too: a step costs one pop, not a pop and a test.

Measured (bench/results/ray_anatomy.md, 2-core CPU): a step costs about 60 us plus
0.35-0.5 us per lane, so its time is per-lane work, not the loop's overhead; that work
is spread over ~160 compiled kernels per step, of which the two row reads (the node's
row, the leaf run's rows; cache misses) are a third. Hence the packed layout of
:mod:`jaxbvh.rays.traversal` (one read per node, one per leaf run, their indices made
apart from the reads) and lanes that do not pop reading one fixed node.
"""

from __future__ import annotations

import dataclasses
from functools import partial
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
    parent: Any = None      # int32 [] or None: reference of the node above ``ref`` (walks that climb)
    parent_tag: Any = None  # int32 [] or None: its tag (tagged walks)


class Hooks(NamedTuple):
    """The tree-specific functions of a walk (module docstring)."""

    primitive: Callable  # (slot, tag) -> (t, u, v, prim id) of the primitive in prim_index slot ``slot``
    node: Callable       # (ref, tag, entry, t_far) -> Node
    # optional (start, tag, width) -> (t, u, v, prim id) [width] of slots start .. start + width - 1
    # read as one run (slots past the leaf are masked by the walk); None: ``primitive`` per slot
    run: Callable | None = None


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
    """Loop state of one lane (one ray at a time), its stack excepted (:class:`Stacks`)."""

    ray: Any             # int32 []: the ray this lane traces (-1: none)
    sp: Any              # int32 []: logical stack height; the top is entry sp - 1, held in slot (sp - 1) % capacity
    base: Any            # int32 []: entries below this one were overwritten (spilled); sp == base: stack empty
    last: Any            # int32 []: the node last popped, or climbed to (where a climb starts)
    last_tag: Any        # int32 [] or None: its tag
    up: Any              # int32 []: the node above ``last`` (read with it: a climb needs no extra read)
    up_tag: Any          # int32 [] or None: its tag
    leaf_pos: Any        # int32 []: next prim_index slot of the open leaf
    leaf_end: Any        # int32 []: end of the open leaf's run (leaf_pos == leaf_end: no leaf open)
    leaf_tag: Any        # int32 [] or None: tag the open leaf was opened with
    found: Found         # hits so far
    counts: Counts       # counters
    stack_overflow: Any  # bool []: the stack spilled and there are no parent links (hit and counts untrustworthy)
    done: Any            # bool []: any-hit mode found its hit, or the climb reached the root
    steps: Any           # int32 []: steps taken (node pops + primitive tests + climbs), bounded by step_limit


class Stacks(NamedTuple):
    """The lanes' stacks, [L, capacity] each; kept out of the per-lane state so that a
    step reads and writes only the entries it pops and pushes (a ``vmap``-ed
    ``while_loop`` would select the whole carry, every stack entry, every step)."""

    node: Any   # int32: node reference of each entry (the hooks' numbering)
    tag: Any    # int32 or None: tag of each entry (two-level: instance, -1 top level)
    entry: Any  # float: where the ray enters the entry's box


class Ray(NamedTuple):
    """What the walk needs of ray ``i`` (``ray(i)`` in :func:`walk_rays`)."""

    hooks: Hooks     # the tree's hooks, bound to this ray
    root: Any        # int32 []: the root's node reference
    root_hit: Any    # bool []: the ray meets the root box within its interval
    root_entry: Any  # float []: where it enters the root box
    t_min: Any       # float []: open interval start
    t_max: Any       # float []: open interval end


MODES = ("closest", "any", "all")
"""The walk's modes: closest hit, any hit (stops at the first), all hits (lists them)."""

# One source of truth for the walk's throughput knobs (static: each value is a compile).
LANES = 512
"""Rays in flight per call: lanes whose ray ended take the next ray (a wavefront), so a
call runs for about (total steps / lanes), not for its slowest ray times the batches."""
STACK = 64
"""Default stack entries per lane, whatever the tree's depth: trees with parent links
climb when it spills (module docstring). Balanced trees of a few million primitives
need fewer, so for them the walk is the plain stack walk."""
STACK_ENTRIES = 1 << 21
"""Upper bound of lanes * stack capacity (two int32/float arrays of this size): a caller
that asks for a huge stack gets fewer lanes rather than a huge carry."""
LEAF_WIDTH = 4
"""Primitive slots of an open leaf tested together in one step (closest and any hit; all
hits test one per step, to list them in order)."""
REFILL_EVERY = 4
"""Steps between refills: a refill costs about as much as a step, and a lane whose ray
ended idles at most this many steps minus one."""


def lanes_for(rays: int, capacity: int, lanes: int | None = None) -> int:
    """Lanes of a call tracing ``rays`` rays with stacks of ``capacity`` (host, static)."""
    lanes = LANES if lanes is None else int(lanes)
    return max(1, min(lanes, rays, max(32, STACK_ENTRIES // max(capacity, 1))))


def walk_rays(ray: Callable, n_rays: int, *, mode: str, capacity: int, max_hits: int, step_limit,
              lanes: int, leaf_width: int, tagged: bool = False, climbs: bool = True) -> Hits:
    """Trace rays ``0 .. n_rays - 1`` on ``lanes`` lanes; returns :class:`Hits` [n_rays].

    ``ray(i) -> Ray`` (``i`` int32 []): the hooks and root test of ray ``i`` (made
    under ``vmap``, so it reads per-ray arrays by index). ``mode``: "closest", "any" or
    "all"; ``capacity``: static stack size per lane (at least the tree's arity);
    ``max_hits``: all-hits list length; ``step_limit``: a ray's bound on steps (int or
    int32 []); ``leaf_width``: primitive slots tested per step (all-hits mode uses 1);
    ``tagged``: entries carry tags; ``climbs``: the node hook reports parents
    (``Node.parent``), so a spilled stack climbs; else a spill is an overflow.

    One ``while_loop`` steps every lane at once. Before each step a lane whose ray ended
    (no work left, or at the step bound) writes the ray's :class:`Hits` and takes the
    next ray not yet started, so lanes do not idle behind the slowest ray. Each lane's
    walk is the one-ray walk of the module docstring; results do not depend on ``lanes``.
    """
    width = 1 if mode == "all" else max(1, int(leaf_width))
    lane_ids = jnp.arange(lanes)

    def fresh(i):
        r = ray(i)
        return (_start(i, r.root, r.root_hit, r.t_max, mode=mode, max_hits=max_hits, tagged=tagged),
                r.root, r.root_entry)

    s0, _, entry0 = jax.vmap(fresh)(jnp.zeros(lanes, I32))
    s0 = s0._replace(ray=jnp.full(lanes, -1, I32))
    dtype = entry0.dtype
    stacks = Stacks(node=jnp.zeros((lanes, capacity), I32),
                    tag=jnp.full((lanes, capacity), -1, I32) if tagged else None,
                    entry=jnp.full((lanes, capacity), jnp.inf, dtype))
    finish_lane = jax.vmap(partial(finish, mode=mode, max_hits=max_hits))
    out = jax.tree_util.tree_map(lambda x: jnp.zeros((n_rays,) + x.shape[1:], x.dtype), finish_lane(s0))

    def live(s):
        return (s.ray >= 0) & working(s) & (s.steps < step_limit)

    def refill(s, stacks, out, next_ray):
        has = s.ray >= 0
        free = ~live(s)
        retire = has & free
        # a lane whose ray ended writes its record, then takes the next ray
        where_out = jnp.where(retire, s.ray, n_rays)
        out = jax.tree_util.tree_map(lambda o, h: o.at[where_out].set(h, mode="drop"), out, finish_lane(s))
        new_id = next_ray + jnp.cumsum(free.astype(I32)) - 1
        take = free & (new_id < n_rays)
        f, root, root_entry = jax.vmap(fresh)(jnp.where(take, new_id, 0))
        s = jax.tree_util.tree_map(lambda a, b: _select(take, a, b), f, s)
        s = s._replace(ray=jnp.where(take, new_id, jnp.where(retire, -1, s.ray)))
        col = jnp.where(take, 0, capacity)
        stacks = Stacks(node=stacks.node.at[lane_ids, col].set(root, mode="drop"),
                        tag=None if stacks.tag is None else stacks.tag.at[lane_ids, col].set(-1, mode="drop"),
                        entry=stacks.entry.at[lane_ids, col].set(root_entry, mode="drop"))
        return s, stacks, out, next_ray + jnp.sum(take, dtype=I32)

    def lane_step(s, top_node, top_tag, top_entry):
        r = ray(jnp.maximum(s.ray, 0))
        go = live(s)
        # the node step first, then the primitive step: a leaf popped in this step is
        # tested in it too (one iteration per pop, not two). A leaf still open from the
        # last step blocks the pop: the order of the walk's steps is the one-ray order.
        pop = go & (s.leaf_pos >= s.leaf_end) & (s.sp > s.base)
        s = s._replace(steps=s.steps + pop.astype(I32))
        s, *writes = _node_step(r, s, pop, top_node, top_tag, top_entry, capacity=capacity, climbs=climbs)
        # the bound holds per step: a ray that reached it with this pop tests nothing more
        in_leaf = go & (s.leaf_pos < s.leaf_end) & (s.steps < step_limit)
        s = _primitive_step(r.hooks, s, in_leaf, r.t_min, r.t_max, mode=mode, max_hits=max_hits,
                            width=width)
        return (s, *writes)

    def lane_climb(s):
        r = ray(jnp.maximum(s.ray, 0))
        climb = live(s) & (s.leaf_pos >= s.leaf_end) & (s.sp <= s.base)  # live: after a spill
        s = s._replace(steps=s.steps + climb.astype(I32))
        return _climb_step(r, s, climb, capacity=capacity)

    def write(stacks, pos, kids, kid_tags, kid_entry):
        rows = lane_ids[:, None]
        return Stacks(node=stacks.node.at[rows, pos].set(kids, mode="drop"),
                      tag=None if stacks.tag is None else stacks.tag.at[rows, pos].set(kid_tags, mode="drop"),
                      entry=stacks.entry.at[rows, pos].set(kid_entry, mode="drop"))

    def climb_all(s, stacks):
        s, *writes = jax.vmap(lane_climb)(s)
        return s, write(stacks, *writes)

    def step(_, carry):
        s, stacks = carry
        if climbs:
            # a climb step only where a stack spilled and ran empty (rare but for deep
            # trees): its own pass, skipped when no lane needs it, so the common step
            # stays a pop or a primitive step
            needs = jnp.any(live(s) & (s.leaf_pos >= s.leaf_end) & (s.sp <= s.base))
            s, stacks = jax.lax.cond(needs, climb_all, lambda s, stacks: (s, stacks), s, stacks)
        top = jax.lax.rem(jnp.maximum(s.sp - 1, 0), I32(capacity))
        top_node = stacks.node[lane_ids, top]
        top_tag = None if stacks.tag is None else stacks.tag[lane_ids, top]
        top_entry = stacks.entry[lane_ids, top]
        s, *writes = jax.vmap(lane_step)(s, top_node, top_tag, top_entry)
        return s, write(stacks, *writes)

    def body(carry):
        s, stacks, out, next_ray = refill(*carry)
        s, stacks = jax.lax.fori_loop(0, REFILL_EVERY, step, (s, stacks))
        return s, stacks, out, next_ray

    def cond(carry):
        s, _, _, next_ray = carry
        return jnp.any(s.ray >= 0) | (next_ray < n_rays)

    _, _, out, _ = jax.lax.while_loop(cond, body, (s0, stacks, out, I32(0)))
    return out


def _select(mask, a, b):
    """``where(mask, a, b)`` with ``mask`` [L] broadcast over the trailing axes of ``a``."""
    return jnp.where(mask.reshape(mask.shape + (1,) * (a.ndim - 1)), a, b)


def working(s: Walk):
    """The ray has work left (bool []): not done, and a stack entry, an open leaf, or a
    climb to make (the stack spilled, and parent links recover what it lost)."""
    return ~s.done & ((s.sp > s.base) | (s.leaf_pos < s.leaf_end) | ((s.base > 0) & ~s.stack_overflow))


def _start(ray, root, root_hit, t_max, *, mode, max_hits, tagged) -> Walk:
    dtype = t_max.dtype
    all_hits = mode == "all"
    found = Found(t=t_max, prim=I32(-1), u=jnp.zeros((), dtype), v=jnp.zeros((), dtype),
                  best=t_max if all_hits else None,
                  count=I32(0) if all_hits else None,
                  prims=jnp.full(max_hits, -1, I32) if all_hits else None,
                  ts=jnp.full(max_hits, jnp.inf, dtype) if all_hits else None)
    return Walk(
        ray=jnp.asarray(ray, I32), sp=jnp.where(root_hit, 1, 0).astype(I32), base=I32(0),
        last=jnp.asarray(root, I32), last_tag=I32(-1) if tagged else None, up=I32(-1),
        up_tag=I32(-1) if tagged else None,
        leaf_pos=I32(0), leaf_end=I32(0), leaf_tag=I32(0) if tagged else None,
        found=found, counts=Counts(box_tests=I32(1), prim_tests=I32(0), nodes_visited=I32(0),
                                   leaves_visited=I32(0)),
        stack_overflow=jnp.zeros((), bool), done=jnp.zeros((), bool), steps=I32(0))


def _primitive_step(hooks, s: Walk, in_leaf, t_min, t_max, *, mode, max_hits, width) -> Walk:
    """Test the open leaf's next ``width`` primitives together (masked out unless
    ``in_leaf``). The hit kept is the one the same tests made one by one would keep:
    closest, the smallest ``(t, id)``; any, the first valid in slot order, and only the
    tests up to it count (and count as steps)."""
    slots = s.leaf_pos + jnp.arange(width, dtype=I32)
    tested = in_leaf & (slots < s.leaf_end)
    # slots not tested read slot 0: the same address in every lane, a cache hit, where a
    # stale slot would be a cache miss (gathers of scattered triangles dominate a step)
    if hooks.run is not None:  # one read of the run's rows (one gather per lane, not width)
        t, u, v, prim = hooks.run(jnp.where(in_leaf, s.leaf_pos, 0), s.leaf_tag, width)
    else:
        t, u, v, prim = jax.vmap(hooks.primitive, in_axes=(0, None))(jnp.where(tested, slots, 0), s.leaf_tag)
    valid = tested & (t > t_min) & (t < t_max)
    n_tested = jnp.sum(tested, dtype=I32)  # int32 under x64 too (a loop carry)
    if mode == "all":  # width 1: list in order
        found = _record(s.found, valid[0], t[0], u[0], v[0], prim[0], mode=mode, max_hits=max_hits)
    else:
        if mode == "any":
            j = jnp.argmax(valid)
            n_tested = jnp.where(valid[j], j + 1, n_tested).astype(I32)
        else:
            t_best = jnp.min(jnp.where(valid, t, jnp.inf))
            at_best = valid & (t == t_best)
            p_best = jnp.min(jnp.where(at_best, prim, jnp.iinfo(jnp.int32).max))
            j = jnp.argmax(at_best & (prim == p_best))
        found = _record(s.found, valid[j], t[j], u[j], v[j], prim[j], mode=mode, max_hits=max_hits)
    counts = s.counts._replace(prim_tests=s.counts.prim_tests + n_tested)
    return s._replace(found=found, counts=counts, leaf_pos=s.leaf_pos + n_tested,
                      steps=s.steps + n_tested,
                      # or, not instead of: a climb may have ended the ray in this step (the
                      # masked primitive step must not revive it; it would climb to the bound)
                      done=s.done | (found.prim >= 0) if mode == "any" else s.done)


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


def _node_step(r: Ray, s: Walk, pop, top_node, top_tag, entry, *, capacity, climbs):
    """Pop the top entry (``top_node``, ``top_tag``, ``entry``; masked out unless
    ``pop``); a visited leaf opens, a visited interior node pushes the children the ray
    enters, nearest on top. Returns ``(s, pos, kids, kid_tags, kid_entry)``: the stack
    writes, ``pos`` [k] the slots (``capacity``: none)."""
    # closest: cull against the best hit; any / all: found.t stays t_max
    visit = pop & (entry <= s.found.t)
    # a lane that does not pop reads node 0 (a cache hit for all of them, see _primitive_step)
    node = r.hooks.node(jnp.where(pop, top_node, 0), top_tag, entry, s.found.t)
    counted = visit if node.assumed is None else visit & ~node.assumed
    open_leaf = visit & node.is_leaf
    expand = visit & ~node.is_leaf
    c = s.counts
    counts = c._replace(
        nodes_visited=c.nodes_visited + counted.astype(I32),
        leaves_visited=c.leaves_visited + open_leaf.astype(I32),
        box_tests=c.box_tests + jnp.where(expand, jnp.sum(node.tested, dtype=I32), 0))
    s = s._replace(
        counts=counts,
        leaf_pos=jnp.where(open_leaf, node.leaf_start, s.leaf_pos),
        leaf_end=jnp.where(open_leaf, node.leaf_start + node.leaf_count, s.leaf_end),
        leaf_tag=None if s.leaf_tag is None else jnp.where(open_leaf, node.leaf_tag, s.leaf_tag))
    if climbs:  # where a climb would start: the node popped and the one above it
        s = s._replace(
            last=jnp.where(pop, top_node, s.last), up=jnp.where(pop, node.parent, s.up),
            last_tag=None if top_tag is None else jnp.where(pop, top_tag, s.last_tag),
            up_tag=None if top_tag is None else jnp.where(pop, node.parent_tag, s.up_tag))
    return _push(s, node, _order(node), node.kid_hit & expand, pop, s.sp - 1, capacity=capacity, climbs=climbs)


def _climb_step(r: Ray, s: Walk, climb, *, capacity):
    """A climb step (masked out unless ``climb``): look at ``s.up``, the parent of
    ``s.last``, testing its children's boxes again; push the first child after
    ``s.last`` in visiting order that the ray enters, or move up (the root: the ray
    ends). A skip-flagged child is entered at ``t_min`` (module docstring). Returns
    ``(s, pos, kids, kid_tags, kid_entry)`` as :func:`_node_step`."""
    at_root = s.last == r.root
    ends = climb & at_root  # (not in a valid tree: a climb starts below a spill)
    climb = climb & ~at_root
    node = r.hooks.node(jnp.where(climb, jnp.maximum(s.up, 0), 0), s.up_tag, r.t_min, s.found.t)
    before = _order(node)
    came = node.kids == s.last
    if s.last_tag is not None:
        came = came & (_kid_tags(node) == s.last_tag)
    candidate = node.kid_hit & jnp.any(came[:, None] & before, axis=0)  # after ``last``, entered
    first = candidate & ~jnp.any(candidate[:, None] & before, axis=0)
    moved = climb & ~jnp.any(candidate)
    s = s._replace(
        counts=s.counts._replace(box_tests=s.counts.box_tests + jnp.where(climb, jnp.sum(node.tested, dtype=I32), 0)),
        last=jnp.where(moved, s.up, s.last), up=jnp.where(moved, node.parent, s.up),
        last_tag=None if s.last_tag is None else jnp.where(moved, s.up_tag, s.last_tag),
        up_tag=None if s.up_tag is None else jnp.where(moved, node.parent_tag, s.up_tag),
        done=s.done | ends | (moved & (s.up == r.root)))
    return _push(s, node, before, first, climb & ~moved, s.sp, capacity=capacity, climbs=True)


def _order(node: Node):
    """``before`` [k, k] bool: child i comes before child j in visiting order (keys of
    :func:`_visit_key`; ties: the lower slot)."""
    key = _visit_key(node)
    slot_ids = jnp.arange(key.shape[0])
    return (key[:, None] < key[None, :]) | ((key[:, None] == key[None, :]) & (slot_ids[:, None] < slot_ids[None, :]))


def _kid_tags(node: Node):
    k = node.kids.shape[0]
    return None if node.kid_tags is None else jnp.broadcast_to(node.kid_tags, (k,)).astype(I32)


def _visit_key(node: Node):
    """Sort key of the children [k] (smaller first; ties: lower slot): by slot along the
    split axis (lower child first when the direction is >= 0 there), else by entry
    distance, a child assumed hit (skip flag: hit but not tested) first. The key depends
    only on the ray and the boxes, so a climb recomputes the order of a push."""
    assumed = node.kid_hit & ~node.tested
    by_entry = jnp.where(assumed, -jnp.inf, node.kid_entry)
    if node.split is None:
        return by_entry
    k = node.kid_entry.shape[0]
    slot_ids = jnp.arange(k)
    lower_first = node.direction[jnp.maximum(node.split, 0)] >= 0
    by_axis = jnp.where(lower_first, slot_ids, k - 1 - slot_ids).astype(node.kid_entry.dtype)
    return jnp.where(node.split >= 0, by_axis, by_entry)


def _push(s: Walk, node: Node, before, kid_hit, replace, top, *, capacity, climbs):
    """Push the children ``kid_hit`` [k] at logical entry ``top`` up, in visiting order
    (``before`` [k, k]), nearest on top; ``replace``: the lane pushes (a pop replaces its
    entry; a climb writes on the empty stack). The ring keeps the newest ``capacity``
    entries: older ones are spilled (``base``), an overflow unless the walk ``climbs``.
    Returns the new state and the stack writes (:func:`_node_step`)."""
    rank = jnp.sum(kid_hit[:, None] & before, axis=0, dtype=I32)  # visiting position of each kid (int32 under x64 too)
    n_push = jnp.sum(kid_hit, dtype=I32)
    pos = top + n_push - 1 - rank  # nearest on top
    pos = jnp.where(kid_hit & replace, jax.lax.rem(pos, I32(capacity)), capacity)  # pos >= 0
    sp = jnp.where(replace, top + n_push, s.sp).astype(I32)
    base = jnp.maximum(s.base, sp - capacity)
    spilled = base > s.base
    if not climbs:
        s = s._replace(stack_overflow=s.stack_overflow | spilled)
    s = s._replace(sp=sp, base=base)
    return s, pos.astype(I32), node.kids, _kid_tags(node), node.kid_entry


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
