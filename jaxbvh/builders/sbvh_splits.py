"""The two split searches of :mod:`jaxbvh.builders.sbvh` over all open nodes of a level at once.

Every open node of a level has a *slot* ``0 .. F - 1`` (its id minus the level's first
id); a reference's ``seg`` is its node's slot, ``F`` when its node is not open. Per-slot
sums, minima and maxima over references are segment reductions with ``F + 1`` segments,
the last one thrown away; binned counts and boxes live in cells [B, F, 3] (bin, slot,
axis), one array per coordinate. Rules: :mod:`jaxbvh.builders.sbvh`'s docstring.
"""

from __future__ import annotations

from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from jaxbvh.builders import sbvh_rules as rules
from jaxbvh.numerics import TIE_TOLERANCE, half_area, take


class Split(NamedTuple):
    """The best split of one kind per slot, all [F] (boxes [F, 3])."""

    cost: Any      # A_L N_L + A_R N_R; inf without a candidate
    axis: Any      # int32 axis of the plane
    plane: Any     # int32 k: between bins k and k + 1
    left_lo: Any   # box of the left side (object: exact; spatial: the bins' estimate)
    left_hi: Any
    right_lo: Any
    right_hi: Any
    n_left: Any    # int32 references on each side (spatial: before unsplitting)
    n_right: Any


def segment(op, values, seg, slots):
    """``op`` (a jax.ops.segment_*) of ``values`` [M, ...] over ``seg`` [M] in ``0 .. slots``, the
    last segment (references of no open node) dropped: [slots, ...]."""
    return op(values, seg, num_segments=slots + 1)[:slots]


