"""Depth buffers (OpenGL, D3D, reversed-Z, infinite, linear) and radial distance -> planar depth (camera z,
``+inf`` = no surface, float64). Conventions: ``engine.conventions`` (the package docstring).
"""
from __future__ import annotations

import math
from typing import Literal, Optional

import numpy as np

from engine.conventions.cameras import CLIP_RANGES, perspective_matrix
from engine.conventions.values import count_bad, float_buffer, near_far
from engine.core.errors import InputError
from engine.core.frames import validate_intrinsics

#: Depth-buffer conventions understood by :func:`decode_depth_buffer` / :func:`encode_depth_buffer`.
DEPTH_CONVENTIONS = ("opengl", "d3d", "reversed", "infinite", "reversed_infinite", "linear", "linear01")

# --------------------------------------------------------------------------------------------
# Depth buffers
# --------------------------------------------------------------------------------------------

def decode_depth_buffer(buffer: object, near: float, far: Optional[float], *, convention: str,
                        file=None, frame=None, field_name: str = "depth_buffer") -> np.ndarray:
    """Planar depth (camera z > 0, ``+inf`` = no surface), float64, from a depth buffer.

    Output units are those of ``near`` and ``far`` (pass them in metres to match converted poses).
    Window depth d in [0, 1] is what the depth buffer stores (after glDepthRange(0, 1) / the D3D
    viewport). Conventions, with r = near / far (0 for an infinite far plane):

    - ``"opengl"``: NDC z in [-1, 1], d = (ndc + 1) / 2; near -> 0, far -> 1.
    - ``"d3d"``: D3D / Vulkan / Metal, NDC z = d in [0, 1]; near -> 0, far -> 1. For the standard
      matrices both give the same d(z) = (1 - near / z) / (1 - r), so they decode identically:
      ``z = near / ((1 - d) + d r)`` (no cancellation: 1 - d is exact in float64).
    - ``"reversed"``: reversed-Z, near -> 1, far -> 0: ``z = near / (d (1 - r) + r)`` (never forms
      1 - d, so small d at far depths keep their float32 precision).
    - ``"infinite"``: standard with far = inf: ``z = near / (1 - d)``.
    - ``"reversed_infinite"``: the common game setup (Unreal): ``z = near / d``.
    - ``"linear"``: the buffer already holds planar z in the units of near/far (Unity
      LinearEyeDepth, Unreal SceneDepth); values >= far (the clear value) and +inf map to +inf;
      NaN and values <= 0 are errors.
    - ``"linear01"``: Unity's Linear01Depth, d = z / far in (0, 1]: ``z = d far``.

    ``far`` may be ``inf`` or ``None`` for an infinite far plane ("opengl"/"d3d"/"reversed" then act as
    "infinite"/"reversed_infinite"). The far clear value (1.0 standard, 0.0 reversed) maps to +inf, so
    a surface exactly on the far plane reads as "no surface". NaN or values outside [0, 1] raise an
    InputError naming the field and how many values are bad; nothing is clamped.

    Example:
        >>> decode_depth_buffer([0.5, 0.0], 0.1, None, convention="reversed_infinite").tolist()
        [0.2, inf]
    """
    where = dict(file=file, frame=frame, field=field_name)
    if convention not in DEPTH_CONVENTIONS:
        raise InputError(f"unknown depth convention {convention!r}; expected one of {DEPTH_CONVENTIONS}",
                         field="convention")
    infinite_only = convention in ("infinite", "reversed_infinite")
    if infinite_only and far is not None and not math.isinf(float(far)):
        raise InputError(f"must be None or inf for convention {convention!r}, got {far}", field="far")
    near, far = near_far(near, far, allow_inf=True)
    d = float_buffer(buffer, where)
    if convention == "linear":
        count_bad(d, ~(d > 0), "(0, inf]", where)
        return np.where(d >= far, np.inf, d)
    if convention == "linear01":
        if math.isinf(far):
            raise InputError("must be finite for convention 'linear01'", field="far")
        count_bad(d, ~((d > 0) & (d <= 1)), "(0, 1]", where)
        return np.where(d == 1.0, np.inf, d * far)
    count_bad(d, (d < 0) | (d > 1), "[0, 1]", where)
    ratio = near / far
    with np.errstate(divide="ignore"):
        if convention in ("reversed", "reversed_infinite"):
            z = near / (d * (1.0 - ratio) + ratio)
            clear = d == 0.0
        else:
            z = near / ((1.0 - d) + d * ratio)
            clear = d == 1.0
    return np.where(clear, np.inf, z)


