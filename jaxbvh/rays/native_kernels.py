"""The numba kernels of the native ray engine (imported only by :mod:`jaxbvh.rays.native`).

This module imports numba at its top, so nothing imports it but
:func:`jaxbvh.rays.native.kernels`, which first imports numba through
:func:`jaxbvh.native.numba` (its on-disk cache in jaxbvh's cache folder). The walk is :mod:`jaxbvh.rays.stack_walk`'s, one ray at a time
(its docstring has the rules; every branch below names the JAX function it mirrors):
the same ring stack of ``capacity`` entries with its ``sp`` / ``base`` bookkeeping,
the same parent-link climb, the same visiting order and tie rules, the same primitive
step of ``leaf_width`` slots, the same step bound. So every counter equals the JAX
walk's, ray by ray.

Floats stay in the tree's dtype: every constant (1, the robust factor, the huge inverse)
comes from ``consts`` (an array of that dtype), because numba, like NumPy, would widen
``float32 op python-int`` to float64. ``error_model="numpy"``: a division by zero gives
``inf`` as in XLA (numba's default raises). numba does not contract ``a * b + c`` into
a fused multiply-add (XLA on CPU does), so hit distances equal the NumPy twin's bit for
bit and the JAX walk's to the last bits (``tests/rays/test_rays.py::assert_t_close``).

Speed (bench/results/bench_rays_native.md): binary nodes and 4-wide nodes in distance
order are written out on scalars (the generic k-ary branch, loops over small arrays and
calls, costs about twice as much per node); the children's rows are prefetched while
their boxes are tested (a step on a tree that does not fit the caches waits on memory).
Tried and not kept (within the noise of the shared machine, or slower): a depth-first
renumbering of the packed rows, rays sorted by Morton code and octant, huge pages,
64-byte triangle rows, and pushes without branches (15% slower).

Signatures: the integer arrays are int32, the float arrays all in the tree's dtype, the
scalars int64, so :func:`trace_rays` is compiled once per float dtype (float32, float64)
and per kind of tree: its ``four_wide`` and ``other_nodes`` arguments are None (numba then
leaves that branch out of the compiled code) or 1 (:func:`jaxbvh.rays.native._branches`);
each version costs a few CPU seconds once, then loads from the cache.
"""

from __future__ import annotations

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.core import cgutils
from numba.extending import intrinsic

from jaxbvh import native

#: numba's on-disk cache, as jaxbvh.native set it up before this import
CACHE_KERNELS = native.caching()

CLOSEST, ANY, ALL = 0, 1, 2
"""``mode`` codes: one kernel for the three modes (one compile, not three)."""

_jit = numba.njit(cache=CACHE_KERNELS, nogil=True, error_model="numpy")
# numba-level inlining for the slab test only (the binary fast path: measured 25% more
# rays/s there); the k-ary helpers are left to LLVM: inlining _children too cost 2.5 CPU s
# more compile (9.2 against 6.7, load 0.8) for ~15% more rays/s on 4-wide trees
_inline = numba.njit(cache=CACHE_KERNELS, nogil=True, error_model="numpy", inline="always")


@_jit
def _children(rows, irows, flags, has_skip, ref, entry, t_min, t_far, ox, oy, oz, ix, iy, iz, dx, dy, dz, robust,
              kid_hit, kid_entry, key):
    """The ``node`` hook (``traversal._expand``) and ``stack_walk._visit_key`` for node
    ``ref``: fills ``kid_hit``, ``kid_entry``, ``key`` [k]; returns the boxes tested."""
    k = kid_hit.shape[0]
    split = irows[ref, 7 * k + 1]
    lower_first = False
    if split >= 0:
        lower_first = (dx if split == 0 else (dy if split == 1 else dz)) >= 0
    tested = 0
    for j in range(k):
        real = irows[ref, 6 * k + j] >= 0
        skipped = real and has_skip and ((flags[ref] >> (1 + j)) & 1) != 0
        if skipped:
            hit = True
            e = entry
        else:
            hit, e = _slab(rows, ref, j, t_min, t_far, ox, oy, oz, ix, iy, iz, robust)
            if real:
                tested += 1
        kid_hit[j] = hit and real
        kid_entry[j] = e
        if split >= 0:
            key[j] = j if lower_first else k - 1 - j
        elif skipped:
            key[j] = -np.inf  # assumed hit: first in distance order
        else:
            key[j] = e
    return tested


