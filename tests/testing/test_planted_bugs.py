"""Proof that the kit finds bugs: a small sound builder passes it, and four copies of it,
each with one planted bug, fail it, with a shrunk example of at most a few triangles.

The builder is a plain median split (leaves of one primitive), written here as a user
would write theirs. The bugs are the kinds that slip past example tests: one that drops a
primitive on some inputs, boxes one ulp too small, a cycle only on ties, and a padding
that overflows only at the 1e30 scale. Each is hunted the way a user's test would run: a
hypothesis test (nested, ``@given``) asserts ``assert_valid_tree`` on soups of the kit;
it fails, hypothesis shrinks the failure, and its last run is the shrunk example.
(:func:`hypothesis.find` shrinks far less here: it stopped at two triangles at the 1e10
scale where ``@given`` reaches one triangle at the origin.)
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, given, settings

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
                with np.errstate(over="ignore"):  # the overflow is the planted bug
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


def hunt(bug, soups):
    """The shrunk soup on which the kit fails ``bug``'s builder, or None if none is found."""
    runs = []

    @HUNT
    @given(soups)
    def the_users_test(tri):
        runs.append(tri)
        lo, hi = boxes(tri)
        assert_valid_tree(median_build(lo, hi, bug), lo, hi)

    try:
        the_users_test()
    except AssertionError:
        return runs[-1]  # hypothesis runs the shrunk failure last, to report it
    return None


def kit_failure(tri, bug):
    """The kit's one-line message on the tree ``bug`` builds over ``tri``, or None."""
    lo, hi = boxes(tri)
    try:
        assert_valid_tree(median_build(lo, hi, bug), lo, hi)
    except AssertionError as failure:
        return str(failure)
    return None


# How hard the hunt looks: enough to meet each bug among the kit's draws, with a fixed seed;
# soups of up to 12 triangles (every bug shows on fewer: the search is what costs)
SOUPS = triangle_soups(1, 12)
HUNT = settings(max_examples=300, phases=[Phase.generate, Phase.shrink], database=None, derandomize=True, deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])

# bug -> (the invariant the kit names, the most triangles a shrunk example may keep)
BUGS = {
    "drop": (DEFECTS["lost_primitive"], 3),
    "ulp": (DEFECTS["primitive_outside_leaf"], 1),
    "cycle": (DEFECTS["cycle"], 2),
    # 1 when this module runs alone, 5 beside the suite's other modules (jaxbvh.cli imported):
    # the scale is drawn after the coordinates, so removing a triangle shifts the draws the
    # scale reads and the shrinker must get around that; see docs/testing.md
    "overflow": (DEFECTS["nan_box"], 5),
}


@given(triangle_soups(1, 40))
def test_the_sound_builder_passes_the_kit(tri):
    assert kit_failure(tri, None) is None


@pytest.mark.parametrize("bug", sorted(BUGS))
def test_the_kit_finds_each_planted_bug_and_shrinks_it(bug):
    named, most = BUGS[bug]
    tri = hunt(bug, SOUPS)
    assert tri is not None, f"{bug}: not found"
    message = kit_failure(tri, bug)
    assert tri.shape[0] <= most, f"{bug}: shrunk to {tri.shape[0]} triangles: {message}"
    assert named in message and "\n" not in message, message
    if bug == "overflow":  # found at the 1e30 scale (1e30 times the smallest lattice step)
        assert np.abs(tri).max() > 1e20
    else:  # shrunk to small round coordinates
        assert np.abs(tri).max() <= 4


def test_the_overflow_is_not_found_without_extreme_scales():
    # why the kit draws scales of 1e-30 .. 1e30: without them this bug hides
    assert hunt("overflow", triangle_soups(1, 12, extreme=False)) is None
