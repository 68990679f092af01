"""The native engine of the two-level walk: :mod:`jaxbvh.twolevel.traversal` compiled by numba.

:func:`jaxbvh.twolevel.trace` (``closest_hit``, ``any_hit``) runs on the engine that
:func:`jaxbvh.native.choose` picks; this module is ``"native"``: the JAX walk's steps one
ray at a time in a loop numba compiles for the CPU (the JAX walk runs every step as
dozens of kernels over lanes of rays, :mod:`jaxbvh.rays.native`).

The walk is the JAX one step for step (:mod:`jaxbvh.rays.stack_walk` with the hooks of
:mod:`jaxbvh.twolevel.traversal`; every branch below names the JAX function it mirrors):
stack entries ``(reference, tag)`` (a reference below ``n_top`` is a top-level node, tag
-1; ``n_top + f`` is forest node ``f`` entered through the top-level leaf ``tag``), a
top-level leaf expanded as the forest node of its BRef, nodes below it tested with the
ray mapped into the BRef's instance (``to_object``, in the tree's dtype, the same
operation order), the ring stack of ``capacity`` entries, the parent-link climb from an
object back to the top-level leaf it was entered through, the visiting order and tie
rules, ``leaf_width`` primitive slots per step, the counters and the step bound. So
hits and counters equal the JAX walk's ray by ray, with one exception: XLA on the CPU
may contract multiply-adds (the instance transform, Möller–Trumbore) and numba does
not, so a distance may differ in its last bit, and then a box entered exactly there is
culled by one engine and not the other (counters only); there the native walk equals
the NumPy twin :mod:`jaxbvh.twolevel.traversal_reference` bit for bit, as everywhere
(``tests/twolevel/test_twolevel_native.py``).

Out-of-range ids (a broken tree) are read as JAX reads them (negative from the end, then
clamped), never outside an array; the step bound ends every ray.

numba is imported by :func:`kernel` on the first native call (:func:`jaxbvh.native.numba`,
its cache in jaxbvh's cache folder), never by importing this module. One kernel for
both modes and every capacity: two compiled versions (float32, float64).
"""

from __future__ import annotations

import functools

import numpy as np

from jaxbvh import native
from jaxbvh.numerics import INV_BIG, robust_factor
from jaxbvh.rays.stack_walk import LEAF_WIDTH, Hits

__all__ = ["kernel", "trace"]

CLOSEST, ANY = 0, 1
"""``mode`` codes of the kernel (the modes of the two-level walk)."""

# columns of the packed int32 node rows [N, 6] (:func:`_rows`)
LEFT, RIGHT, PARENT, START, COUNT, AXIS = range(6)


@functools.cache
def kernel():
    """The numba kernel (compiled, or loaded from numba's cache, on first use)."""
    return _make(native.numba())


