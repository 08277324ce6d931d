"""numpy oracle of ``engine.predict.decomp.upsample.upsample_flow``, imported by tests and benchmarks only."""
from __future__ import annotations

import numpy as np

from engine.predict.decomp.upsample import spread_plane, upsample_blocks

__all__ = ["upsample_flow_reference"]


def upsample_flow_reference(flow: np.ndarray, alpha: np.ndarray, factor: int, full_alpha: np.ndarray) -> np.ndarray:
    """Per-plane, alpha-normalised bilinear upsampling of a network-resolution flow to the full MPI.

    ``flow`` (3, Z, h, w) on the network grid (pixel ``i`` covers full pixels ``[f i, f (i + 1))``), alpha
    (Z, h, w); ``full_alpha`` (Z, H, W) is the full-resolution MPI on the same planes. (du, dv) are scaled by
    ``factor``, dz is kept. Each plane's flow is first spread two pixels into its empty neighbours
    (normalised 3 x 3 means), so full-resolution points whose block went to another plane still find a
    value; points with no value within reach get 0. Returns (3, Z, H, W), 0 where ``full_alpha`` is 0.
    """
    num_z = flow.shape[1]
    big_h, big_w = full_alpha.shape[1:]
    out = np.zeros((3, num_z) + full_alpha.shape[1:], dtype=np.float32)
    scale = np.array([factor, factor, 1.0], np.float32)
    for z in range(num_z):
        if not full_alpha[z].any():
            continue
        packed = spread_plane(flow[:, z], alpha[z])
        up = upsample_blocks(packed, factor, (big_h, big_w))  # past the last whole block: the edge repeats
        where = np.flatnonzero(full_alpha[z])  # only this plane's points (a one-hot MPI: each pixel once)
        picked = up.reshape(-1, 4)[where]
        ok = picked[:, 3] > 1e-6
        values = np.where(ok[:, None], picked[:, :3] / np.where(ok, picked[:, 3], 1.0)[:, None], 0.0) * scale
        out.reshape(3, num_z, -1)[:, z, where] = values.T
    return out
