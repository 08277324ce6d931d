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
from engine.core.frames import MAX_MOTION_DIAGONALS, Camera
from engine.geometry import kernels

__all__ = ["rigid_motion_vectors", "camera_motion_vectors", "compose_motion_vectors", "sample_nearest",
           "sample_smooth", "CHAIN_SPREAD_PX", "projected_offsets", "drop_long_vectors", "sample_footprint",
           "sample_depths", "upsample_motion_vectors", "undilate_motion_vectors", "scene_velocity", "velocity_change",
           "velocity_change_args", "run_velocity_change", "extrapolated_flow",
           "DEFAULT_STATIC_TOLERANCE", "DEFAULT_DEPTH_BAND"]

#: A vector within this many pixels (in x and in y) of the camera's own motion is a static surface ...
DEFAULT_STATIC_TOLERANCE = 1.0 / 32.0
#: ... plus this fraction of the vector's largest component: twice the rounding of a half float (engines
#: often store vectors as RG16F), so a static surface's stored vector never reads as motion.
RELATIVE_TOLERANCE = 2.0 ** -10
#: The previous frame's depth at a vector's end is trusted within this ratio of the depth the point would
#: have there had it not moved (else it belongs to another surface, e.g. an occluder).
DEFAULT_DEPTH_BAND = 1.5


def _pixels(h: int, w: int) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    return u + 0.5, v + 0.5


