"""Engine motion vectors -> Interleave's motion vectors and screen flow, in pixels (x right, y down).
Conventions: ``engine.conventions``; per-engine values: ``engine.runtime.session``."""
from __future__ import annotations

from typing import Literal, Optional

import numpy as np

from engine.conventions.values import float_buffer, frame_size
from engine.core.errors import InputError

__all__ = ["MOTION_UNITS", "MOTION_DIRECTIONS", "motion_vectors_to_previous", "motion_vectors_to_flow"]

#: Units of engine motion vectors: pixels (of the vector buffer), the viewport spanning 1 (uv) or 2 (ndc).
MOTION_UNITS = ("pixels", "uv", "ndc")
#: Where engine motion vectors point: "previous": from this frame's pixel to where its surface point was in
#: the previous frame (FSR, DLSS, Godot); "next": the reverse, from there to this pixel, i.e. the motion
#: since the previous frame (current minus previous position: Unity, Unreal).
MOTION_DIRECTIONS = ("previous", "next")

# --------------------------------------------------------------------------------------------
# Motion vectors
# --------------------------------------------------------------------------------------------


def motion_vectors_to_previous(mv: object, width: int, height: int, *, units: str, direction: str, y_up: bool,
                               scale: tuple[float, float] = (1.0, 1.0),
                               buffer_size: Optional[tuple[int, int]] = None,
                               file=None, frame=None, field_name: str = "motion_vectors") -> np.ndarray:
    """Engine motion vectors as ``Frame.motion_vectors``: float64 (..., 2) pixels of the (width, height)
    viewport, x right, y down, from each pixel centre to where its surface point was in the previous frame.

    Args:
        mv: (..., 2) engine motion vectors (x, y). NaN marks a pixel without a vector and stays NaN;
            +-inf is an InputError.
        width, height: the viewport in pixels (the frame's full resolution).
        units: "pixels": pixels of the vector buffer, ``buffer_size`` (w, h) (default: the viewport),
            rescaled by (width / w, height / h); "uv": the viewport spans 1 (pixels = mv * (W, H));
            "ndc": it spans 2 (pixels = mv * (W / 2, H / 2)).
        direction: "previous" keeps the direction; "next" (previous -> current, the motion since the
            previous frame) is negated, which is exact (no constant-velocity assumption).
        y_up: the vectors' y points to the top of the picture (NDC y up; UV with v = 0 at the bottom); it
            is negated so that the result's y points down.
        scale: (x, y) multiplier applied first (FSR's ``motionVectorScale`` into ``units``, DLSS's
            ``mvecScale`` into "uv").
    """
    where = dict(file=file, frame=frame, field=field_name)
    w, h = frame_size(width, height)
    v = float_buffer(mv, where)
    if v.ndim < 1 or v.shape[-1] != 2:
        raise InputError(f"must have shape (..., 2), got {v.shape}", **where)
    inf = int(np.count_nonzero(np.isinf(v)))
    if inf:
        raise InputError(f"has {inf} infinite values (NaN marks a pixel without a vector; inf is an error)", **where)
    if units not in MOTION_UNITS:
        raise InputError(f"must be one of {', '.join(MOTION_UNITS)}, got {units!r}", field="units")
    if direction not in MOTION_DIRECTIONS:
        raise InputError(f"must be one of {', '.join(MOTION_DIRECTIONS)}, got {direction!r}", field="direction")
    sx, sy = (float(s) for s in scale)
    if not (np.isfinite(sx) and np.isfinite(sy) and sx != 0 and sy != 0):
        raise InputError(f"must be two finite non-zero numbers, got {tuple(scale)}", field="scale")
    bw, bh = (w, h) if buffer_size is None else frame_size(*buffer_size)
    units_px = {"ndc": (w / 2.0, h / 2.0), "uv": (float(w), float(h)), "pixels": (w / bw, h / bh)}[units]
    sign = -1.0 if direction == "next" else 1.0
    factor = np.array([sign * sx * units_px[0], sign * sy * units_px[1] * (-1.0 if y_up else 1.0)])
    return v * factor


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

    Non-finite values are an InputError (a flow has no "missing" value; motion vectors, with NaN for
    none, go through :func:`motion_vectors_to_previous`). Remove TAA jitter before calling if the engine
    includes it.
    """
    where = dict(file=file, frame=frame, field=field_name)
    v = float_buffer(mv, where)
    if v.ndim < 1 or v.shape[-1] != 2:
        raise InputError(f"must have shape (..., 2), got {v.shape}", **where)
    bad = int(np.count_nonzero(~np.isfinite(v)))
    if bad:
        raise InputError(f"has {bad} non-finite values", **where)
    if points_to not in ("previous", "next"):
        raise InputError(f"must be 'previous' or 'next', got {points_to!r}", field="points_to")
    # Vectors to the next frame are the reverse of "previous -> current" motion numerically: one converter.
    return -motion_vectors_to_previous(v, width, height, units=units, direction=points_to, y_up=y_up,
                                       file=file, frame=frame, field_name=field_name)