@_inline
def _slab(rows, ref, j, t_min, t_far, ox, oy, oz, ix, iy, iz, robust):
    """Robust slab test (``traversal.slab``) of child slot ``j``'s box in node ``ref``'s
    row: ``(hit, entry)``, the far side scaled by 1 + 2 gamma(3)."""
    t0 = (rows[ref, 6 * j + 0] - ox) * ix
    t1 = (rows[ref, 6 * j + 3] - ox) * ix
    near = min(t0, t1)
    far = max(t0, t1)
    t0 = (rows[ref, 6 * j + 1] - oy) * iy
    t1 = (rows[ref, 6 * j + 4] - oy) * iy
    near = max(near, min(t0, t1))
    far = min(far, max(t0, t1))
    t0 = (rows[ref, 6 * j + 2] - oz) * iz
    t1 = (rows[ref, 6 * j + 5] - oz) * iz
    near = max(near, min(t0, t1))
    far = min(far, max(t0, t1)) * robust
    e = max(near, t_min)
    return e <= min(far, t_far), e


@intrinsic
def prefetch(typingctx, rows, row, column):
    """Ask the CPU to start loading the cache line of ``rows[row, column]`` (2-D, C order;
    in range): ``llvm.prefetch``, a hint that never faults and changes no result."""

    def codegen(context, builder, signature, args):
        rows_type = signature.args[0]
        array = context.make_array(rows_type)(context, builder, args[0])
        index = context.cast(builder, args[1], signature.args[1], types.intp)
        column = context.cast(builder, args[2], signature.args[2], types.intp)
        pointer = cgutils.get_item_pointer2(context, builder, data=array.data,
                                            shape=cgutils.unpack_tuple(builder, array.shape),
                                            strides=cgutils.unpack_tuple(builder, array.strides),
                                            layout=rows_type.layout, inds=[index, column],
                                            wraparound=False, boundscheck=False)
        i32 = ir.IntType(32)
        signature_ir = ir.FunctionType(ir.VoidType(), [pointer.type, i32, i32, i32])
        hint = cgutils.get_or_insert_function(builder.module, signature_ir, "llvm.prefetch.p0")
        builder.call(hint, [pointer, i32(0), i32(3), i32(1)])  # read, keep in all caches, data
        return context.get_dummy_value()

    return types.void(rows, row, column), codegen


@_jit
def _before(key, i, j):
    """Child slot ``i`` comes before slot ``j`` (``stack_walk._order``: key, then slot)."""
    return key[i] < key[j] or (key[i] == key[j] and i < j)


@_jit
def _push(irows, ref, mask, key, kid_entry, top_slot, capacity, stack_node, stack_entry):
    """``stack_walk._push``: write the children ``mask`` [k] from ring slot ``top_slot``
    (the slot of logical entry ``top``) up, nearest on top; returns how many. Ring
    positions wrap by one subtraction (at most ``k <= capacity`` past ``top_slot``), not
    a modulo: an integer division per push cost more than the rest of a step."""
    k = mask.shape[0]
    n_push = 0
    for j in range(k):
        if mask[j]:
            n_push += 1
    for j in range(k):
        if mask[j]:
            rank = 0
            for i in range(k):
                if mask[i] and _before(key, i, j):
                    rank += 1
            slot = top_slot + n_push - 1 - rank
            if slot >= capacity:
                slot -= capacity
            stack_node[slot] = irows[ref, 6 * k + j]
            stack_entry[slot] = kid_entry[j]
    return n_push


