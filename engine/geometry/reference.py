"""numpy oracles of the compiled geometry (imported by tests and benchmarks only).

Each computes what its fast twin computes, in plain numpy: ``build_mpi_reference`` (``mpi.build_mpi``),
``scene_velocity_reference``, ``velocity_change_reference`` and ``extrapolated_flow_reference`` (``motion``),
``composite_reference`` (``mpi.composite``), ``forward_warp_mpi_reference``
(``splat.forward_warp_mpi_unchecked``, same arguments), ``row_sources_reference``
(``holefill.fill_sources``' row search), ``seen_before_reference`` (``camera.seen_before``). The kernels
reproduce them bit for bit (compositing to 1e-6).
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.geometry.camera import pixel_grid, reproject, reproject_points, reprojection_matrix
from engine.geometry.holefill import nearest_known
from engine.geometry.mpi import Mpi, nearest_plane, plane_depths, plane_index, visibility
from engine.geometry.splat import (COVERAGE_THRESHOLD, MIN_LOG_WEIGHT, SCRATCH, SKY_ONLY_WEIGHT, SKY_WEIGHT,
                                   SUBPIXEL_SNAP)

#: Points per chunk of the numpy warp (work arrays of 32k values stay in the L2 cache).
CHUNK = 1 << 15
#: The splat pass skips the points that do not land (alpha 0 or outside the output) when fewer than this
#: fraction land: e.g. a box-sized output of a whole frame costs in proportion to the box, not the frame.
COMPACT_BELOW = 0.94


def build_mpi_reference(color: np.ndarray, depth: np.ndarray, num_planes: int,
                         planes: Optional[np.ndarray] = None) -> Mpi:
    h, w = depth.shape
    planes = plane_depths(depth, num_planes) if planes is None else planes
    index = plane_index(depth, planes)
    alpha = np.zeros((num_planes, h, w), dtype=np.float32)
    np.put_along_axis(alpha, index[None], np.float32(1.0), axis=0)
    on = alpha > 0
    mpi_depth = np.where(on, depth[None], np.float32(0.0))
    mpi_color = np.where(on[None], np.moveaxis(color, -1, 0)[:, None], np.float32(0.0))
    return Mpi(mpi_color, mpi_depth, alpha, planes)


def composite_reference(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    weight = mpi.alpha * visibility(mpi)
    color = np.einsum("czhw,zhw->hwc", mpi.color, weight, optimize=False)
    acc = weight.sum(axis=0)
    seen = weight > 0
    sky = (seen & np.isinf(mpi.depth)).any(axis=0)
    depth_sum = (np.where(seen & ~np.isinf(mpi.depth), mpi.depth, np.float32(0.0)) * weight).sum(axis=0)
    covered = (acc > 0) & ~sky
    depth = np.where(covered, depth_sum / np.where(covered, acc, np.float32(1.0)), np.float32(np.inf))
    return color, depth.astype(np.float32, copy=False), acc


def _log_depth_range(z: np.ndarray, finite: np.ndarray, current: tuple[float, float]) -> tuple[float, float]:
    """Update (min, max) of log(1 + z) over the ``finite`` points (finite z, alpha > 0, splatted)."""
    if not finite.any():
        return current
    log_z = np.log1p(z[finite], dtype=np.float64)
    return min(current[0], float(log_z.min())), max(current[1], float(log_z.max()))


def _soft_zbuffer_weight(z: np.ndarray, sky: np.ndarray, log_range: tuple[float, float],
                         sharpness: float) -> np.ndarray:
    """exp(-sharpness * log(1 + z) / max log(1 + z)) relative to the nearest point (largest weight 1), float64.

    ``log_range`` = (min, max) of log(1 + z) over the finite points of the warp (``_log_depth_range``). The
    log-weight is clipped to [MIN_LOG_WEIGHT, 0]: finite points are >= e^MIN_LOG_WEIGHT, nothing overflows.
    Sky points get SKY_WEIGHT = e^-300, so any finite point outweighs them by > e^200 (the torch reference
    keeps sky in a separate layer instead: the results agree to ~1e-100).
    """
    lo, hi = log_range
    log_z = np.log1p(np.where(sky, np.float32(0.0), z), dtype=np.float64)
    if lo != np.inf:  # else no finite point is splatted at all
        log_z -= lo
    log_z *= -sharpness / max(hi, 1e-30)
    np.clip(log_z, MIN_LOG_WEIGHT, 0.0, out=log_z)
    weight = np.exp(log_z, out=log_z)
    weight[sky] = SKY_WEIGHT
    return weight


def _bilinear_fraction(x: np.ndarray, limit: int):
    """Integer left/top tap (padded coordinates, 1 = first pixel) and snapped fraction of the right/bottom tap."""
    x = np.clip(x - np.float32(0.5), np.float32(-2.0), np.float32(limit + 1))
    left = np.floor(x)
    frac = np.clip((x - left - np.float32(SUBPIXEL_SNAP)) * np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP)),
                   np.float32(0.0), np.float32(1.0))
    return left.astype(np.intp) + 1, frac


def _splat(sums: np.ndarray, base, row, fx, fy, point_alpha, zbuf, values) -> None:
    """Add a chunk of points to ``sums`` (2 + len(values), bins): bilinear splat with ``np.add.at``.

    ``base`` is each point's top-left tap in the flat padded volume, whose rows are ``row`` long: the taps
    are base, base + 1, base + row, base + row + 1 with weights (1-fx)(1-fy), fx(1-fy), (1-fx)fy, fx fy.
    Row 0 of ``sums`` gets the coverage (weights times ``point_alpha``), row 1 the weight (coverage times
    ``zbuf``), the others the weighted ``values``.
    """
    gx, gy = 1.0 - fx, 1.0 - fy
    for offset, wx, wy in ((0, gx, gy), (1, fx, gy), (row, gx, fy), (row + 1, fx, fy)):
        taps = base + offset
        cover = np.multiply(wx, wy, dtype=np.float64)
        cover *= point_alpha
        weight = cover * zbuf
        np.add.at(sums[0], taps, cover)
        np.add.at(sums[1], taps, weight)
        for i, value in enumerate(values):
            np.add.at(sums[2 + i], taps, weight * value)


def forward_warp_mpi_reference(mpi: Mpi, k_src, t_src, k_dst, t_dst, object_flow, out_size, sharpness):
    """numpy body of ``forward_warp_mpi``: the oracle of the compiled ``forward_warp_mpi_unchecked`` (same arguments).

    Points are processed in chunks of CHUNK so every temporary stays in cache and is recycled by the
    allocator (fresh multi-megabyte arrays cost a page fault per 4 KiB); two passes, because the soft
    z-buffer needs the depth range of the whole warp before the first splat.
    """
    color, depth, alpha, planes = mpi
    num_z, h, w = alpha.shape
    ho, wo = out_size
    hp, wp = ho + 2, wo + 2
    # the source points: every pixel of a one-plane MPI (in order, no gather), else the alpha > 0 ones
    index = None if num_z == 1 else np.flatnonzero(alpha)
    n = h * w if index is None else index.size
    gu, gv = pixel_grid(h, w)
    flat_depth, flat_alpha = depth.reshape(-1), alpha.reshape(-1)
    flat_flow = None if object_flow is None else object_flow.reshape(3, -1)
    flat_color = color.reshape(3, -1)
    matrix = reprojection_matrix(k_src, t_src, k_dst, t_dst)
    point_base = SCRATCH.get("base", n, np.intp)
    point_fx, point_fy, point_z, point_alpha = (SCRATCH.get(name, n, np.float32) for name in ("fx", "fy", "z", "a"))
    log_range = (np.inf, 0.0)
    # pass 1: reproject, pick the pixel taps and the destination plane of every point
    for start in range(0, n, CHUNK):
        part = slice(start, min(start + CHUNK, n))
        src = part if index is None else index[part]
        pixel = src if index is None else src % (h * w)
        u, v, d = gu[pixel], gv[pixel], flat_depth[src]
        if flat_flow is not None:
            u, v, d = u + flat_flow[0, src], v + flat_flow[1, src], d + flat_flow[2, src]  # sky stays +inf
        uo, vo, z, valid = reproject_points(u, v, d, matrix)
        x0, point_fx[part] = _bilinear_fraction(uo, wo)
        y0, point_fy[part] = _bilinear_fraction(vo, ho)
        keep = valid & (x0 >= 0) & (x0 <= wo) & (y0 >= 0) & (y0 <= ho)  # else dropped: weight 0
        a = point_alpha[part]
        np.multiply(flat_alpha[src], keep, out=a)
        plane = nearest_plane(np.float32(1.0) / np.where(valid, z, np.float32(1.0)), planes)  # sky: far
        base = point_base[part]
        np.multiply(plane * hp + y0, wp, out=base)
        base += x0
        base[~keep] = 0
        point_z[part] = z
        log_range = _log_depth_range(z, (a > 0) & np.isfinite(z), log_range)
    # pass 2: splat [coverage, weight, weight * (r, g, b, z)] with the soft z-buffer, only the points that
    # land (alpha > 0 inside the output): a box-sized output of a full frame splats the box's points only
    kept = np.flatnonzero(point_alpha[:n])
    compact = kept.size < COMPACT_BELOW * n
    m = kept.size if compact else n
    sums = SCRATCH.get("sums", 6 * num_z * hp * wp).reshape(6, -1)
    sums.fill(0.0)
    for start in range(0, m, CHUNK):
        part = kept[start:start + CHUNK] if compact else slice(start, min(start + CHUNK, n))
        src = part if index is None else index[part]
        z = point_z[part]
        sky = np.isinf(z)
        zbuf = _soft_zbuffer_weight(z, sky, log_range, sharpness)
        values = [flat_color[0, src], flat_color[1, src], flat_color[2, src], np.where(sky, np.float32(0.0), z)]
        _splat(sums, point_base[part], wp, point_fx[part], point_fy[part], point_alpha[part], zbuf, values)
    cov, wsum, r, g, b, dsum = (s.reshape(num_z, hp, wp)[:, 1:ho + 1, 1:wo + 1] for s in sums)
    # normalise; pixels whose weight is all sky (below any finite point's) get depth +inf
    covered = cov > COVERAGE_THRESHOLD
    inv_w = np.divide(1.0, wsum, out=np.zeros_like(wsum), where=covered & (wsum > 0))
    out_color = np.empty((3,) + covered.shape, dtype=np.float32)
    for c, channel in enumerate((r, g, b)):
        np.multiply(channel, inv_w, out=out_color[c])
    out_depth = np.empty(covered.shape, dtype=np.float32)
    np.multiply(dsum, inv_w, out=out_depth)
    out_depth[covered & (wsum < SKY_ONLY_WEIGHT)] = np.inf
    warped = Mpi(out_color, out_depth, covered.astype(np.float32), planes)
    return warped, cov.astype(np.float32)


def row_sources_reference(depth: np.ndarray, holes: np.ndarray) -> np.ndarray:
    """numpy ``holefill.row_sources``: the oracle of the compiled kernel."""
    left, right = nearest_known(~holes)
    rows = np.broadcast_to(np.arange(holes.shape[0])[:, None], holes.shape)
    depth_left = np.where(left >= 0, depth[rows, np.maximum(left, 0)], -np.inf)
    depth_right = np.where(right >= 0, depth[rows, np.maximum(right, 0)], -np.inf)
    source = np.where(depth_right > depth_left, right, left)
    return np.where(holes, source, -1)


def scene_velocity_reference(depth: np.ndarray, vectors: np.ndarray, prev_depth: np.ndarray, k_inv: np.ndarray,
                             k_prev: np.ndarray, k_prev_inv: np.ndarray, rot: np.ndarray, trans: np.ndarray,
                             static_tolerance: float, relative_tolerance: float, band: float) -> np.ndarray:
    """numpy ``kernels.scene_velocity`` (whole frame): the oracle of the compiled kernel (float64 inside)."""
    h, w = depth.shape
    v, u = np.mgrid[0:h, 0:w].astype(np.float64) + 0.5
    z = depth.astype(np.float64)
    mx, my = vectors[..., 0].astype(np.float64), vectors[..., 1].astype(np.float64)
    usable = np.isfinite(z) & ~np.isnan(mx) & ~np.isnan(my)
    zz = np.where(usable, z, 1.0)
    pix = np.stack([u, v, np.ones_like(u)], axis=-1)
    p = zz[..., None] * (pix @ k_inv.T)
    s = p @ rot.T + trans
    usable &= s[..., 2] > 1e-9 * zz
    sz = np.where(usable, s[..., 2], 1.0)
    qx, qy = u + np.where(usable, mx, 0.0), v + np.where(usable, my, 0.0)
    # |q - project(s)| <= tolerance in x and y, multiplied through by sz > 0
    tolerance = (static_tolerance + relative_tolerance * np.maximum(np.abs(mx), np.abs(my))) * sz
    nx = k_prev[0, 0] * s[..., 0] + k_prev[0, 1] * s[..., 1] + k_prev[0, 2] * sz
    ny = k_prev[1, 1] * s[..., 1] + k_prev[1, 2] * sz
    usable &= ~((np.abs(qx * sz - nx) <= tolerance) & (np.abs(qy * sz - ny) <= tolerance))
    hp, wp = prev_depth.shape
    d = sz.copy()
    best = np.full(depth.shape, float(band))
    x0, y0 = np.floor(qx - 0.5), np.floor(qy - 0.5)
    for dy in range(2):
        for dx in range(2):
            xi, yi = x0 + dx, y0 + dy
            inside = (xi >= 0) & (xi < wp) & (yi >= 0) & (yi < hp) & usable
            c = np.full(depth.shape, np.inf)
            c[inside] = prev_depth[yi[inside].astype(np.intp), xi[inside].astype(np.intp)]
            with np.errstate(divide="ignore", invalid="ignore"):
                ratio = c / sz
                off = np.where(ratio < 1.0, sz / c, ratio)
            take = inside & np.isfinite(c) & (off <= best)
            best = np.where(take, off, best)
            d = np.where(take, c, d)
    q = np.stack([qx, qy, np.ones_like(qx)], axis=-1)
    a = d[..., None] * (q @ k_prev_inv.T) - trans
    b = a @ rot
    out = np.where(usable[..., None], p - b, 0.0)
    return out.astype(np.float32)


def velocity_change_reference(depth, vectors, velocity, moving, k_inv, rot, trans, prev_depth, prev_velocity,
                              interval_ratio, band, limit) -> np.ndarray:
    """numpy ``kernels.velocity_change``: the oracle of the compiled kernel (float64 inside)."""
    h, w = depth.shape
    ph, pw = prev_depth.shape
    idx = np.asarray(moving)
    y, x = np.divmod(idx, w)
    qx = x + 0.5 + vectors[y, x, 0].astype(np.float64)
    qy = y + 0.5 + vectors[y, x, 1].astype(np.float64)
    inside = (qx >= 0) & (qx < pw) & (qy >= 0) & (qy < ph)
    xi, yi = np.where(inside, qx, 0).astype(np.intp), np.where(inside, qy, 0).astype(np.intp)
    v1 = velocity[y, x].astype(np.float64)
    z = depth[y, x].astype(np.float64)
    rays = np.stack([x + 0.5, y + 0.5, np.ones_like(z)], axis=-1) @ k_inv.T
    before_z = (rays * z[:, None] - v1) @ rot[2] + trans[2]
    seen = prev_depth[yi, xi].astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = seen / before_z
        off = np.where(ratio < 1.0, before_z / seen, ratio)
        same = inside & (before_z > 0) & np.isfinite(seen) & (off <= band)
    v0 = prev_velocity[yi, xi].astype(np.float64) @ rot * interval_ratio  # into this camera's axes
    change = v1 - v0
    smooth = same & (np.sum(change * change, axis=-1) <= limit * limit * np.sum(v1 * v1, axis=-1))
    return np.where(smooth[:, None], change, 0.0).astype(np.float32)


def extrapolated_flow_reference(depth, velocity, moving, acceleration, k, k_inv, step) -> np.ndarray:
    """numpy ``kernels.extrapolate_points`` into a zero (H, W, 3) flow: the oracle of the compiled kernel."""
    h, w = depth.shape
    idx = np.asarray(moving)
    out = np.zeros((h * w, 3), dtype=np.float32)
    y, x = np.divmod(idx, w)
    u, v = x + 0.5, y + 0.5
    z = depth.reshape(-1)[idx].astype(np.float64)
    px = z * (k_inv[0, 0] * u + k_inv[0, 1] * v + k_inv[0, 2])
    py = z * (k_inv[1, 1] * v + k_inv[1, 2])
    move = step * velocity.reshape(-1, 3)[idx].astype(np.float64)
    if acceleration is not None:
        move += (0.5 * step * (step + 1.0)) * acceleration.astype(np.float64)
    nx, ny, nz = px + move[:, 0], py + move[:, 1], z + move[:, 2]
    ok = nz > 1e-6 * z
    nz_safe = np.where(ok, nz, 1.0)
    du = (k[0, 0] * nx + k[0, 1] * ny) / nz_safe + k[0, 2] - u
    dv = k[1, 1] * ny / nz_safe + k[1, 2] - v
    flow = np.stack([du, dv, nz - z], axis=-1)
    flow[~ok] = np.nan
    out[idx] = flow
    return out.reshape(h, w, 3)


def seen_before_reference(depth_n: np.ndarray, K_n, T_n, K_prev, T_prev, size_prev: tuple[int, int]) -> np.ndarray:
    uv, _, valid = reproject(depth_n, K_n, T_n, K_prev, T_prev)
    h, w = size_prev
    return valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