def sweep_bins(count, box_lo, box_hi, usable, scale, bins: int, most=None) -> Split:
    """Best plane of binned counts and boxes per slot and axis.

    ``count``: (entries, exits), ``box_lo``, ``box_hi``: three coordinate arrays each,
    all [B, F, 3] (bin, slot, axis). The plane after bin ``k`` has on its left the bins
    ``<= k`` (``N_L``: entries there) and on its right the others (``N_R``: exits
    there). Tie-rule winner: least cost; within TIE_TOLERANCE the lowest axis, then the
    lowest plane. ``most`` [F] int32 (spatial splits): a plane is a candidate only if
    each side has fewer references than that (the node's count: neither child may get
    every reference, :func:`jaxbvh.builders.sbvh_rules.separates`). The sweeps are two
    ``lax.scan`` over the bins on flat [F * 3] rows (XLA's cumulative ops and arrays
    with a trailing axis of 3 are many times slower on CPU; the same sweeps unrolled bin
    by bin ran as fast but took ~6 s of compile each, two per stage). Sums of counts and
    minima of boxes are exact: any order gives the same values.
    """
    entries, exits = count
    dt = box_lo[0].dtype
    slots = entries.shape[1]

    def rows(values):  # [B, F, 3] -> [B, F * 3]
        return values.reshape(bins, slots * 3)

    def sweep(n, lo, hi, reverse: bool):
        """Running count and half-area of the running box over the bins (rows of [B - 1,
        F * 3] arrays), one output row per bin: that bin and those before it (after it
        when ``reverse``). Only counts and areas come out: the winner's boxes are
        reduced afterwards from its own axis's cells (seventh round: the scans' 14
        stacked outputs and their transposes were most of the object split at 8,192
        node slots)."""
        def step(carry, row):
            carry = (carry[0] + row[0], tuple(jnp.minimum(c, r) for c, r in zip(carry[1], row[1])),
                     tuple(jnp.maximum(c, r) for c, r in zip(carry[2], row[2])))
            return carry, (carry[0], half_area(jnp.stack(carry[1], -1), jnp.stack(carry[2], -1), scale))
        width = n.shape[1]
        start = (jnp.zeros(width, jnp.int32), (jnp.full(width, jnp.inf, dt),) * 3, (jnp.full(width, -jnp.inf, dt),) * 3)
        return jax.lax.scan(step, start, (n, tuple(lo), tuple(hi)), reverse=reverse)[1]

    n_l, a_l = sweep(rows(entries)[:-1], [rows(c)[:-1] for c in box_lo], [rows(c)[:-1] for c in box_hi],
                     False)  # row k, plane k: bins 0 .. k
    n_r, a_r = sweep(rows(exits)[1:], [rows(c)[1:] for c in box_lo], [rows(c)[1:] for c in box_hi],
                     True)  # row k, plane k: bins k + 1 ..

    candidate = usable.reshape(1, -1) & (n_l > 0) & (n_r > 0)
    if most is not None:
        candidate = candidate & rules.separates(n_l, n_r, jnp.repeat(most, 3)[None, :])
    cost = jnp.where(candidate, a_l * n_l.astype(dt) + a_r * n_r.astype(dt), jnp.inf)

    # the winner in (axis, plane) order, reduced over the planes first: over the leading
    # axis of the [B - 1, F * 3] rows, with no transpose (tenth round: an argmax over a
    # transposed [F, 3 (B - 1)] view was 2-3 ms a search at 4,096 node slots)
    by_axis = cost.min(axis=0).reshape(slots, 3)  # [F, 3] each axis's least cost
    best = by_axis.min(axis=1)
    near = best * jnp.asarray(1 + TIE_TOLERANCE, dt)
    within = (by_axis <= near[:, None]) & (by_axis < jnp.inf)  # axes with a plane near the best
    axis = jnp.where(within[:, 0], 0, jnp.where(within[:, 1], 1, jnp.where(within[:, 2], 2, 0))).astype(jnp.int32)
    planes = jnp.arange(bins - 1, dtype=jnp.int32)[:, None]
    near_planes = (cost <= jnp.repeat(near, 3)[None, :]) & (cost < jnp.inf)
    lowest = jnp.min(jnp.where(near_planes, planes, bins - 1), axis=0).reshape(slots, 3)  # [F, 3]
    plane = jnp.take_along_axis(lowest, axis[:, None], axis=1)[:, 0]
    plane = jnp.where(plane < bins - 1, plane, 0)  # no candidate: plane 0 on axis 0

    # the winner's sides: its axis's bins up to its plane and after it (min, max and
    # sums in any order: the values of the running sweeps at that plane)
    column = jnp.arange(slots, dtype=jnp.int32) * 3 + axis  # each slot's winner axis in a row of F * 3
    left = jnp.arange(bins, dtype=jnp.int32)[:, None] <= plane[None, :]  # [B, F]

    def side(values, op, fill, mask):  # [B, F, 3] -> [F], over the bins of one side
        return op(jnp.where(mask, rows(values)[:, column], fill), axis=0)

    def box(coords, op, fill, mask):  # three [B, F, 3] -> [F, 3], the coordinates at once
        stacked = jnp.stack(coords).reshape(3, bins, slots * 3)[:, :, column]  # [3, B, F]
        return op(jnp.where(mask[None], stacked, fill), axis=1).T

    inf = jnp.asarray(jnp.inf, dt)
    return Split(best, axis, plane, box(box_lo, jnp.min, inf, left), box(box_hi, jnp.max, -inf, left),
                 box(box_lo, jnp.min, inf, ~left), box(box_hi, jnp.max, -inf, ~left),
                 side(entries, jnp.sum, 0, left).astype(jnp.int32), side(exits, jnp.sum, 0, ~left).astype(jnp.int32))


def _cells(op, columns, key, cells: int, slots: int, bins: int):
    """``op`` (segment min or max) of each coordinate column [M] over ``key`` into
    ``cells`` (bin, slot, axis) cells (``cells`` itself: dropped): three arrays [B, F, 3]."""
    return [segment(op, column, key, cells).reshape(bins, slots, 3) for column in columns]


def cell_key(bin_, seg, axis, slots: int):
    """Cell of (bin, slot, axis) in the [B, F, 3] layout of the binned sweeps."""
    return (bin_ * slots + seg) * 3 + axis


