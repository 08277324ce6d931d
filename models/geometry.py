"""Reprojection, multi-plane images (MPI), forward splatting and compositing in torch: the reference.

Batched and differentiable where it means something (colour, alpha, flow); training uses these functions
and ``engine/geometry/ops.py`` is their numpy mirror (same names, same semantics, no batch axis), checked
against them by ``tests/geometry/test_geometry.py``. The design note is ``docs/geometry.md``.

Conventions (those of ``engine/core/frames.py``; every function below depends on them):

- Camera axes are OpenCV's: x right, y down, z forward. ``world_to_camera`` is a rigid 4x4 matrix;
  ``intrinsics`` is a 3x3 pinhole matrix whose last row is [0, 0, 1].
- Pixel (u, v) (column, row) has its centre at (u + 0.5, v + 0.5) in the coordinates ``intrinsics`` maps
  to; ``uv`` tensors hold (x, y) = (column, row) coordinates in that continuous frame.
- ``depth`` is planar (camera z), > 0, with ``+inf`` for "no surface" (sky). Sky points are points at
  infinity, homogeneous w = 0: only the rotation of a camera moves them, and nothing produces NaN.
- Images are channel-last like the engine's, with a leading batch axis: color (B, H, W, 3) linear RGB,
  depth (B, H, W), flow (B, H, W, 2 or 3). Cameras: intrinsics (B, 3, 3), world_to_camera (B, 4, 4).
- MPI tensors are (B, C, Z, H, W) (Conv3d's N, C, D, H, W; the plane axis is D): color (B, 3, Z, H, W),
  depth (B, 1, Z, H, W), alpha (B, 1, Z, H, W), plane_depths (B, Z). Planes are ordered near (0) to far
  (Z - 1), uniform in inverse depth between the frame's smallest and largest *finite* depth (no cap).
- Alpha built from a frame is one-hot: each pixel goes to the plane nearest in inverse depth (ties go to
  the farther plane); sky pixels go to the farthest plane and keep depth +inf. The MPI depth channel holds
  the true depth where alpha = 1 and 0 elsewhere.

Export: no Python loop runs over pixels (only over the Z planes), no data-dependent shapes, no matrix
inverse (closed forms), and the splat is one ``index_add`` on a flattened padded volume.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch
from torch import Tensor

from engine.core.checks import check_shape, checked_out_size, checked_sharpness
from engine.core.errors import InputError
from engine.geometry import (COVERAGE_THRESHOLD, DEFAULT_SHARPNESS, MAX_PIXEL_COORD, MIN_LOG_WEIGHT, SUBPIXEL_SNAP,
                             TINY_DEPTH)

__all__ = ["Mpi", "pixel_centers", "unproject", "relative_transform", "project", "reproject", "plane_depths",
           "build_mpi", "forward_warp_mpi", "forward_warp_frame", "composite", "disocclusion_mask",
           "visibility"]


class Mpi(NamedTuple):
    """A batch of multi-plane images, near (plane 0) to far (plane Z - 1).

    Attributes:
        color: (B, 3, Z, H, W) linear RGB, 0 where alpha = 0.
        depth: (B, 1, Z, H, W) true planar depth of the point where alpha = 1 (+inf for sky), 0 elsewhere.
        alpha: (B, 1, Z, H, W) occupancy; in {0, 1} for MPIs built or warped here.
        plane_depths: (B, Z) nominal depth of each plane, increasing (+inf for an all-sky frame).
    """

    color: Tensor
    depth: Tensor
    alpha: Tensor
    plane_depths: Tensor


# ----------------------------------------------------------------------------------------------------
# Validation (public entry points only)


def check_mpi(mpi, sizes: dict) -> Mpi:
    if not isinstance(mpi, tuple) or len(mpi) != 4:
        raise InputError(f"must be an Mpi(color, depth, alpha, plane_depths), got {type(mpi).__name__}", field="mpi")
    check_shape(mpi[0], "mpi.color", ("B", 3, "Z", "H", "W"), sizes)
    check_shape(mpi[1], "mpi.depth", ("B", 1, "Z", "H", "W"), sizes)
    check_shape(mpi[2], "mpi.alpha", ("B", 1, "Z", "H", "W"), sizes)
    check_shape(mpi[3], "mpi.plane_depths", ("B", "Z"), sizes)
    if sizes["Z"] < 1:
        raise InputError("has Z = 0 planes, need at least 1", field="mpi")
    return Mpi(*mpi)


def _check_cameras(sizes: dict, **cameras: Tensor) -> None:
    for name, value in cameras.items():
        n = 3 if name.startswith("K") else 4
        check_shape(value, name, ("B", n, n), sizes)


def _num_planes(num_planes) -> int:
    if isinstance(num_planes, bool) or not isinstance(num_planes, int) or num_planes < 1:
        raise InputError(f"must be an integer >= 1, got {num_planes!r}", field="num_planes")
    return num_planes


def _flow3(flow: Tensor, sizes: dict, name: str = "flow") -> Tensor:
    """(B, H, W, 2 or 3) flow -> (B, H, W, 3) with dz = 0 when absent."""
    check_shape(flow, name, ("B", "H", "W", "C"), sizes)
    if flow.shape[-1] == 3:
        return flow
    if flow.shape[-1] == 2:
        return torch.cat([flow, torch.zeros_like(flow[..., :1])], dim=-1)
    raise InputError(f"must have shape (B, H, W, 2) or (B, H, W, 3), got {tuple(flow.shape)}", field=name)


# ----------------------------------------------------------------------------------------------------
# Pixels, cameras, points


def pixel_centers(height: int, width: int, *, dtype: torch.dtype = torch.float32,
                  device: Optional[torch.device] = None) -> Tensor:
    """Pixel-centre coordinates, (H, W, 2): ``out[v, u] = (u + 0.5, v + 0.5)`` (x = column first).

    >>> pixel_centers(2, 3)[1, 2].tolist()
    [2.5, 1.5]
    """
    if height < 0 or width < 0:
        raise InputError(f"must be non-negative, got {height} x {width}", field="height, width")
    u = torch.arange(width, dtype=dtype, device=device) + 0.5
    v = torch.arange(height, dtype=dtype, device=device) + 0.5
    return torch.stack([u.expand(height, width), v[:, None].expand(height, width)], dim=-1)


def _per_batch(coef: Tensor, ndim: int) -> Tensor:
    """A (B,) coefficient reshaped to broadcast against a (B, ...) tensor with ``ndim`` axes."""
    return coef.reshape(coef.shape[:1] + (1,) * (ndim - 1))


def _pinhole_inverse(k: Tensor) -> Tensor:
    """Inverse of (..., 3, 3) intrinsics with last row [0, 0, 1], in closed form (exportable)."""
    a, b, c = k[..., 0, 0], k[..., 0, 1], k[..., 0, 2]
    d, e, f = k[..., 1, 0], k[..., 1, 1], k[..., 1, 2]
    det = a * e - b * d
    ia, ib, id_, ie = e / det, -b / det, -d / det, a / det
    zero, one = torch.zeros_like(a), torch.ones_like(a)
    rows = [torch.stack([ia, ib, -(ia * c + ib * f)], -1), torch.stack([id_, ie, -(id_ * c + ie * f)], -1),
            torch.stack([zero, zero, one], -1)]
    return torch.stack(rows, dim=-2)


def _block(k3: Tensor) -> Tensor:
    """The (..., 4, 4) homogeneous form [[k3, 0], [0, 1]] of (..., 3, 3) matrices."""
    out = torch.nn.functional.pad(k3, (0, 1, 0, 1))
    corner = torch.zeros_like(out)
    corner[..., 3, 3] = 1.0
    return out + corner


def _rigid_inverse(t: Tensor) -> Tensor:
    """Inverse of rigid (..., 4, 4) transforms as [R^T, -R^T t] (exact, no general inverse)."""
    rt = t[..., :3, :3].transpose(-1, -2)
    trans = -(rt @ t[..., :3, 3:])
    top = torch.cat([rt, trans], dim=-1)
    return torch.cat([top, t[..., 3:, :]], dim=-2)


def _pixel_points(u: Tensor, v: Tensor, depth: Tensor):
    """Homogeneous pixel-space points (d u, d v, d, 1); sky (+inf) -> (u, v, 1, 0). See engine twin."""
    sky = torch.isinf(depth)
    scale = torch.where(sky, torch.ones_like(depth), depth)
    return u * scale, v * scale, scale, (~sky).to(depth.dtype)


def _transform(m: Tensor, x: Tensor, y: Tensor, z: Tensor, w: Tensor):
    """Apply (B, 4, 4) matrices (last row [0, 0, 0, 1]) to (B, ...) homogeneous component tensors."""
    nd = x.dim()
    out = []
    for i in range(3):
        out.append(_per_batch(m[:, i, 0], nd) * x + _per_batch(m[:, i, 1], nd) * y
                   + _per_batch(m[:, i, 2], nd) * z + _per_batch(m[:, i, 3], nd) * w)
    return out[0], out[1], out[2], w


def _project_pixels(hu: Tensor, hv: Tensor, z: Tensor, w: Tensor):
    """(u, v, depth, valid) of homogeneous pixel-space points (hu, hv, z, w); see ``project``."""
    valid = z > (hu.abs() + hv.abs()) * (1.0 / MAX_PIXEL_COORD) + TINY_DEPTH
    one, zero = torch.ones_like(z), torch.zeros_like(z)
    z_safe = torch.where(valid, z, one)  # no division by 0 even in the branch torch.where discards
    u = torch.where(valid, hu / z_safe, zero)
    v = torch.where(valid, hv / z_safe, zero)
    finite = w > 0
    depth = torch.where(finite, z / torch.where(finite, w, one), torch.full_like(z, float("inf")))
    return u, v, torch.where(valid, depth, zero), valid


def unproject(depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Homogeneous camera points of every pixel: depth (B, ..., H, W) -> (B, ..., H, W, 4).

    ``intrinsics`` is (B, 3, 3), one per batch item. A finite depth d gives ``[d K^-1 [u+0.5, v+0.5, 1], 1]``;
    ``+inf`` (sky) gives the direction ``[K^-1 [u+0.5, v+0.5, 1], 0]`` (translations leave it in place).

    >>> k = torch.tensor([[[2.0, 0, 1], [0, 2, 1], [0, 0, 1]]])
    >>> unproject(torch.tensor([[[4.0, float("inf")]]]), k)[0, 0].tolist()
    [[-1.0, -1.0, 4.0, 1.0], [0.25, -0.25, 1.0, 0.0]]
    """
    sizes: dict = {}
    check_shape(depth, "depth", ("...", "H", "W"), sizes)
    if depth.dim() < 3:
        raise InputError(f"must have shape (B, ..., H, W), got {tuple(depth.shape)}", field="depth")
    check_shape(intrinsics, "intrinsics", (depth.shape[0], 3, 3))
    h, w = depth.shape[-2:]
    grid = pixel_centers(h, w, dtype=depth.dtype, device=depth.device)
    pixels = _pixel_points(grid[..., 0], grid[..., 1], depth)
    return torch.stack(_transform(_block(_pinhole_inverse(intrinsics)), *pixels), dim=-1)


