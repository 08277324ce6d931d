"""Pixels, cameras and points: unproject, project and reproject (thesis Eq. 6.2), numpy (``seen_before``:
its numba kernel).

Conventions (``engine/core/frames.py``): OpenCV camera axes (x right, y down, z forward), rigid
``world_to_camera`` 4x4, pinhole ``intrinsics`` 3x3 with last row [0, 0, 1]; pixel (u, v) has its centre at
(u + 0.5, v + 0.5) and ``uv`` arrays hold (x, y) = (column, row); ``depth`` is planar, > 0, ``+inf`` for sky
(a point at infinity, homogeneous w = 0: only rotations move it, nothing produces NaN). 4x4 compositions
are made in float64, per-point arithmetic in float32.
"""
from __future__ import annotations

from functools import lru_cache
from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix
from engine.core.errors import InputError
from engine.core.frames import rigid_inverse
from engine.geometry import kernels

#: A projected point is valid (in front of the camera) when z > (|z u| + |z v|) / MAX_PIXEL_COORD +
#: TINY_DEPTH: relative to its own scale, and so that |u| + |v| < 1e7 px; other points get uv = 0, z = 0.
MAX_PIXEL_COORD = 1e7
#: Smallest camera z counted as "in front" (keeps 1 / z finite in float32).
TINY_DEPTH = 1e-30


