"""Colour encodings of whole frames, compiled: what ``engine.core.colorspace`` computes in numpy (its
functions are the oracles), for the per-frame paths (``engine.runtime.session``'s pixels in and out, the 8-bit
lumas the flow estimators read). Frames are (H, W, C) arrays, rows split over the kernel threads
(``engine.geometry.kernels.split_rows``).

- ``encode8``: linear -> 8-bit display encoding, equal to ``colorspace.encode8_reference``.
- ``display_encode``: linear -> sRGB-encoded float32 in [0, 1], ``colorspace.display_encode`` to one float32 ulp.
- ``srgb_to_linear``: sRGB-encoded float -> linear float32, ``colorspace.srgb_to_linear`` to one float32 ulp.
- ``decode8``: 8-bit sRGB -> linear float32 through ``colorspace``'s table, exactly.

(One ulp: numpy may evaluate ``power`` with SIMD code that rounds differently from libm's ``pow``.)
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np

from engine.core.colorspace import ENCODE8_BUCKETS, encode8_table, srgb_to_linear as srgb_to_linear_reference
from engine.geometry import kernels

__all__ = ["encode8", "display_encode", "srgb_to_linear", "decode8", "encode8_lookup", "decode8_lookup",
           "FRAME_ENCODINGS"]

#: The encodings a predicted frame can be handed out in: ``linear`` float32 light, or ``srgb8`` (H, W, 3)
#: uint8 display codes (``encode8``), which the ``gl`` backend makes on the GPU (``engine.predict.Target``).
FRAME_ENCODINGS = ("linear", "srgb8")


def _convert(kernel, array: np.ndarray, in_dtype, out_dtype, *args) -> np.ndarray:
    """``kernel(frame rows, *args, out rows)`` over the rows of ``array`` (H, W[, C]) as a (H, W, C) frame of
    ``in_dtype``, split over the kernel threads; the output has ``array``'s shape. A view of ``in_dtype`` (the
    RGB of an RGBA buffer, flipped rows) is read in place: copying it first cost more than the conversion."""
    array = np.asarray(array)
    frame = array if array.dtype == in_dtype else array.astype(in_dtype)
    frame = frame.reshape(frame.shape + (1,) * (3 - frame.ndim))
    out = np.empty(frame.shape, dtype=out_dtype)
    kernels.run_ranges(lambda r0, r1: kernel(frame[r0:r1], *args, out[r0:r1]),
                       kernels.split_rows(frame.shape[0], frame.shape[1] * frame.shape[2]))
    return out.reshape(array.shape)


@lru_cache(maxsize=1)
def encode8_lookup() -> tuple[np.ndarray, np.ndarray]:
    """``colorspace.encode8_table()`` (level uint8, step float32; ``ENCODE8_BUCKETS`` + 1 entries), computed
    once: the table ``encode8`` reads, and the GL backend's ``encode8`` pass."""
    return encode8_table()


@lru_cache(maxsize=1)
def decode8_lookup() -> np.ndarray:
    """(256,) float32 linear light of each 8-bit sRGB code, computed once: the table ``decode8`` reads, and the
    GL backend's ``frame_from_codes`` pass."""
    return srgb_to_linear_reference(np.arange(256, dtype=np.float64) / 255.0)


def encode8(color: np.ndarray) -> np.ndarray:
    """(H, W[, C]) uint8 display encoding of linear ``color`` (float), equal to ``colorspace.encode8_reference``
    (``kernels.encode8``, by the exact per-bucket table of ``colorspace.encode8_table``); NaN -> 0."""
    level, step = encode8_lookup()
    return _convert(kernels.encode8, color, np.float32, np.uint8, level, step, ENCODE8_BUCKETS)


def display_encode(linear: np.ndarray) -> np.ndarray:
    """(H, W[, C]) float32: ``colorspace.display_encode`` (clipped to [0, 1], sRGB-encoded) of ``linear``."""
    return _convert(kernels.srgb_encode, linear, np.float32, np.float32)


def srgb_to_linear(encoded: np.ndarray) -> np.ndarray:
    """(H, W[, C]) float32: ``colorspace.srgb_to_linear`` (the sRGB EOTF, unclipped) of float ``encoded``."""
    return _convert(kernels.srgb_decode, encoded, np.float32, np.float32)


def decode8(codes: np.ndarray) -> np.ndarray:
    """(H, W[, C]) float32 linear light of 8-bit sRGB ``codes`` (uint8): ``srgb_to_linear(codes / 255)``."""
    return _convert(kernels.lookup, codes, np.uint8, np.float32, decode8_lookup())
