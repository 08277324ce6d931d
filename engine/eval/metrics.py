"""Image-quality metrics on display-encoded frames: PSNR, SSIM, FLIP, with DeCOMPnet's border crop.

Conventions: inputs are linear RGB (H, W, 3) float32 frames (Interleave's internal colour). Every metric
first encodes them with the sRGB transfer function and clips to [0, 1] (what a display shows), then
crops the border in proportion to DeCOMPnet's protocol (40 px top/bottom and 60 px left/right at
1920x1080), so scores at any resolution measure the same part of the frame.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Optional

import cv2
import numpy as np

from engine.core.colorspace import display_encode
from engine.core.errors import InputError

#: DeCOMPnet's crop at 1920x1080, as fractions of the frame size.
CROP_TOP_BOTTOM = 40.0 / 1080.0
CROP_LEFT_RIGHT = 60.0 / 1920.0


def crop_slices(height: int, width: int) -> tuple[slice, slice]:
    """Row and column slices of the evaluated region (DeCOMPnet's border crop, scaled to the size)."""
    top = int(round(CROP_TOP_BOTTOM * height))
    left = int(round(CROP_LEFT_RIGHT * width))
    return slice(top, height - top), slice(left, width - left)


def psnr(reference: np.ndarray, test: np.ndarray, mask: Optional[np.ndarray] = None) -> float:
    """PSNR in dB of display-encoded images in [0, 1], optionally over the pixels where ``mask`` is True.

    Returns +inf for identical images and NaN for an empty mask.
    """
    diff2 = np.mean((reference.astype(np.float64) - test.astype(np.float64)) ** 2, axis=-1)
    if mask is not None:
        if not np.any(mask):
            return float("nan")
        diff2 = diff2[mask]
    mse = float(np.mean(diff2))
    return float("inf") if mse == 0.0 else float(10.0 * np.log10(1.0 / mse))


def ssim_map(reference: np.ndarray, test: np.ndarray, sigma: float = 1.5) -> np.ndarray:
    """Per-pixel SSIM (Wang et al. 2004) with a Gaussian window (sigma 1.5, 11x11), no sample covariance.

    Inputs are display-encoded (H, W, C) images in [0, 1]; returns (H, W), averaged over channels.
    """
    c1, c2 = 0.01 ** 2, 0.03 ** 2
    x = reference.astype(np.float64)
    y = test.astype(np.float64)

    def blur(a: np.ndarray) -> np.ndarray:
        return cv2.GaussianBlur(a, (11, 11), sigma, borderType=cv2.BORDER_REFLECT)

    mu_x, mu_y = blur(x), blur(y)
    sxx = blur(x * x) - mu_x ** 2
    syy = blur(y * y) - mu_y ** 2
    sxy = blur(x * y) - mu_x * mu_y
    num = (2 * mu_x * mu_y + c1) * (2 * sxy + c2)
    den = (mu_x ** 2 + mu_y ** 2 + c1) * (sxx + syy + c2)
    out = num / den
    return out.mean(axis=-1) if out.ndim == 3 else out


def flip_map(reference: np.ndarray, test: np.ndarray) -> np.ndarray:
    """Per-pixel LDR-FLIP error (NVIDIA's ``flip-evaluator``, default 67 pixels per degree), in [0, 1]."""
    import flip_evaluator

    error, _, _ = flip_evaluator.evaluate(np.ascontiguousarray(reference, dtype=np.float32),
                                          np.ascontiguousarray(test, dtype=np.float32), "LDR",
                                          applyMagma=False, computeMeanError=False)
    return np.asarray(error, dtype=np.float32).reshape(reference.shape[:2])


@dataclass(frozen=True)
class Scores:
    """PSNR (dB, sRGB-encoded), SSIM and FLIP over the cropped region and over its moving pixels (NaN where
    there are none, or FLIP was skipped)."""

    psnr: float
    ssim: float
    flip: float
    psnr_moving: float
    ssim_moving: float
    flip_moving: float


#: The score fields every frame and every method result carries.
SCORE_FIELDS = tuple(f.name for f in fields(Scores))


@dataclass(frozen=True)
class FrameScores(Scores):
    """Scores of one predicted frame against the true one (over the cropped region)."""

    moving_fraction: float


def score_frame(truth: np.ndarray, prediction: np.ndarray, moving: Optional[np.ndarray] = None,
                *, with_flip: bool = True) -> FrameScores:
    """Score a predicted linear-RGB frame against the true one, whole crop and moving pixels.

    Args:
        truth, prediction: (H, W, 3) linear RGB.
        moving: (H, W) bool, pixels of moving objects in the TRUE frame (the `moving` channel); the
            moving-pixel scores are NaN when it is None or empty inside the crop.
        with_flip: FLIP costs ~0.4 s per 960x540 frame; pass False to skip it (NaN).
    Returns FrameScores: PSNR, SSIM and FLIP over the crop and over its moving pixels.
    """
    if truth.shape != prediction.shape or truth.ndim != 3 or truth.shape[2] != 3:
        raise InputError(f"truth {truth.shape} and prediction {prediction.shape} must both be (H, W, 3)")
    if not np.all(np.isfinite(prediction)):
        raise InputError("prediction has non-finite values", field="prediction")
    rows, cols = crop_slices(*truth.shape[:2])
    ref = display_encode(truth)[rows, cols]
    out = display_encode(prediction)[rows, cols]
    ssim_px = ssim_map(ref, out)
    mask = None if moving is None else np.asarray(moving, dtype=bool)[rows, cols]
    has_moving = mask is not None and bool(np.any(mask))
    flip_px = flip_map(ref, out) if with_flip else None
    nan = float("nan")
    return FrameScores(
        psnr=psnr(ref, out),
        ssim=float(np.mean(ssim_px)),
        flip=float(np.mean(flip_px)) if flip_px is not None else nan,
        psnr_moving=psnr(ref, out, mask) if has_moving else nan,
        ssim_moving=float(np.mean(ssim_px[mask])) if has_moving else nan,
        flip_moving=float(np.mean(flip_px[mask])) if has_moving and flip_px is not None else nan,
        moving_fraction=float(np.mean(mask)) if mask is not None else 0.0,
    )
