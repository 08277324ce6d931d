"""Forward warping of an MPI to another camera: bilinear splatting with a soft z-buffer (thesis Eq. 6.1-6.2).

The warp runs as compiled kernels (``engine.geometry.kernels``), its passes split over threads;
``engine.geometry.reference.forward_warp_mpi_reference`` is its numpy oracle (same arguments as
``forward_warp_mpi_unchecked``), reproduced bit for bit. Values are float32; splat sums accumulate in
float64 in per-thread work buffers reused across calls (``SCRATCH``).
"""
from __future__ import annotations

import threading
from typing import Optional

import numpy as np

from engine.core.checks import checked_array, checked_matrix, checked_out_size, checked_sharpness
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.camera import MAX_PIXEL_COORD, TINY_DEPTH, checked_flow, reprojection_matrix
from engine.geometry.mpi import Mpi, checked_mpi, plane_bounds

#: A warped MPI pixel is covered (alpha = 1) when its summed bilinear splat weight exceeds this.
COVERAGE_THRESHOLD = 1e-3
#: Bilinear fractions within this many pixels of a pixel centre snap onto it (continuously), so round-off
#: of an exact landing cannot leak a tiny weight that the soft z-buffer would amplify by up to e^50.
SUBPIXEL_SNAP = 1.0 / 256.0
#: Floor of the soft z-buffer's log-weight: keeps float32 weights far from underflow (binds only when
#: sharpness > 60).
MIN_LOG_WEIGHT = -60.0
# Soft z-buffer weight of sky points (float64 sums): below any finite point's weight (>= e^-60 times a
# bilinear weight >= ~1e-9) by > e^100; a pixel whose summed weight is below SKY_ONLY_WEIGHT saw only sky.
SKY_WEIGHT = float(np.exp(-300.0))
SKY_ONLY_WEIGHT = float(np.exp(-200.0))
#: Default soft z-buffer sharpness (the authors' 50).
DEFAULT_SHARPNESS = 50.0


class _Scratch(threading.local):
    """Per-thread, grow-only work buffers of the warp (per-point taps and weights, the padded sums),
    reused across calls and never returned to callers.

    Fresh large temporaries cost a page fault per 4 KiB on first touch (two for calloc'd memory), which
    dominated the run time on the 2-core VM this was tuned on; ``np.bincount`` always allocates its output,
    so the splat accumulates with ``np.add.at`` (fast path since NumPy 1.25) into these buffers instead.
    They hold ~37 MB after a 960x540 frame warp, ~115 MB after a Z = 4 MPI warp (4x at 1920x1080).
    """

    def __init__(self) -> None:
        self.buffers: dict[str, np.ndarray] = {}

    def get(self, name: str, size: int, dtype=np.float64) -> np.ndarray:
        buf = self.buffers.get(name)
        if buf is None or buf.size < size or buf.dtype != dtype:
            buf = self.buffers[name] = np.empty(size, dtype=dtype)
        return buf[:size]


SCRATCH = _Scratch()
#: Smallest share of a split warp pass per thread (smaller warps run on one thread: a hand-off costs ~0.1 ms).
MIN_POINTS_PER_THREAD = 1 << 16
MIN_ROWS_PER_THREAD = 8


def _pass_buffers(n: int) -> tuple[np.ndarray, ...]:
    """Pass 1's per-point outputs for ``n`` points (this thread's ``SCRATCH``): base, fx, fy, z, a, log_z."""
    base = SCRATCH.get("base", n, np.intp)
    fx, fy, z, a = (SCRATCH.get(name, n, np.float32) for name in ("fx", "fy", "z", "a"))
    return base, fx, fy, z, a, SCRATCH.get("log_z", n)


#: pass 1's constants after the matrix: the snap's scale and width, 1 / MAX_PIXEL_COORD and TINY_DEPTH
_CONSTANTS = (np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP)), np.float32(SUBPIXEL_SNAP),
              np.float32(1.0 / MAX_PIXEL_COORD), np.float32(TINY_DEPTH))


