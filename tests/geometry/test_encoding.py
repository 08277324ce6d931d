"""Compiled colour encodings of whole frames (engine/geometry/encoding.py) against ``engine.core.colorspace``:
the 8-bit encoding and decoding exactly, the float sRGB curves to one float32 ulp (numpy may evaluate ``power``
with SIMD code that rounds differently from libm's ``pow``); any split of the rows over threads."""
from __future__ import annotations

import numpy as np
import pytest

from engine.core import colorspace
from engine.geometry import encoding, kernels


def _values(rng) -> np.ndarray:
    special = [np.nan, np.inf, -np.inf, -0.0, 0.0, 1.0, -1e-30, 1e-30, 0.0031308, 0.04045, 0.5, 2.0]
    edges = [np.nextafter(np.float32(v), np.float32(d)) for v in (0.0031308, 0.04045, 1.0) for d in (0, 2)]
    values = np.concatenate([special, edges, rng.uniform(-0.2, 1.3, 30000), np.linspace(0.0, 1.0, 20011)])  # hard first
    return values.astype(np.float32)


def _assert_within_one_ulp(fast: np.ndarray, reference: np.ndarray) -> None:
    assert fast.dtype == np.float32 and fast.shape == reference.shape
    both_nan = np.isnan(fast) & np.isnan(reference)
    assert not (np.isnan(fast) ^ np.isnan(reference)).any()
    steps = np.abs(fast.view(np.int32).astype(np.int64) - reference.view(np.int32).astype(np.int64))
    assert ((steps <= 1) | both_nan | (fast == reference)).all()


@pytest.mark.parametrize("threads", [1, 2, 3])
def test_frame_encodings_equal_the_colorspace_references(monkeypatch, threads):
    monkeypatch.setenv("INTERLEAVE_KERNEL_THREADS", str(threads))
    monkeypatch.setattr(kernels, "MIN_PIXELS_PER_THREAD", 16)
    rng = np.random.default_rng(threads)
    values = _values(rng)
    n = (values.size // 183) * 183
    frame = values[:n].reshape(-1, 61, 3)
    _assert_within_one_ulp(encoding.display_encode(frame), colorspace.display_encode(frame))
    _assert_within_one_ulp(encoding.srgb_to_linear(frame), colorspace.srgb_to_linear(frame))
    with np.errstate(invalid="ignore"):  # the reference casts NaN to uint8
        expected = colorspace.encode8_reference(np.nan_to_num(frame, nan=0.0))
    np.testing.assert_array_equal(encoding.encode8(np.nan_to_num(frame, nan=0.0)), expected)
    assert (encoding.encode8(np.full((2, 2, 3), np.nan, np.float32)) == 0).all()
    codes = rng.integers(0, 256, (37, 41, 3), dtype=np.uint8)
    np.testing.assert_array_equal(encoding.decode8(codes), colorspace.srgb_to_linear(codes / 255.0))


def test_shapes_dtypes_and_views_are_kept():
    rng = np.random.default_rng(0)
    rgba = rng.uniform(0, 1, (9, 7, 4)).astype(np.float32)
    view = rgba[:, ::2, :3]  # not contiguous
    for fn, ref in ((encoding.display_encode, colorspace.display_encode),
                    (encoding.srgb_to_linear, colorspace.srgb_to_linear)):
        _assert_within_one_ulp(fn(view), ref(view))
        _assert_within_one_ulp(fn(rgba[..., 0]), ref(rgba[..., 0]))  # (H, W)
    assert encoding.encode8(view).shape == view.shape and encoding.encode8(view).dtype == np.uint8
    assert encoding.decode8(np.zeros((3, 5), np.uint8)).shape == (3, 5)
    assert encoding.display_encode(np.zeros((0, 4, 3), np.float32)).shape == (0, 4, 3)


def test_views_are_read_in_place_with_the_same_result():
    """The RGB of an RGBA buffer and flipped rows (views with strides) convert as their contiguous copies do."""
    rng = np.random.default_rng(17)
    codes = rng.integers(0, 256, (13, 21, 4), dtype=np.uint8)
    floats = rng.uniform(-0.2, 1.3, (13, 21, 4)).astype(np.float32)
    for view in (codes[..., :3], codes[::-1, :, :3], codes[:, ::2, 1:]):
        np.testing.assert_array_equal(encoding.decode8(view), encoding.decode8(np.ascontiguousarray(view)))
    for view in (floats[..., :3], floats[::-1, :, :3]):
        contiguous = np.ascontiguousarray(view)
        np.testing.assert_array_equal(encoding.srgb_to_linear(view), encoding.srgb_to_linear(contiguous))
        np.testing.assert_array_equal(encoding.display_encode(view), encoding.display_encode(contiguous))
        np.testing.assert_array_equal(encoding.encode8(view), encoding.encode8(contiguous))