@_jit
def trace_rays(rows, irows, flags, has_skip, parent, root_box, slot_rows, slot_irows, root,
               origin, direction, t_lo, t_hi, consts, mode, capacity, max_hits, step_limit, leaf_width,
               four_wide, other_nodes, first, stop, out_t, out_u, out_v, out_prim, out_counts, out_limit, out_hit_count,
               out_hit_prims, out_hit_t):
    """Trace rays ``first .. stop - 1``; writes their results into the ``out_*`` arrays.

    Tree, packed as :class:`jaxbvh.rays.traversal.Packed` (a node's children's boxes in
    its own row: a node costs one row read, 64 bytes for a binary float32 tree): ``rows``
    [N, W] float, ``W = 7 k + 2`` or padded to whole cache lines with ``(W - 2) // 7 == k``
    (:func:`jaxbvh.rays.native.row_width`), and ``irows``, an integer view of the same
    memory; row ``n``: child
    ``j``'s lo, hi at ``6 j``, the children at ``6 k`` (-1: none), ``prim_count`` at
    ``7 k``, then ``prim_start`` (a leaf) or the split axis (-1: by distance; wide trees);
    ``flags`` [N] int32 skip flags (bit 0 the node's own, bit ``1 + j`` child ``j``'s; read
    only when ``has_skip``), ``parent`` [N] int32 (read by climbs), ``root_box`` [6];
    ``slot_rows`` [P, 10] per ``prim_index`` slot: v0, v1 - v0, v2 - v0, and the
    primitive id (in ``slot_irows``, the integer view).
    Rays: ``origin``, ``direction`` [R, 3], ``t_lo``, ``t_hi`` [R] (open interval).
    ``consts`` [3]: 1, the robust factor, the huge inverse of a zero component, all in
    the tree's dtype. Out: ``out_counts`` [R, 4] int32 (box, primitive tests, nodes,
    leaves visited), ``out_limit`` [R] bool (the ray reached ``step_limit``), the lists
    ``out_hit_prims`` [R, H] (filled with -1) and ``out_hit_t`` [R, H] (inf) for ``ALL``.
    ``four_wide``, ``other_nodes``: None leaves the written-out 4-wide branch, resp. the
    general k-ary branch, out of the compiled kernel (a tree with no such node), else 1.
    """
    k = (rows.shape[1] - 2) // 7
    n_nodes = rows.shape[0]
    n_slots = slot_rows.shape[0]
    one = consts[0]
    robust = consts[1]
    big = consts[2]
    zero = one - one
    inf = one / zero
    stack_node = np.zeros(capacity, np.int64)
    stack_entry = np.zeros(capacity, rows.dtype)
    kid_hit = np.zeros(k, np.bool_)
    candidate = np.zeros(k, np.bool_)
    first_kid = np.zeros(k, np.bool_)
    order = np.zeros(k, np.int64)
    kid_entry = np.zeros(k, rows.dtype)
    key = np.zeros(k, rows.dtype)
    width = 1 if mode == ALL else leaf_width
    for i in range(first, stop):
        ox, oy, oz = origin[i, 0], origin[i, 1], origin[i, 2]
        dx, dy, dz = direction[i, 0], direction[i, 1], direction[i, 2]
        # traversal.inverse_direction: a zero component gets +-big (its sign), not inf
        ix = one / dx
        iy = one / dy
        iz = one / dz
        if dx == 0:
            ix = big if ix > 0 else -big
        if dy == 0:
            iy = big if iy > 0 else -big
        if dz == 0:
            iz = big if iz > 0 else -big
        t_min = t_lo[i]
        t_max = t_hi[i]
        # stack_walk.Found: t (closest / any: the interval end), best (all), the hit
        found_t = t_max
        best = t_max
        hit_prim = -1
        hit_u = zero
        hit_v = zero
        count = 0
        # stack_walk.Walk
        sp = 0
        sp_slot = 0  # sp % capacity, kept apart (no division per step)
        base = 0
        last = root
        leaf_pos = 0
        leaf_end = 0
        done = False
        steps = 0
        box_tests = 1
        prim_tests = 0
        nodes_visited = 0
        leaves_visited = 0
        # the root box (traversal._ray)
        t0 = (root_box[0] - ox) * ix
        t1 = (root_box[3] - ox) * ix
        near = min(t0, t1)
        far = max(t0, t1)
        t0 = (root_box[1] - oy) * iy
        t1 = (root_box[4] - oy) * iy
        near = max(near, min(t0, t1))
        far = min(far, max(t0, t1))
        t0 = (root_box[2] - oz) * iz
        t1 = (root_box[5] - oz) * iz
        near = max(near, min(t0, t1))
        far = min(far, max(t0, t1)) * robust
        root_entry = max(near, t_min)
        if root_entry <= min(far, t_max):
            sp = 1
            sp_slot = 1 if capacity > 1 else 0
            stack_node[0] = root
            stack_entry[0] = root_entry
        while True:
            # stack_walk.working and the step bound (live)
            working = (not done) and (sp > base or leaf_pos < leaf_end or base > 0)
            if not working or steps >= step_limit:
                break
            if leaf_pos < leaf_end:
                # stack_walk._primitive_step: the next ``width`` slots together
                n_tested = min(width, leaf_end - leaf_pos)
                pick = -1
                pick_t = inf
                pick_u = zero
                pick_v = zero
                for s in range(n_tested):
                    slot = min(max(leaf_pos + s, 0), n_slots - 1)
                    # Moller-Trumbore, traversal.moller_trumbore_edges (same operation order)
                    e1x, e1y, e1z = slot_rows[slot, 3], slot_rows[slot, 4], slot_rows[slot, 5]
                    e2x, e2y, e2z = slot_rows[slot, 6], slot_rows[slot, 7], slot_rows[slot, 8]
                    px = dy * e2z - dz * e2y
                    py = dz * e2x - dx * e2z
                    pz = dx * e2y - dy * e2x
                    det = e1x * px + e1y * py + e1z * pz
                    ok = det != 0
                    inv_det = one / (det if ok else one)
                    sx = ox - slot_rows[slot, 0]
                    sy = oy - slot_rows[slot, 1]
                    sz = oz - slot_rows[slot, 2]
                    u = (sx * px + sy * py + sz * pz) * inv_det
                    qx = sy * e1z - sz * e1y
                    qy = sz * e1x - sx * e1z
                    qz = sx * e1y - sy * e1x
                    v = (dx * qx + dy * qy + dz * qz) * inv_det
                    t = (e2x * qx + e2y * qy + e2z * qz) * inv_det
                    if not (ok and u >= 0 and u <= 1 and v >= 0 and u + v <= 1):
                        t = inf
                    if not (t > t_min and t < t_max):
                        continue
                    prim = slot_irows[slot, 9]
                    if mode == ALL:
                        # stack_walk._record, all hits: a primitive listed already is the same hit
                        listed = False
                        for h in range(max_hits):
                            if out_hit_prims[i, h] == prim:
                                listed = True
                        if listed:
                            continue
                        if count < max_hits:
                            out_hit_prims[i, count] = prim
                            out_hit_t[i, count] = t
                        count += 1
                        if t < best or (t == best and prim < hit_prim):
                            best = t
                            hit_prim, hit_u, hit_v = prim, u, v
                    elif mode == ANY:
                        # the first valid slot; only the tests up to it count
                        pick, pick_t, pick_u, pick_v = prim, t, u, v
                        n_tested = s + 1
                        break
                    elif pick < 0 or t < pick_t or (t == pick_t and prim < pick):
                        pick, pick_t, pick_u, pick_v = prim, t, u, v
                if pick >= 0:  # closest / any: stack_walk._record
                    if mode == ANY or pick_t < found_t or (pick_t == found_t and pick < hit_prim):
                        found_t = pick_t
                        hit_prim, hit_u, hit_v = pick, pick_u, pick_v
                prim_tests += n_tested
                leaf_pos += n_tested
                steps += n_tested
                if mode == ANY and hit_prim >= 0:
                    done = True
            elif sp > base:
                # stack_walk._node_step: pop the top entry
                steps += 1
                top = sp - 1
                slot = sp_slot - 1 if sp_slot > 0 else capacity - 1  # top % capacity
                node = stack_node[slot]
                entry = stack_entry[slot]
                ref = min(max(node, 0), n_nodes - 1)
                last = node  # (its parent is read when a climb starts from it)
                sp = top
                sp_slot = slot
                if entry <= found_t:  # closest: cull against the best hit; any / all: t_max
                    if not (has_skip and (flags[ref] & 1) != 0):
                        nodes_visited += 1
                    n_prims = irows[ref, 7 * k]
                    if n_prims > 0:
                        leaves_visited += 1
                        leaf_pos = irows[ref, 7 * k + 1]
                        leaf_end = leaf_pos + n_prims
                    else:
                        if k == 2 and not (has_skip and (flags[ref] & 6) != 0):
                            # a binary node without skip flags, written out (the common case; the
                            # loops over k below cost about twice as much): the same tests, order, push
                            c0 = irows[ref, 12]
                            c1 = irows[ref, 13]
                            # the children's rows start loading while their boxes are tested
                            prefetch(rows, min(max(c0, 0), n_nodes - 1), 0)
                            prefetch(rows, min(max(c1, 0), n_nodes - 1), 0)
                            h0 = False
                            h1 = False
                            e0 = zero
                            e1 = zero
                            if c0 >= 0:
                                box_tests += 1
                                h0, e0 = _slab(rows, ref, 0, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            if c1 >= 0:
                                box_tests += 1
                                h1, e1 = _slab(rows, ref, 1, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            split = irows[ref, 15]
                            if split >= 0:  # by axis: the lower child first where the direction is >= 0
                                zero_first = (dx if split == 0 else (dy if split == 1 else dz)) >= 0
                            else:  # by entry; ties: the lower slot
                                zero_first = not (e1 < e0)
                            n_push = 0
                            if h0 and h1:
                                upper = slot + 1 if slot + 1 < capacity else 0
                                stack_node[upper] = c0 if zero_first else c1  # nearest on top
                                stack_entry[upper] = e0 if zero_first else e1
                                stack_node[slot] = c1 if zero_first else c0
                                stack_entry[slot] = e1 if zero_first else e0
                                n_push = 2
                            elif h0 or h1:
                                stack_node[slot] = c0 if h0 else c1
                                stack_entry[slot] = e0 if h0 else e1
                                n_push = 1
                        elif four_wide is not None and k == 4 and irows[ref, 29] < 0 and not (has_skip and (flags[ref] >> 1) != 0):
                            # a 4-wide node in distance order without skip flags, written out on
                            # scalars (the loops over k and the arrays below cost about twice as
                            # much): the same tests; each hit child's rank in visiting order
                            # (entry, then slot: stack_walk._order) is the number of hit children
                            # before it, the nearest goes on top (stack_walk._push)
                            c0 = irows[ref, 24]
                            c1 = irows[ref, 25]
                            c2 = irows[ref, 26]
                            c3 = irows[ref, 27]
                            # (a row is two cache lines; its last one holds the children's ids)
                            for c in (c0, c1, c2, c3):
                                prefetch(rows, min(max(c, 0), n_nodes - 1), 0)
                                prefetch(rows, min(max(c, 0), n_nodes - 1), rows.shape[1] - 1)
                            h0 = False
                            h1 = False
                            h2 = False
                            h3 = False
                            e0 = zero
                            e1 = zero
                            e2 = zero
                            e3 = zero
                            if c0 >= 0:
                                box_tests += 1
                                h0, e0 = _slab(rows, ref, 0, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            if c1 >= 0:
                                box_tests += 1
                                h1, e1 = _slab(rows, ref, 1, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            if c2 >= 0:
                                box_tests += 1
                                h2, e2 = _slab(rows, ref, 2, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            if c3 >= 0:
                                box_tests += 1
                                h3, e3 = _slab(rows, ref, 3, t_min, found_t, ox, oy, oz, ix, iy, iz, robust)
                            # (a hit child's entry is never NaN: NaN fails the slab's <=)
                            n_push = np.int64(h0) + np.int64(h1) + np.int64(h2) + np.int64(h3)
                            top_at = slot + n_push - 1
                            if h0:
                                at = top_at - ((h1 and e1 < e0) + (h2 and e2 < e0) + (h3 and e3 < e0))
                                at = at - capacity if at >= capacity else at
                                stack_node[at] = c0
                                stack_entry[at] = e0
                            if h1:
                                at = top_at - ((h0 and e0 <= e1) + (h2 and e2 < e1) + (h3 and e3 < e1))
                                at = at - capacity if at >= capacity else at
                                stack_node[at] = c1
                                stack_entry[at] = e1
                            if h2:
                                at = top_at - ((h0 and e0 <= e2) + (h1 and e1 <= e2) + (h3 and e3 < e2))
                                at = at - capacity if at >= capacity else at
                                stack_node[at] = c2
                                stack_entry[at] = e2
                            if h3:
                                at = top_at - ((h0 and e0 <= e3) + (h1 and e1 <= e3) + (h2 and e2 <= e3))
                                at = at - capacity if at >= capacity else at
                                stack_node[at] = c3
                                stack_entry[at] = e3
                        elif other_nodes is not None:
                            box_tests += _children(rows, irows, flags, has_skip, ref, entry, t_min, found_t, ox, oy,
                                                   oz, ix, iy, iz, dx, dy, dz, robust, kid_hit, kid_entry, key)
                            # the hit children in visiting order (key, then slot: an insertion sort,
                            # stable), nearest on top: the ranks of stack_walk._push
                            n_push = 0
                            for j in range(k):
                                if kid_hit[j]:
                                    pos = n_push
                                    while pos > 0 and key[order[pos - 1]] > key[j]:
                                        order[pos] = order[pos - 1]
                                        pos -= 1
                                    order[pos] = j
                                    n_push += 1
                            for rank in range(n_push):
                                at = slot + n_push - 1 - rank
                                if at >= capacity:
                                    at -= capacity
                                stack_node[at] = irows[ref, 6 * k + order[rank]]
                                stack_entry[at] = kid_entry[order[rank]]
                        else:  # not reached: other_nodes is None only where every node takes the binary branch
                            n_push = 0
                        sp = top + n_push
                        sp_slot = slot + n_push
                        if sp_slot >= capacity:
                            sp_slot -= capacity
                        base = max(base, sp - capacity)
            else:
                # stack_walk._climb_step: the stack spilled and ran empty
                steps += 1
                if last == root:
                    done = True
                    continue
                up = parent[min(max(last, 0), parent.shape[0] - 1)]  # the JAX walk reads it with ``last``
                ref = min(max(up, 0), n_nodes - 1)
                box_tests += _children(rows, irows, flags, has_skip, ref, t_min, t_min, found_t, ox, oy, oz, ix,
                                       iy, iz, dx, dy, dz, robust, kid_hit, kid_entry, key)
                # candidates: children after ``last`` in visiting order that the ray enters;
                # push the first of them (all with no candidate before them, as the JAX walk)
                for j in range(k):
                    candidate[j] = False
                    if kid_hit[j]:
                        for c in range(k):
                            if irows[ref, 6 * k + c] == last and _before(key, c, j):
                                candidate[j] = True
                moved = True
                for j in range(k):
                    first_kid[j] = candidate[j]
                    if candidate[j]:
                        moved = False
                        for c in range(k):
                            if candidate[c] and _before(key, c, j):
                                first_kid[j] = False
                if moved:
                    if up == root:
                        done = True
                    last = up
                else:
                    n_push = _push(irows, ref, first_kid, key, kid_entry, sp_slot, capacity, stack_node, stack_entry)
                    sp += n_push
                    sp_slot += n_push
                    if sp_slot >= capacity:
                        sp_slot -= capacity
                    base = max(base, sp - capacity)
        hit = hit_prim >= 0
        out_prim[i] = hit_prim
        out_t[i] = (best if mode == ALL else found_t) if hit else inf
        out_u[i] = hit_u
        out_v[i] = hit_v
        out_counts[i, 0] = box_tests
        out_counts[i, 1] = prim_tests
        out_counts[i, 2] = nodes_visited
        out_counts[i, 3] = leaves_visited
        out_limit[i] = (not done) and (sp > base or leaf_pos < leaf_end or base > 0)
        out_hit_count[i] = count


@_jit
def pack(child, lo, hi, prim_start, prim_count, axis, skip, prim_index, triangles, rows, irows, flags, slot_rows,
         slot_irows):
    """Fill every row of the packed arrays (:func:`pack_rows`, its rows from ``M`` on copies
    of row ``M - 1``, which they equal)."""
    n_rows = pack_rows(child, lo, hi, prim_start, prim_count, axis, skip, prim_index, triangles, rows, irows, flags,
                       slot_rows, slot_irows)
    for i in range(n_rows, irows.shape[0]):
        irows[i, :] = irows[n_rows - 1, :]  # (the integer view: the bits as they are)
        flags[i] = flags[n_rows - 1]


@_jit
def pack_rows(child, lo, hi, prim_start, prim_count, axis, skip, prim_index, triangles, rows, irows, flags, slot_rows,
              slot_irows):
    """Fill the packed arrays :func:`trace_rays` reads (``rows`` / ``irows``, ``flags``,
    ``slot_rows`` / ``slot_irows``, [N, ...] each) from a tree's arrays (``child`` [N, k],
    ``skip`` [N] int32) and ``triangles`` [T, 3, 3]; indices out of range are clamped (as
    XLA's gathers clamp them: a broken tree reads some node, the step bound ends its rays).

    Returns ``M``: only rows ``0 .. M - 1`` are filled and read. The nodes from ``M - 1``
    on all pack to the same row (no children, the same count, start or axis and skip flag
    as the last node: a capacity's padding), so :func:`trace_rays`, clamping a node to
    ``M - 1``, reads what their own rows would hold (``jaxbvh.build``'s bunny4 tree: 786k
    nodes, 300k rows)."""
    n, k = child.shape
    last_tag = prim_start[n - 1] if prim_count[n - 1] > 0 else axis[n - 1]
    n_rows = n
    while n_rows > 1:
        i = n_rows - 2
        same = prim_count[i] == prim_count[n - 1] and skip[i] == skip[n - 1]
        same = same and (prim_start[i] if prim_count[i] > 0 else axis[i]) == last_tag
        for j in range(k):
            same = same and child[i, j] == -1 and child[n - 1, j] == -1
        if not same:
            break
        n_rows -= 1
    for i in range(n_rows):
        f = 1 if skip[i] != 0 else 0
        for j in range(k):
            c = child[i, j]
            b = min(max(c, 0), n - 1)
            for a in range(3):
                rows[i, 6 * j + a] = lo[b, a]
                rows[i, 6 * j + 3 + a] = hi[b, a]
            irows[i, 6 * k + j] = c
            if c >= 0 and skip[b] != 0:
                f |= 1 << (1 + j)
        irows[i, 7 * k] = prim_count[i]
        irows[i, 7 * k + 1] = prim_start[i] if prim_count[i] > 0 else axis[i]
        flags[i] = f
    n_tri = triangles.shape[0]
    for s in range(prim_index.shape[0]):
        p = min(max(prim_index[s], 0), n_tri - 1)
        for a in range(3):
            v0 = triangles[p, 0, a]
            slot_rows[s, a] = v0
            slot_rows[s, 3 + a] = triangles[p, 1, a] - v0
            slot_rows[s, 6 + a] = triangles[p, 2, a] - v0
        slot_irows[s, 9] = prim_index[s]
    return n_rows
