"""Flow upsampling of ``decomp``: the network's per-plane flow at the working resolution onto the
full-resolution MPI (numpy reference: ``engine.predict.decomp.reference.upsample_flow_reference``).

Grids: working-resolution pixel ``i`` covers full pixels ``[f i, f (i + 1))`` (``geometry.downsample_frame``);
flows are (3, Z, H, W) = (du, dv) pixels, dz scene units; MPIs (C, Z, H, W).
"""
from __future__ import annotations

import cv2
import numpy as np

from engine.geometry import kernels

__all__ = ["upsample_blocks", "spread_plane", "upsample_flow"]


def upsample_blocks(image: np.ndarray, block: int, size: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of an image (h, w[, C]) whose pixel ``i`` spans full pixels ``[b i, b (i + 1))``
    (``geometry.downsample_frame``'s grid) to full size (H, W) >= (b h, b w); rows and columns past the last
    whole block repeat the edge. Values are not scaled."""
    h, w = image.shape[:2]
    up = cv2.resize(image, (w * block, h * block), interpolation=cv2.INTER_LINEAR) if block > 1 else image
    pad = [(0, size[0] - h * block), (0, size[1] - w * block)] + [(0, 0)] * (image.ndim - 2)
    return np.pad(up, pad, mode="edge") if pad[0][1] or pad[1][1] else np.ascontiguousarray(up)


def spread_plane(flow: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(h, w, 4) alpha-weighted (du, dv, dz) and alpha of one plane (``flow`` (3, h, w), ``alpha`` (h, w)),
    spread two pixels into empty neighbours by normalised 3 x 3 sums; the four channels side by side, so
    every filter runs once on all of them. Both ``upsample_flow`` and its reference start from this."""
    a = alpha.astype(np.float32)
    packed = np.ascontiguousarray(np.concatenate([np.moveaxis(flow * a, 0, -1), a[..., None]], axis=-1),
                                  dtype=np.float32)
    for _ in range(2):
        sums = cv2.boxFilter(packed, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        grow = (packed[..., 3] <= 0) & (sums[..., 3] > 0)
        packed[grow, :3] = sums[grow, :3] / sums[grow, 3:]
        packed[grow, 3] = 1.0
    return packed


def upsample_flow(flow: np.ndarray, alpha: np.ndarray, factor: int, full_alpha: np.ndarray) -> np.ndarray:
    """Per-plane, alpha-normalised bilinear upsampling of a working-resolution flow (3, Z, h, w) with its
    alpha (Z, h, w) onto the full-resolution MPI's alpha ``full_alpha`` (Z, H, W) on the same planes
    (semantics: ``upsample_flow_reference``); the full-resolution sampling is compiled
    (``engine.geometry.kernels.upsample_planes``, held to the reference to 1e-5 by the tests).
    Returns (3, Z, H, W), (du, dv) scaled by ``factor``, 0 where ``full_alpha`` is 0."""
    num_z = flow.shape[1]
    packed = np.stack([spread_plane(flow[:, z], alpha[z]) for z in range(num_z)])
    out = np.empty((3,) + full_alpha.shape, dtype=np.float32)
    kernels.upsample_planes(packed, int(factor), np.ascontiguousarray(full_alpha, dtype=np.float32),
                            np.array([factor, factor, 1.0], np.float32), out)
    return out