def relative_transform(src_world_to_camera: Tensor, dst_world_to_camera: Tensor) -> Tensor:
    """``T_dst @ inv(T_src)`` (exact rigid inverse), (..., 4, 4): source-camera to destination-camera points."""
    check_shape(src_world_to_camera, "src_world_to_camera", ("...", 4, 4))
    check_shape(dst_world_to_camera, "dst_world_to_camera", ("...", 4, 4))
    return dst_world_to_camera @ _rigid_inverse(src_world_to_camera)


def project(points_h: Tensor, intrinsics: Tensor) -> tuple[Tensor, Tensor, Tensor]:
    """Project homogeneous camera points (B, ..., 4) (w = 1 finite, w = 0 at infinity) with (B, 3, 3) intrinsics.

    Returns ``(uv (B, ..., 2), z (B, ...), valid (B, ...))``: continuous pixel coordinates (pixel centres at
    +0.5), camera depth z / w (+inf at infinity) and ``valid``: in front of the camera by a margin relative
    to the point's scale, ``z > (|z u| + |z v|) / MAX_PIXEL_COORD + TINY_DEPTH``. Points behind, on or
    grazing the camera plane are invalid and get uv = 0 and z = 0 (their gradients are 0, never NaN).
    """
    check_shape(points_h, "points_h", ("...", 4))
    if points_h.dim() < 2:
        raise InputError(f"must have shape (B, ..., 4), got {tuple(points_h.shape)}", field="points_h")
    check_shape(intrinsics, "intrinsics", (points_h.shape[0], 3, 3))
    p = points_h.unbind(-1)
    u, v, z, valid = _project_pixels(*_transform(_block(intrinsics), *p))
    return torch.stack([u, v], dim=-1), z, valid