@lru_cache(maxsize=16)
def pixel_grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Flat, read-only float32 pixel-centre coordinates (u + 0.5, v + 0.5), each (H * W,), cached by size."""
    u = np.tile(np.arange(width, dtype=np.float32) + 0.5, height)
    v = np.repeat(np.arange(height, dtype=np.float32) + 0.5, width)
    u.flags.writeable = False
    v.flags.writeable = False
    return u, v


def pixel_centers(height: int, width: int) -> np.ndarray:
    """Pixel-centre coordinates, (H, W, 2) float32: ``out[v, u] = (u + 0.5, v + 0.5)`` (x = column first).

    >>> pixel_centers(2, 3)[1, 2].tolist()
    [2.5, 1.5]
    """
    height, width = int(height), int(width)
    if height < 0 or width < 0:
        raise InputError(f"must be non-negative, got {height} x {width}", field="height, width")
    u, v = pixel_grid(height, width)
    return np.stack([u, v], axis=-1).reshape(height, width, 2)


def _pinhole_inverse(k: np.ndarray) -> np.ndarray:
    """Inverse of a 3x3 intrinsics matrix with last row [0, 0, 1], in closed form (no general inverse)."""
    a, b, c = k[0]
    d, e, f = k[1]
    det = a * e - b * d
    ia, ib, id_, ie = e / det, -b / det, -d / det, a / det
    return np.array([[ia, ib, -(ia * c + ib * f)], [id_, ie, -(id_ * c + ie * f)], [0.0, 0.0, 1.0]])


def _block(k3: np.ndarray) -> np.ndarray:
    """The 4x4 homogeneous form [[k3, 0], [0, 1]] of a 3x3 matrix (float64)."""
    out = np.eye(4)
    out[:3, :3] = k3
    return out


def _pixel_points(u, v, depth):
    """Homogeneous pixel-space points (d u, d v, d, 1) of pixels at (u, v); sky (+inf) -> (u, v, 1, 0).

    ``[[K^-1, 0], [0, 1]]`` maps them to camera points (``unproject``); the whole of Eq. 6.2 is then a
    single 4x4 matrix ``[[K_dst, 0], [0, 1]] T_dst T_src^-1 [[K_src^-1, 0], [0, 1]]``.
    """
    sky = np.isinf(depth)
    if sky.any():
        scale = np.where(sky, np.float32(1.0), depth)
        return u * scale, v * scale, scale, (~sky).astype(np.float32)
    return u * depth, v * depth, depth.astype(np.float32, copy=True), np.ones_like(depth)


def _transform(m: np.ndarray, x, y, z, w):
    """Apply a 4x4 matrix whose last row is [0, 0, 0, 1] to homogeneous points given as component arrays."""
    rows = m.astype(np.float32).tolist()  # float32 coefficients keep the arithmetic in float32
    out = []
    for r in rows[:3]:
        acc = r[0] * x
        for coef, comp in ((r[1], y), (r[2], z), (r[3], w)):
            if coef != 0.0:
                acc += coef * comp
        out.append(acc)
    return out[0], out[1], out[2], w


def _project_pixels(hu, hv, z, w):
    """(u, v, depth, valid) of homogeneous pixel-space points (hu, hv, z, w) = (K [x, y, z], w); see ``project``."""
    valid = z > (np.abs(hu) + np.abs(hv)) * np.float32(1.0 / MAX_PIXEL_COORD) + np.float32(TINY_DEPTH)
    z_safe = np.where(valid, z, np.float32(1.0))
    invalid = ~valid
    u = hu / z_safe
    v = hv / z_safe
    u[invalid] = 0.0
    v[invalid] = 0.0
    depth = np.full_like(z, np.inf)
    np.divide(z, w, out=depth, where=w > 0)
    depth[invalid] = 0.0
    return u, v, depth, valid


def unproject(depth: np.ndarray, intrinsics: np.ndarray) -> np.ndarray:
    """Homogeneous camera-space points of every pixel: (..., H, W) planar depth -> (..., H, W, 4) float32.

    A finite depth d gives ``[d * K^-1 [u+0.5, v+0.5, 1], 1]``; ``+inf`` (sky) gives the direction
    ``[K^-1 [u+0.5, v+0.5, 1], 0]`` (a point at infinity: translations leave it where it is).

    >>> k = np.array([[2.0, 0, 1], [0, 2, 1], [0, 0, 1]])
    >>> unproject(np.array([[4.0, np.inf]], np.float32), k)[0].tolist()
    [[-1.0, -1.0, 4.0, 1.0], [0.25, -0.25, 1.0, 0.0]]
    """
    depth = checked_array(depth, "depth", ("...", "H", "W"), None)
    k = checked_matrix(intrinsics, "intrinsics", 3)
    h, w = depth.shape[-2:]
    u, v = pixel_grid(h, w)
    lead = depth.shape[:-2]
    pixels = _pixel_points(np.broadcast_to(u, lead + (h * w,)), np.broadcast_to(v, lead + (h * w,)),
                           depth.reshape(lead + (h * w,)))
    points = _transform(_block(_pinhole_inverse(k)), *pixels)
    return np.stack(points, axis=-1).reshape(depth.shape + (4,))


def relative_transform(src_world_to_camera: np.ndarray, dst_world_to_camera: np.ndarray) -> np.ndarray:
    """``T_dst @ inv(T_src)`` (float64, exact rigid inverse): maps source-camera points to destination-camera.

    Both are rigid world-to-camera (..., 4, 4) matrices; leading axes broadcast.
    """
    src = checked_array(src_world_to_camera, "src_world_to_camera", ("...", 4, 4), None, np.float64, floating=False)
    dst = checked_array(dst_world_to_camera, "dst_world_to_camera", ("...", 4, 4), None, np.float64, floating=False)
    return dst @ rigid_inverse(src)


def project(points_h: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Project homogeneous camera points (..., 4) (w = 1 finite, w = 0 at infinity) with ``intrinsics``.

    Returns ``(uv (..., 2), z (...), valid (...))``: continuous pixel coordinates (pixel centres at +0.5),
    camera depth z (z / w; +inf for points at infinity) and ``valid``: in front of the camera by a margin
    relative to the point's scale, ``z > (|z u| + |z v|) / MAX_PIXEL_COORD + TINY_DEPTH`` (so |u| + |v| <
    1e7 px). Points behind, on or grazing the camera plane are invalid and get uv = 0 and z = 0, never NaN
    or inf garbage.

    >>> uv, z, ok = project(np.array([[0.5, 0.0, 2.0, 1.0], [0.0, 0.0, -1.0, 1.0]]), np.diag([100.0, 100, 1]))
    >>> uv.tolist(), z.tolist(), ok.tolist()
    ([[25.0, 0.0], [0.0, 0.0]], [2.0, 0.0], [True, False])
    """
    pts = checked_array(points_h, "points_h", ("...", 4), None)
    k = checked_matrix(intrinsics, "intrinsics", 3)
    u, v, z, valid = _project_pixels(*_transform(_block(k), pts[..., 0], pts[..., 1], pts[..., 2], pts[..., 3]))
    return np.stack([u, v], axis=-1), z, valid


