"""Compiled (numba) kernels of the engine's hot loops, each held to a numpy reference by the tests.

- ``encode8``: 8-bit display encoding of linear RGB (``engine.core.colorspace.encode8_reference``), by the
  exact per-bucket table of ``engine.core.colorspace.encode8_table``.
- ``srgb_encode``, ``srgb_decode``, ``lookup``: ``display_encode``, ``srgb_to_linear`` and the 8-bit decoding table
  of ``engine.core.colorspace`` (to one float32 ulp: numpy's SIMD ``power`` and libm's ``pow`` may round
  differently), for whole frames (``engine.geometry.encoding``).
- ``project_points``, ``splat_points``, ``normalize``: ``engine.geometry._forward_warp_mpi``, the forward
  splat, in one pass per stage. The numpy body in ``engine/geometry/ops.py`` (``_forward_warp_mpi_reference``)
  is the test oracle of these kernels and states the semantics: every point with alpha > 0 moves by its
  object flow, is reprojected with one 4x4 matrix on homogeneous pixel points (float32 arithmetic, float32
  coefficients), lands on the destination plane nearest in inverse depth and is splatted into its 4
  neighbouring pixels (a volume padded by one pixel, then cropped) with inverse bilinear weights times
  alpha times the soft z-buffer weight; sums accumulate in float64. The numpy version needs ~30 array
  passes and 24 ``np.add.at`` calls per chunk of points; here each point is read once per pass.
- ``one_hot_mpi``, ``composite``: ``engine.geometry._build_mpi`` and ``_composite``; ``normalize_frame``: the
  last warp pass and the composite of a one-plane warp in one (``forward_warp_frame``).
- ``project_moved_frame``: ``project_points`` of a one-plane frame whose moving pixels' flow
  (``extrapolate_points``') is computed in the pass (``forward_warp_moved_frame``); the two share their
  arithmetic (``_landing``, ``_moved_flow``: scalars in and out, since an array handed to an inlined helper
  costs a reference count per point).
- ``row_sources``, ``fill_rows``, ``fill_columns``: the row scan of the simple hole fill
  (``engine.geometry.holefill``), the second also copying the sources, and its column pass for holes no row
  source reaches (oracle: the fill's numpy path, ``holefill.fill_holes_reference``).
- ``seen_pixels``: ``engine.geometry.camera.seen_before`` (reference: ``seen_before_reference``).
- ``zero_untrusted``: ``engine.predict.dis.drop_untrusted`` (reference: ``trusted_motion``'s mask; tested in
  ``tests/predict/test_trusted_motion.py``).
- ``upsample_planes``: the full-resolution sampling of ``engine.predict.decomp.upsample.upsample_flow`` (to 1e-5: OpenCV's
  resize, the reference, may round its bilinear sums differently).

``tests/geometry/test_kernels.py`` holds every kernel to its reference (bit-identical, compositing to 1e-6, the
flow upsampling to 1e-5; a warp split over threads, ``split_ranges`` / ``run_ranges``, to 1e-6, because
its per-thread partial sums are added in another order).
Conventions are ``engine/geometry/ops.py``'s (pixel centres at +0.5, planar depth, +inf sky).

The kernels are compiled on first use (about 3 s for all, then cached on disk beside this file) and
release the GIL: ``engine.geometry`` splits the warp's passes over a pool of plain threads
(``thread_count``: the CPUs the process may use, at most 8, or ``$INTERLEAVE_KERNEL_THREADS``), which sleep
when idle, unlike numba's OpenMP threads (tried and dropped: they spun and slowed onnxruntime and OpenCV).
``run_beside`` runs a serial step on that pool while the calling thread does another.
"""
from __future__ import annotations

import math
import os
import threading
from concurrent.futures import ThreadPoolExecutor
from typing import Callable, TypeVar

import numpy as np
from numba import njit

from engine.core.colorspace import SRGB_LINEAR_SLOPE

_F32 = np.float32

#: Environment variable that sets how many threads the split kernels use (default: the CPUs this process
#: may run on, at most 8; 1: everything on the calling thread).
THREADS_ENV = "INTERLEAVE_KERNEL_THREADS"
_POOL: dict = {}
_IN_WORKER = threading.local()
T = TypeVar("T")


def thread_count() -> int:
    """Threads the split kernels use: ``$INTERLEAVE_KERNEL_THREADS`` if set (>= 1), else the CPUs this
    process may run on (at most 8)."""
    raw = os.environ.get(THREADS_ENV, "").strip()
    if raw:
        try:
            value = int(raw)
        except ValueError:
            value = 0
        if value < 1:
            raise ValueError(f"{THREADS_ENV} must be an integer >= 1, got {raw!r}")
        return value
    try:
        cpus = len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        cpus = os.cpu_count() or 1
    return max(1, min(8, cpus))


