"""Hostile tree files: every array's type and shape, the frame, float widths, subnormals.

The interchange reader either loads a file as exactly the tree it stores (boxes widened
exactly, or narrowed outward), or refuses it with one ``ValueError`` naming the file
and an array; never another exception.
"""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from helpers import three_triangle_files
from hypothesis import given
from hypothesis import strategies as st
from strategies import tree_file_changes

import jaxbvh
from jaxbvh.tree.interchange import INTERCHANGE_KEYS


@pytest.fixture(scope="module")
def sound(tmp_path_factory):
    """The three-triangle tree with a frame that is not the identity."""
    _, arrays = three_triangle_files(tmp_path_factory.mktemp("three"))
    return {**arrays, "origin": np.array([0.5, -1.0, 2.0]), "scale": np.float64(4.0)}


def _load(tmp_path, arrays, name="tree.npz"):
    path = tmp_path / name
    np.savez(path, **arrays)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        tree, frame = jaxbvh.load(path)
    return path, tree, frame, [str(w.message) for w in caught]


@given(st.data())
def test_any_type_and_shape_of_any_array_loads_exactly_or_is_named(sound, tmp_path_factory, data):
    changed, changes = data.draw(tree_file_changes(sound))
    tmp_path = tmp_path_factory.mktemp("fuzz")
    try:
        path, tree, frame, said = _load(tmp_path, changed)
    except ValueError as exc:
        message = str(exc)
        assert "\n" not in message
        assert message.startswith(str(tmp_path / "tree.npz") + ": ")
        assert any(f"'{key}'" in message for key, _, _ in changes), (message, changes)
        return
    # loaded: the structure is the sound file's (a changed type that kept every value is
    # fine), the frame is the one stored, and the boxes contain the stored values
    # exactly (no box shrank)
    again = jaxbvh.to_interchange(tree)
    for key in ("child", "prim_start", "prim_count", "prim_index", "root"):
        assert np.array_equal(again[key], sound[key]), key
    assert np.array_equal(frame.origin, np.asarray(changed["origin"]).astype(np.float64))
    assert frame.scale == float(changed["scale"]) > 0
    for key in ("lo", "hi"):
        stored, got = np.asarray(changed[key]), again[key]
        assert got.dtype in (np.float32, np.float64) and got.shape == stored.shape
        wide, exact = got.astype(np.longdouble), stored.astype(np.longdouble)
        assert (wide <= exact).all() if key == "lo" else (wide >= exact).all()
        if stored.dtype.itemsize <= 8:
            assert np.array_equal(wide, exact), key  # float16 widens exactly
        if stored.dtype not in (np.float32, np.float64):
            assert any(f"'{key}' is stored as {stored.dtype}" in s for s in said), said


@pytest.mark.parametrize("origin, scale, named", [
    (np.zeros(3), np.ones(1), "'scale' must be a real scalar"),
    (np.zeros(2), np.float64(1), "'origin' must be real [3]"),
    (np.array([np.nan, 0, 0]), np.float64(1), "'origin' must be finite"),
    (np.zeros(3), np.float64(0), "'scale' must be finite and > 0"),
    (np.zeros(3), np.float64(-2), "'scale' must be finite and > 0"),
    (np.zeros(3), np.float64(np.nan), "'scale' must be finite and > 0"),
    (np.zeros(3), np.float64(np.inf), "'scale' must be finite and > 0"),
    (np.zeros(3), np.complex128(1), "'scale' must be a real scalar"),
    (None, np.float64(2), "has 'scale' but no 'origin'"),
])
def test_a_bad_frame_is_refused_naming_the_array(sound, tmp_path, origin, scale, named):
    arrays = {k: v for k, v in sound.items() if k in INTERCHANGE_KEYS}
    arrays["scale"] = scale
    if origin is not None:
        arrays["origin"] = origin
    with pytest.raises(ValueError) as info:
        _load(tmp_path, arrays)
    assert str(info.value).startswith(f"{tmp_path / 'tree.npz'}: ") and named in str(info.value)


def test_root_must_be_a_scalar_and_ids_must_fit_int32(sound, tmp_path):
    with pytest.raises(ValueError, match=r"'root' must be an integer scalar \(shape \(\)\)"):
        _load(tmp_path, {**sound, "root": np.array([0])})
    with pytest.raises(ValueError, match="'prim_index' holds values outside int32"):
        _load(tmp_path, {**sound, "prim_index": sound["prim_index"].astype(np.int64) + 2 ** 31})


def test_float16_boxes_widen_exactly_and_long_double_narrows_outward(sound, tmp_path):
    half = {**sound, "lo": sound["lo"].astype(np.float16), "hi": sound["hi"].astype(np.float16)}
    _, tree, _, said = _load(tmp_path, half)
    assert tree.lo.dtype == np.float32
    assert np.array_equal(jaxbvh.to_interchange(tree)["lo"], half["lo"].astype(np.float32))
    assert len(said) == 2 and all("widened to float32 (exact)" in s for s in said)
    # a long double that float64 cannot hold moves outward, not to nearest
    tiny = np.longdouble(2) ** -60  # 1 + 2^-60: exact in long double (x87), not in float64
    lo, hi = sound["lo"].astype(np.longdouble) + tiny, sound["hi"].astype(np.longdouble) - tiny
    if np.finfo(np.longdouble).eps >= np.finfo(np.float64).eps:
        pytest.skip("long double is float64 on this platform")
    _, tree, _, said = _load(tmp_path, {**sound, "lo": lo, "hi": hi})
    got = jaxbvh.to_interchange(tree)
    assert got["lo"].dtype == np.float64 and (got["lo"] <= lo).all() and (got["hi"] >= hi).all()
    assert (got["lo"] < lo).any()  # rounded down where it was not exact
    assert any("narrowed to float64, rounded outward" in s for s in said)


def test_subnormal_boxes_are_scaled_out_of_range_with_the_frame_scaled_back(sound, tmp_path):
    """Boxes at 1e-40 with the frame's scale at 1e40: the same world, the same costs."""
    tiny = {**sound, "lo": sound["lo"] * np.float32(2.0 ** -140), "hi": sound["hi"] * np.float32(2.0 ** -140),
            "scale": np.float64(sound["scale"] * 2.0 ** 140)}
    _, normal, normal_frame, _ = _load(tmp_path, sound, "normal.npz")
    _, tree, frame, said = _load(tmp_path, tiny)
    assert any("subnormal" in s for s in said)
    assert np.array_equal(frame.to_world(jaxbvh.to_interchange(tree)["lo"]),
                          normal_frame.to_world(jaxbvh.to_interchange(normal)["lo"]))
    assert jaxbvh.all_costs(tree) == jaxbvh.all_costs(normal)


def test_costs_of_subnormal_boxes_are_not_flushed(sound):
    """all_costs scales small trees up on the host: XLA would flush subnormals to zero."""
    normal = jaxbvh.from_interchange(sound)
    tiny = jaxbvh.from_interchange({**sound, "lo": sound["lo"] * np.float32(2.0 ** -140),
                                    "hi": sound["hi"] * np.float32(2.0 ** -140)})
    assert np.asarray(tiny.lo)[2, 0] != 0 and abs(np.asarray(tiny.lo)[2, 0]) < np.finfo(np.float32).tiny
    assert jaxbvh.all_costs(tiny) == jaxbvh.all_costs(normal)