def object_split(ref_lo, ref_hi, seg, slots: int, scale, bins: int):
    """Binned object split of every slot over its references' box centres: ``(split,
    bin3)``, ``bin3`` [R, 3] int32 each reference's bin per axis."""
    dt = ref_lo.dtype
    centre = jnp.asarray(0.5, dt) * ref_lo + jnp.asarray(0.5, dt) * ref_hi
    active = seg < slots
    c = jnp.where(active[:, None], centre, jnp.inf)
    cmin = segment(jax.ops.segment_min, c, seg, slots)
    cmax = segment(jax.ops.segment_max, jnp.where(active[:, None], centre, -jnp.inf), seg, slots)
    span = cmax - cmin
    low_r, span_r = take(cmin, seg, 0), take(span, seg, 0)
    bin3 = rules.bin_of(centre, low_r, span_r, bins)  # [R, 3]
    cells = slots * 3 * bins
    key = cell_key(bin3, seg[:, None], jnp.arange(3, dtype=jnp.int32)[None, :], slots)
    key = jnp.where(active[:, None], key, cells).T.ravel()  # axis-major: [3 R]
    count = segment(jax.ops.segment_sum, jnp.ones(key.shape, jnp.int32), key, cells).reshape(bins, slots, 3)
    box_lo = _cells(jax.ops.segment_min, [jnp.tile(column, 3) for column in ref_lo.T], key, cells, slots, bins)
    box_hi = _cells(jax.ops.segment_max, [jnp.tile(column, 3) for column in ref_hi.T], key, cells, slots, bins)
    split = sweep_bins((count, count), box_lo, box_hi, span > 0, scale, bins)
    return split, bin3


def overlap_area(split: Split, scale):
    """Half-area [F] of the intersection of the two sides' boxes, 0 when they do not meet."""
    lo, hi = jnp.maximum(split.left_lo, split.right_lo), jnp.minimum(split.left_hi, split.right_hi)
    return jnp.where(jnp.all(lo <= hi, axis=-1), half_area(lo, hi, scale), 0)


class Bins(NamedTuple):
    """A reference's entry and exit bins per axis, [R, 3] int32."""

    entry: Any
    exit: Any


#: the spatial search's piece chunk is 3 R / PIECE_CHUNK_DIVISOR pieces (:func:`piece_chunk`)
PIECE_CHUNK_DIVISOR = 16
#: ... and at least this many pieces
MIN_PIECE_CHUNK = 64


