"""Metrics: sRGB transfer function, crop, PSNR, SSIM against known values, FLIP sanity, bad input."""
import numpy as np
import pytest

from engine.core.colorspace import display_encode, srgb_to_linear
from engine.core.errors import InputError
from engine.eval.metrics import crop_slices, psnr, score_frame, ssim_map


def test_srgb_round_trip_and_known_points():
    x = np.linspace(0, 1, 1001, dtype=np.float32)
    np.testing.assert_allclose(srgb_to_linear(display_encode(x)), x, atol=2e-6)
    assert display_encode(np.float32(0.0031308)) == pytest.approx(0.04045, abs=1e-5)
    assert display_encode(np.float32(0.5)) == pytest.approx(0.7353569, abs=1e-5)
    assert display_encode(np.float32(4.0)) == 1.0  # clipped for display, never > 1


def test_crop_matches_decompnet_at_1080p_and_scales():
    rows, cols = crop_slices(1080, 1920)
    assert (rows.start, rows.stop, cols.start, cols.stop) == (40, 1040, 60, 1860)
    rows, cols = crop_slices(540, 960)
    assert (rows.start, cols.start) == (20, 30)


def test_psnr_known_value_and_mask():
    a = np.zeros((10, 10, 3))
    b = np.full((10, 10, 3), 0.1)
    assert psnr(a, b) == pytest.approx(20.0)
    assert psnr(a, a) == float("inf")
    mask = np.zeros((10, 10), bool)
    assert np.isnan(psnr(a, b, mask))
    mask[0, 0] = True
    c = b.copy()
    c[0, 0] = 0.0
    assert psnr(a, c, mask) == float("inf")


def test_ssim_identity_and_degradation():
    rng = np.random.default_rng(0)
    img = rng.random((40, 50, 3))
    assert np.allclose(ssim_map(img, img), 1.0)
    noisy = np.clip(img + rng.normal(0, 0.1, img.shape), 0, 1)
    noisier = np.clip(img + rng.normal(0, 0.3, img.shape), 0, 1)
    # uniform noise image: var 1/12; SSIM ~ 2 var / (2 var + noise var) for small noise
    assert 0.9 < ssim_map(img, noisy).mean() < 0.97
    assert 0.0 < ssim_map(img, noisier).mean() < ssim_map(img, noisy).mean()


def test_ssim_matches_direct_formula_on_constant_images():
    # constant images: variances vanish, SSIM = (2 mx my + c1) / (mx^2 + my^2 + c1)
    a, b = np.full((30, 30, 1), 0.2), np.full((30, 30, 1), 0.4)
    c1 = 0.01 ** 2
    expected = (2 * 0.2 * 0.4 + c1) / (0.2 ** 2 + 0.4 ** 2 + c1)
    np.testing.assert_allclose(ssim_map(a, b), expected, rtol=1e-9)


def test_score_frame_orders_errors_and_moving_scores():
    rng = np.random.default_rng(1)
    truth = rng.random((64, 96, 3)).astype(np.float32)
    small = np.clip(truth + 0.01, 0, None).astype(np.float32)
    large = np.clip(truth + 0.2, 0, None).astype(np.float32)
    moving = np.zeros((64, 96), bool)
    moving[20:40, 30:60] = True
    s_small, s_large = score_frame(truth, small, moving), score_frame(truth, large, moving)
    assert s_small.psnr > s_large.psnr and s_small.ssim > s_large.ssim and s_small.flip < s_large.flip
    assert np.isfinite(s_small.psnr_moving) and 0 < s_small.moving_fraction < 1
    assert np.isnan(score_frame(truth, small, None, with_flip=False).psnr_moving)


def test_score_frame_rejects_bad_input():
    a = np.zeros((8, 8, 3), np.float32)
    with pytest.raises(InputError, match="must both be"):
        score_frame(a, np.zeros((8, 9, 3), np.float32))
    bad = a.copy()
    bad[0, 0, 0] = np.nan
    with pytest.raises(InputError, match="non-finite"):
        score_frame(a, bad)