def _make(numba):
    # helpers are module globals, not closure cells: numba's disk cache cannot find a
    # closure's entry again in a new process (jaxbvh.queries.native_search)
    global _at, _frame, _look, _slab
    # error_model="numpy": 1 / 0 is inf as in XLA (numba's default raises)
    jit = numba.njit(cache=native.caching(), nogil=True, error_model="numpy")

    @jit
    def _at(i, n):
        # JAX's gather: a negative index counts from the end, then clamped into [0, n)
        if i < 0:
            i += n
        return min(max(i, 0), n - 1)

    @jit
    def _frame(to_object, k, ray, one, big, out):
        """``_ray.ray_in``: the ray ``ray`` [6] (origin, direction) in instance ``k``'s
        frame (-1: the identity, the last row of ``to_object``) and its inverse
        direction (``traversal.inverse_direction``), written to ``out`` [9] (no
        allocation: a ray changes frames at every instance it enters)."""
        n = to_object.shape[0] - 1
        m = to_object[_at(k, n + 1) if k >= 0 else n]
        for a in range(3):
            out[a] = m[a, 0] * ray[0] + m[a, 1] * ray[1] + m[a, 2] * ray[2] + m[a, 3]
            out[3 + a] = m[a, 0] * ray[3] + m[a, 1] * ray[4] + m[a, 2] * ray[5]
        for a in range(3):
            d = out[3 + a]
            inv = one / d
            if d == 0:
                inv = big if inv > 0 else -big  # copysign(INV_BIG, d)
            out[6 + a] = inv

    @jit
    def _slab(box, c, frames, fr, t_min, t_far, robust, inf):
        """``traversal.slab`` of box ``c`` (row of ``box`` [N, 6]) against the ray in frame
        row ``fr`` of ``frames``: ``(entry, hit)``, the far side scaled by 1 + 2 gamma(3)."""
        near = -inf
        far = inf
        for a in range(3):
            t0 = (box[c, a] - frames[fr, a]) * frames[fr, 6 + a]
            t1 = (box[c, 3 + a] - frames[fr, a]) * frames[fr, 6 + a]
            near = max(near, min(t0, t1))
            far = min(far, max(t0, t1))
        far = far * robust
        e = max(near, t_min)
        return e, e <= min(far, t_far)

    @jit
    def _look(ref, tag, n_top, top_rows, top_index, f_rows, bref_node, bref_instance):
        """``traversal._expand`` without the box tests: ``(in_forest, row, entered, k,
        parent, parent_tag)`` of reference ``ref`` with tag ``tag``: the node's row in the
        top level (``in_forest`` False) or the forest, the top-level leaf it is reached
        through, its instance (-1: the scene frame) and the reference above it."""
        n_f = f_rows.shape[0]
        is_top = ref < n_top
        tid = _at(ref, n_top) if is_top else 0
        top_leaf = is_top and top_rows[tid, COUNT] > 0
        entered = tid if top_leaf else tag
        b = _at(top_index[_at(top_rows[_at(max(entered, 0), n_top), START], top_index.shape[0])],
                bref_node.shape[0])
        if is_top:
            fid = bref_node[b] if top_leaf else 0
        else:
            fid = ref - n_top
        in_forest = (not is_top) or top_leaf
        k = bref_instance[b] if in_forest else -1
        fid = _at(max(fid, 0), n_f)
        up = f_rows[fid, PARENT]
        back = is_top or up == bref_node[b] or up < 0
        if is_top:
            parent = top_rows[tid, PARENT]
        elif back:
            parent = entered
        else:
            parent = n_top + up
        row = fid if in_forest else tid
        return in_forest, row, entered, k, parent, (-1 if back else entered)

    @jit
    def run(top_rows, top_box, top_index, root, f_rows, f_box, f_index, f_tri, bref_node, bref_instance,
            to_object, prim_shift, origin, direction, t_hi, consts, mode, capacity, step_limit, leaf_width,
            out_t, out_u, out_v, out_prim, out_counts, out_limit):
        """Trace every ray; writes the ``out_*`` arrays [R] (``out_counts`` [R, 4]: box,
        primitive tests, nodes, leaves visited; ``out_limit``: at the step bound).

        ``top_rows``, ``f_rows`` int32 [N, 6] (columns ``LEFT`` .. ``AXIS``); ``top_box``,
        ``f_box`` [N, 6] lo, hi; ``top_index`` (BRef ids), ``f_index`` (object triangle
        ids); ``f_tri`` [T, 3, 3]; ``to_object`` [I + 1, 3, 4] (the identity last);
        ``prim_shift`` [I]; rays ``origin``, ``direction`` [R, 3], ``t_hi`` [R] (the
        interval is ``(0, t_hi)``); ``consts``: 1, the robust factor, the huge inverse, in
        the tree's dtype (every float is: numba would widen ``float32 op int``).
        """
        one = consts[0]
        robust = consts[1]
        big = consts[2]
        zero = one - one
        inf = one / zero
        n_top = top_rows.shape[0]
        n_f = f_rows.shape[0]
        n_slots = f_index.shape[0]
        n_tri = f_tri.shape[0]
        stack_ref = np.zeros(capacity, np.int64)
        stack_tag = np.zeros(capacity, np.int64)
        stack_entry = np.zeros(capacity, top_box.dtype)
        ray = np.empty(6, top_box.dtype)
        # the ray in the scene frame and in the last instance entered (_frame): a ray goes
        # back and forth between the top level and an instance; each frame is made once
        frames = np.empty((2, 9), top_box.dtype)  # row 0: scene frame, row 1: the instance obj_k
        inv = np.empty(3, top_box.dtype)
        kid_ref = np.zeros(2, np.int64)
        kid_hit = np.zeros(2, np.bool_)
        kid_entry = np.zeros(2, top_box.dtype)
        key = np.zeros(2, top_box.dtype)
        width = leaf_width
        for i in range(origin.shape[0]):
            for a in range(3):
                ray[a] = origin[i, a]
                ray[3 + a] = direction[i, a]
            t_min = zero
            t_max = t_hi[i]
            _frame(to_object, -1, ray, one, big, frames[0])
            obj_k = -2  # no instance yet
            # the root box with the ray as given (traversal._ray), not mapped by the identity
            for a in range(3):
                inv[a] = one / ray[3 + a]
                if ray[3 + a] == 0:
                    inv[a] = big if inv[a] > 0 else -big
            r = _at(root, n_top)
            near = -inf
            far = inf
            for a in range(3):
                t0 = (top_box[r, a] - ray[a]) * inv[a]
                t1 = (top_box[r, 3 + a] - ray[a]) * inv[a]
                near = max(near, min(t0, t1))
                far = min(far, max(t0, t1))
            far = far * robust
            root_entry = max(near, t_min)
            # stack_walk._start
            found_t = t_max
            hit_prim = -1
            hit_u = zero
            hit_v = zero
            sp = 0
            sp_slot = 0  # sp % capacity
            base = 0
            last = root
            last_tag = -1
            up = -1
            up_tag = -1
            leaf_pos = 0
            leaf_end = 0
            leaf_tag = 0
            done = False
            steps = 0
            box_tests = 1
            prim_tests = 0
            nodes_visited = 0
            leaves_visited = 0
            if root_entry <= min(far, t_max):
                sp = 1
                sp_slot = 1 if capacity > 1 else 0
                stack_ref[0] = root
                stack_tag[0] = -1
                stack_entry[0] = root_entry
            while True:
                # stack_walk.working and the step bound
                if done or not (sp > base or leaf_pos < leaf_end or base > 0) or steps >= step_limit:
                    break
                if leaf_pos < leaf_end:
                    # stack_walk._primitive_step with traversal._primitive: ``width`` slots
                    b = _at(top_index[_at(top_rows[_at(max(leaf_tag, 0), n_top), START], top_index.shape[0])],
                            bref_node.shape[0])
                    k = bref_instance[b]
                    if k != obj_k and k >= 0:
                        _frame(to_object, k, ray, one, big, frames[1])
                        obj_k = k
                    fr = 0 if k < 0 else 1
                    shift = prim_shift[_at(k, prim_shift.shape[0])]
                    n_tested = min(width, leaf_end - leaf_pos)
                    pick = -1
                    pick_t = inf
                    pick_u = zero
                    pick_v = zero
                    for s in range(n_tested):
                        g = f_index[_at(leaf_pos + s, n_slots)]
                        tri = _at(max(g, 0), n_tri)
                        # Moller-Trumbore (traversal.moller_trumbore, same operation order)
                        v0x, v0y, v0z = f_tri[tri, 0, 0], f_tri[tri, 0, 1], f_tri[tri, 0, 2]
                        e1x, e1y, e1z = f_tri[tri, 1, 0] - v0x, f_tri[tri, 1, 1] - v0y, f_tri[tri, 1, 2] - v0z
                        e2x, e2y, e2z = f_tri[tri, 2, 0] - v0x, f_tri[tri, 2, 1] - v0y, f_tri[tri, 2, 2] - v0z
                        ox, oy, oz, dx, dy, dz = frames[fr, 0], frames[fr, 1], frames[fr, 2], frames[fr, 3], frames[fr, 4], frames[fr, 5]
                        px = dy * e2z - dz * e2y
                        py = dz * e2x - dx * e2z
                        pz = dx * e2y - dy * e2x
                        det = e1x * px + e1y * py + e1z * pz
                        ok = det != 0
                        inv_det = one / (det if ok else one)
                        sx = ox - v0x
                        sy = oy - v0y
                        sz = oz - v0z
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
                        prim = g + shift
                        if mode == ANY:  # the first valid slot; only the tests up to it count
                            pick, pick_t, pick_u, pick_v = prim, t, u, v
                            n_tested = s + 1
                            break
                        if pick < 0 or t < pick_t or (t == pick_t and prim < pick):
                            pick, pick_t, pick_u, pick_v = prim, t, u, v
                    if pick >= 0:  # stack_walk._record
                        if mode == ANY or pick_t < found_t or (pick_t == found_t and pick < hit_prim):
                            found_t = pick_t
                            hit_prim, hit_u, hit_v = pick, pick_u, pick_v
                    prim_tests += n_tested
                    leaf_pos += n_tested
                    steps += n_tested
                    if mode == ANY and hit_prim >= 0:
                        done = True
                    continue
                climb = not (sp > base)
                steps += 1
                if climb:
                    # stack_walk._climb_step: the stack spilled and ran empty
                    if last == root:
                        done = True
                        continue
                    ref = max(up, 0)
                    tag = up_tag
                    entry = t_min
                else:
                    # stack_walk._node_step: pop the top entry
                    sp -= 1
                    sp_slot = sp_slot - 1 if sp_slot > 0 else capacity - 1
                    slot = sp_slot
                    ref = stack_ref[slot]
                    tag = stack_tag[slot]
                    entry = stack_entry[slot]
                in_forest, row, entered, k, parent, parent_tag = _look(ref, tag, n_top, top_rows, top_index, f_rows,
                                                                       bref_node, bref_instance)
                if climb:
                    expand = True
                else:
                    last, last_tag, up, up_tag = ref, tag, parent, parent_tag
                    if not entry <= found_t:  # closest: culled by the best hit; any: found_t is t_max
                        continue
                    nodes_visited += 1
                    expand = not (in_forest and f_rows[row, COUNT] > 0)
                    if not expand:  # a leaf: open its run
                        leaves_visited += 1
                        leaf_pos = f_rows[row, START]
                        leaf_end = leaf_pos + f_rows[row, COUNT]
                        leaf_tag = entered
                        continue
                # the children's boxes in the node's frame (traversal._expand)
                if k != obj_k and k >= 0:
                    _frame(to_object, k, ray, one, big, frames[1])
                    obj_k = k
                fr = 0 if k < 0 else 1
                for j in range(2):
                    # the two levels' arrays apart, not one chosen into a variable: numba counts
                    # references on every such choice (choosing the frame row that way cost 25%)
                    if in_forest:
                        c = f_rows[row, LEFT + j]
                        kid_ref[j] = c + n_top
                        e, inside = _slab(f_box, min(max(c, 0), n_f - 1), frames, fr, t_min, found_t, robust, inf)
                    else:
                        c = top_rows[row, LEFT + j]
                        kid_ref[j] = c
                        e, inside = _slab(top_box, min(max(c, 0), n_top - 1), frames, fr, t_min, found_t, robust,
                                          inf)
                    real = c >= 0
                    if real:
                        box_tests += 1
                    kid_entry[j] = e
                    kid_hit[j] = real and inside
                # stack_walk._visit_key: by slot along the split axis, else by entry
                split = f_rows[row, AXIS] if in_forest else top_rows[row, AXIS]
                if split >= 0:
                    lower_first = frames[fr, 3 + min(split, 2)] >= 0
                    key[0] = zero if lower_first else one
                    key[1] = one if lower_first else zero
                else:
                    key[0] = kid_entry[0]
                    key[1] = kid_entry[1]
                kid_tag = entered if in_forest else -1
                # stack_walk._order: slot i before slot j (key, then the lower slot)
                first_before = key[0] < key[1] or key[0] == key[1]
                second_before = key[1] < key[0]
                if climb:
                    # push the first child after ``last`` in visiting order that the ray enters
                    came0 = kid_ref[0] == last and kid_tag == last_tag
                    came1 = kid_ref[1] == last and kid_tag == last_tag
                    cand0 = kid_hit[0] and came1 and second_before
                    cand1 = kid_hit[1] and came0 and first_before
                    if not (cand0 or cand1):  # none left: move up
                        if up == root:
                            done = True
                        last, last_tag, up, up_tag = up, up_tag, parent, parent_tag
                        continue
                    j = 0 if cand0 else 1
                    stack_ref[sp_slot] = kid_ref[j]
                    stack_tag[sp_slot] = kid_tag
                    stack_entry[sp_slot] = kid_entry[j]
                    n_push = 1
                else:
                    # stack_walk._push: nearest on top
                    n_push = 0
                    if kid_hit[0] and kid_hit[1]:
                        near_j = 0 if first_before else 1
                        far_j = 1 - near_j
                        upper = sp_slot + 1 if sp_slot + 1 < capacity else 0
                        stack_ref[sp_slot] = kid_ref[far_j]
                        stack_tag[sp_slot] = kid_tag
                        stack_entry[sp_slot] = kid_entry[far_j]
                        stack_ref[upper] = kid_ref[near_j]
                        stack_tag[upper] = kid_tag
                        stack_entry[upper] = kid_entry[near_j]
                        n_push = 2
                    elif kid_hit[0] or kid_hit[1]:
                        j = 0 if kid_hit[0] else 1
                        stack_ref[sp_slot] = kid_ref[j]
                        stack_tag[sp_slot] = kid_tag
                        stack_entry[sp_slot] = kid_entry[j]
                        n_push = 1
                # stack_walk._push: the ring keeps the newest ``capacity`` entries
                sp += n_push
                sp_slot += n_push  # the slot of logical entry sp (sp % capacity, no division)
                if sp_slot >= capacity:
                    sp_slot -= capacity
                base = max(base, sp - capacity)
            out_prim[i] = hit_prim
            out_t[i] = found_t if hit_prim >= 0 else inf
            out_u[i] = hit_u
            out_v[i] = hit_v
            out_counts[i, 0] = box_tests
            out_counts[i, 1] = prim_tests
            out_counts[i, 2] = nodes_visited
            out_counts[i, 3] = leaves_visited
            out_limit[i] = (not done) and (sp > base or leaf_pos < leaf_end or base > 0)

    return run