def _reprojection_matrix(k_src: Tensor, t_src: Tensor, k_dst: Tensor, t_dst: Tensor, dtype) -> Tensor:
    """[[K_dst, 0], [0, 1]] T_dst T_src^-1 [[K_src^-1, 0], [0, 1]], composed in float64 (like the mirror)."""
    k_src, t_src, k_dst, t_dst = (m.to(torch.float64) for m in (k_src, t_src, k_dst, t_dst))
    m = _block(k_dst) @ t_dst @ _rigid_inverse(t_src) @ _block(_pinhole_inverse(k_src))
    return m.to(dtype)


def _reproject_points(u: Tensor, v: Tensor, depth: Tensor, matrix: Tensor):
    """Source pixel coordinates + depth -> destination (u, v, z, valid): Eq. 6.2 as one 4x4 matrix."""
    return _project_pixels(*_transform(matrix, *_pixel_points(u, v, depth)))


def reproject(depth: Tensor, K_src: Tensor, T_src: Tensor, K_dst: Tensor, T_dst: Tensor,
              flow: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
    """Where each source pixel lands in the destination view (thesis Eq. 6.2).

    ``X = (d + dz) K_src^-1 [u + 0.5 + du, v + 0.5 + dv, 1]``, then ``T_dst T_src^-1``, then ``K_dst``.

    Args:
        depth: (B, H, W) planar source depth, +inf for sky (sky ignores dz and moves with rotation only).
        K_src, T_src, K_dst, T_dst: (B, 3, 3) intrinsics and (B, 4, 4) world-to-camera of both views.
        flow: optional (B, H, W, 3) 3D object flow in the source view, (du, dv) pixels and dz scene units;
            (B, H, W, 2) means dz = 0.

    Returns:
        uv (B, H, W, 2), z (B, H, W), valid (B, H, W) (uv = z = 0 where not valid).
    """
    sizes: dict = {}
    check_shape(depth, "depth", ("B", "H", "W"), sizes)
    _check_cameras(sizes, K_src=K_src, T_src=T_src, K_dst=K_dst, T_dst=T_dst)
    h, w = depth.shape[1:]
    grid = pixel_centers(h, w, dtype=depth.dtype, device=depth.device)
    u, v, d = grid[..., 0], grid[..., 1], depth
    if flow is not None:
        flow = _flow3(flow, sizes)
        u, v, d = u + flow[..., 0], v + flow[..., 1], d + flow[..., 2]
    u, v = u.expand_as(depth), v.expand_as(depth)
    matrix = _reprojection_matrix(K_src, T_src, K_dst, T_dst, depth.dtype)
    uo, vo, z, valid = _reproject_points(u, v, d, matrix)
    return torch.stack([uo, vo], dim=-1), z, valid


# ----------------------------------------------------------------------------------------------------
# MPI


def _plane_depths(depth: Tensor, num_planes: int) -> Tensor:
    d = depth.detach().flatten(1).to(torch.float64)
    finite = torch.isfinite(d)
    inf = torch.tensor(float("inf"), dtype=torch.float64, device=d.device)
    near = torch.where(finite, d, inf).amin(dim=1, keepdim=True) if d.shape[1] else inf.expand(d.shape[0], 1)
    far = torch.where(finite, d, torch.zeros_like(d)).amax(dim=1, keepdim=True) if d.shape[1] else near
    if num_planes == 1:
        t = torch.full((1,), 0.5, dtype=torch.float64, device=d.device)
    else:
        t = torch.arange(num_planes, dtype=torch.float64, device=d.device) / (num_planes - 1)
    planes = 1.0 / ((1.0 - t) / near + t / far)
    if num_planes > 1:
        planes = torch.cat([near, planes[:, 1:-1], far], dim=1)
    planes = torch.where(torch.isinf(near), inf, planes)  # no finite depth: all sky
    return planes.to(depth.dtype)


def plane_depths(depth: Tensor, num_planes: int) -> Tensor:
    """Depths of ``num_planes`` MPI planes per batch item, (B, Z), near to far, uniform in inverse depth.

    The planes span the smallest and largest *finite* depth of each (H, W) frame of ``depth`` (B, H, W)
    (sky ignored, nothing capped). Z = 1 puts the plane halfway in inverse depth; a single finite depth
    value puts every plane at it; a frame with no finite depth (all sky) gives all +inf. Computed in
    float64, not differentiable.
    """
    check_shape(depth, "depth", ("B", "H", "W"))
    return _plane_depths(depth, _num_planes(num_planes))


def _nearest_plane(inv_depth: Tensor, planes: Tensor) -> Tensor:
    """Index (long) of the plane nearest in inverse depth (ties to the farther one); (B, ...) and (B, Z)."""
    inv_planes = 1.0 / planes
    mids = (inv_planes[:, :-1] + inv_planes[:, 1:]) * 0.5
    index = torch.zeros(inv_depth.shape, dtype=torch.long, device=inv_depth.device)
    for k in range(planes.shape[1] - 1):
        index = index + (inv_depth <= _per_batch(mids[:, k], inv_depth.dim())).long()
    return index


def _build_mpi(color: Tensor, depth: Tensor, num_planes: int) -> Mpi:
    planes = _plane_depths(depth, num_planes)
    index = _nearest_plane(1.0 / depth, planes)  # (B, H, W); sky: 1 / inf = 0 -> the farthest plane
    z_axis = torch.arange(num_planes, device=depth.device).reshape(1, num_planes, 1, 1)
    on = (index[:, None] == z_axis)[:, None]  # (B, 1, Z, H, W)
    alpha = on.to(color.dtype)
    mpi_color = color.permute(0, 3, 1, 2)[:, :, None] * alpha
    mpi_depth = torch.where(on, depth[:, None, None], torch.zeros_like(alpha))
    return Mpi(mpi_color, mpi_depth, alpha, planes)


def build_mpi(color: Tensor, depth: Tensor, num_planes: int) -> Mpi:
    """One-hot MPI of RGB-D frames: each pixel goes to the plane nearest in inverse depth.

    Args:
        color: (B, H, W, 3) linear RGB (gradients flow to the MPI colour).
        depth: (B, H, W) planar depth, +inf for sky (sky goes to the farthest plane with depth +inf).
        num_planes: Z >= 1; planes from ``plane_depths``.

    Returns:
        ``Mpi(color (B, 3, Z, H, W), depth (B, 1, Z, H, W), alpha (B, 1, Z, H, W) in {0, 1}, plane_depths
        (B, Z))``; colour and depth are 0 where alpha = 0, depth is the true depth where alpha = 1.
    """
    sizes: dict = {}
    check_shape(depth, "depth", ("B", "H", "W"), sizes)
    check_shape(color, "color", ("B", "H", "W", 3), sizes)
    return _build_mpi(color, depth, _num_planes(num_planes))


def alpha_visibility(alpha: Tensor) -> Tensor:
    planes = [torch.ones_like(alpha[:, :, 0])]
    for z in range(1, alpha.shape[2]):
        planes.append(planes[-1] * (1.0 - alpha[:, :, z - 1]))
    return torch.stack(planes, dim=2)


def visibility(mpi: Mpi) -> Tensor:
    """Transmittance in front of each plane (thesis Eq. 6.9), (B, 1, Z, H, W): ``prod_{j < z} (1 - alpha_j)``."""
    return alpha_visibility(check_mpi(mpi, {}).alpha)


def composite_unchecked(mpi: Mpi) -> tuple[Tensor, Tensor, Tensor]:
    weight = mpi.alpha * alpha_visibility(mpi.alpha)  # (B, 1, Z, H, W)
    color = (mpi.color * weight).sum(dim=2).permute(0, 2, 3, 1)
    acc = weight.sum(dim=2)[:, 0]
    seen = weight > 0
    sky_point = torch.isinf(mpi.depth)
    sky = (seen & sky_point).any(dim=2)[:, 0]
    depth_sum = (torch.where(seen & ~sky_point, mpi.depth, torch.zeros_like(weight)) * weight).sum(dim=2)[:, 0]
    covered = (acc > 0) & ~sky
    depth = torch.where(covered, depth_sum / torch.where(covered, acc, torch.ones_like(acc)),
                        torch.full_like(acc, float("inf")))
    return color, depth, acc


def composite(mpi: Mpi) -> tuple[Tensor, Tensor, Tensor]:
    """Render MPIs with the "over" operator (front-to-back: weight = alpha * visibility), differentiable.

    Returns:
        color (B, H, W, 3) (premultiplied over black: 0 where nothing is covered), depth (B, H, W) (the
        weight-normalised depth of the visible surfaces; +inf where sky is visible or nothing is covered),
        accumulated alpha (B, H, W). Uncovered pixels are reported by ``disocclusion_mask``.
    """
    return composite_unchecked(check_mpi(mpi, {}))


def disocclusion_mask(mpi: Mpi) -> Tensor:
    """(B, H, W) bool, True where no plane has alpha > 0 (a hole left by warping)."""
    return ~(check_mpi(mpi, {}).alpha > 0).any(dim=2)[:, 0]


# ----------------------------------------------------------------------------------------------------
# Forward warping (bilinear splatting with a soft z-buffer)


def _bilinear_fraction(x: Tensor, limit: int):
    """Left/top tap (long, padded coordinates: 1 = first pixel) and snapped fraction of the right/bottom tap."""
    x = (x - 0.5).clamp(-2.0, limit + 1.0)
    left = torch.floor(x)
    frac = ((x - left - SUBPIXEL_SNAP) * (1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP))).clamp(0.0, 1.0)
    return left.long() + 1, frac


