"""Hypothesis strategies shared by the tests: triangle soups, plain and extreme."""

from __future__ import annotations

import numpy as np
from hypothesis import strategies as st


@st.composite
def triangle_soups(draw, min_size: int = 1, max_size: int = 40, extreme: bool = True):
    """World-space triangles float64 [n, 3, 3].

    Mixes random triangles with degenerate ones (a repeated vertex, all three in one
    point, every triangle in one point), flat scenes (one plane), and, with
    ``extreme``, scales of 1e-30 ... 1e30 and offsets up to 1e7.
    """
    n = draw(st.integers(min_size, max_size))
    seed = draw(st.integers(0, 2**32 - 1))
    rng = np.random.default_rng(seed)
    kind = draw(st.sampled_from(["random", "clustered", "flat", "degenerate", "one_point", "grid"]))
    if kind == "one_point":
        tri = np.broadcast_to(rng.normal(size=3), (n, 3, 3)).copy()
    elif kind == "grid":  # many exact ties in centres and costs
        cells = rng.integers(0, 3, size=(n, 1, 3)).astype(np.float64)
        tri = cells + np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], np.float64)
    else:
        centres = rng.normal(size=(n, 1, 3)) * (0.2 if kind == "clustered" else 1.0)
        tri = centres + rng.normal(size=(n, 3, 3)) * 10.0 ** rng.uniform(-3, 0, size=(n, 1, 1))
        if kind == "flat":
            tri[..., 2] = 0.0
        if kind == "degenerate":
            pick = rng.random(n) < 0.5
            tri[pick, 1] = tri[pick, 0]  # a line or a point
            tri[rng.random(n) < 0.2] = tri[0, 0]
    if extreme:
        scale = 10.0 ** draw(st.sampled_from([0, -30, -10, 10, 30]))
        offset = draw(st.sampled_from([0.0, 1e7, -1e7]))  # in units of the scene size
        tri = (tri + offset) * scale  # offset relative to the scene size
    return tri


def boxes(tri: np.ndarray):
    """World boxes (lo, hi) float64 [n, 3] of triangles [n, 3, 3]."""
    return tri.min(axis=1), tri.max(axis=1)


@st.composite
def box_sets(draw, min_size: int = 1, max_size: int = 40):
    """Random float32 primitive boxes (lo, hi) [n, 3] in [-1, 1] with a sprinkle of ties."""
    n = draw(st.integers(min_size, max_size))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    centre = rng.uniform(-1, 1, size=(n, 3))
    half = rng.uniform(0, 0.3, size=(n, 3)) * (rng.random((n, 1)) < 0.9)
    if draw(st.booleans()):
        centre = np.round(centre * 4) / 4  # shared centres, equal costs
    return (centre - half).astype(np.float32), (centre + half).astype(np.float32)
