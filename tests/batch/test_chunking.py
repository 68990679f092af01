"""Chunks of a run of files (:mod:`jaxbvh.batch.chunking`): one capacity bucket per chunk,
every file once, and triangle estimates equal to what the mesh loader finds."""

from __future__ import annotations

import collections

import numpy as np
import pytest
import trimesh
from helpers import grid_obj
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxbvh
from jaxbvh.batch.chunking import chunk_items, triangle_estimate
from jaxbvh.tree.layout import capacity_bucket


@settings(max_examples=60, deadline=None)
@given(counts=st.lists(st.one_of(st.none(), st.integers(0, 5000)), min_size=1, max_size=60),
       chunk_files=st.integers(1, 9))
def test_chunks_never_mix_buckets_and_hold_every_file_once(counts, chunk_files):
    items = [(f"m{i}.obj", f"m{i}.obj.npz") for i in range(len(counts))]
    estimate = dict(zip((p for p, _ in items), counts)).get
    chunks = chunk_items(items, chunk_files, estimate=estimate)
    flat = [item for chunk in chunks for item in chunk]
    assert sorted(flat) == sorted(items)  # every file, once
    assert all(1 <= len(chunk) <= chunk_files for chunk in chunks)
    per_bucket = collections.Counter()
    for chunk in chunks:
        known = {estimate(p) is None for p, _ in chunk}
        assert len(known) == 1  # files without an estimate never share a chunk with others
        if known == {True}:
            continue
        buckets = {capacity_bucket(max(estimate(p), 1)) for p, _ in chunk}
        assert len(buckets) == 1  # one capacity bucket: one compiled call
        if len(chunk) < chunk_files:
            per_bucket[buckets.pop()] += 1
    assert all(n == 1 for n in per_bucket.values())  # a bucket's chunks are full but its last
    # within a bucket the input order is kept
    for chunk in chunks:
        positions = [items.index(item) for item in chunk]
        assert positions == sorted(positions)


def test_chunk_files_below_one_is_an_error():
    with pytest.raises(ValueError, match="chunk_files"):
        chunk_items([("a.obj", "a.obj.npz")], 0)


def test_triangle_estimates_equal_the_loaders_counts(tmp_path):
    grid = grid_obj(tmp_path / "grid.obj", 3, 1)  # 18 triangles
    (tmp_path / "quads.obj").write_text(  # a quad and a pentagon: 2 + 3 triangles, as trimesh splits them
        "v 0 0 0\nv 1 0 0\nv 1 1 0\nv 0 1 0\nv 0.5 1.5 0\nf 1 2 3 4\nf 1/1 2/2 3/3 5/5 4/4\n")
    mesh = jaxbvh.load_mesh(grid)
    solid = trimesh.Trimesh(mesh.vertices, mesh.faces, process=False)
    for suffix, options in ((".ply", {}), (".stl", {}), (".off", {})):
        solid.export(tmp_path / f"grid{suffix}", **options)
    (tmp_path / "ascii.stl").write_text(trimesh.exchange.stl.export_stl_ascii(solid))
    names = ["grid.obj", "quads.obj", "grid.ply", "grid.stl", "grid.off", "ascii.stl"]
    for name in names:
        assert triangle_estimate(tmp_path / name) == jaxbvh.load_mesh(tmp_path / name).n_triangles, name
    assert triangle_estimate(tmp_path / "missing.obj") is None
    assert triangle_estimate(tmp_path / "grid.glb") is None  # no cheap count: chunked by size


def test_a_run_builds_one_compiled_call_per_chunk(tmp_path, monkeypatch):
    """Meshes of two buckets, interleaved in the folder: each chunk is one call of one capacity."""
    from jaxbvh.batch import runs

    folder = tmp_path / "in"
    folder.mkdir()
    for i in range(6):
        grid_obj(folder / f"m{i}.obj", 2 + 2 * (i % 2), i)  # 8 triangles (bucket 8) or 32 (bucket 32)
    calls = []
    real_build = runs.build

    def spy(meshes, *args, **kwargs):
        made = real_build(meshes, *args, **kwargs)
        calls.append(made.trees.capacities)
        return made

    monkeypatch.setattr(runs, "build", spy)
    made = runs.run_files(sorted(folder.iterdir()), tmp_path / "out", chunk_files=2)
    assert made.done == 6 and np.isfinite([r["sah"] for r in made.rows]).all()
    assert sorted(calls) == [(8,), (8,), (32,), (32,)]  # 3 files of each bucket in chunks of 2 and 1