def split_ranges(count: int, min_size: int, parts: int = 0) -> list[tuple[int, int]]:
    """[0, count) cut into at most ``parts`` (default ``thread_count()``) contiguous ranges of >= ``min_size``
    items each (one range when ``count`` < 2 ``min_size``, or from a worker thread of ``run_ranges``).

    >>> split_ranges(10, 3, 2), split_ranges(10, 6, 2), split_ranges(0, 1, 2)
    ([(0, 5), (5, 10)], [(0, 10)], [(0, 0)])
    """
    parts = parts or thread_count()
    if getattr(_IN_WORKER, "active", False):
        parts = 1
    parts = max(1, min(parts, count // max(1, min_size)))
    edges = [count * i // parts for i in range(parts + 1)]
    return list(zip(edges[:-1], edges[1:]))


#: Smallest share of a split image kernel per thread, in pixels (smaller images run on one thread: a hand-off
#: costs ~0.1 ms)
MIN_PIXELS_PER_THREAD = 1 << 16


def split_rows(height: int, width: int) -> list[tuple[int, int]]:
    """``split_ranges`` of an image's rows for a per-pixel kernel: at least ``MIN_PIXELS_PER_THREAD`` pixels
    a thread."""
    return split_ranges(height, -(-MIN_PIXELS_PER_THREAD // max(1, width)))


#: Smallest share of a split per-point kernel (one over a list of moving pixels) per thread
MIN_POINTS_PER_THREAD = 1 << 14


def split_points(count: int) -> list[tuple[int, int]]:
    """``split_ranges`` of ``count`` points for a kernel whose points are independent (each writes its own
    rows): at least ``MIN_POINTS_PER_THREAD`` points a thread, so the split gives the same bits as one range."""
    return split_ranges(count, MIN_POINTS_PER_THREAD)


def run_ranges(fn: Callable[[int, int], object], ranges: list[tuple[int, int]]) -> list:
    """[fn(start, stop) for each range], the first on the calling thread and the others on a shared pool
    (the kernels release the GIL, so they run in parallel); results in range order."""
    if len(ranges) == 1:
        return [fn(*ranges[0])]
    pool = _pool(len(ranges) - 1)
    futures = [pool.submit(fn, *r) for r in ranges[1:]]
    first = fn(*ranges[0])
    return [first] + [f.result() for f in futures]


def _pool(workers: int) -> ThreadPoolExecutor:
    """The shared pool of ``workers`` kernel threads (made on first use)."""
    pool = _POOL.get(workers)
    if pool is None:
        pool = _POOL[workers] = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="interleave-kernel",
                                                   initializer=_mark_worker)
    return pool


def run_beside(fn: Callable[[], T]) -> Callable[[], T]:
    """Start ``fn()`` on a thread of the kernel pool that ``run_ranges`` uses with all ``thread_count()`` threads,
    while the calling thread goes on with other work (a serial step that would leave the other cores idle):
    returns a function that waits for ``fn``'s result and returns it (raising its error). ``fn`` runs its own
    split kernels as one range there, in order after what was started before it, and must not read what the
    calling thread writes meanwhile (then the results do not depend on the timing). With one kernel thread, or
    from a worker, ``fn`` runs at once on the calling thread."""
    workers = thread_count() - 1
    if workers < 1 or getattr(_IN_WORKER, "active", False):
        result = fn()
        return lambda: result
    return _pool(workers).submit(fn).result


@njit(cache=True, nogil=True)
def fill_zeros(out):
    """``out`` (1-D, contiguous) set to 0, without the GIL (a memset that ``run_beside`` can run)."""
    out[:] = 0


def _mark_worker() -> None:
    _IN_WORKER.active = True


@njit(cache=True, nogil=True)
def encode8(linear, level, step, buckets, out):
    """``out`` (H, W, C) uint8 = the 8-bit display encoding of ``linear`` (H, W, C) float32: per value,
    clipped to [0, 1], ``level[b] + (c >= step[b])`` in its bucket b = floor(c * buckets); NaN -> 0."""
    h, w, channels = linear.shape
    for y in range(h):
        for x in range(w):
            for ch in range(channels):
                c = linear[y, x, ch]
                if not c > 0.0:  # also NaN
                    out[y, x, ch] = level[0]
                    continue
                if c > 1.0:
                    c = _F32(1.0)
                b = int(c * _F32(buckets))
                out[y, x, ch] = level[b] + 1 if c >= step[b] else level[b]


@njit(cache=True, nogil=True)
def srgb_encode(linear, out):
    """``out`` (H, W, C) float32 = ``engine.core.colorspace.display_encode(linear)`` of ``linear`` (H, W, C)
    float32: clipped to [0, 1], then ``12.92 c`` (c <= 0.0031308) or ``1.055 c^(1/2.4) - 0.055`` in float64,
    rounded to float32; NaN stays NaN."""
    h, w, channels = linear.shape
    for y in range(h):
        for x in range(w):
            for ch in range(channels):
                v = linear[y, x, ch]
                if v != v:
                    out[y, x, ch] = _F32(np.nan)
                    continue
                c = np.float64(min(max(v, _F32(0.0)), _F32(1.0)))
                if c <= 0.0031308:
                    out[y, x, ch] = _F32(c * SRGB_LINEAR_SLOPE)
                else:
                    out[y, x, ch] = _F32(1.055 * c ** (1.0 / 2.4) - 0.055)


@njit(cache=True, nogil=True)
def srgb_decode(encoded, out):
    """``out`` (H, W, C) float32 = ``engine.core.colorspace.srgb_to_linear(encoded)`` of ``encoded`` (H, W, C)
    float32: ``c / 12.92`` (c <= 0.04045) or ``((c + 0.055) / 1.055)^2.4`` in float64, rounded to float32; NaN
    stays NaN."""
    h, w, channels = encoded.shape
    for y in range(h):
        for x in range(w):
            for ch in range(channels):
                c = np.float64(encoded[y, x, ch])
                if c != c:
                    out[y, x, ch] = _F32(np.nan)
                elif c <= 0.04045:
                    out[y, x, ch] = _F32(c / SRGB_LINEAR_SLOPE)
                else:
                    out[y, x, ch] = _F32(((c + 0.055) / 1.055) ** 2.4)


@njit(cache=True, nogil=True)
def lookup(codes, table, out):
    """``out`` (H, W, C) = ``table[codes]`` for uint8 ``codes`` (H, W, C) and a (256,) ``table``."""
    h, w, channels = codes.shape
    for y in range(h):
        for x in range(w):
            for ch in range(channels):
                out[y, x, ch] = table[codes[y, x, ch]]


@njit(cache=True, nogil=True)
def _plane_of(inv_depth, half_inv):
    """Index of the plane nearest in inverse depth: the number of mid-points ``inv_depth`` is <= to."""
    index = 0
    for k in range(half_inv.shape[0]):
        if inv_depth <= half_inv[k]:
            index += 1
    return index


@njit(cache=True, nogil=True)
def _pixel_point(u, v, d):
    """Homogeneous pixel point (d u, d v, d, 1) of pixel (u, v) at depth d; sky (+inf) -> (u, v, 1, 0)."""
    if math.isinf(d):
        return u, v, _F32(1.0), _F32(0.0)
    return u * d, v * d, d, _F32(1.0)


@njit(cache=True, nogil=True, inline="always")
def _landing(u, v, d, m, x_max, y_max, snap_scale, snap, max_coord_inv, tiny):
    """Pass 1's arithmetic for one point: pixel (``u``, ``v``) at depth ``d`` (after its flow) reprojected by
    ``m`` (``_matrix_entries``): (in front of the camera, padded tap x0, y0, bilinear fractions fx, fy, depth z).
    Scalars only (an array argument costs a reference count per point)."""
    one, half, zero = _F32(1.0), _F32(0.5), _F32(0.0)
    px, py, pz, pw = _pixel_point(u, v, d)
    hu = m[0] * px + m[1] * py + m[2] * pz + m[3] * pw
    hv = m[4] * px + m[5] * py + m[6] * pz + m[7] * pw
    hz = m[8] * px + m[9] * py + m[10] * pz + m[11] * pw
    valid = hz > (abs(hu) + abs(hv)) * max_coord_inv + tiny
    if valid:
        uo = hu / hz
        vo = hv / hz
        zo = hz / pw if pw > zero else _F32(np.inf)
    else:
        uo = zero
        vo = zero
        zo = zero
    xc = min(max(uo - half, _F32(-2.0)), x_max)  # the clip of _bilinear_fraction
    yc = min(max(vo - half, _F32(-2.0)), y_max)
    left = math.floor(xc)
    top = math.floor(yc)
    fx = min(max((xc - _F32(left) - snap) * snap_scale, zero), one)
    fy = min(max((yc - _F32(top) - snap) * snap_scale, zero), one)
    return valid, int(left) + 1, int(top) + 1, fx, fy, zo


@njit(cache=True, nogil=True)
def project_points(depth, alpha, flow, has_flow, m, half_inv, ho, wo, snap_scale, snap, max_coord_inv,
                   tiny, row_start, row_stop, base_out, fx_out, fy_out, z_out, a_out, log_out):
    """Pass 1: per source point (Z * H * W, plane-major) of rows [``row_start``, ``row_stop``) its top-left
    tap ``base_out`` in the padded (Z, ho + 2, wo + 2) volume, bilinear fractions, destination depth and
    alpha (0 when dropped). Calls on disjoint row ranges write disjoint points (threads may share the arrays).

    ``log_out`` gets log(1 + z) (float64) of the landing finite points (the splat's soft z-buffer reads it).
    Returns (min, max) of it over them ((inf, 0) when none lands).
    """
    num_z, h, w = alpha.shape
    hp, wp = ho + 2, wo + 2
    one, half, zero = _F32(1.0), _F32(0.5), _F32(0.0)
    entries = _matrix_entries(m)
    x_max, y_max = _F32(wo + 1), _F32(ho + 1)
    lo, hi = np.inf, 0.0
    for z_index in range(num_z):
        for y in range(row_start, row_stop):
            for x in range(w):
                i = (z_index * h + y) * w + x
                a = alpha[z_index, y, x]
                base_out[i] = 0
                a_out[i] = zero
                fx_out[i] = zero
                fy_out[i] = zero
                z_out[i] = zero
                if num_z > 1 and a == zero:  # empty MPI entries are never read again
                    continue
                u = _F32(x) + half
                v = _F32(y) + half
                d = depth[z_index, y, x]
                if has_flow:
                    u += flow[0, z_index, y, x]
                    v += flow[1, z_index, y, x]
                    d += flow[2, z_index, y, x]
                valid, x0, y0, fx, fy, zo = _landing(u, v, d, entries, x_max, y_max, snap_scale, snap,
                                                     max_coord_inv, tiny)
                fx_out[i] = fx
                fy_out[i] = fy
                z_out[i] = zo
                if not (valid and 0 <= x0 <= wo and 0 <= y0 <= ho):
                    continue
                a_out[i] = a
                plane = _plane_of(one / (zo if valid else one), half_inv)
                base_out[i] = (plane * hp + y0) * wp + x0
                if a > zero and not math.isinf(zo):
                    log_z = math.log1p(np.float64(zo))
                    log_out[i] = log_z
                    lo = min(lo, log_z)
                    hi = max(hi, log_z)
    return lo, hi


@njit(cache=True, nogil=True, inline="always")
def _matrix_entries(m):
    """The top three rows of the 4x4 ``m`` as a tuple of 12 scalars (held in registers by the loops)."""
    return (m[0, 0], m[0, 1], m[0, 2], m[0, 3], m[1, 0], m[1, 1], m[1, 2], m[1, 3], m[2, 0], m[2, 1], m[2, 2],
            m[2, 3])


@njit(cache=True, nogil=True)
def project_moved_frame(depth, velocity, moving, acceleration, has_acceleration, k, k_inv, step, m, snap_scale, snap,
                        max_coord_inv, tiny, row_start, row_stop, base_out, fx_out, fy_out, z_out, a_out, log_out):
    """``project_points`` of a one-plane frame (``depth`` (H, W), alpha 1, output the frame's size) whose
    ``moving`` pixels (flat indices, increasing) move by ``extrapolate_points``' flow, computed here as each is
    reached: the same bits as ``extrapolate_points`` into a zero buffer, then ``project_points`` of it, without
    the buffer (nothing to write, read or clear again). Returns (min, max) of log(1 + z) as ``project_points``
    does, and the rows of ``moving`` these rows walked, [first, stop): calls on consecutive row ranges walk
    consecutive rows, from 0 to len(moving), exactly when ``moving`` increases and lies in the frame."""
    h, w = depth.shape
    wp = w + 2
    one, half, zero = _F32(1.0), _F32(0.5), _F32(0.0)
    entries = _matrix_entries(m)
    kk, ki = _camera_entries(k, k_inv)
    x_max, y_max = _F32(w + 1), _F32(h + 1)
    scale = 0.5 * step * (step + 1.0)
    first = np.searchsorted(moving, row_start * w)  # the first moving pixel of these rows
    p = first
    lo, hi = np.inf, 0.0
    for y in range(row_start, row_stop):
        for x in range(w):
            i = y * w + x
            u = _F32(x) + half
            v = _F32(y) + half
            d = depth[y, x]
            if p < moving.shape[0] and moving[p] == i:
                vel = (velocity[y, x, 0], velocity[y, x, 1], velocity[y, x, 2])
                acc = (acceleration[p, 0], acceleration[p, 1], acceleration[p, 2]) if has_acceleration else vel
                du, dv, dz = _moved_flow(x, y, np.float64(d), vel, acc, has_acceleration, kk, ki, step, scale)
                u += du
                v += dv
                d += dz
                p += 1
            valid, x0, y0, fx, fy, zo = _landing(u, v, d, entries, x_max, y_max, snap_scale, snap, max_coord_inv,
                                                 tiny)
            fx_out[i] = fx
            fy_out[i] = fy
            z_out[i] = zo
            base_out[i] = 0
            a_out[i] = zero
            if not (valid and 0 <= x0 <= w and 0 <= y0 <= h):
                continue
            a_out[i] = one
            base_out[i] = y0 * wp + x0  # the one plane
            if not math.isinf(zo):
                log_z = math.log1p(np.float64(zo))
                log_out[i] = log_z
                lo = min(lo, log_z)
                hi = max(hi, log_z)
    return lo, hi, first, p


@njit(cache=True, nogil=True)
def splat_points(flat_color, base, fx, fy, zs, a, log_z1, lo, hi, sharpness, row, min_log_weight, sky_weight,
                 start, stop, sums):
    """Pass 2: splat [coverage, weight, weight * (r, g, b, z)] of the landing points (``a`` > 0) among points
    [``start``, ``stop``) into the padded volume ``sums`` (N, 6), zeroed first (``flat_color`` (3, points),
    the other per-point arrays from pass 1). Threads splat disjoint point ranges into their own ``sums``."""
    sums[:] = 0.0
    scale = -sharpness / max(hi, 1e-30)
    for i in range(start, stop):
        ai = a[i]
        if ai == 0.0:
            continue
        z = zs[i]
        sky = math.isinf(z)
        if sky:
            zbuf = sky_weight
            zval = 0.0
        else:
            log_z = log_z1[i]
            if lo != np.inf:
                log_z -= lo
            zbuf = math.exp(min(max(log_z * scale, min_log_weight), 0.0))
            zval = np.float64(z)
        r = np.float64(flat_color[0, i])
        g = np.float64(flat_color[1, i])
        b = np.float64(flat_color[2, i])
        gx = np.float32(1.0) - fx[i]
        gy = np.float32(1.0) - fy[i]
        b0 = base[i]
        for tap in range(4):
            if tap == 0:
                t, wx, wy = b0, gx, gy
            elif tap == 1:
                t, wx, wy = b0 + 1, fx[i], gy
            elif tap == 2:
                t, wx, wy = b0 + row, gx, fy[i]
            else:
                t, wx, wy = b0 + row + 1, fx[i], fy[i]
            cover = np.float64(wx) * np.float64(wy) * np.float64(ai)
            weight = cover * zbuf
            sums[t, 0] += cover
            sums[t, 1] += weight
            sums[t, 2] += weight * r
            sums[t, 3] += weight * g
            sums[t, 4] += weight * b
            sums[t, 5] += weight * zval


@njit(cache=True, nogil=True, inline="always")
def _bin_sums(sums, t):
    """The six splat sums (coverage, weight, weight x (r, g, b, z)) of padded bin ``t``, the threads' parts
    ``sums`` (P, N, 6) added in part order."""
    cov, wsum, r, g, b, d = sums[0, t, 0], sums[0, t, 1], sums[0, t, 2], sums[0, t, 3], sums[0, t, 4], sums[0, t, 5]
    for p in range(1, sums.shape[0]):
        cov += sums[p, t, 0]
        wsum += sums[p, t, 1]
        r += sums[p, t, 2]
        g += sums[p, t, 3]
        b += sums[p, t, 4]
        d += sums[p, t, 5]
    return cov, wsum, r, g, b, d


@njit(cache=True, nogil=True)
def normalize(sums, num_z, ho, wo, coverage_threshold, sky_only_weight, row_start, row_stop, out_color, out_depth,
              out_alpha, out_cov):
    """Add up the splat's partial sums (P, N, 6) (one per thread, in order), crop the padding and divide by
    the weight, for output rows [``row_start``, ``row_stop``): colour, depth (+inf where only sky landed),
    alpha (coverage > threshold) and coverage, each (.., Z, ho, wo) float32; 0 where not covered."""
    hp, wp = ho + 2, wo + 2
    for z in range(num_z):
        for y in range(row_start, row_stop):
            for x in range(wo):
                t = (z * hp + y + 1) * wp + x + 1
                cov, wsum, r, g, b, d = _bin_sums(sums, t)
                covered = cov > coverage_threshold
                inv_w = 1.0 / wsum if covered and wsum > 0.0 else 0.0
                out_color[0, z, y, x] = r * inv_w
                out_color[1, z, y, x] = g * inv_w
                out_color[2, z, y, x] = b * inv_w
                out_depth[z, y, x] = np.inf if covered and wsum < sky_only_weight else d * inv_w
                out_alpha[z, y, x] = 1.0 if covered else 0.0
                out_cov[z, y, x] = cov


@njit(cache=True, nogil=True)
def normalize_frame(sums, ho, wo, coverage_threshold, sky_only_weight, row_start, row_stop, out_color, out_depth,
                    out_holes):
    """``normalize`` and ``composite`` of a one-plane warp in one pass, for output rows [``row_start``,
    ``row_stop``): colour (ho, wo, 3), depth (ho, wo) (+inf where only sky landed or nothing is covered) and
    holes (ho, wo) (not covered), bit for bit the composite of ``normalize``'s one-plane MPI: a covered pixel's
    float32 colour plus +0 (the "over" sum starts at +0: -0 becomes +0) and its depth; 0 and +inf elsewhere."""
    wp = wo + 2
    zero = _F32(0.0)
    for y in range(row_start, row_stop):
        for x in range(wo):
            t = (y + 1) * wp + x + 1
            cov, wsum, r, g, b, d = _bin_sums(sums, t)
            if not cov > coverage_threshold:
                out_color[y, x, 0] = zero
                out_color[y, x, 1] = zero
                out_color[y, x, 2] = zero
                out_depth[y, x] = np.inf
                out_holes[y, x] = True
                continue
            inv_w = 1.0 / wsum if wsum > 0.0 else 0.0
            out_color[y, x, 0] = zero + _F32(r * inv_w)
            out_color[y, x, 1] = zero + _F32(g * inv_w)
            out_color[y, x, 2] = zero + _F32(b * inv_w)
            out_depth[y, x] = np.inf if wsum < sky_only_weight else _F32(d * inv_w)
            out_holes[y, x] = False


@njit(cache=True, nogil=True, inline="always")
def _farther_side(depth, y, left, right):
    """The column a hole on row ``y`` copies: of its nearest known pixels ``left`` and ``right`` (-1: none), the
    one with the larger ``depth`` (ties and NaN: the left one); -1 when neither exists."""
    depth_left = depth[y, left] if left >= 0 else -np.inf
    depth_right = depth[y, right] if right >= 0 else -np.inf
    return right if depth_right > depth_left else left


@njit(cache=True, nogil=True)
def row_sources(depth, holes, out):
    """``engine.geometry.holefill._row_sources_reference`` compiled: ``out`` (H, W) int64 = per hole pixel the column
    of the farther (larger ``depth``; ties: the left one) of its nearest known left / right pixels on its
    row, -1 for known pixels and rows without a known pixel."""
    h, w = holes.shape
    for y in range(h):
        last = -1
        for x in range(w):  # left neighbours, kept in ``out`` until the right pass
            if holes[y, x]:
                out[y, x] = last
            else:
                last = x
                out[y, x] = -1
        after = -1
        for x in range(w - 1, -1, -1):
            if not holes[y, x]:
                after = x
                continue
            out[y, x] = _farther_side(depth, y, out[y, x], after)


@njit(cache=True, nogil=True)
def fill_rows(color, depth, holes, row_start, row_stop, out_color, out_depth, out_unfilled):
    """Rows ``row_start`` .. ``row_stop`` - 1 of the row pass of ``engine.geometry.holefill.fill_holes``: each hole
    pixel of ``holes`` (H, W) copies ``color`` (H, W, C) and ``depth`` (H, W) from the column ``row_sources``
    picks (the farther of its nearest known left / right pixels; ties: the left one), each known pixel copies
    itself, into ``out_color`` / ``out_depth``. A hole that finds no source (a row without a known pixel, or a
    NaN depth beside it) is left for ``fill_columns`` and set in ``out_unfilled`` (H, W) (only such pixels are
    written: the caller passes zeros). Returns how many there were."""
    w = holes.shape[1]
    channels = color.shape[2]
    left_of = np.empty(w, np.int64)
    unfilled = 0
    for y in range(row_start, row_stop):
        last = -1
        for x in range(w):
            if holes[y, x]:
                left_of[x] = last
            else:
                last = x
        after = -1
        for x in range(w - 1, -1, -1):
            source = x
            if holes[y, x]:
                source = _farther_side(depth, y, left_of[x], after)
                if source < 0:
                    unfilled += 1
                    out_unfilled[y, x] = True
                    continue
            else:
                after = x
            out_depth[y, x] = depth[y, source]
            for ch in range(channels):
                out_color[y, x, ch] = color[y, source, ch]
    return unfilled


@njit(cache=True, nogil=True)
def fill_columns(color, depth, remaining, rows, col_start, col_stop, fallback, has_fallback):
    """The column pass of ``engine.geometry.holefill.fill_holes`` for columns [``col_start``, ``col_stop``), in
    place on the row-filled ``color`` (H, W, C) / ``depth`` (H, W) that ``fill_rows`` wrote: each ``remaining``
    pixel (a hole its row could not fill; ``rows``: the sorted rows holding one) copies the farther (larger
    depth; ties and NaN: the upper one) of its nearest pixels above and below that are not remaining
    (``_farther_side`` along the column); where neither exists, ``fallback`` (H, W, C) (0 without
    ``has_fallback``) and depth +inf. Only the remaining rows are visited (a row next to them that holds no
    remaining pixel is the nearest one there); only remaining pixels are written and only others read, so
    column ranges are independent (threads may share the arrays)."""
    h = remaining.shape[0]
    n = rows.shape[0]
    width = col_stop - col_start
    channels = color.shape[2]
    above = np.empty((n, width), np.int64)
    near = np.empty(width, np.int64)
    for i in range(n):  # top down: the nearest row above that is not remaining, per column
        y = rows[i]
        clean_above = i == 0 or rows[i - 1] != y - 1
        for j in range(width):
            if clean_above or not remaining[y - 1, col_start + j]:
                near[j] = y - 1
            above[i, j] = near[j]
    for i in range(n - 1, -1, -1):  # bottom up: the nearest below, the choice and the copies
        y = rows[i]
        clean_below = i == n - 1 or rows[i + 1] != y + 1
        for j in range(width):
            x = col_start + j
            if clean_below or not remaining[y + 1, x]:
                near[j] = y + 1 if y + 1 < h else -1
            if not remaining[y, x]:
                continue
            up, down = above[i, j], near[j]
            depth_up = depth[up, x] if up >= 0 else -np.inf
            depth_down = depth[down, x] if down >= 0 else -np.inf
            source = down if depth_down > depth_up else up
            if source < 0:
                for ch in range(channels):
                    color[y, x, ch] = fallback[y, x, ch] if has_fallback else _F32(0.0)
                depth[y, x] = np.inf
                continue
            depth[y, x] = depth[source, x]
            for ch in range(channels):
                color[y, x, ch] = color[source, x, ch]


@njit(cache=True, nogil=True)
def seen_pixels(depth, m, max_coord_inv, tiny, h_prev, w_prev, row0, out):
    """``out`` (h, W) bool: each pixel of ``depth`` (h, W), rows ``row0`` .. ``row0 + h - 1`` of a frame,
    reprojected by the float32 4x4 ``m`` (pixel points to the other view's pixel points, ``camera.reprojection_matrix``)
    lands in front of that camera and inside its [0, ``w_prev``) x [0, ``h_prev``) image
    (``camera.seen_before``; the arithmetic of ``project_points``)."""
    h, w = depth.shape
    half, zero = _F32(0.5), _F32(0.0)
    m00, m01, m02, m03 = m[0, 0], m[0, 1], m[0, 2], m[0, 3]
    m10, m11, m12, m13 = m[1, 0], m[1, 1], m[1, 2], m[1, 3]
    m20, m21, m22, m23 = m[2, 0], m[2, 1], m[2, 2], m[2, 3]
    x_max, y_max = _F32(w_prev), _F32(h_prev)
    for y in range(h):
        v = _F32(y + row0) + half
        for x in range(w):
            u = _F32(x) + half
            d = depth[y, x]
            px, py, pz, pw = _pixel_point(u, v, d)
            hu = m00 * px + m01 * py + m02 * pz + m03 * pw
            hv = m10 * px + m11 * py + m12 * pz + m13 * pw
            hz = m20 * px + m21 * py + m22 * pz + m23 * pw
            inside = False
            if hz > (abs(hu) + abs(hv)) * max_coord_inv + tiny:
                uo = hu / hz
                vo = hv / hz
                inside = zero <= uo < x_max and zero <= vo < y_max
            out[y, x] = inside


@njit(cache=True, nogil=True)
def zero_untrusted(flow, seen, confident, small, row_start, row_stop):
    """Rows ``row_start`` .. ``row_stop`` - 1 of ``flow`` (H, W, 2) float32 set to 0 where the trust rules of
    ``engine.predict.dis.trusted_motion`` drop the motion: not ``seen`` (H, W) bool, or a magnitude under
    ``small`` pixels that is not ``confident`` (H, W) bool. The magnitude is float32 ``hypot`` (the float64 root
    of the float64 sum of squares, rounded once: numpy's ``np.hypot`` on float32, to the bit)."""
    for y in range(row_start, row_stop):
        for x in range(flow.shape[1]):
            u, v = np.float64(flow[y, x, 0]), np.float64(flow[y, x, 1])
            magnitude = _F32(math.sqrt(u * u + v * v))
            if not seen[y, x] or (magnitude < small and not confident[y, x]):
                flow[y, x, 0] = _F32(0.0)
                flow[y, x, 1] = _F32(0.0)


@njit(cache=True, nogil=True)
def one_hot_mpi(color, depth, half_inv, out_color, out_depth, out_alpha):
    """``engine.geometry._build_mpi_reference`` compiled: each pixel of ``color`` (H, W, 3) / ``depth`` (H, W)
    goes to the plane nearest in inverse depth (``half_inv``: the Z - 1 mid-points between the planes'
    inverse depths; sky -> the farthest plane); ``out_*`` (3, Z, H, W) / (Z, H, W) are written whole."""
    num_z = out_alpha.shape[0]
    h, w = depth.shape
    one, zero = _F32(1.0), _F32(0.0)
    for z in range(num_z):
        for y in range(h):
            for x in range(w):
                out_alpha[z, y, x] = zero
                out_depth[z, y, x] = zero
                out_color[0, z, y, x] = zero
                out_color[1, z, y, x] = zero
                out_color[2, z, y, x] = zero
    for y in range(h):
        for x in range(w):
            d = depth[y, x]
            z = _plane_of(one / d, half_inv)
            out_alpha[z, y, x] = one
            out_depth[z, y, x] = d
            out_color[0, z, y, x] = color[y, x, 0]
            out_color[1, z, y, x] = color[y, x, 1]
            out_color[2, z, y, x] = color[y, x, 2]


@njit(cache=True, nogil=True)
def composite(color, depth, alpha, out_color, out_depth, out_acc):
    """``engine.geometry._composite_reference`` compiled: front-to-back "over" of an MPI (colour (3, Z, H, W),
    depth and alpha (Z, H, W)) into colour (H, W, 3), depth (H, W) (weight-normalised over the finite
    surfaces seen; +inf where sky is seen or nothing is covered) and accumulated alpha (H, W)."""
    num_z, h, w = alpha.shape
    for y in range(h):
        for x in range(w):
            vis = _F32(1.0)
            r = g = b = acc = dsum = _F32(0.0)
            sky = False
            for z in range(num_z):
                a = alpha[z, y, x]
                weight = a * vis
                if z + 1 < num_z:
                    vis = vis * (_F32(1.0) - a)
                if not weight > 0.0:
                    continue
                r += color[0, z, y, x] * weight
                g += color[1, z, y, x] * weight
                b += color[2, z, y, x] * weight
                acc += weight
                d = depth[z, y, x]
                if math.isinf(d):
                    sky = True
                else:
                    dsum += d * weight
            out_color[y, x, 0] = r
            out_color[y, x, 1] = g
            out_color[y, x, 2] = b
            out_acc[y, x] = acc
            out_depth[y, x] = dsum / acc if acc > 0.0 and not sky else np.inf


@njit(cache=True, nogil=True)
def _linear_taps(size, small, factor):
    """OpenCV INTER_LINEAR taps of an upscale by ``factor``: per output index (past ``small * factor``: the
    last one's), the left source index, the right one (clamped) and the right weight (float32)."""
    left = np.empty(size, np.int64)
    right = np.empty(size, np.int64)
    weight = np.empty(size, np.float32)
    inv = 1.0 / factor
    for i in range(size):
        f = _F32((min(i, small * factor - 1) + 0.5) * inv - 0.5)
        s = math.floor(f)
        t = f - _F32(s)
        if s < 0:
            s, t = 0, _F32(0.0)
        if s >= small - 1:
            s, t = small - 1, _F32(0.0)
        left[i], right[i], weight[i] = s, min(s + 1, small - 1), t
    return left, right, weight


@njit(cache=True, nogil=True)
def upsample_planes(packed, factor, full_alpha, scale, out):
    """The full-resolution half of ``engine.predict.decomp.reference.upsample_flow_reference``: per plane z, ``packed``
    (Z, h, w, 4) (alpha-weighted (du, dv, dz) and alpha, already spread into empty neighbours) is sampled
    bilinearly at each full-resolution pixel with ``full_alpha`` (Z, H, W) != 0, as OpenCV's INTER_LINEAR
    resize by ``factor`` samples it (source x = (X + 0.5) / factor - 0.5, clamped at the borders; rows and
    columns past the last whole block repeat the last one), then divided by the sampled alpha (0 where it
    is <= 1e-6) and multiplied by ``scale`` (3,); ``out`` (3, Z, H, W) is written whole (0 where
    ``full_alpha`` is 0)."""
    num_z, h, w, _ = packed.shape
    big_h, big_w = full_alpha.shape[1:]
    top, bottom, v_weight = _linear_taps(big_h, h, factor)
    left, right, u_weight = _linear_taps(big_w, w, factor)
    one = _F32(1.0)
    for z in range(num_z):
        for y in range(big_h):
            sy, sy1, v = top[y], bottom[y], v_weight[y]
            for x in range(big_w):
                if full_alpha[z, y, x] == 0.0:
                    out[0, z, y, x] = out[1, z, y, x] = out[2, z, y, x] = 0.0
                    continue
                sx, sx1, u = left[x], right[x], u_weight[x]
                a = (packed[z, sy, sx, 3] * (one - u) + packed[z, sy, sx1, 3] * u) * (one - v) \
                    + (packed[z, sy1, sx, 3] * (one - u) + packed[z, sy1, sx1, 3] * u) * v
                for c in range(3):
                    value = (packed[z, sy, sx, c] * (one - u) + packed[z, sy, sx1, c] * u) * (one - v) \
                        + (packed[z, sy1, sx, c] * (one - u) + packed[z, sy1, sx1, c] * u) * v
                    out[c, z, y, x] = value / a * scale[c] if a > _F32(1e-6) else _F32(0.0)


@njit(cache=True, nogil=True)
def _marked_row(depth, vectors, v, h00, h10, h20, c0, c1, c2, e0, e1, e2, static_tolerance, relative_tolerance,
                marked):
    """``scene_velocity``'s first pass over one row (``depth`` (W,), ``vectors`` (2 W,) interleaved): ``marked[x]``
    whether pixel x moves. A function of its own over one row's one-dimensional arrays and the homography's
    entries as scalars: so it compiles to SIMD (the same loop inline in ``scene_velocity`` ran 4x slower); the
    same bits."""
    for x in range(marked.size):  # no branches: NaN and inf fail the comparisons that mark a pixel
        z = np.float64(depth[x])
        mx = np.float64(vectors[2 * x])
        my = np.float64(vectors[2 * x + 1])
        u = x + 0.5
        sz = z * (h20 * u + c2) + e2
        # |q - project(s)| <= tolerance in x and y, multiplied through by sz > 0 (no division)
        tolerance = (static_tolerance + relative_tolerance * max(abs(mx), abs(my))) * sz
        static = ((abs((u + mx) * sz - (z * (h00 * u + c0) + e0)) <= tolerance)
                  & (abs((v + my) * sz - (z * (h10 * u + c1) + e1)) <= tolerance))
        # sz > 1e-9 z: in front of the previous camera had it not moved (else no reference to measure from)
        marked[x] = (z < np.inf) & (sz > 1e-9 * z) & (mx == mx) & (my == my) & ~static


@njit(cache=True, nogil=True)
def scene_velocity(depth, vectors, prev_depth, k_inv, k_prev, k_prev_inv, rot, trans, static_tolerance,
                   relative_tolerance, band, row_start, row_stop, row_step, out, found, row_counts):
    """``engine.geometry.reference.scene_velocity_reference`` compiled, rows ``row_start``, ``row_start`` +
    ``row_step``, .. below ``row_stop``:
    ``out`` (H, W, 3) float32 = each pixel's 3D displacement (this camera's axes) from where its surface
    point was in the previous frame to where it is now, 0 where it does not move (the rows are zeroed here,
    by the thread that writes them: ``out`` may come from ``np.empty``); the moving pixels' flat indices in
    ``found`` (1-D, room for the rows' pixels), row by row in increasing order, and each row's count in
    ``row_counts[y]`` (``merge_rows`` merges the row sets of several calls). Sky, missing (NaN) vectors and pixels whose
    vector is the camera's own (within ``static_tolerance`` px plus ``relative_tolerance`` times the vector's
    largest component) do not move. Returns the number of moving pixels.

    Each row is read twice: a branch-free pass (``_marked_row``: SIMD) marks the moving pixels, with the
    camera's homography ``k_prev rot k_inv`` and ``k_prev trans`` folded per row; the second pass computes
    the velocity of the marked ones only."""
    h, w = depth.shape
    hp, wp = prev_depth.shape
    # a pixel's point, moved by the camera alone, in the previous camera: s = z (rot k_inv) (u, v, 1) + trans;
    # its projection's numerators k_prev s = z hm (u, v, 1) + e
    hm = np.zeros((3, 3))
    e = np.zeros(3)
    for r in range(3):
        e[r] = k_prev[r, 0] * trans[0] + k_prev[r, 1] * trans[1] + k_prev[r, 2] * trans[2]
        for c in range(3):
            for a in range(3):
                for b in range(3):
                    hm[r, c] += k_prev[r, a] * rot[a, b] * k_inv[b, c]
    marked = np.empty(w, np.bool_)
    moving = 0
    for y in range(row_start, row_stop, row_step):
        v = y + 0.5
        _marked_row(depth[y], vectors[y].reshape(-1), v, hm[0, 0], hm[1, 0], hm[2, 0], hm[0, 1] * v + hm[0, 2],
                    hm[1, 1] * v + hm[1, 2], hm[2, 1] * v + hm[2, 2], e[0], e[1], e[2], static_tolerance,
                    relative_tolerance, marked)
        out[y] = 0.0
        row_first = moving
        for x in range(w):
            if not marked[x]:
                continue
            z = np.float64(depth[y, x])
            u = x + 0.5
            px = z * (k_inv[0, 0] * u + k_inv[0, 1] * v + k_inv[0, 2])
            py = z * (k_inv[1, 0] * u + k_inv[1, 1] * v + k_inv[1, 2])
            pz = z * (k_inv[2, 0] * u + k_inv[2, 1] * v + k_inv[2, 2])
            sz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
            qx = u + np.float64(vectors[y, x, 0])
            qy = v + np.float64(vectors[y, x, 1])
            # depth of the point in the previous frame: the 2x2 neighbour closest to the static guess sz
            d = sz
            best = band  # the ratio max(c / sz, sz / c) of the best candidate so far
            x0 = math.floor(qx - 0.5)
            y0 = math.floor(qy - 0.5)
            for dy in range(2):
                for dx in range(2):
                    xi = x0 + dx
                    yi = y0 + dy
                    if 0 <= xi < wp and 0 <= yi < hp:
                        c = np.float64(prev_depth[yi, xi])
                        if not math.isinf(c):
                            off = c / sz
                            if off < 1.0:
                                off = sz / c
                            if off <= best:
                                best = off
                                d = c
            # previous point in the previous camera, then in this camera's axes
            ax = d * (k_prev_inv[0, 0] * qx + k_prev_inv[0, 1] * qy + k_prev_inv[0, 2]) - trans[0]
            ay = d * (k_prev_inv[1, 0] * qx + k_prev_inv[1, 1] * qy + k_prev_inv[1, 2]) - trans[1]
            az = d * (k_prev_inv[2, 0] * qx + k_prev_inv[2, 1] * qy + k_prev_inv[2, 2]) - trans[2]
            bx = rot[0, 0] * ax + rot[1, 0] * ay + rot[2, 0] * az
            by = rot[0, 1] * ax + rot[1, 1] * ay + rot[2, 1] * az
            bz = rot[0, 2] * ax + rot[1, 2] * ay + rot[2, 2] * az
            out[y, x, 0] = px - bx
            out[y, x, 1] = py - by
            out[y, x, 2] = pz - bz
            found[moving] = y * w + x
            moving += 1
        row_counts[y] = moving - row_first
    return moving


@njit(cache=True, nogil=True)
def merge_rows(found, row_counts, row_step, out):
    """The flat indices of ``scene_velocity``'s calls with ``row_start`` 0 .. ``row_step`` - 1 (``found[t]``: the
    call of row_start t, its rows in order) merged row by row into ``out`` (increasing); returns their count."""
    taken = np.zeros(row_step, np.int64)
    n = 0
    for y in range(row_counts.size):
        t = y % row_step
        for i in range(taken[t], taken[t] + row_counts[y]):
            out[n] = found[t, i]
            n += 1
        taken[t] += row_counts[y]
    return n


@njit(cache=True, nogil=True)
def velocity_change(depth, vectors, velocity, moving, k_inv, rot, trans, prev_depth, prev_velocity, interval_ratio,
                    band, limit, out):
    """``engine.geometry.reference.velocity_change_reference`` compiled: ``out`` (len(moving), 3) float32, the
    change of velocity of each moving pixel (0 where its point's previous pixel shows another surface or
    the change exceeds ``limit`` times the velocity)."""
    h, w = depth.shape
    ph, pw = prev_depth.shape
    for i in range(moving.shape[0]):
        out[i, 0] = 0.0
        out[i, 1] = 0.0
        out[i, 2] = 0.0
        y = moving[i] // w
        x = moving[i] - y * w
        qx = x + 0.5 + np.float64(vectors[y, x, 0])
        qy = y + 0.5 + np.float64(vectors[y, x, 1])
        if not (qx >= 0 and qx < pw and qy >= 0 and qy < ph):
            continue
        xi = int(qx)
        yi = int(qy)
        z = np.float64(depth[y, x])
        v0 = np.float64(velocity[y, x, 0])
        v1 = np.float64(velocity[y, x, 1])
        v2 = np.float64(velocity[y, x, 2])
        u = x + 0.5
        v = y + 0.5
        px = z * (k_inv[0, 0] * u + k_inv[0, 1] * v + k_inv[0, 2]) - v0
        py = z * (k_inv[1, 0] * u + k_inv[1, 1] * v + k_inv[1, 2]) - v1
        pz = z * (k_inv[2, 0] * u + k_inv[2, 1] * v + k_inv[2, 2]) - v2
        bz = rot[2, 0] * px + rot[2, 1] * py + rot[2, 2] * pz + trans[2]
        seen = np.float64(prev_depth[yi, xi])
        if not (bz > 0) or math.isinf(seen):
            continue
        off = seen / bz
        if off < 1.0:
            off = bz / seen
        if off > band:  # another surface: the point was not seen there
            continue
        a0 = np.float64(prev_velocity[yi, xi, 0])
        a1 = np.float64(prev_velocity[yi, xi, 1])
        a2 = np.float64(prev_velocity[yi, xi, 2])
        c0 = v0 - (a0 * rot[0, 0] + a1 * rot[1, 0] + a2 * rot[2, 0]) * interval_ratio
        c1 = v1 - (a0 * rot[0, 1] + a1 * rot[1, 1] + a2 * rot[2, 1]) * interval_ratio
        c2 = v2 - (a0 * rot[0, 2] + a1 * rot[1, 2] + a2 * rot[2, 2]) * interval_ratio
        if c0 * c0 + c1 * c1 + c2 * c2 <= limit * limit * (v0 * v0 + v1 * v1 + v2 * v2):
            out[i, 0] = c0
            out[i, 1] = c1
            out[i, 2] = c2


@njit(cache=True, nogil=True, inline="always")
def _camera_entries(k, k_inv):
    """The entries of the intrinsics ``k`` and their inverse that ``_moved_flow`` reads, as scalars."""
    return (k[0, 0], k[0, 1], k[0, 2], k[1, 1], k[1, 2]), (k_inv[0, 0], k_inv[0, 1], k_inv[0, 2], k_inv[1, 1],
                                                           k_inv[1, 2])


@njit(cache=True, nogil=True, inline="always")
def _moved_flow(x, y, z, velocity, acceleration, has_acceleration, k, k_inv, step, scale):
    """The float32 (du, dv, dz) flow of pixel (``x``, ``y``) at depth ``z`` (float64) moved ``step`` intervals
    ahead by its ``velocity`` and ``acceleration`` (3-tuples of float32), ``scale`` = step (step + 1) / 2, ``k``
    and ``k_inv`` as ``_camera_entries`` gives them: ``extrapolate_points``' formula (NaN: it reaches the
    camera plane; ``acceleration`` is not read without ``has_acceleration``). Scalars only (an array argument costs a reference count per point)."""
    u = x + 0.5
    v = y + 0.5
    px = z * (k_inv[0] * u + k_inv[1] * v + k_inv[2])
    py = z * (k_inv[3] * v + k_inv[4])
    mx = step * np.float64(velocity[0])
    my = step * np.float64(velocity[1])
    mz = step * np.float64(velocity[2])
    if has_acceleration:
        mx += scale * np.float64(acceleration[0])
        my += scale * np.float64(acceleration[1])
        mz += scale * np.float64(acceleration[2])
    nx = px + mx
    ny = py + my
    nz = z + mz
    if nz > 1e-6 * z:
        return _F32((k[0] * nx + k[1] * ny) / nz + k[2] - u), _F32(k[3] * ny / nz + k[4] - v), _F32(nz - z)
    return _F32(np.nan), _F32(np.nan), _F32(np.nan)


@njit(cache=True, nogil=True)
def extrapolate_points(depth, velocity, moving, acceleration, has_acceleration, k, k_inv, step, out):
    """``engine.geometry.reference.extrapolated_flow_reference`` compiled: writes the (du, dv, dz) flow of the
    ``moving`` pixels into ``out`` (H, W, 3) (other pixels are left as they are): P' = P + s V + s (s + 1) / 2 A,
    NaN where P' reaches the camera plane (``_moved_flow``)."""
    w = depth.shape[1]
    scale = 0.5 * step * (step + 1.0)
    kk, ki = _camera_entries(k, k_inv)
    for i in range(moving.shape[0]):
        y = moving[i] // w
        x = moving[i] - y * w
        vel = (velocity[y, x, 0], velocity[y, x, 1], velocity[y, x, 2])
        acc = (acceleration[i, 0], acceleration[i, 1], acceleration[i, 2]) if has_acceleration else vel
        out[y, x, 0], out[y, x, 1], out[y, x, 2] = _moved_flow(x, y, np.float64(depth[y, x]), vel, acc,
                                                               has_acceleration, kk, ki, step, scale)
