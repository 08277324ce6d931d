"""Colour encodings: the exact sRGB transfer function (IEC 61966-2-1), in one place.

Interleave holds colour as linear-light Rec.709 RGB; loaders decode display-encoded input with
``srgb_to_linear`` and metrics and videos encode with ``display_encode`` (clip to [0, 1], then sRGB).
"""
from __future__ import annotations

import numpy as np

#: Slope of the sRGB encoding's linear segment, ``encoded = 12.92 * linear`` below linear 0.0031308: the
#: steepest the encoding gets (the curve above it is flatter), so a linear-light error ``e`` moves an encoded
#: value by at most ``SRGB_LINEAR_SLOPE * e``.
SRGB_LINEAR_SLOPE = 12.92


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """Exact sRGB EOTF: ``c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055) ** 2.4``.

    Computed in float64, returned as float32. NaN stays NaN (validation reports it).
    """
    c = np.asarray(encoded, dtype=np.float64)
    curve = ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(c <= 0.04045, c / SRGB_LINEAR_SLOPE, curve).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_to_linear`: ``12.92 c`` for ``c <= 0.0031308``, else ``1.055 c^(1/2.4) - 0.055``."""
    c = np.asarray(linear, dtype=np.float64)
    curve = 1.055 * np.maximum(c, 0.0031308) ** (1.0 / 2.4) - 0.055
    return np.where(c <= 0.0031308, c * SRGB_LINEAR_SLOPE, curve).astype(np.float32)


def display_encode(linear: np.ndarray) -> np.ndarray:
    """What a display shows: linear light clipped to [0, 1], then sRGB-encoded, float32."""
    return linear_to_srgb(np.clip(linear, 0.0, 1.0))


#: Buckets per unit of linear light in ``encode8_table`` (at most one 8-bit step falls in each: checked there).
ENCODE8_BUCKETS = 4096


def encode8_reference(linear: np.ndarray) -> np.ndarray:
    """8-bit display encoding: ``display_encode(linear) * 255 + 0.5`` truncated to uint8 (the oracle of the
    compiled ``engine.geometry.kernels.encode8``, which reads the table of ``encode8_table``)."""
    return (display_encode(linear) * 255.0 + 0.5).astype(np.uint8)


def encode8_table() -> tuple[np.ndarray, np.ndarray]:
    """(level, step) of ``encode8_reference`` per bucket b of [b / B, (b + 1) / B), B = ``ENCODE8_BUCKETS``:
    ``level[b]`` (uint8) is the code of the bucket's first value and ``step[b]`` (float32) the smallest value
    of the bucket coded ``level[b] + 1`` (+inf if none), found by bisection on float32 bit patterns, so that
    ``level[b] + (c >= step[b])`` equals the reference for every float32 c in the bucket (tested)."""
    buckets = ENCODE8_BUCKETS
    start = (np.arange(buckets + 1, dtype=np.float64) / buckets).astype(np.float32)
    level = encode8_reference(start)
    last = np.nextafter(np.append(start[1:], np.float32(np.inf)), np.float32(0.0)).astype(np.float32)
    last[-1] = np.float32(1.0)
    top = encode8_reference(last)
    if (top.astype(int) - level > 1).any():
        raise AssertionError("encode8_table: more than one 8-bit step in a bucket")
    lo, hi = start.view(np.int32).copy(), last.view(np.int32).copy()  # positive floats order as their bits
    has_step = top > level
    for _ in range(32):  # smallest value coded level + 1: the answer stays in (lo, hi]
        mid = lo + (hi - lo) // 2
        up = encode8_reference(mid.view(np.float32)) > level
        hi = np.where(up, mid, hi)
        lo = np.where(up, lo, mid)
    step = np.where(has_step, hi.view(np.float32), np.float32(np.inf)).astype(np.float32)
    return level, step