def encode_depth_buffer(depth: object, near: float, far: Optional[float], *, convention: str) -> np.ndarray:
    """Window depth d (float64) that a renderer writes for planar depth ``depth``: the inverse of
    :func:`decode_depth_buffer` (same conventions, same units). ``+inf`` encodes as the far clear
    value. Depths outside [near, far] (the renderer would clip them), NaN and values <= 0 are errors.
    Cast the result to float32 to model a D32F buffer.
    """
    where = dict(field="depth")
    if convention not in DEPTH_CONVENTIONS:
        raise InputError(f"unknown depth convention {convention!r}; expected one of {DEPTH_CONVENTIONS}",
                         field="convention")
    if convention in ("infinite", "reversed_infinite") and far is not None and not math.isinf(float(far)):
        raise InputError(f"must be None or inf for convention {convention!r}, got {far}", field="far")
    near, far = near_far(near, far, allow_inf=True)
    z = float_buffer(depth, where)
    finite = np.isfinite(z)
    count_bad(z, z <= 0, "(0, inf]", where)
    if convention == "linear":
        return z
    clipped = int(np.count_nonzero(finite & ((z < near) | (z > far))))
    if clipped:
        raise InputError(f"has {clipped} values outside [near, far] = [{near}, {far}]", **where)
    if convention == "linear01":
        if math.isinf(far):
            raise InputError("must be finite for convention 'linear01'", field="far")
        return np.where(finite, z / far, 1.0)
    ratio = near / far
    with np.errstate(divide="ignore", invalid="ignore"):
        if convention in ("reversed", "reversed_infinite"):
            d = (near / z - ratio) / (1.0 - ratio)
            return np.where(finite, d, 0.0)
        d = (1.0 - near / z) / (1.0 - ratio)
        return np.where(finite, d, 1.0)


