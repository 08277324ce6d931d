"""Engine motion vectors -> screen flow in pixels (x right, y down). Conventions: ``engine.conventions``."""
from __future__ import annotations

from typing import Literal

import numpy as np

from engine.conventions.values import float_buffer, frame_size
from engine.core.errors import InputError

# --------------------------------------------------------------------------------------------
# Motion vectors
# --------------------------------------------------------------------------------------------

def motion_vectors_to_flow(mv: object, width: int, height: int, *, units: Literal["ndc", "uv", "pixels"],
                           points_to: Literal["previous", "next"], y_up: bool,
                           file=None, frame=None, field_name: str = "motion_vectors") -> np.ndarray:
    """Screen flow in pixels (x right, y down, pointing to the NEXT frame), float64, shape (..., 2).

    Args:
        mv: (..., 2) engine motion vectors (x, y). Game engines usually write current -> previous.
        width, height: the viewport size in pixels that the flow is measured in (the vectors may be
            stored at another resolution; only their units matter).
        units: "ndc" (the viewport spans 2 units: pixels = mv * (W / 2, H / 2)), "uv" (spans 1:
            pixels = mv * (W, H)) or "pixels".
        points_to: "next" keeps the direction; "previous" negates it. The negation is an approximation
            valid for constant screen velocity: the true forward motion of a pixel is not the reverse
            of its backward motion under acceleration, rotation or disocclusion.
        y_up: the vectors' y component points up (NDC y up; UV with v = 0 at the bottom); it is
            negated so that the result's y points down.

    Non-finite values are an InputError. Remove TAA jitter before calling if the engine includes it.
    """
    where = dict(file=file, frame=frame, field=field_name)
    w, h = frame_size(width, height)
    v = float_buffer(mv, where)
    if v.ndim < 1 or v.shape[-1] != 2:
        raise InputError(f"must have shape (..., 2), got {v.shape}", **where)
    bad = int(np.count_nonzero(~np.isfinite(v)))
    if bad:
        raise InputError(f"has {bad} non-finite values", **where)
    scales = {"ndc": (w / 2.0, h / 2.0), "uv": (float(w), float(h)), "pixels": (1.0, 1.0)}
    if units not in scales:
        raise InputError(f"must be 'ndc', 'uv' or 'pixels', got {units!r}", field="units")
    if points_to not in ("previous", "next"):
        raise InputError(f"must be 'previous' or 'next', got {points_to!r}", field="points_to")
    sign = -1.0 if points_to == "previous" else 1.0
    sx, sy = scales[units]
    factor = np.array([sign * sx, sign * sy * (-1.0 if y_up else 1.0)])
    return v * factor