def _c(x, dtype):
    """``x`` as a C-contiguous, writable array of ``dtype`` (numba types read-only arrays
    apart: each type would be one more compile)."""
    a = np.ascontiguousarray(x, dtype)
    return a if a.flags.writeable else a.copy()


def _rows(tree):
    """A tree's (top level's or forest's) int32 node rows [N, 6] and boxes [N, 6]."""
    rows = np.stack([np.asarray(getattr(tree, name)) for name in ("left", "right", "parent", "prim_start",
                                                                  "prim_count", "axis")], axis=1)
    return _c(rows, np.int32), np.concatenate([np.asarray(tree.lo), np.asarray(tree.hi)], axis=1)


def trace(tl, origin, direction, t_max, *, dtype, mode: str, capacity: int, step_limit: int,
          leaf_width: int = LEAF_WIDTH) -> Hits:
    """The native engine of :func:`jaxbvh.twolevel.traversal.trace` (checked arguments):
    :class:`~jaxbvh.rays.stack_walk.Hits` of NumPy arrays [R], the JAX engine's dtypes.

    ``tl``: :class:`~jaxbvh.twolevel.rebraid.TwoLevelBVH` (NumPy or JAX arrays);
    ``origin``, ``direction`` [R, 3] scene frame; ``t_max`` [R]; ``dtype``: the tree's
    float dtype as the JAX engine sees it (float32 unless x64); ``mode``: "closest" or
    "any"; ``capacity``: stack entries; ``step_limit``: :func:`~jaxbvh.twolevel.traversal.step_bound`.
    """
    run = kernel()
    top_rows, top_box = _rows(tl.top)
    f_rows, f_box = _rows(tl.forest)
    inst = tl.instances
    to_object = np.asarray(inst.to_object, dtype)
    eye = np.zeros((1, 3, 4), dtype)
    eye[0, :, :3] = np.eye(3, dtype=dtype)
    r = origin.shape[0]
    out = dict(t=np.empty(r, dtype), u=np.empty(r, dtype), v=np.empty(r, dtype), prim=np.empty(r, np.int32),
               counts=np.empty((r, 4), np.int32), limit=np.empty(r, np.bool_))
    run(top_rows, _c(top_box, dtype), _c(tl.top.prim_index, np.int32), int(np.asarray(tl.top.root)), f_rows,
        _c(f_box, dtype), _c(tl.forest.prim_index, np.int32), _c(tl.forest.triangles, dtype),
        _c(tl.bref_node, np.int32), _c(tl.bref_instance, np.int32), _c(np.concatenate([to_object, eye]), dtype),
        _c(inst.prim_shift, np.int32), _c(origin, dtype), _c(direction, dtype),
        _c(np.broadcast_to(np.asarray(t_max, dtype), (r,)), dtype),
        np.array([1, robust_factor(dtype), INV_BIG], dtype), (CLOSEST, ANY)[("closest", "any").index(mode)],
        int(capacity), int(step_limit), int(max(1, leaf_width)), out["t"], out["u"], out["v"], out["prim"],
        out["counts"], out["limit"])
    c = out["counts"]
    return Hits(t=out["t"], prim=out["prim"], u=out["u"], v=out["v"], box_tests=c[:, 0].copy(),
                prim_tests=c[:, 1].copy(), nodes_visited=c[:, 2].copy(), leaves_visited=c[:, 3].copy(),
                stack_overflow=np.zeros(r, np.bool_), step_limit=out["limit"])