def _soft_zbuffer_weight(z: Tensor, finite: Tensor, sharpness: float) -> Tensor:
    """exp(-sharpness log(1 + z) / max log(1 + z)) relative to the nearest point, per batch item.

    Max and min run over the ``finite`` points (finite z, alpha > 0, splatted). The log-weight is clipped to
    [MIN_LOG_WEIGHT, 0] (0 is the nearest point's), so nothing under- or overflows for any sharpness.
    """
    dims = tuple(range(1, z.dim()))
    log_z = torch.log1p(torch.where(finite, z, torch.zeros_like(z)))
    lo = torch.where(finite, log_z, torch.full_like(log_z, float("inf"))).amin(dim=dims, keepdim=True)
    lo = torch.where(torch.isinf(lo), torch.zeros_like(lo), lo)
    hi = log_z.amax(dim=dims, keepdim=True).clamp(min=1e-30)
    return torch.exp(((log_z - lo) * (-sharpness / hi)).clamp(MIN_LOG_WEIGHT, 0.0))


def _forward_warp_mpi(mpi: Mpi, k_src: Tensor, t_src: Tensor, k_dst: Tensor, t_dst: Tensor,
                      object_flow: Optional[Tensor], out_size: tuple[int, int], sharpness: float):
    """Unvalidated body of ``forward_warp_mpi``."""
    color, depth, alpha, planes = mpi
    b, _, num_z, h, w = color.shape
    ho, wo = out_size
    hp, wp = ho + 2, wo + 2
    dtype = color.dtype
    # 1. every MPI point (alpha = 0 points get zero weight), moved by the object flow
    grid = pixel_centers(h, w, dtype=dtype, device=color.device)
    u, v, d = grid[..., 0].expand(b, num_z, h, w), grid[..., 1].expand(b, num_z, h, w), depth[:, 0]
    if object_flow is not None:
        u, v, d = u + object_flow[:, 0], v + object_flow[:, 1], d + object_flow[:, 2]
    # 2. Eq. 6.2: unproject, move, project
    uo, vo, z, valid = _reproject_points(u, v, d, _reprojection_matrix(k_src, t_src, k_dst, t_dst, dtype))
    # 3. points behind the camera or outside the 1-pixel-padded destination get zero weight
    x0, fx = _bilinear_fraction(uo, wo)
    y0, fy = _bilinear_fraction(vo, ho)
    keep = valid & (x0 >= 0) & (x0 <= wo) & (y0 >= 0) & (y0 <= ho)
    point_alpha = alpha[:, 0] * keep.to(dtype)
    # 4. destination plane: nearest in inverse depth; sky (1/z = 0) goes to an extra layer Z, merged below
    sky = torch.isinf(z)
    plane = _nearest_plane(1.0 / torch.where(valid, z, torch.ones_like(z)), planes)
    plane = torch.where(sky, torch.full_like(plane, num_z), plane)
    batch = torch.arange(b, device=color.device).reshape(b, 1, 1, 1)
    base = ((batch * (num_z + 1) + plane) * hp + y0.clamp(0, ho)) * wp + x0.clamp(0, wo)
    # 5. splat [coverage, weight, weight * (r, g, b, z)] into the 4 neighbours with one index_add
    zbuf = _soft_zbuffer_weight(z, (point_alpha > 0) & ~sky, sharpness)
    gx, gy = 1.0 - fx, 1.0 - fy
    corners = torch.stack([gx * gy, fx * gy, gx * fy, fx * fy], dim=-1) * point_alpha[..., None]
    taps = torch.stack([base, base + 1, base + wp, base + wp + 1], dim=-1)
    values = torch.stack([color[:, 0], color[:, 1], color[:, 2],
                          torch.where(sky | ~valid, torch.zeros_like(z), z)], dim=-1)  # (B, Z, H, W, 4)
    cover = corners[..., None]  # (B, Z, H, W, 4 taps, 1)
    weight = cover * zbuf[..., None, None]
    source = torch.cat([cover, weight, weight * values[..., None, :]], dim=-1)  # (B, Z, H, W, 4, 6)
    volume = torch.zeros(b * (num_z + 1) * hp * wp, 6, dtype=dtype, device=color.device)
    volume = volume.index_add(0, taps.reshape(-1), source.reshape(-1, 6))
    volume = volume.reshape(b, num_z + 1, hp, wp, 6)[:, :, 1:ho + 1, 1:wo + 1].permute(0, 4, 1, 2, 3)
    # 6. normalise; the sky layer fills the far plane only where no finite point landed there
    cov, wsum, sums = volume[:, 0], volume[:, 1], volume[:, 2:]  # (B, Z+1, Ho, Wo), (B, 4, Z+1, Ho, Wo)
    one = torch.ones_like(wsum)
    mean = sums / torch.where(wsum > 0, wsum, one)[:, None]
    finite_w = wsum[:, num_z - 1:num_z]
    sky_only = (finite_w <= 0) & (wsum[:, num_z:] > 0)  # (B, 1, Ho, Wo)
    last = torch.where(sky_only[:, None], mean[:, :, num_z:], mean[:, :, num_z - 1:num_z])
    last_depth = torch.where(sky_only, torch.full_like(finite_w, float("inf")), last[:, 3])
    mean_color = torch.cat([mean[:, :3, :num_z - 1], last[:, :3]], dim=2)
    mean_depth = torch.cat([mean[:, 3, :num_z - 1], last_depth], dim=1)
    coverage = torch.cat([cov[:, :num_z - 1], cov[:, num_z - 1:num_z] + cov[:, num_z:]], dim=1)[:, None]
    covered = coverage > COVERAGE_THRESHOLD
    out_color = torch.where(covered, mean_color, torch.zeros_like(mean_color))
    out_depth = torch.where(covered, mean_depth[:, None], torch.zeros_like(coverage))
    return Mpi(out_color, out_depth, covered.to(dtype), planes), coverage