def _vectors_of(k_now_inv_rays: np.ndarray, depth: np.ndarray, camera: Camera,
                previous: Camera, transform: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Vectors of the pixels ``u, v`` (1-D) with ``depth`` whose world points move by ``transform``, in float64
    (``engine.geometry.reproject`` computes the same projection in float32, the warp's precision)."""
    finite = np.isfinite(depth)
    # finite points: camera -> world -> moved -> previous camera; sky: directions, rotation only
    to_prev = previous.world_to_camera @ transform @ camera.camera_to_world
    p = np.where(finite[:, None], k_now_inv_rays * np.where(finite, depth, 1.0)[:, None], k_now_inv_rays)
    q = p @ to_prev[:3, :3].T + np.where(finite, 1.0, 0.0)[:, None] * to_prev[:3, 3]
    return projected_offsets(q, previous.intrinsics, u, v)


def projected_offsets(q: np.ndarray, intrinsics: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """(N, 2) float64 offsets from the pixel positions ``u, v`` (1-D) to where the points ``q`` (N, 3, in a
    camera's axes; a direction for the sky) project with that camera's ``intrinsics``; NaN where a point is
    not finite or lies behind (or on) the camera's plane, ``z <= 1e-9 max(1, |x|, |y|)``."""
    k = intrinsics
    z = q[:, 2]
    with np.errstate(invalid="ignore"):
        ok = np.isfinite(q).all(axis=1) & (z > 1e-9 * np.maximum(1.0, np.abs(q[:, :2]).max(axis=1)))
    z_safe = np.where(ok, z, 1.0)
    x = k[0, 0] * q[:, 0] / z_safe + k[0, 1] * q[:, 1] / z_safe + k[0, 2]
    y = k[1, 1] * q[:, 1] / z_safe + k[1, 2]
    out = np.stack([x - u, y - v], axis=-1)
    out[~ok] = np.nan
    return out


def drop_long_vectors(vectors: np.ndarray, height: int, width: int) -> np.ndarray:
    """``vectors`` (N, 2) with NaN where a component exceeds ``MAX_MOTION_DIAGONALS`` frame diagonals (no screen
    position: the rgbd-seq format refuses such vectors as a unit error), in place; returns them."""
    with np.errstate(invalid="ignore"):
        vectors[np.abs(vectors).max(axis=1) > MAX_MOTION_DIAGONALS * np.hypot(height, width)] = np.nan
    return vectors


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
        NaN where that point is behind (or on) the earlier camera's plane, or so close to that plane that it
        projects more than ``MAX_MOTION_DIAGONALS`` frame diagonals away (no screen position: the rgbd-seq
        format refuses such vectors as a unit error; an object brushing past the camera makes them).
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
    return drop_long_vectors(out, h, w).reshape(h, w, 2).astype(np.float32)


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


#: Chaining (``compose_motion_vectors``) interpolates the second step's vectors bilinearly where the four around
#: the landing point agree within this many pixels (one surface, smooth motion), else takes the nearest one.
CHAIN_SPREAD_PX = 0.5


def sample_smooth(field: np.ndarray, u: np.ndarray, v: np.ndarray, spread: float = CHAIN_SPREAD_PX) -> np.ndarray:
    """``field`` (H, W, C) at continuous pixel coordinates ``u, v`` (pixel centres at +0.5): bilinear between the
    four pixel centres around the point (clamped at the border) where all four are finite and agree within
    ``spread`` in every channel, else :func:`sample_nearest` (no blend across a silhouette); NaN outside the
    frame or where ``u, v`` are NaN. float64."""
    h, w = field.shape[:2]
    nearest = sample_nearest(field, u, v)
    ok = np.isfinite(nearest).all(axis=-1)
    x = np.where(ok, u, 0.5) - 0.5
    y = np.where(ok, v, 0.5) - 0.5
    x0 = np.clip(np.floor(x), 0, w - 1).astype(np.intp)
    y0 = np.clip(np.floor(y), 0, h - 1).astype(np.intp)
    x1, y1 = np.minimum(x0 + 1, w - 1), np.minimum(y0 + 1, h - 1)
    fx = np.clip(x - x0, 0.0, 1.0)[..., None]
    fy = np.clip(y - y0, 0.0, 1.0)[..., None]
    corners = [field[y0, x0], field[y0, x1], field[y1, x0], field[y1, x1]]
    stack = np.stack(corners).astype(np.float64)
    with np.errstate(invalid="ignore"):
        agree = ok & np.isfinite(stack).all(axis=(0, -1)) & \
            ((stack.max(axis=0) - stack.min(axis=0)) <= spread).all(axis=-1)
    blend = (stack[0] * (1 - fx) + stack[1] * fx) * (1 - fy) + (stack[2] * (1 - fx) + stack[3] * fx) * fy
    return np.where(agree[..., None], blend, nearest)


def compose_motion_vectors(first: np.ndarray, second: np.ndarray) -> np.ndarray:
    """Chain vectors over two steps: ``first`` (H, W, 2) points from frame c to frame b, ``second``
    (H, W, 2) from frame b to frame a; returns c -> a, float32.

    ``second`` is read where ``first`` lands in frame b (:func:`sample_smooth`: bilinear where the four
    vectors around that point agree within ``CHAIN_SPREAD_PX``, so smooth motion such as a camera's chains
    without the nearest pixel's half-pixel error; the nearest vector across a silhouette): exact where the
    point shows the same surface; NaN where ``first`` is NaN or leaves the frame (frame b does not know where
    the point was before), or where ``second`` is NaN there. For sequences with object transforms,
    ``rigid_motion_vectors`` between the two frames is exact and preferable.
    """
    sizes: dict = {}
    first = checked_array(first, "first", ("H", "W", 2), sizes)
    second = checked_array(second, "second", ("H", "W", 2), sizes)
    h, w = first.shape[:2]
    u, v = _pixels(h, w)
    bu, bv = u + first[..., 0], v + first[..., 1]
    step = sample_smooth(second, bu, bv)
    return (first.astype(np.float64) + step).astype(np.float32)


def sample_footprint(small: int, big: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Along one axis of ``big`` full-resolution pixels spanned by ``small`` lower-resolution samples: for
    each sample's point, the full-resolution pixels whose centres bracket it, (lo, hi) int arrays, and the
    point's fraction of the way from lo's centre to hi's (float64).

    Sample i is at the point (i + 0.5) big / small: the centre of its pixel in a frame rendered at the
    lower resolution, where a GPU rendering at that resolution samples. At an odd integer ratio that point
    is a full-resolution pixel centre: lo == hi, fraction 0. At an even ratio it is the boundary between
    two pixels, both half a pixel away: hi == lo + 1, fraction 0.5 (neither is nearer: where they show
    different surfaces, which one covers the point is not in the full-resolution depth).
    """
    numerator = (2 * np.arange(small, dtype=np.int64) + 1) * big - small  # 2 small (point - 0.5) >= 0
    lo, rest = np.divmod(numerator, 2 * small)
    return lo.astype(np.intp), (lo + (rest > 0)).astype(np.intp), rest / (2.0 * small)


def sample_depths(depth: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """(h, w) float32 planar depth at the points of the samples of an (h, w) grid spanning the frame of
    ``depth`` (H, W) (:func:`sample_footprint`): inverse depth interpolated bilinearly between the pixels
    whose centres surround the point (one pixel where the point is its centre), exact for a plane, whose
    inverse depth is affine in the image; +inf where they are all sky. Where they show different surfaces
    the point's surface is unknown and the depth lies between them, as the camera motion it gives does."""
    depth = checked_array(depth, "depth", ("H", "W"), {})
    (r0, r1, fy), (c0, c1, fx) = sample_footprint(shape[0], depth.shape[0]), sample_footprint(shape[1], depth.shape[1])
    inverse = 1.0 / depth.astype(np.float64)  # sky: 0
    top = inverse[r0][:, c0] * (1.0 - fx) + inverse[r0][:, c1] * fx
    bottom = inverse[r1][:, c0] * (1.0 - fx) + inverse[r1][:, c1] * fx
    with np.errstate(divide="ignore"):
        return (1.0 / (top * (1.0 - fy)[:, None] + bottom * fy[:, None])).astype(np.float32)


def upsample_motion_vectors(vectors: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Motion vectors (h, w, 2) of a lower resolution at the frame's size (H, W) of ``depth``, float32.

    The low-resolution grid spans the frame: sample (i, j) is the point ((j + 0.5) W / w, (i + 0.5) H / h)
    of the full-resolution frame, between full-resolution pixels at even ratios (:func:`sample_footprint`).
    Depth-guided nearest neighbour (no blending across silhouettes, where a blend is a vector of neither
    surface): each full-resolution pixel takes, of the 4 samples around it, the one whose surface matches
    its own best in log depth, sky matching sky. A sample's surface is that of the full-resolution pixels
    whose centres surround its point; the match is the mean distance from the pixel's log depth to the
    nearest and the farthest of them, so a sample whose point lies between two surfaces (unknown: either
    may cover it) ranks after a sample of the pixel's own surface and before one of another. At odd
    integer ratios each point is a pixel centre: the sample's surface is that pixel's. Vectors are already in
    full-resolution pixels (``Frame.motion_vectors``).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("h", "w", 2), {})
    big_h, big_w = depth.shape
    h, w = vectors.shape[:2]
    if (h, w) == (big_h, big_w):
        return vectors
    if h > big_h or w > big_w:
        raise InputError(f"are {w}x{h}, larger than the frame's {big_w}x{big_h}", field="motion_vectors")
    log_d = np.log(np.where(np.isfinite(depth), depth, np.float32(1e30))).astype(np.float32)
    # the log depths of the full-resolution pixels nearest each sample's point: their nearest and farthest
    (r0, r1, _), (c0, c1, _) = sample_footprint(h, big_h), sample_footprint(w, big_w)
    around = np.stack([log_d.take(r, axis=0).take(c, axis=1) for r in (r0, r1) for c in (c0, c1)])
    near, far = around.min(axis=0), around.max(axis=0)
    # the 4 samples around each full-resolution pixel centre (its continuous position in the small grid)
    fy = (np.arange(big_h) + 0.5) * h / big_h - 0.5
    fx = (np.arange(big_w) + 0.5) * w / big_w - 0.5
    y0 = np.clip(np.floor(fy).astype(np.intp), 0, h - 1)
    x0 = np.clip(np.floor(fx).astype(np.intp), 0, w - 1)
    y1, x1 = np.minimum(y0 + 1, h - 1), np.minimum(x0 + 1, w - 1)
    off = np.stack([np.abs(near.take(ys, axis=0).take(xs, axis=1) - log_d)
                    + np.abs(far.take(ys, axis=0).take(xs, axis=1) - log_d) for ys in (y0, y1) for xs in (x0, x1)])
    best = np.argmin(off, axis=0)  # the first of equals, in the order (y0, x0), (y0, x1), (y1, x0), (y1, x1)
    pick = np.where(best < 2, y0[:, None] * w, y1[:, None] * w) + np.where(best % 2 == 0, x0, x1)
    return vectors.reshape(-1, 2)[pick]


def undilate_motion_vectors(vectors: np.ndarray, depth: np.ndarray, depth_gap: float = 0.1) -> np.ndarray:
    """Undo the edge dilation of motion vectors (FSR-style: each pixel takes the vector of the nearest
    surface in its 3x3 neighbourhood), float32 (H, W, 2), NaN where a vector was dilated.

    A pixel's vector counts as dilated when it equals (within 1e-3 px) the vector of the nearest pixel of
    its 3x3 neighbourhood while its own surface lies more than ``depth_gap`` (relative) behind that pixel's:
    a background pixel that was handed the foreground's motion. Such pixels lose their vector (NaN: treated
    as static by ``mvec``). Vectors and depth at the same (H, W).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("H", "W", 2), sizes)
    h, w = depth.shape
    pad_d = np.pad(np.where(np.isfinite(depth), depth, np.float32(np.inf)), 1, constant_values=np.inf)
    pad_v = np.pad(vectors, ((1, 1), (1, 1), (0, 0)), constant_values=np.nan)
    nearest = np.full((h, w), np.inf, dtype=np.float32)
    nearest_v = np.full((h, w, 2), np.nan, dtype=np.float32)
    for dy in range(3):
        for dx in range(3):
            d = pad_d[dy:dy + h, dx:dx + w]
            closer = d < nearest
            nearest = np.where(closer, d, nearest)
            nearest_v = np.where(closer[..., None], pad_v[dy:dy + h, dx:dx + w], nearest_v)
    behind = depth > nearest * (1.0 + depth_gap)
    same = np.all(np.abs(vectors - nearest_v) <= 1e-3, axis=-1)
    out = vectors.copy()
    out[behind & same] = np.nan
    return out


def scene_velocity(depth: np.ndarray, vectors: np.ndarray, prev_depth: np.ndarray, camera: Camera,
                   previous: Camera, *, static_tolerance: float = DEFAULT_STATIC_TOLERANCE,
                   band: float = DEFAULT_DEPTH_BAND) -> tuple[np.ndarray, np.ndarray]:
    """The 3D motion of every pixel's surface point between two frames, from motion vectors and depth.

    For pixel p with depth z, ``P = z K^-1 p`` in this camera; its vector says where it was in the previous
    frame's image, ``q = p + vector``. The point's previous depth is the previous frame's depth at q (the
    2x2 neighbour closest to the depth the point would have there had it not moved, trusted within
    ``band``; else that static depth, i.e. motion parallel to the previous image plane). The previous point
    ``Q`` is brought into this camera's axes; the velocity is ``P - Q`` (scene units per frame interval).

    Args:
        depth: (H, W) planar depth of this frame, +inf for sky; vectors: (H, W, 2) current -> previous
            pixels, NaN for none; prev_depth: (h', w') planar depth of the previous frame.
        camera, previous: the two frames' cameras.
        static_tolerance: pixels; a vector this close to the camera's own motion (plus ``RELATIVE_TOLERANCE``
            of its length, for half-float storage) means a static surface.
        band: ratio > 1 (see above).

    Returns:
        velocity (H, W, 3) float32 in this camera's axes (0 for sky, missing vectors and static pixels; a
        static scene gives exactly 0), and the flat indices of the moving pixels (the others).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("H", "W", 2), sizes)
    prev_depth = checked_array(prev_depth, "prev_depth", ("h", "w"), {})
    if not (static_tolerance >= 0 and band > 1 and np.isfinite(band)):
        raise InputError(f"need static_tolerance >= 0 and a finite band > 1, got {static_tolerance}, {band}",
                         field="mvec")
    relative = previous.world_to_camera @ camera.camera_to_world
    args = (np.ascontiguousarray(depth), np.ascontiguousarray(vectors), np.ascontiguousarray(prev_depth),
            np.linalg.inv(camera.intrinsics), np.ascontiguousarray(previous.intrinsics, dtype=np.float64),
            np.linalg.inv(previous.intrinsics), np.ascontiguousarray(relative[:3, :3]),
            np.ascontiguousarray(relative[:3, 3]), float(static_tolerance), RELATIVE_TOLERANCE, float(band))
    out = np.empty(depth.shape + (3,), dtype=np.float32)  # each thread zeroes its rows (a memset split in two)
    h, w = depth.shape
    # thread i takes rows i, i + parts, ..: the moving pixels, which cost the most, are shared evenly however they
    # lie in the frame; each lists its moving pixels row by row (pages never written are never touched)
    parts = len(kernels.split_ranges(h, 64))
    found, row_counts = np.empty((parts, -(-h // parts) * w), np.int64), np.empty(h, np.int64)
    counts = kernels.run_ranges(lambda first, step: kernels.scene_velocity(*args, first, h, step, out, found[first],
                                                                           row_counts),
                                [(i, parts) for i in range(parts)])
    if parts == 1:
        return out, found[0, :counts[0]].copy()
    moving = np.empty(sum(counts), np.intp)
    kernels.merge_rows(found, row_counts, parts, moving)
    return out, moving


def velocity_change(depth: np.ndarray, vectors: np.ndarray, velocity: np.ndarray, moving: np.ndarray,
                    camera: Camera, previous: Camera, prev_depth: np.ndarray, prev_velocity: np.ndarray,
                    interval_ratio: float = 1.0, *, band: float = DEFAULT_DEPTH_BAND,
                    limit: float = 0.5) -> np.ndarray:
    """The change of velocity (len(moving), 3) of the moving pixels of a frame: its velocity minus the one its
    point had in the previous frame, both in this camera's axes (an acceleration per frame interval).

    The previous velocity is ``prev_velocity`` (the previous frame's ``scene_velocity``, in its camera's
    axes) at the pixel of the previous frame the vector lands in, rotated into this camera and scaled by
    ``interval_ratio`` (this frame's interval over the previous one). It counts only where that pixel shows
    the same surface (its depth within ``band`` of the point's previous depth) and where the change is at
    most ``limit`` times the velocity: smooth motion. Elsewhere (a point unseen in the previous frame, a
    bounce, a start, a stop) the change is 0, i.e. constant velocity.
    """
    args = velocity_change_args(depth, vectors, velocity, camera, previous, prev_depth, prev_velocity,
                                interval_ratio, band=band, limit=limit)
    moving = np.ascontiguousarray(moving, dtype=np.int64)
    out = np.empty((moving.size, 3), dtype=np.float32)
    run_velocity_change(args, moving, out)
    return out


def velocity_change_args(depth: np.ndarray, vectors: np.ndarray, velocity: np.ndarray, camera: Camera,
                         previous: Camera, prev_depth: np.ndarray, prev_velocity: np.ndarray,
                         interval_ratio: float = 1.0, *, band: float = DEFAULT_DEPTH_BAND,
                         limit: float = 0.5) -> tuple:
    """``velocity_change``'s inputs checked and laid out for its compiled kernel (``kernels.velocity_change``):
    (depth, vectors, velocity, k_inv, rot, trans, prev_depth, prev_velocity, interval_ratio, band, limit), for
    a pass that computes the change of only some moving pixels (``rigid.kept_part_motion``)."""
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    vectors = checked_array(vectors, "motion_vectors", ("H", "W", 2), sizes)
    velocity = checked_array(velocity, "velocity", ("H", "W", 3), sizes)
    prev_sizes: dict = {}
    prev_depth = checked_array(prev_depth, "prev_depth", ("h", "w"), prev_sizes)
    prev_velocity = checked_array(prev_velocity, "prev_velocity", ("h", "w", 3), prev_sizes)
    relative = previous.world_to_camera @ camera.camera_to_world
    return (np.ascontiguousarray(depth), np.ascontiguousarray(vectors), np.ascontiguousarray(velocity),
            np.linalg.inv(camera.intrinsics), np.ascontiguousarray(relative[:3, :3]),
            np.ascontiguousarray(relative[:3, 3]), np.ascontiguousarray(prev_depth),
            np.ascontiguousarray(prev_velocity), float(interval_ratio), float(band), float(limit))


def run_velocity_change(args: tuple, moving: np.ndarray, out: np.ndarray) -> None:
    """``kernels.velocity_change`` of the pixels ``moving`` (int64, contiguous) into ``out`` (len(moving), 3)
    float32, with ``args`` = ``velocity_change_args``; split over the kernel threads (each pixel's row is its
    own: the same bits)."""
    kernels.run_ranges(lambda a, b: kernels.velocity_change(*args[:3], moving[a:b], *args[3:], out[a:b]),
                       kernels.split_points(moving.size))


def extrapolated_flow(depth: np.ndarray, velocity: np.ndarray, intrinsics: np.ndarray, step: float,
                      where: Optional[np.ndarray] = None, acceleration: Optional[np.ndarray] = None,
                      out: Optional[np.ndarray] = None) -> np.ndarray:
    """The (H, W, 3) flow (du, dv pixels, dz planar depth) that moves each pixel's point P along its motion,
    in 3D in this camera's axes: ``P' = P + s V + s (s + 1) / 2 A`` for ``s = step`` (frame intervals
    n-k -> n ahead), the parabola through the point's positions at s = -2, -1, 0 (``A``: the change of
    velocity V between the two intervals; without it, constant velocity); flow = project(P') - (pixel
    centre, z). ``out`` (H, W, 3) float32, zero outside ``where``, is written in place of a new array (a
    caller that reuses one keeps it zero by clearing what it wrote); any strides: the view
    ``np.moveaxis(buffer, 0, -1)`` of a channel-first (3, H, W) ``buffer`` is what ``forward_warp_frame`` reads
    without a copy. ``where`` (flat indices) limits the
    work to the pixels that move (the rest get 0; default:
    those with a non-zero velocity); ``acceleration`` (len(where), 3) belongs to those. A point that would
    reach or cross the camera plane gets NaN (the warp drops it). The result is the object flow of
    ``engine.geometry.forward_warp_frame``.
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    velocity = checked_array(velocity, "velocity", ("H", "W", 3), sizes)
    k = checked_matrix(intrinsics, "intrinsics", 3)
    h, w = depth.shape
    idx = np.flatnonzero(np.any(velocity != 0, axis=-1)) if where is None else np.asarray(where)
    idx = np.ascontiguousarray(idx, dtype=np.int64)
    if out is None:
        out = np.zeros((h, w, 3), dtype=np.float32)
    elif out.shape != (h, w, 3) or out.dtype != np.float32 or not out.flags.writeable:
        raise InputError(f"must be a writeable float32 ({h}, {w}, 3) array, got {out.dtype} {out.shape}", field="out")
    if idx.size == 0:
        return out
    has = acceleration is not None
    accel = (np.ascontiguousarray(checked_array(acceleration, "acceleration", (idx.size, 3), {})) if has
             else np.zeros((1, 3), np.float32))
    depth, velocity, k_inv = np.ascontiguousarray(depth), np.ascontiguousarray(velocity), np.linalg.inv(k)
    kernels.run_ranges(lambda a, b: kernels.extrapolate_points(depth, velocity, idx[a:b], accel[a:b] if has else accel,
                                                               has, k, k_inv, float(step), out),
                       kernels.split_points(idx.size))  # each pixel writes its own flow: the same bits
    return out


