"""The background-biased hole fill: copies only known pixels, prefers the farther side, never NaN."""
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from engine.geometry.holefill import fill_holes


def test_fills_from_background_side():
    color = np.zeros((1, 7, 3), np.float32)
    depth = np.array([[1.0, 1.0, 9, 9, 9, 5.0, 5.0]], np.float32)
    color[0, :2] = 0.9  # near foreground on the left
    color[0, 5:] = 0.2  # farther background on the right
    holes = np.array([[False, False, True, True, True, False, False]])
    out, d = fill_holes(color, depth, holes)
    np.testing.assert_allclose(out[0, 2:5], 0.2)
    np.testing.assert_allclose(d[0, 2:5], 5.0)
    assert np.all(color[0, 2:5] == 0)  # input untouched


def test_sky_counts_as_background_and_rows_without_pixels_use_columns():
    color = np.zeros((3, 4, 3), np.float32)
    color[0] = 0.5
    depth = np.full((3, 4), 2.0, np.float32)
    depth[0, 3] = np.inf
    color[0, 3] = 0.7
    holes = np.zeros((3, 4), bool)
    holes[0, 2] = True
    holes[1:] = True  # rows 1 and 2 are all hole: filled along columns
    out, _ = fill_holes(color, depth, holes)
    np.testing.assert_allclose(out[0, 2], 0.7)  # the sky side wins
    np.testing.assert_allclose(out[1:, 0], 0.5)


def test_all_hole_frame_takes_fallback():
    color = np.full((4, 5, 3), np.nan, np.float32)
    fallback = np.full((4, 5, 3), 0.3, np.float32)
    out, d = fill_holes(color, np.full((4, 5), np.nan, np.float32), np.ones((4, 5), bool), fallback)
    np.testing.assert_allclose(out, 0.3)
    assert np.all(np.isinf(d))


@settings(max_examples=40, deadline=None)
@given(st.integers(1, 12), st.integers(1, 12), st.floats(0.0, 1.0), st.integers(0, 2 ** 31 - 1))
def test_every_filled_pixel_is_a_copy_of_a_known_pixel(h, w, hole_rate, seed):
    rng = np.random.default_rng(seed)
    color = rng.random((h, w, 3)).astype(np.float32)
    depth = rng.uniform(0.1, 100, (h, w)).astype(np.float32)
    holes = rng.random((h, w)) < hole_rate
    poisoned = color.copy()
    poisoned[holes] = np.nan
    out, _ = fill_holes(poisoned, depth, holes, fallback=np.zeros_like(color))
    assert np.all(np.isfinite(out))
    np.testing.assert_array_equal(out[~holes], color[~holes])
    if (~holes).any():
        known = {tuple(c) for c in color[~holes].tolist()}
        assert all(tuple(c) in known for c in out[holes].tolist())


@pytest.mark.parametrize("threads", [1, 2])
@pytest.mark.parametrize("seed", range(6))
def test_compiled_fill_equals_the_numpy_fill(monkeypatch, threads, seed):
    """``fill_holes`` (the compiled row pass, or the numpy path when a hole finds no source on its row) equals
    ``fill_holes_reference`` to the bit: sky, NaN depths beside holes, all-hole rows and columns, fallbacks."""
    from engine.geometry import kernels
    from engine.geometry.holefill import fill_holes_reference

    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 32)
    rng = np.random.default_rng(seed)
    h, w = int(rng.integers(1, 50)), int(rng.integers(1, 70))
    color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    depth = rng.uniform(1, 10, (h, w)).astype(np.float32)
    depth[rng.uniform(size=(h, w)) < 0.1] = np.inf
    holes = rng.uniform(size=(h, w)) < rng.uniform(0.05, 0.95)
    if seed % 2:
        holes[h // 2] = True  # a row without a known pixel: the column pass
    if seed % 3 == 0:
        depth[rng.uniform(size=(h, w)) < 0.05] = np.nan
    fallback = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    for fast, ref in zip(fill_holes(color, depth, holes, fallback), fill_holes_reference(color, depth, holes, fallback)):
        np.testing.assert_array_equal(fast, ref)
        assert fast.dtype == np.float32
    color_in, depth_in = color.copy(), depth.copy()
    fill_holes(color, depth, holes, fallback)
    np.testing.assert_array_equal(color, color_in)  # inputs untouched
    np.testing.assert_array_equal(depth, depth_in)


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_the_compiled_column_pass_equals_the_numpy_fill_on_bands_of_empty_rows(monkeypatch, threads):
    """Rows with no known pixel, in bands at the top, the bottom and inside, beside rows with holes, NaN
    depths and sky, with and without a fallback, a frame that is all hole, columns split over threads."""
    from engine.geometry import kernels
    from engine.geometry.holefill import fill_holes_reference

    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 16)
    rng = np.random.default_rng(40 + threads)
    h, w = 37, 53
    color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    depth = rng.uniform(1, 10, (h, w)).astype(np.float32)
    depth[rng.uniform(size=(h, w)) < 0.1] = np.inf
    depth[rng.uniform(size=(h, w)) < 0.03] = np.nan
    holes = rng.uniform(size=(h, w)) < 0.3
    for band in (slice(0, 3), slice(10, 11), slice(15, 21), slice(34, 37)):
        holes[band] = True
    fallback = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    for case_holes in (holes, np.ones((h, w), bool)):
        for back in (fallback, None):
            fast = fill_holes(color, depth, case_holes, back)
            for a, b in zip(fast, fill_holes_reference(color, depth, case_holes, back)):
                np.testing.assert_array_equal(a, b)