def forward_warp_mpi(mpi: Mpi, K_src: Tensor, T_src: Tensor, K_dst: Tensor, T_dst: Tensor,
                     object_flow: Optional[Tensor] = None, *, out_size: Optional[tuple[int, int]] = None,
                     sharpness: float = DEFAULT_SHARPNESS) -> tuple[Mpi, Tensor]:
    """Forward-warp MPIs to other cameras by bilinear splatting with a soft z-buffer (thesis Eq. 6.1-6.2).

    Every point moves by ``object_flow`` (in the source view), is reprojected with ``K_dst T_dst T_src^-1``,
    goes to the destination plane nearest in inverse depth (destination planes = ``mpi.plane_depths``) and is
    splatted into the 4 neighbouring pixels of that plane with inverse bilinear weights times alpha times
    the soft z-buffer weight ``exp(-sharpness log(1 + z) / max log(1 + z))`` (z in the destination; max over
    the finite points of this warp). Sky points (+inf) splat into a separate layer that counts only where
    no finite point landed on the far plane. Points behind the destination camera or outside the frame are
    dropped (a volume padded by 1 pixel, then cropped): nothing wraps around or piles up at the border.
    Differentiable w.r.t. colour, alpha (weights) and object flow (positions, soft z-buffer); the plane
    choice and the coverage threshold are discrete.

    Args:
        mpi: the source ``Mpi`` (B, ...).
        K_src, T_src, K_dst, T_dst: (B, 3, 3) intrinsics and (B, 4, 4) world-to-camera of both views.
        object_flow: optional (B, 3, Z, H, W) = (du, dv) pixels, dz scene units per MPI point (source view).
        out_size: destination (height, width); default the source size.
        sharpness: soft z-buffer sharpness >= 0 (0 = plain average).

    Returns:
        ``(warped Mpi, coverage (B, 1, Z, H, W))``: colour and depth are weighted means of what landed;
        alpha = 1 where coverage (summed bilinear weight times alpha, no z factor) > COVERAGE_THRESHOLD, and
        colour = depth = alpha = 0 elsewhere.
    """
    sizes: dict = {}
    mpi = check_mpi(mpi, sizes)
    _check_cameras(sizes, K_src=K_src, T_src=T_src, K_dst=K_dst, T_dst=T_dst)
    if object_flow is not None:
        check_shape(object_flow, "object_flow", ("B", 3, "Z", "H", "W"), sizes)
    out = checked_out_size(out_size, (sizes["H"], sizes["W"]))
    return _forward_warp_mpi(mpi, K_src, T_src, K_dst, T_dst, object_flow, out, checked_sharpness(sharpness))