def _warp_matrix(k_src, t_src, k_dst, t_dst) -> np.ndarray:
    return np.ascontiguousarray(reprojection_matrix(k_src, t_src, k_dst, t_dst).astype(np.float32))


def _row_ranges(h: int, per_row: int) -> list[tuple[int, int]]:
    """Pass 1's split of ``h`` source rows of ``per_row`` points over the kernel threads."""
    return kernels.split_ranges(h, max(MIN_ROWS_PER_THREAD, -(-MIN_POINTS_PER_THREAD // max(1, per_row))))


def _splat_sums(flat_color, depth, alpha, half_inv, k_src, t_src, k_dst, t_dst, object_flow, out_size, sharpness):
    """Passes 1 and 2 of the warp (``project_points``, ``splat_points``) for points with colour ``flat_color``
    (3, Z * H * W) (any strides), ``depth`` and ``alpha`` (Z, H, W): the per-thread padded sum volumes
    (P, Z * (ho + 2) * (wo + 2), 6) that ``normalize`` or ``normalize_frame`` turn into the result."""
    num_z, h, w = alpha.shape
    ho, wo = out_size
    n = num_z * h * w
    flow = np.zeros((3, 1, 1, 1), np.float32) if object_flow is None else np.ascontiguousarray(object_flow)
    matrix = _warp_matrix(k_src, t_src, k_dst, t_dst)
    buffers = _pass_buffers(n)
    # each pass split over threads (engine.geometry.kernels.run_ranges): pass 1 by source rows, pass 2 by points into
    # one padded sum volume per part, the normalisation by output rows (it adds the parts in order)
    extents = kernels.run_ranges(lambda r0, r1: kernels.project_points(
        depth, alpha, flow, object_flow is not None, matrix, half_inv, ho, wo, *_CONSTANTS, r0, r1,
        *buffers), _row_ranges(h, num_z * w))
    return _splat_pass(flat_color, buffers, extents, num_z, out_size, sharpness)


def _splat_pass(flat_color, buffers, extents, num_z: int, out_size, sharpness) -> np.ndarray:
    """Pass 2 (``splat_points``) of pass 1's ``buffers`` and (min, max) log(1 + z) ``extents`` (one per
    range): the per-thread padded sum volumes (P, Z * (ho + 2) * (wo + 2), 6)."""
    base, fx, fy, z, a, log_z = buffers
    lo, hi = min(e[0] for e in extents), max(e[1] for e in extents)
    hp, wp = out_size[0] + 2, out_size[1] + 2
    ranges = kernels.split_ranges(base.size, MIN_POINTS_PER_THREAD)
    sums = SCRATCH.get("sums", len(ranges) * 6 * num_z * hp * wp).reshape(len(ranges), -1, 6)  # six sums a pixel
    kernels.run_ranges(lambda p0, p1: kernels.splat_points(
        flat_color, base, fx, fy, z, a, log_z, lo, hi, float(sharpness), wp, MIN_LOG_WEIGHT, SKY_WEIGHT, p0, p1,
        sums[ranges.index((p0, p1))]), ranges)
    return sums


def forward_warp_mpi_unchecked(mpi: Mpi, k_src, t_src, k_dst, t_dst, object_flow, out_size, sharpness):
    """Unvalidated body of ``forward_warp_mpi`` (inputs already float32 / float64 arrays): the compiled
    kernels of ``engine.geometry.kernels``, held to ``forward_warp_mpi_reference`` by the tests."""
    color, depth, alpha, planes = mpi
    num_z = alpha.shape[0]
    ho, wo = out_size
    depth, alpha, color = (np.ascontiguousarray(v) for v in (depth, alpha, color))
    sums = _splat_sums(color.reshape(3, -1), depth, alpha, plane_bounds(planes), k_src, t_src, k_dst, t_dst,
                       object_flow, out_size, sharpness)
    out_color = np.empty((3, num_z, ho, wo), dtype=np.float32)
    out_depth, out_alpha, cov = (np.empty((num_z, ho, wo), dtype=np.float32) for _ in range(3))
    kernels.run_ranges(lambda r0, r1: kernels.normalize(
        sums, num_z, ho, wo, COVERAGE_THRESHOLD, SKY_ONLY_WEIGHT, r0, r1, out_color, out_depth, out_alpha, cov),
        kernels.split_ranges(ho, MIN_ROWS_PER_THREAD))
    return Mpi(out_color, out_depth, out_alpha, planes), cov


def _warp_frame_unchecked(color, depth, k_src, t_src, k_dst, t_dst, object_flow, sharpness):
    """``forward_warp_frame``'s body: the one-plane MPI warp + composite without the MPI's layout. The frame is
    that MPI already (every pixel on its one plane, alpha 1), read in place (colour (H, W, 3) as (3, H * W) with
    strides), and ``normalize_frame`` writes the composite straight into frame layout: bit for bit the MPI path
    (tested), without its two transposing copies."""
    h, w = depth.shape
    ones = np.broadcast_to(np.float32(1.0), (1, h, w))
    sums = _splat_sums(color.reshape(-1, 3).T, depth[None], ones, np.zeros(0, np.float32), k_src, t_src, k_dst,
                       t_dst, object_flow, (h, w), sharpness)
    return _normalized_frame(sums, h, w)


def _normalized_frame(sums, h: int, w: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``normalize_frame`` of a one-plane warp's sums: (colour (H, W, 3), depth (H, W), holes (H, W))."""
    out_color = np.empty((h, w, 3), dtype=np.float32)
    out_depth = np.empty((h, w), dtype=np.float32)
    holes = np.empty((h, w), dtype=bool)
    kernels.run_ranges(lambda r0, r1: kernels.normalize_frame(
        sums, h, w, COVERAGE_THRESHOLD, SKY_ONLY_WEIGHT, r0, r1, out_color, out_depth, holes),
        kernels.split_ranges(h, MIN_ROWS_PER_THREAD))
    return out_color, out_depth, holes


def forward_warp_mpi(mpi: Mpi, K_src: np.ndarray, T_src: np.ndarray, K_dst: np.ndarray, T_dst: np.ndarray,
                     object_flow: Optional[np.ndarray] = None, *, out_size: Optional[tuple[int, int]] = None,
                     sharpness: float = DEFAULT_SHARPNESS) -> tuple[Mpi, np.ndarray]:
    """Forward-warp an MPI to another camera by bilinear splatting with a soft z-buffer (thesis Eq. 6.1-6.2).

    Every point with alpha > 0 moves by ``object_flow`` (in the source view), is reprojected with
    ``K_dst T_dst T_src^-1``, goes to the destination plane nearest in inverse depth (destination planes =
    ``mpi.plane_depths``) and is splatted into the 4 neighbouring pixels of that plane with inverse bilinear
    weights times alpha times the soft z-buffer weight ``exp(-sharpness log(1 + z) / max log(1 + z))`` (z in
    the destination; max over the finite points of this warp). Sky points (+inf) count only where no finite
    point landed. Points behind the destination camera or outside the frame are dropped (splatted into a
    volume padded by 1 pixel, then cropped): nothing wraps around or piles up at the border.

    Args:
        mpi: the source ``Mpi``.
        K_src, T_src, K_dst, T_dst: intrinsics (3, 3) and world-to-camera (4, 4) of both views.
        object_flow: optional (3, Z, H, W) = (du, dv) pixels, dz scene units per MPI point (source view).
        out_size: destination (height, width); default the source size.
        sharpness: soft z-buffer sharpness >= 0 (0 = plain average).

    Returns:
        ``(warped Mpi, coverage (Z, H, W))``: warped colour and depth are the weighted means of what landed,
        alpha = 1 where coverage (the summed bilinear weight, without the z factor) > COVERAGE_THRESHOLD,
        and colour = depth = alpha = 0 elsewhere.
    """
    sizes: dict = {}
    mpi = checked_mpi(mpi, sizes)
    if object_flow is not None:
        object_flow = checked_array(object_flow, "object_flow", (3, "Z", "H", "W"), sizes)
    out = checked_out_size(out_size, (sizes["H"], sizes["W"]))
    return forward_warp_mpi_unchecked(mpi, checked_matrix(K_src, "K_src", 3), checked_matrix(T_src, "T_src", 4),
                             checked_matrix(K_dst, "K_dst", 3), checked_matrix(T_dst, "T_dst", 4), object_flow, out,
                             checked_sharpness(sharpness))


def forward_warp_frame(color: np.ndarray, depth: np.ndarray, K_src: np.ndarray, T_src: np.ndarray,
                       K_dst: np.ndarray, T_dst: np.ndarray, flow: Optional[np.ndarray] = None,
                       sharpness: float = DEFAULT_SHARPNESS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward-warp an RGB-D frame: a one-plane ``build_mpi`` + ``forward_warp_mpi`` + ``composite`` (computed
    without building the MPI: the same bits).

    Args:
        color: (H, W, 3) linear RGB; depth: (H, W) planar, +inf for sky.
        K_src, T_src, K_dst, T_dst: intrinsics (3, 3) and world-to-camera (4, 4) of both views.
        flow: optional (H, W, 3) (du, dv, dz) or (H, W, 2) (dz = 0) object flow in the source view.
        sharpness: soft z-buffer sharpness.

    Returns:
        color (H, W, 3), depth (H, W) (+inf on sky and holes), holes (H, W) bool (nothing landed).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    color = checked_array(color, "color", ("H", "W", 3), sizes)
    object_flow = None
    if flow is not None:
        flow = checked_flow(flow, sizes)
        planar = np.moveaxis(flow, -1, 0)
        if flow.shape[2] == 3 and flow.dtype == np.float32 and planar.flags.c_contiguous:
            object_flow = planar[:, None]  # held channel-first already (a view of a (3, H, W) array): no copy
        else:
            # per-thread scratch, not a fresh 6 MB a 960x540 frame: first touches of new pages cost page faults
            object_flow = SCRATCH.get("frame_flow", 3 * flow.shape[0] * flow.shape[1], np.float32).reshape(
                (3, 1) + depth.shape)
            object_flow[:flow.shape[2], 0] = planar
            object_flow[flow.shape[2]:] = 0.0
    return _warp_frame_unchecked(np.ascontiguousarray(color), np.ascontiguousarray(depth),
                                 checked_matrix(K_src, "K_src", 3), checked_matrix(T_src, "T_src", 4),
                                 checked_matrix(K_dst, "K_dst", 3), checked_matrix(T_dst, "T_dst", 4), object_flow,
                                 checked_sharpness(sharpness))


#: pass 1 of a moved frame: a moving pixel's extrapolation counted as this many pixels' projections when its rows
#: are split over the threads (``_moved_rows``; any split gives the same bits). Measured on spin4101's 960x540
#: frames (58k-107k moving pixels), one thread per range: the two ranges 0.13 ms apart at 2, 0.34-0.55 at 1
MOVED_POINT_COST = 2.0


def _moved_rows(moving: np.ndarray, h: int, w: int) -> list[tuple[int, int]]:
    """``_row_ranges`` of a frame's rows with each range's end moved so that the ranges hold even shares of the
    pixels plus ``MOVED_POINT_COST`` per moving pixel (flat indices, increasing)."""
    ranges = _row_ranges(h, w)
    if len(ranges) == 1:
        return ranges
    firsts = np.searchsorted(moving, np.arange(h + 1, dtype=np.int64) * w)  # each row's first moving pixel
    cost = w * np.arange(h + 1) + MOVED_POINT_COST * firsts  # the rows before each row
    edges = np.searchsorted(cost, cost[-1] * np.arange(1, len(ranges)) / len(ranges))
    # increasing however ``moving`` is ordered (the warp refuses one out of order after its first pass)
    edges = [0] + [int(e) for e in np.maximum.accumulate(np.clip(edges, 1, h - 1))] + [h]
    return [(a, b) for a, b in zip(edges[:-1], edges[1:]) if b > a]


def forward_warp_moved_frame(color: np.ndarray, depth: np.ndarray, K_src: np.ndarray, T_src: np.ndarray,
                             K_dst: np.ndarray, T_dst: np.ndarray, velocity: np.ndarray, moving: np.ndarray,
                             step: float, acceleration: Optional[np.ndarray] = None,
                             sharpness: float = DEFAULT_SHARPNESS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``forward_warp_frame`` of an RGB-D frame whose ``moving`` pixels move by their extrapolated motion
    (``engine.geometry.motion.extrapolated_flow(depth, velocity, K_src, step, moving, acceleration)``), that flow
    computed in the warp's first pass as each moving pixel is reached (``kernels.project_moved_frame``): no
    (H, W, 3) flow is written, read or cleared again. The same bits as ``forward_warp_frame`` of that flow.

    Args:
        color, depth, K_src, T_src, K_dst, T_dst, sharpness: as ``forward_warp_frame``'s.
        velocity: (H, W, 3) scene units per frame interval in the source camera's axes (read at ``moving`` only).
        moving: (M,) flat indices of the moving pixels, strictly increasing.
        step: frame intervals ahead (``P' = P + s V + s (s + 1) / 2 A``, s = ``step``).
        acceleration: (M, 3) the moving pixels' change of velocity per interval, or None (constant velocity).

    Returns:
        color (H, W, 3), depth (H, W), holes (H, W), as ``forward_warp_frame``.
    """
    sizes: dict = {}
    depth = np.ascontiguousarray(checked_array(depth, "depth", ("H", "W"), sizes))
    color = np.ascontiguousarray(checked_array(color, "color", ("H", "W", 3), sizes))
    velocity = np.ascontiguousarray(checked_array(velocity, "velocity", ("H", "W", 3), sizes))
    moving = np.ascontiguousarray(moving, dtype=np.int64)
    if moving.ndim != 1:
        raise InputError(f"must be (M,) flat pixel indices, got shape {moving.shape}", field="moving")
    has = acceleration is not None
    accel = (np.ascontiguousarray(checked_array(acceleration, "acceleration", (moving.size, 3), {})) if has
             else np.zeros((1, 3), np.float32))
    k_src = checked_matrix(K_src, "K_src", 3)
    matrix = _warp_matrix(k_src, checked_matrix(T_src, "T_src", 4), checked_matrix(K_dst, "K_dst", 3),
                          checked_matrix(T_dst, "T_dst", 4))
    sharpness = checked_sharpness(sharpness)
    h, w = depth.shape
    k_inv = np.linalg.inv(k_src)
    buffers = _pass_buffers(h * w)
    ranges = _moved_rows(moving, h, w)
    extents = kernels.run_ranges(lambda r0, r1: kernels.project_moved_frame(
        depth, velocity, moving, accel, has, k_src, k_inv, float(step), matrix, *_CONSTANTS, r0, r1, *buffers), ranges)
    walked = [0] + [e[3] for e in extents]  # each range walks on where the one before stopped, to the last point
    if [e[2] for e in extents] != walked[:-1] or walked[-1] != moving.size:
        raise InputError(f"must be strictly increasing flat indices of the {h}x{w} frame", field="moving")
    sums = _splat_pass(color.reshape(-1, 3).T, buffers, extents, 1, (h, w), sharpness)
    return _normalized_frame(sums, h, w)
