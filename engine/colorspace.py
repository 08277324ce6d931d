"""Colour encodings: the exact sRGB transfer function (IEC 61966-2-1), in one place.

Interleave holds colour as linear-light Rec.709 RGB; loaders decode display-encoded input with
``srgb_to_linear`` and metrics and videos encode with ``display_encode`` (clip to [0, 1], then sRGB).
"""
from __future__ import annotations

import numpy as np


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """Exact sRGB EOTF: ``c / 12.92`` for ``c <= 0.04045``, else ``((c + 0.055) / 1.055) ** 2.4``.

    Computed in float64, returned as float32. NaN stays NaN (validation reports it).
    """
    c = np.asarray(encoded, dtype=np.float64)
    curve = ((np.maximum(c, 0.04045) + 0.055) / 1.055) ** 2.4
    return np.where(c <= 0.04045, c / 12.92, curve).astype(np.float32)


def linear_to_srgb(linear: np.ndarray) -> np.ndarray:
    """Inverse of :func:`srgb_to_linear`: ``12.92 c`` for ``c <= 0.0031308``, else ``1.055 c^(1/2.4) - 0.055``."""
    c = np.asarray(linear, dtype=np.float64)
    curve = 1.055 * np.maximum(c, 0.0031308) ** (1.0 / 2.4) - 0.055
    return np.where(c <= 0.0031308, c * 12.92, curve).astype(np.float32)


def display_encode(linear: np.ndarray) -> np.ndarray:
    """What a display shows: linear light clipped to [0, 1], then sRGB-encoded, float32."""
    return linear_to_srgb(np.clip(linear, 0.0, 1.0))
