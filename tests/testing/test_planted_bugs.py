"""Proof that the kit finds bugs: a small sound builder passes it, and four copies of it,
each with one planted bug, fail it, with a shrunk example of at most a few triangles.

The builder is a plain median split (leaves of one primitive), written here as a user
would write theirs. The bugs are the kinds that slip past example tests: one that drops a
primitive on some inputs, boxes one ulp too small, a cycle only on ties, and a padding
that overflows only at the 1e30 scale. Each is hunted the way a user's test would run:
:func:`hypothesis.find` looks for triangle soups on which ``assert_valid_tree`` fails,
and shrinks the first it finds.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, find, given, settings
from hypothesis.errors import NoSuchExample

import jaxbvh
from jaxbvh.testing import DEFECTS, assert_valid_tree
from jaxbvh.testing.strategies import boxes, triangle_soups


def median_build(lo, hi, bug: str | None = None):
    """A binary tree over boxes ``lo``, ``hi`` [n, 3] (float64): median splits of the
    centroids along the widest centroid axis, one primitive per leaf. ``bug`` plants
    one bug (module docstring): "drop", "ulp", "cycle" or "overflow"."""
    lo, hi = np.asarray(lo), np.asarray(hi)
    ids = list(range(lo.shape[0]))
    if bug == "drop" and len(ids) >= 3:
        ids = ids[:-1]  # an off-by-one in the primitive count, only seen from three on
    centroid = (lo + hi) / 2
    child, start, count, prim_index, box_lo, box_hi = [], [], [], [], [], []

    def make(group):  # bounded: each call splits its group into two smaller ones
        i = len(child)
        child.append([-1, -1]), start.append(0), count.append(0), box_lo.append(None), box_hi.append(None)
        if len(group) == 1:
            start[i], count[i] = len(prim_index), 1
            prim_index.append(group[0])
            box_lo[i], box_hi[i] = lo[group[0]].copy(), hi[group[0]].copy()
            if bug == "ulp":  # rounds the leaf box to nearest instead of outwards
                box_hi[i] = np.nextafter(box_hi[i], -np.inf)
            if bug == "overflow":  # a conservative margin from the squared size, in float32
                size = np.float32(np.sqrt(np.sum(np.float32(hi[group[0]] - lo[group[0]]) ** 2)))
                margin = np.float64(size * np.float32(2.0 ** -40))
                box_lo[i], box_hi[i] = box_lo[i] - margin, box_hi[i] + margin
            return i
        c = centroid[group]
        axis = int(np.argmax(c.max(0) - c.min(0)))
        order = [group[j] for j in np.argsort(c[:, axis], kind="stable")]
        half = len(order) // 2
        a = make(order[:half])
        tie = centroid[order[half - 1], axis] == centroid[order[half], axis]
        b = i if bug == "cycle" and tie else make(order[half:])  # reuses the node id on a tie
        child[i] = [a, b]
        if b == i:  # the right half is lost with the link: keep the box of what was built
            box_lo[i], box_hi[i] = box_lo[a], box_hi[a]
        else:
            box_lo[i], box_hi[i] = np.minimum(box_lo[a], box_lo[b]), np.maximum(box_hi[a], box_hi[b])
        return i

    make(ids)
    return jaxbvh.from_interchange(dict(
        child=np.array(child, np.int32), prim_start=np.array(start, np.int32), prim_count=np.array(count, np.int32),
        prim_index=np.array(prim_index, np.int32), lo=np.array(box_lo), hi=np.array(box_hi), root=np.int32(0)),
        pad=False)


def kit_failure(tri, bug):
    """The kit's one-line message on the tree ``bug`` builds over ``tri``, or None."""
    lo, hi = boxes(tri)
    try:
        assert_valid_tree(median_build(lo, hi, bug), lo, hi)
    except AssertionError as failure:
        return str(failure)
    return None


# How hard find() looks: enough to meet each bug from the kit's draws, with a fixed seed
HUNT = settings(max_examples=500, database=None, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# bug -> (the invariant the kit names, the most triangles a shrunk example may keep)
BUGS = {
    "drop": (DEFECTS["lost_primitive"], 3),
    "ulp": (DEFECTS["primitive_outside_leaf"], 1),
    "cycle": (DEFECTS["cycle"], 2),
    "overflow": (DEFECTS["nan_box"], 1),
}


@given(triangle_soups(1, 40))
def test_the_sound_builder_passes_the_kit(tri):
    assert kit_failure(tri, None) is None


@pytest.mark.parametrize("bug", sorted(BUGS))
def test_the_kit_finds_each_planted_bug_and_shrinks_it(bug):
    named, most = BUGS[bug]
    tri = find(triangle_soups(1, 40), lambda tri: kit_failure(tri, bug) is not None, settings=HUNT)
    message = kit_failure(tri, bug)
    assert tri.shape[0] <= most, f"{bug}: shrunk to {tri.shape[0]} triangles: {message}"
    assert named in message and "\n" not in message, message


def test_the_overflow_is_found_only_at_1e30():
    # the same hunt without the extreme scales finds nothing: why the kit draws them
    with pytest.raises(NoSuchExample):
        find(triangle_soups(1, 40, extreme=False), lambda tri: kit_failure(tri, "overflow") is not None,
             settings=HUNT)
    tri = find(triangle_soups(1, 40), lambda tri: kit_failure(tri, "overflow") is not None, settings=HUNT)
    assert np.abs(tri).max() >= 1e29
