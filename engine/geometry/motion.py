"""Screen motion vectors of rigid scenes: exact vectors from depth + poses, and chaining vectors over frames.

Motion vectors follow ``engine.core.frames.Frame.motion_vectors``: for each pixel (centre at (u + 0.5,
v + 0.5)), the displacement in pixels (x right, y down) to where the same surface point was in an EARLIER
frame, NaN where there is none (the point is behind that camera). Cameras are OpenCV (x right, y down,
z forward), depth planar with +inf for sky (sky moves with the camera rotation only).
"""
from __future__ import annotations

from typing import Mapping, Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix
from engine.core.errors import InputError
from engine.core.frames import Camera, rigid_inverse

__all__ = ["rigid_motion_vectors", "camera_motion_vectors", "compose_motion_vectors", "sample_nearest"]


def _pixels(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return u + 0.5, v + 0.5


def _vectors_of(k_now_inv_rays: np.ndarray, depth: np.ndarray, camera: Camera,
                previous: Camera, transform: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors of the pixels ``u, v`` (1-D) with ``depth`` whose world points move by ``transform``."""
    finite = np.isfinite(depth)
    # finite points: camera -> world -> moved -> previous camera; sky: directions, rotation only
    to_prev = previous.world_to_camera @ transform @ camera.camera_to_world
    p = np.where(finite[:, None], k_now_inv_rays * np.where(finite, depth, 1.0)[:, None], k_now_inv_rays)
    q = p @ to_prev[:3, :3].T + np.where(finite, 1.0, 0.0)[:, None] * to_prev[:3, 3]
    k = previous.intrinsics
    z = q[:, 2]
    ok = z > 1e-9 * np.maximum(1.0, np.abs(q[:, :2]).max(axis=1))
    z_safe = np.where(ok, z, 1.0)
    x = k[0, 0] * q[:, 0] / z_safe + k[0, 1] * q[:, 1] / z_safe + k[0, 2]
    y = k[1, 1] * q[:, 1] / z_safe + k[1, 2]
    out = np.stack([x - u, y - v], axis=-1)
    out[~ok] = np.nan
    return out


def rigid_motion_vectors(depth: np.ndarray, camera: Camera, previous: Camera,
                         object_id: Optional[np.ndarray] = None,
                         motions: Optional[Mapping[int, np.ndarray]] = None) -> np.ndarray:
    """Exact motion vectors (H, W, 2) float32 of a frame seen by ``camera`` to the frame seen by ``previous``.

    Args:
        depth: (H, W) planar depth, +inf for sky.
        camera, previous: the cameras of this frame and of the earlier frame the vectors point to.
        object_id: (H, W) integer ids (0: static background), or None (everything static).
        motions: object id -> (4, 4) world-space rigid motion from this frame to the earlier one,
            ``world_from_object[earlier] @ inv(world_from_object[this])``; ids not listed do not move.

    Returns:
        float32 vectors in pixels (x right, y down) from each pixel centre to where its surface point was;
        NaN where that point is behind (or on) the earlier camera's plane.
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    h, w = depth.shape
    u, v = _pixels(h, w)
    u, v, d = u.reshape(-1), v.reshape(-1), depth.reshape(-1).astype(np.float64)
    k_inv = np.linalg.inv(checked_matrix(camera.intrinsics, "intrinsics", 3))
    rays = np.stack([u, v, np.ones_like(u)], axis=-1) @ k_inv.T
    out = np.empty((h * w, 2), dtype=np.float64)
    ids = None if object_id is None else checked_array(object_id, "object_id", ("H", "W"), sizes, np.int64,
                                                                     floating=False).reshape(-1)
    moving = {int(i): np.asarray(m, dtype=np.float64) for i, m in (motions or {}).items()}
    groups: list[tuple[np.ndarray, np.ndarray]] = []
    if ids is None or not moving:
        groups.append((np.ones(h * w, dtype=bool), np.eye(4)))
    else:
        static = ~np.isin(ids, list(moving)) | ~np.isfinite(d)  # the sky belongs to no object
        groups.append((static, np.eye(4)))
        for oid, m in moving.items():
            if m.shape != (4, 4):
                raise InputError(f"motion of object {oid} must be (4, 4), got {m.shape}", field="motions")
            groups.append(((ids == oid) & np.isfinite(d), m))
    for mask, transform in groups:
        if mask.any():
            out[mask] = _vectors_of(rays[mask], d[mask], camera, previous, transform, u[mask], v[mask])
    return out.reshape(h, w, 2).astype(np.float32)


def camera_motion_vectors(depth: np.ndarray, camera: Camera, previous: Camera) -> np.ndarray:
    """The motion vectors (H, W, 2) a static scene would have: camera motion alone (see ``rigid_motion_vectors``)."""
    return rigid_motion_vectors(depth, camera, previous)


def sample_nearest(field: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """``field`` (H, W, C) at continuous pixel coordinates ``u, v`` (pixel centres at +0.5) by nearest
    neighbour; NaN outside the frame or where ``u, v`` are NaN."""
    h, w = field.shape[:2]
    ok = np.isfinite(u) & np.isfinite(v) & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    x = np.where(ok, np.floor(np.where(ok, u, 0.0)), 0).astype(np.intp)
    y = np.where(ok, np.floor(np.where(ok, v, 0.0)), 0).astype(np.intp)
    out = field[y, x].astype(np.float64)
    out[~ok] = np.nan
    return out


def compose_motion_vectors(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Chain vectors over two steps: ``first`` (H, W, 2) points from frame c to frame b, ``second``
    (H, W, 2) from frame b to frame a; returns c -> a, float32.

    ``second`` is read at the pixel of frame b that ``first`` lands in (nearest neighbour): exact where
    that pixel shows the same surface point and its vector varies little within the pixel; NaN where
    ``first`` is NaN or leaves the frame (frame b does not know where the point was before), or where
    ``second`` is NaN there. For sequences with object transforms, ``rigid_motion_vectors`` between the
    two frames is exact and preferable.
    """
    sizes: dict = {}
    first = checked_array(first, "first", ("H", "W", 2), sizes)
    second = checked_array(second, "second", ("H", "W", 2), sizes)
    h, w = first.shape[:2]
    u, v = _pixels(h, w)
    bu, bv = u + first[..., 0], v + first[..., 1]
    step = sample_nearest(second, bu, bv)
    return (first.astype(np.float64) + step).astype(np.float32)