def decode_from_projection(buffer: object, projection_matrix: object,
                           clip_range: Literal["minus_one_to_one", "zero_to_one"], *,
                           file=None, frame=None, field_name: str = "depth_buffer") -> np.ndarray:
    """Planar depth (float64, +inf = no surface) from a depth buffer and the projection that wrote it.

    ``projection_matrix`` is the 4x4 OpenGL-style math matrix the GPU used (eye looks down -z, last row
    [0, 0, -1, 0] up to scale, e.g. Unity's ``GL.GetGPUProjectionMatrix``, Godot's projection after its
    depth correction). ``clip_range`` is "minus_one_to_one" (OpenGL: d = (ndc_z + 1) / 2) or
    "zero_to_one" (D3D/Vulkan/Metal: d = ndc_z). Near, far, reversed-Z and an infinite far plane are all
    read from the matrix: with z = -z_eye, ``ndc_z = -P22 + P23 / z``, so d = A + B / z and
    ``z = B / (d - A)`` (B < 0: standard, clear value 1; B > 0: reversed, clear value 0).
    Same errors as :func:`decode_depth_buffer`; decoded depths that are not positive (values beyond
    what the matrix can produce) are an InputError too. Units are those of the matrix's near/far.
    """
    where = dict(file=file, frame=frame, field=field_name)
    if clip_range not in CLIP_RANGES:
        raise InputError(f"must be one of {CLIP_RANGES}, got {clip_range!r}", field="clip_range")
    p = perspective_matrix(projection_matrix, "projection_matrix")
    a_ndc, b_ndc = -p[2, 2], p[2, 3]
    if clip_range == "zero_to_one":
        a, b = a_ndc, b_ndc
    else:
        a, b = (a_ndc + 1.0) / 2.0, b_ndc / 2.0
    if b == 0.0:
        raise InputError("has projection[2,3] = 0: window depth does not depend on z", field="projection_matrix")
    d = float_buffer(buffer, where)
    count_bad(d, (d < 0) | (d > 1), "[0, 1]", where)
    reversed_z = b > 0
    clear = d == (0.0 if reversed_z else 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        z = b / (d - a)
    impossible = int(np.count_nonzero(~clear & ~(z > 0)))
    if impossible:
        raise InputError(f"has {impossible} values that the projection cannot produce in front of the camera "
                         f"(d = {a:.6g} + {b:.6g} / z)", **where)
    return np.where(clear, np.inf, z)


def projection_planes(projection_matrix: object) -> tuple[float, ...]:
    """The depths (camera z > 0) at which an OpenGL-style perspective matrix puts NDC z = -1, 0 and 1:
    its near and far planes are among them whatever its clip range and reversed-Z (an infinite far
    plane is ``inf``). With z = -z_eye, ``ndc_z = -P22 + P23 / z``, so ``z = P23 / (ndc_z + P22)``."""
    p = perspective_matrix(projection_matrix, "projection_matrix")
    out = []
    for ndc in (-1.0, 0.0, 1.0):
        denominator = ndc + p[2, 2]
        z = math.inf if denominator == 0.0 else p[2, 3] / denominator
        if z > 0:
            out.append(float(z))
    return tuple(out)


def near_far_problem(near: float, far: float, projection_matrix: object,
                     rtol: float = 0.01) -> Optional[tuple[str, str]]:
    """``(field, why)`` when ``near`` / ``far`` (``far`` may be inf) disagree with the planes of
    ``projection_matrix``, else None: each must be within ``rtol`` of one of :func:`projection_planes` (a
    depth buffer decoded with other planes than the GPU used is wrong everywhere)."""
    planes = projection_planes(projection_matrix)

    def matches(value: float) -> bool:
        return any((math.isinf(value) and math.isinf(z)) or
                   (math.isfinite(value) and math.isfinite(z) and abs(z - value) <= rtol * value) for z in planes)

    for name, value in (("near", near), ("far", far)):
        if not matches(value):
            shown = ", ".join(f"{z:.6g}" for z in planes)
            return name, f"{name} = {value:g} is not a plane of the projection matrix (its planes are at {shown})"
    return None


# --------------------------------------------------------------------------------------------
# Radial vs planar depth
# --------------------------------------------------------------------------------------------

def _ray_norm(shape: tuple[int, int], k: np.ndarray) -> np.ndarray:
    """|(x/z, y/z, 1)| of the ray through each pixel centre (u + 0.5, v + 0.5)."""
    h, w = shape
    x = (np.arange(w, dtype=np.float64) + 0.5 - k[0, 2]) / k[0, 0]
    y = (np.arange(h, dtype=np.float64) + 0.5 - k[1, 2]) / k[1, 1]
    return np.sqrt(1.0 + x[None, :] ** 2 + y[:, None] ** 2)


def _distance_map(values: object, where: dict) -> np.ndarray:
    d = float_buffer(values, where)
    if d.ndim != 2:
        raise InputError(f"must have shape (H, W), got {d.shape}", **where)
    count_bad(d, ~(d > 0), "(0, inf]", where)
    return d


def radial_to_planar(distance: object, intrinsics: object, *, file=None, frame=None,
                     field_name: str = "distance") -> np.ndarray:
    """Planar depth (camera z, float64) from radial distance (Euclidean, camera centre to surface).

    ``distance`` is (H, W); pixel (u, v) is read along the ray through its centre (u + 0.5, v + 0.5):
    ``z = distance / sqrt(1 + ((u + 0.5 - cx) / fx)^2 + ((v + 0.5 - cy) / fy)^2)``. ``+inf`` stays
    ``+inf``; NaN and values <= 0 are an InputError.
    """
    where = dict(file=file, frame=frame, field=field_name)
    k = validate_intrinsics(intrinsics, file=file, frame=frame)
    d = _distance_map(distance, where)
    return d / _ray_norm(d.shape, k)


def planar_to_radial(depth: object, intrinsics: object, *, file=None, frame=None,
                     field_name: str = "depth") -> np.ndarray:
    """Radial distance (float64) from planar depth (H, W): the inverse of :func:`radial_to_planar`."""
    where = dict(file=file, frame=frame, field=field_name)
    k = validate_intrinsics(intrinsics, file=file, frame=frame)
    z = _distance_map(depth, where)
    return z * _ray_norm(z.shape, k)