def reprojection_matrix(k_src, t_src, k_dst, t_dst) -> np.ndarray:
    """Eq. 6.2 as one float64 4x4 matrix on pixel points: [[K_dst, 0], [0, 1]] T_dst T_src^-1 [[K_src^-1, 0], [0, 1]]."""
    return _block(k_dst) @ t_dst @ rigid_inverse(t_src) @ _block(_pinhole_inverse(k_src))


def reproject_points(u, v, depth, matrix):
    """Source pixel coordinates + depth -> destination (u, v, z, valid) (see ``reprojection_matrix``)."""
    return _project_pixels(*_transform(matrix, *_pixel_points(u, v, depth)))


def checked_flow(flow, sizes, name="flow"):
    flow = checked_array(flow, name, ("H", "W", "C"), sizes)
    if flow.shape[2] not in (2, 3):
        raise InputError(f"must have shape (H, W, 2) or (H, W, 3), got {flow.shape}", field=name)
    return flow


def reproject(depth: np.ndarray, K_src: np.ndarray, T_src: np.ndarray, K_dst: np.ndarray, T_dst: np.ndarray,
              flow: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Where each source pixel lands in the destination view (thesis Eq. 6.2).

    ``X = (d + dz) K_src^-1 [u + 0.5 + du, v + 0.5 + dv, 1]``, then ``T_dst T_src^-1``, then ``K_dst``.

    Args:
        depth: (H, W) planar source depth, +inf for sky (sky ignores dz and moves with rotation only).
        K_src, T_src, K_dst, T_dst: intrinsics (3, 3) and world-to-camera (4, 4) of both views.
        flow: optional (H, W, 3) per-pixel 3D object flow in the source view: (du, dv) pixels, dz scene
            units; (H, W, 2) means dz = 0.

    Returns:
        uv (H, W, 2), z (H, W) destination camera depth, valid (H, W) (in front of the destination camera;
        uv = z = 0 where not valid).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    k_src, k_dst = checked_matrix(K_src, "K_src", 3), checked_matrix(K_dst, "K_dst", 3)
    matrix = reprojection_matrix(k_src, checked_matrix(T_src, "T_src", 4), k_dst, checked_matrix(T_dst, "T_dst", 4))
    h, w = depth.shape
    u, v = pixel_grid(h, w)
    d = depth.reshape(-1)
    if flow is not None:
        flow = checked_flow(flow, sizes).reshape(h * w, -1)
        u, v = u + flow[:, 0], v + flow[:, 1]
        if flow.shape[1] == 3:
            d = d + flow[:, 2]
    uo, vo, z, valid = reproject_points(u, v, d, matrix)
    return np.stack([uo, vo], axis=-1).reshape(h, w, 2), z.reshape(h, w), valid.reshape(h, w)


def seen_before(depth_n: np.ndarray, K_n: np.ndarray, T_n: np.ndarray, K_prev: np.ndarray, T_prev: np.ndarray,
                size_prev: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels of frame n whose surface, were it static, lay inside frame n-k's view (reprojected
    into camera n-k in front of it and inside its (h, w) = ``size_prev`` image; sky by the rotation alone).

    Elsewhere frame n-k never saw the surface (content entering at the border as the camera turns), so the
    camera-compensated frame n-k (whatever the warp put there: a farther surface, or nothing) says nothing
    about object motion: the motion gate ignores these pixels and the flow predictors give them none.
    ``depth_n`` (H, W) planar depth, +inf sky; cameras as ``reproject`` takes them (pixel centres at +0.5:
    inside is [0, w) x [0, h)). Compiled (``kernels.seen_pixels``, rows split over the kernel threads); the
    numpy oracle is ``reference.seen_before_reference``.
    """
    depth = checked_array(depth_n, "depth_n", ("H", "W"), None)
    matrix = reprojection_matrix(checked_matrix(K_n, "K_n", 3), checked_matrix(T_n, "T_n", 4),
                                 checked_matrix(K_prev, "K_prev", 3), checked_matrix(T_prev, "T_prev", 4))
    h, w = (int(n) for n in size_prev)
    out = np.empty(depth.shape, dtype=np.bool_)
    depth, matrix = np.ascontiguousarray(depth), matrix.astype(np.float32)
    kernels.run_ranges(lambda r0, r1: kernels.seen_pixels(depth[r0:r1], matrix, np.float32(1.0 / MAX_PIXEL_COORD),
                                                          np.float32(TINY_DEPTH), h, w, r0, out[r0:r1]),
                       kernels.split_rows(*depth.shape))
    return out