def piece_chunk(refs: int, bins: int) -> int:
    """Pieces per step of the spatial search's loop for ``refs`` reference slots.

    A live reference makes one piece per axis and bin it spans: ``3 refs`` pieces when
    none straddles a bin border and at most ``3 refs bins``. The search walks them in
    chunks of one size, so one loop body serves every level (a buffer of several sizes
    chosen by ``lax.switch`` compiles every size); a small chunk wastes little on the
    deep levels (few live references), a large one takes fewer steps near the top.
    """
    return min(3 * refs * bins, max(MIN_PIECE_CHUNK, (3 * refs) // PIECE_CHUNK_DIVISOR))


def _on_axis(axis, coords):
    """The coordinate on ``axis`` [P] of a point given as three coordinate arrays [P]."""
    return jnp.where(axis == 0, coords[0], jnp.where(axis == 1, coords[1], coords[2]))


def _piece_boxes(v, ref_lo, ref_hi, axis, node_lo_a, ext_a, b1, b, valid, bins):
    """What piece ``b`` (a reference's part in spatial bin ``b`` of ``axis``) adds to the
    bins' boxes: ``(corner_lo, corner_hi, cross_lo, cross_hi)``, three coordinate arrays
    [P] each (one entry per piece). ``corner_*``: the box of its corners clamped to its
    box that fall in ``b``, for bin ``b``; ``cross_*``: the clamped crossing of plane
    ``b + 1`` where its box spans it (``b < b1``), for both bins beside that plane.
    Bin ``b``'s box (the twin's ``_bin_boxes`` for one reference and one bin) is then
    the corners in it with the crossings of planes ``b`` and ``b + 1``: each plane's
    crossing is computed once, by the piece below it (computing both planes per piece
    cost nearly twice the search). ``v[k][c]``: vertex ``k``'s coordinate ``c``;
    ``ref_lo[c]``, ``ref_hi[c]``.

    Written coordinate by coordinate on flat arrays, with no concatenation or shift:
    XLA on CPU runs arrays with a trailing axis of 3, and fusions that mix elements,
    many times slower (:func:`spatial_split` shifts the crossings by one lane only
    after they are held in memory).
    """
    dt = ref_lo[0].dtype
    inf = jnp.asarray(jnp.inf, dt)
    corner = [[jnp.clip(v[k][c], ref_lo[c], ref_hi[c]) for c in range(3)] for k in range(3)]
    lo, hi = [inf] * 3, [-inf] * 3
    for k in range(3):
        inside = valid & (rules.bin_of(_on_axis(axis, corner[k]), node_lo_a, ext_a, bins) == b)
        lo = [jnp.minimum(lo[c], jnp.where(inside, corner[k][c], inf)) for c in range(3)]
        hi = [jnp.maximum(hi[c], jnp.where(inside, corner[k][c], -inf)) for c in range(3)]
    a = [_on_axis(axis, v[k]) for k in range(3)]  # the vertices on the split axis
    p = rules.plane_at(node_lo_a, ext_a, b + 1, bins)
    x_lo, x_hi, crossed = [inf] * 3, [-inf] * 3, jnp.zeros(p.shape, bool)
    for i, k in rules.EDGES:
        crosses = ((a[i] < p) & (a[k] > p)) | ((a[i] > p) & (a[k] < p))
        denominator = jnp.where(crosses, a[k] - a[i], jnp.ones((), dt))
        crossed = crossed | crosses
        for c in range(3):
            x = rules.crossing_coordinate(v[i][c], v[k][c], a[i], p, denominator)
            margin = rules.clip_margin(v[i][c], v[k][c])
            x_lo[c] = jnp.minimum(x_lo[c], jnp.where(crosses, jnp.where(axis == c, p, x - margin), inf))
            x_hi[c] = jnp.maximum(x_hi[c], jnp.where(crosses, jnp.where(axis == c, p, x + margin), -inf))
    used = valid & (b < b1) & crossed
    cross_lo = [jnp.where(used, jnp.clip(x_lo[c], ref_lo[c], ref_hi[c]), inf) for c in range(3)]
    cross_hi = [jnp.where(used, jnp.clip(x_hi[c], ref_lo[c], ref_hi[c]), -inf) for c in range(3)]
    return lo, hi, cross_lo, cross_hi


def spatial_split(tri_columns, ref_prim, ref_lo, ref_hi, seg, node_lo, node_hi, tried, node_bins, count, slots: int,
                  scale, bins: int):
    """Binned spatial split of the slots ``tried`` [F] bool: ``(split, bins)``; ``count``
    [F] int32 each slot's references (no side may get all of them).

    Every live reference (one of a tried node) spans bins ``b0 .. b1`` per axis; it is cut
    into one *piece* per (axis, bin) it spans, the pieces are walked in chunks of
    :func:`piece_chunk` (a loop of as many steps as the level needs, one compiled body),
    and each piece's estimated box enters its (node, axis, bin) cell by scatter: its
    corners in that bin and the crossings of the planes below and above it; each plane's
    crossing is computed once, by the piece below it, and handed to the piece above it
    (the next lane: a reference's pieces are consecutive; :func:`_piece_boxes`). A
    reference inside one bin (most of them) is one piece per axis, so the work follows
    the live references and their straddling, not ``bins`` times every slot.
    """
    refs = seg.shape[0]
    ext = node_hi - node_lo  # [F, 3]
    live = (seg < slots) & take(tried, seg, False)
    lo_columns, hi_columns = ref_lo.T, ref_hi.T  # [3, R]
    lo_r, ext_r = take(node_lo, seg, 0), take(ext, seg, 0)  # [R, 3]
    bins_r = take(node_bins, seg, bins)  # [R] the node's spatial bins
    b0 = rules.bin_of(ref_lo, lo_r, ext_r, bins_r[:, None])  # [R, 3] entry and exit bins per axis
    b1 = rules.bin_of(ref_hi, lo_r, ext_r, bins_r[:, None])
    width = jnp.where(live[:, None], b1 - b0 + 1, 0).ravel()  # [3 R] pieces per (reference, axis)
    ends = jnp.cumsum(width)
    total = ends[-1]
    cells = slots * 3 * bins

    chunk = piece_chunk(refs, bins)
    dt = ref_lo.dtype

    def step(i, cell):
        """Pieces ``i chunk .. (i + 1) chunk - 1`` into the cells (scatter min and max: the
        same values as one segment reduction over all pieces).

        A piece's box is its corners with the crossings of the planes below and above
        it. It computes the plane above (:func:`_piece_boxes`); the plane below is the
        one its pair's previous piece computed, which is the previous lane (the pieces
        of a pair are consecutive), so each step also computes the piece before its
        first (lane 0, for that crossing only). One scatter per coordinate and side: the
        crossings need no cells of their own (six scatters a piece, not twelve)."""
        box_lo, box_hi = cell
        p = i * chunk - 1 + jnp.arange(chunk + 1, dtype=jnp.int32)
        owner = jnp.clip(jnp.searchsorted(ends, p, side="right"), 0, 3 * refs - 1).astype(jnp.int32)
        valid = (p >= 0) & (p < total)
        r, axis = owner // 3, owner % 3
        b0_p, b1_p = b0.ravel()[owner], b1.ravel()[owner]
        b = b0_p + p - (ends[owner] - width[owner])
        seg_p = seg[r]
        prim = jnp.clip(ref_prim[r], 0, tri_columns.shape[1] - 1)
        corners = [column[prim] for column in tri_columns]  # gathered column by column
        piece_lo, piece_hi = [column[r] for column in lo_columns], [column[r] for column in hi_columns]
        v = [corners[3 * k: 3 * k + 3] for k in range(3)]
        piece_lo, piece_hi, x_lo, x_hi = _piece_boxes(v, piece_lo, piece_hi, axis, lo_r.ravel()[owner],
                                                      ext_r.ravel()[owner], b1_p, b, valid, bins_r[r])
        # the crossings held in memory once: each is read by its own lane and the next
        x_lo, x_hi = jax.lax.optimization_barrier((x_lo, x_hi))
        below = (b > b0_p)[1:]  # the previous lane is this pair's piece in bin b - 1
        inf = jnp.asarray(jnp.inf, dt)
        lo = [jnp.minimum(jnp.minimum(c[1:], x[1:]), jnp.where(below, x[:-1], inf)) for c, x in zip(piece_lo, x_lo)]
        hi = [jnp.maximum(jnp.maximum(c[1:], x[1:]), jnp.where(below, x[:-1], -inf)) for c, x in zip(piece_hi, x_hi)]
        key = jnp.where(valid, cell_key(b, seg_p, axis, slots), cells)[1:]  # cells: dropped
        box_lo = [c.at[key].min(x, mode="drop") for c, x in zip(box_lo, lo)]
        box_hi = [c.at[key].max(x, mode="drop") for c, x in zip(box_hi, hi)]
        return box_lo, box_hi

    inf = jnp.full(cells, jnp.inf, dt)
    # at most ceil(3 R B / chunk) steps: the pieces are at most 3 R B
    box_lo, box_hi = jax.lax.fori_loop(0, (total + chunk - 1) // chunk, step, ([inf] * 3, [-inf] * 3))
    # entries and exits: one per live reference and axis, counted outside the piece loop
    axes = jnp.arange(3, dtype=jnp.int32)[None, :]
    ones = jnp.ones(3 * refs, jnp.int32)
    counts = [segment(jax.ops.segment_sum, ones, jnp.where(live[:, None], cell_key(b, seg[:, None], axes, slots),
                                                            cells).ravel(), cells).reshape(bins, slots, 3)
              for b in (b0, b1)]
    box_lo = [c.reshape(bins, slots, 3) for c in box_lo]
    box_hi = [c.reshape(bins, slots, 3) for c in box_hi]
    return sweep_bins(counts, box_lo, box_hi, (ext > 0) & tried[:, None], scale, bins, count), Bins(b0, b1)


class Sides(NamedTuple):
    """Where each reference of a spatially split node goes, all [R]."""

    left: Any       # bool: a reference (whole, or its lower piece) goes to the left child
    right: Any      # bool: ... to the right child (both: the reference is split)
    left_lo: Any    # [R, 3] the lower piece's box (straddlers; others keep their box)
    left_hi: Any
    right_lo: Any   # [R, 3] the upper piece's box
    right_hi: Any


def _halfspace_boxes(v, ref_lo, ref_hi, axis, plane):
    """Boxes of the parts of triangles below and above ``plane`` [M] on ``axis`` [M]
    (the plane included in both), intersected with the reference boxes: ``(lo_l, hi_l,
    lo_r, hi_r)``, each three coordinate arrays [M]; ``lo > hi`` somewhere when empty.
    ``v[k][c]``: vertex ``k``'s coordinate ``c`` [M]; ``ref_lo[c]``, ``ref_hi[c]`` [M].

    :func:`jaxbvh.builders.sbvh_rules.halfspace_box` for both sides at once, coordinate
    by coordinate on flat arrays (the crossings are found once for both sides; arrays
    with a trailing axis of 3 ran several times slower on XLA's CPU backend).
    """
    dt = plane.dtype
    inf = jnp.asarray(jnp.inf, dt)
    a = [_on_axis(axis, v[k]) for k in range(3)]
    lo_l, hi_l, lo_r, hi_r = [inf] * 3, [-inf] * 3, [inf] * 3, [-inf] * 3
    for k in range(3):  # the corners on each side (the plane included)
        below, above = a[k] <= plane, a[k] >= plane
        lo_l = [jnp.minimum(lo_l[c], jnp.where(below, v[k][c], inf)) for c in range(3)]
        hi_l = [jnp.maximum(hi_l[c], jnp.where(below, v[k][c], -inf)) for c in range(3)]
        lo_r = [jnp.minimum(lo_r[c], jnp.where(above, v[k][c], inf)) for c in range(3)]
        hi_r = [jnp.maximum(hi_r[c], jnp.where(above, v[k][c], -inf)) for c in range(3)]
    for i, k in rules.EDGES:  # the widened crossings, on both sides
        crosses = ((a[i] < plane) & (a[k] > plane)) | ((a[i] > plane) & (a[k] < plane))
        denominator = jnp.where(crosses, a[k] - a[i], jnp.ones((), dt))
        for c in range(3):
            x = rules.crossing_coordinate(v[i][c], v[k][c], a[i], plane, denominator)
            margin = rules.clip_margin(v[i][c], v[k][c])
            x_lo = jnp.where(crosses, jnp.where(axis == c, plane, x - margin), inf)
            x_hi = jnp.where(crosses, jnp.where(axis == c, plane, x + margin), -inf)
            lo_l[c], lo_r[c] = jnp.minimum(lo_l[c], x_lo), jnp.minimum(lo_r[c], x_lo)
            hi_l[c], hi_r[c] = jnp.maximum(hi_l[c], x_hi), jnp.maximum(hi_r[c], x_hi)

    def clamp(lo, hi):
        return [jnp.maximum(lo[c], ref_lo[c]) for c in range(3)], [jnp.minimum(hi[c], ref_hi[c]) for c in range(3)]

    return (*clamp(lo_l, hi_l), *clamp(lo_r, hi_r))


def spatial_sides(tri_columns, ref_prim, ref_lo, ref_hi, seg, node_lo, node_hi, split: Split, ref_bins: Bins,
                  node_bins, slots: int, scale, bins: int):
    """Sides of every reference under each slot's spatial split (the twin's
    ``_spatial_sides``: forced unsplits, priced unsplits, then drop the priced ones if a
    side would be empty): ``(sides, ok [F], extra [F])``; ``ok`` False where a side stays
    empty. ``tri_columns`` [9, T]: the triangles coordinate by coordinate."""
    dt = ref_lo.dtype
    active = seg < slots
    axis_r, k_r = take(split.axis, seg, 0), take(split.plane, seg, 0)
    b0 = jnp.take_along_axis(ref_bins.entry, axis_r[:, None], axis=1)[:, 0]
    b1 = jnp.take_along_axis(ref_bins.exit, axis_r[:, None], axis=1)[:, 0]
    straddle = active & (b0 <= k_r) & (b1 > k_r)
    to_left = active & (b1 <= k_r)
    to_right = active & (b0 > k_r)
    node_lo_a = jnp.take_along_axis(take(node_lo, seg, 0), axis_r[:, None], axis=1)[:, 0]
    ext_a = jnp.take_along_axis(take(node_hi - node_lo, seg, 0), axis_r[:, None], axis=1)[:, 0]
    plane = rules.plane_at(node_lo_a, ext_a, k_r + 1, take(node_bins, seg, bins))
    prim = jnp.clip(ref_prim, 0, tri_columns.shape[1] - 1)
    corners = [column[prim] for column in tri_columns]
    v = [corners[3 * k: 3 * k + 3] for k in range(3)]
    boxes = _halfspace_boxes(v, list(ref_lo.T), list(ref_hi.T), axis_r, plane)
    lo_l, hi_l, lo_r, hi_r = (jnp.stack(coords, axis=1) for coords in boxes)  # [R, 3] each
    forced_right = straddle & jnp.any(lo_l > hi_l, axis=1)
    forced_left = straddle & jnp.any(lo_r > hi_r, axis=1) & ~forced_right
    # the paper's unsplitting: each straddler priced against the split's totals
    a_l = half_area(split.left_lo, split.left_hi, scale)
    a_r = half_area(split.right_lo, split.right_hi, scale)
    n_l, n_r = split.n_left.astype(dt), split.n_right.astype(dt)
    c_split = take(a_l * n_l + a_r * n_r, seg, 0)
    one = jnp.ones((), dt)
    g = lambda v: take(v, seg, 0)  # noqa: E731  per-reference view of a per-slot value
    c_left = half_area(jnp.minimum(g(split.left_lo), ref_lo), jnp.maximum(g(split.left_hi), ref_hi), scale) * g(n_l) \
        + g(a_r) * (g(n_r) - one)
    c_right = g(a_l) * (g(n_l) - one) \
        + half_area(jnp.minimum(g(split.right_lo), ref_lo), jnp.maximum(g(split.right_hi), ref_hi), scale) * g(n_r)
    tol = jnp.asarray(1 + TIE_TOLERANCE, dt)
    left_wins = c_left * tol < c_split
    right_wins = c_right * tol < c_split
    prefer_left = left_wins & (c_left <= c_right)
    forced = forced_left | forced_right
    cheap_left = straddle & prefer_left & ~forced
    cheap_right = straddle & right_wins & ~prefer_left & ~forced

    def sides(only_left, only_right):
        go_left = to_left | (straddle & ~only_right)
        go_right = to_right | (straddle & ~only_left)
        both = (segment(jax.ops.segment_max, go_left.astype(jnp.int32), seg, slots) > 0) \
            & (segment(jax.ops.segment_max, go_right.astype(jnp.int32), seg, slots) > 0)
        return go_left, go_right, both

    left1, right1, ok1 = sides(forced_left | cheap_left, forced_right | cheap_right)
    left2, right2, ok2 = sides(forced_left, forced_right)
    first = take(ok1, seg, False)
    go_left, go_right = jnp.where(first, left1, left2), jnp.where(first, right1, right2)
    ok = ok1 | ok2
    extra = segment(jax.ops.segment_sum, (go_left & go_right).astype(jnp.int32), seg, slots)
    return Sides(go_left, go_right, lo_l, hi_l, lo_r, hi_r), ok, extra


def rank_by_prim(prim, seg, slots: int):
    """Rank [R] int32 of each reference among its slot's by triangle id (the halves of a
    node whose centres all coincide)."""
    order = jnp.lexsort((prim, seg))
    sorted_seg = seg[order]
    pos = jnp.arange(seg.shape[0], dtype=jnp.int32)
    first = segment(jax.ops.segment_min, pos, sorted_seg, slots)
    rank_sorted = pos - take(first, sorted_seg, 0)
    return jnp.zeros(seg.shape[0], jnp.int32).at[order].set(rank_sorted)

