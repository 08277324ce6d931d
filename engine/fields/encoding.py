"""The view-direction encodings of the exported fields, numpy (mirrors of ``models.fields.components.encodings``,
which reads these constants): real spherical harmonics of 1-4 bands, a Fourier encoding, or none."""
from __future__ import annotations

import numpy as np

__all__ = ["SH_C0", "SH_C1", "SH_C2", "SH_C3", "sh_encoding_np", "direction_encoding_np"]

# Real spherical-harmonics constants, bands 0-3 (shared with models.fields.components.encodings.sh_encoding).
SH_C0 = 0.28209479177387814
SH_C1 = 0.4886025119029199
SH_C2 = (1.0925484305920792, 1.0925484305920792, 0.31539156525252005, 1.0925484305920792, 0.5462742152960396)
SH_C3 = (0.5900435899266435, 2.890611442640554, 0.4570457994644658, 0.3731763325901154, 0.4570457994644658,
         1.445305721320277, 0.5900435899266435)


def sh_encoding_np(d: np.ndarray, bands: int) -> np.ndarray:
    """Real spherical harmonics of unit directions (..., 3) -> (..., bands ** 2), bands 1-4."""
    x, y, z = d[..., 0], d[..., 1], d[..., 2]
    out = [np.full_like(x, SH_C0)]
    if bands > 1:
        out += [-SH_C1 * y, SH_C1 * z, -SH_C1 * x]
    if bands > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [SH_C2[0] * x * y, -SH_C2[1] * y * z, SH_C2[2] * (3 * zz - 1), -SH_C2[3] * x * z, SH_C2[4] * (xx - yy)]
    if bands > 3:
        out += [-SH_C3[0] * y * (3 * xx - yy), SH_C3[1] * x * y * z, -SH_C3[2] * y * (5 * zz - 1),
                SH_C3[3] * z * (5 * zz - 3), -SH_C3[4] * x * (5 * zz - 1), SH_C3[5] * z * (xx - yy),
                -SH_C3[6] * x * (xx - 3 * yy)]
    return np.stack(out, axis=-1)


def direction_encoding_np(d: np.ndarray, kind: str, degree: int) -> np.ndarray:
    """The field's view-direction encoding: ``sh``, ``fourier`` ([d, sin(2^k d), cos(2^k d)]) or ``none``."""
    if kind == "sh":
        return sh_encoding_np(d, degree)
    if kind == "fourier":
        scaled = (d[..., None, :] * (2.0 ** np.arange(degree, dtype=d.dtype))[:, None]).reshape(*d.shape[:-1], -1)
        return np.concatenate([d, np.sin(scaled), np.cos(scaled)], axis=-1)
    return d[..., :0]