def forward_warp_frame(color: Tensor, depth: Tensor, K_src: Tensor, T_src: Tensor, K_dst: Tensor, T_dst: Tensor,
                       flow: Optional[Tensor] = None,
                       sharpness: float = DEFAULT_SHARPNESS) -> tuple[Tensor, Tensor, Tensor]:
    """Forward-warp RGB-D frames: a one-plane ``build_mpi`` + ``forward_warp_mpi`` + ``composite``.

    Args:
        color: (B, H, W, 3) linear RGB; depth: (B, H, W) planar, +inf for sky.
        K_src, T_src, K_dst, T_dst: (B, 3, 3) intrinsics and (B, 4, 4) world-to-camera of both views.
        flow: optional (B, H, W, 3) (du, dv, dz) or (B, H, W, 2) (dz = 0) object flow in the source view.
        sharpness: soft z-buffer sharpness.

    Returns:
        color (B, H, W, 3), depth (B, H, W) (+inf on sky and holes), holes (B, H, W) bool (nothing landed).
    """
    sizes: dict = {}
    check_shape(depth, "depth", ("B", "H", "W"), sizes)
    check_shape(color, "color", ("B", "H", "W", 3), sizes)
    _check_cameras(sizes, K_src=K_src, T_src=T_src, K_dst=K_dst, T_dst=T_dst)
    object_flow = None if flow is None else _flow3(flow, sizes).permute(0, 3, 1, 2)[:, :, None]
    mpi = _build_mpi(color, depth, 1)
    warped, _ = _forward_warp_mpi(mpi, K_src, T_src, K_dst, T_dst, object_flow, (sizes["H"], sizes["W"]),
                                  checked_sharpness(sharpness))
    out_color, out_depth, _ = composite_unchecked(warped)
    return out_color, out_depth, warped.alpha[:, 0, 0] <= 0
