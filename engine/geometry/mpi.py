"""Multi-plane images (MPI): build (one-hot, planes uniform in inverse depth), downsample, composite.

Layouts (torch adds a leading batch axis and a channel axis of 1 to depth and alpha): color (3, Z, H, W),
depth (Z, H, W), alpha (Z, H, W), plane_depths (Z,), planes near (index 0) to far (Z - 1), uniform in
inverse depth between the frame's smallest and largest *finite* depth (no cap). Alpha built from a frame
is one-hot: each pixel goes to the plane nearest in inverse depth (ties to the farther plane); sky pixels
go to the farthest plane and keep depth +inf; the depth channel holds the true depth where alpha = 1 and 0
elsewhere. ``build_mpi`` and ``composite`` run as compiled kernels (``engine.geometry.kernels``); their
numpy oracles are in ``engine.geometry.reference``.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import cv2
import numpy as np

from engine.core.checks import checked_array, checked_matrix
from engine.core.errors import InputError
from engine.geometry import kernels


class Mpi(NamedTuple):
    """A multi-plane image, near (plane 0) to far (plane Z - 1).

    Attributes:
        color: (3, Z, H, W) float32, linear RGB, 0 where alpha = 0.
        depth: (Z, H, W) float32, true planar depth of the point where alpha = 1 (+inf for sky), 0 elsewhere.
        alpha: (Z, H, W) float32, occupancy; in {0, 1} for MPIs built or warped here.
        plane_depths: (Z,) float32, nominal depth of each plane, increasing (+inf for an all-sky frame).
    """

    color: np.ndarray
    depth: np.ndarray
    alpha: np.ndarray
    plane_depths: np.ndarray


def checked_mpi(mpi, sizes) -> Mpi:
    if not isinstance(mpi, tuple) or len(mpi) != 4:
        raise InputError(f"must be an Mpi(color, depth, alpha, plane_depths), got {type(mpi).__name__}", field="mpi")
    color = checked_array(mpi[0], "mpi.color", (3, "Z", "H", "W"), sizes)
    depth = checked_array(mpi[1], "mpi.depth", ("Z", "H", "W"), sizes)
    alpha = checked_array(mpi[2], "mpi.alpha", ("Z", "H", "W"), sizes)
    planes = checked_array(mpi[3], "mpi.plane_depths", ("Z",), sizes)
    if sizes["Z"] < 1:
        raise InputError("has Z = 0 planes, need at least 1", field="mpi")
    return Mpi(color, depth, alpha, planes)


def _num_planes(num_planes) -> int:
    if isinstance(num_planes, bool) or not isinstance(num_planes, (int, np.integer)) or num_planes < 1:
        raise InputError(f"must be an integer >= 1, got {num_planes!r}", field="num_planes")
    return int(num_planes)


def _plane_depths(depth: np.ndarray, num_planes: int) -> np.ndarray:
    finite = depth[np.isfinite(depth)]
    if finite.size == 0:
        return np.full(num_planes, np.inf, dtype=np.float32)
    near, far = np.float64(finite.min()), np.float64(finite.max())
    t = np.array([0.5]) if num_planes == 1 else np.arange(num_planes, dtype=np.float64) / (num_planes - 1)
    inv = (1.0 - t) / near + t / far
    planes = 1.0 / inv
    if num_planes > 1:
        planes[0], planes[-1] = near, far
    return planes.astype(np.float32)


def plane_depths(depth: np.ndarray, num_planes: int) -> np.ndarray:
    """Depths of ``num_planes`` MPI planes, (Z,) float32, near to far, uniform in inverse depth.

    The planes span the smallest and largest *finite* depth of ``depth`` (H, W) (sky is ignored, nothing
    is capped). Z = 1 puts the plane halfway in inverse depth; a single finite depth value puts every plane
    at it; a frame with no finite depth (all sky) gives all +inf.

    >>> plane_depths(np.array([[1.0, 4.0, np.inf]], np.float32), 3).tolist()
    [1.0, 1.600000023841858, 4.0]
    """
    depth = checked_array(depth, "depth", ("H", "W"), None)
    return _plane_depths(depth, _num_planes(num_planes))


def plane_bounds(planes: np.ndarray) -> np.ndarray:
    """The Z - 1 mid-points between consecutive planes' inverse depths, float32: a point's plane is the number
    of them its inverse depth is <= to (``nearest_plane``; the compiled kernels read the same bounds)."""
    inv_planes = np.float32(1.0) / planes
    return ((inv_planes[:-1] + inv_planes[1:]) * np.float32(0.5)).astype(np.float32)


def nearest_plane(inv_depth: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Index of the plane nearest in inverse depth (ties to the farther plane); ``inv_depth`` = 1 / z."""
    index = np.zeros(inv_depth.shape, dtype=np.intp)
    for bound in plane_bounds(planes):
        index += inv_depth <= bound
    return index


def plane_index(depth: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(H, W) index of the plane each pixel of a planar ``depth`` map goes to in ``build_mpi`` (the plane
    nearest in inverse depth; sky (+inf) -> the farthest plane). ``planes`` (Z,) as ``build_mpi`` takes them."""
    return nearest_plane(np.float32(1.0) / depth, planes)


def _build_mpi(color: np.ndarray, depth: np.ndarray, num_planes: int, planes: Optional[np.ndarray] = None) -> Mpi:
    """Unvalidated ``build_mpi``: ``engine.geometry.kernels.one_hot_mpi``, rows over the kernel threads (its
    oracle: ``build_mpi_reference``)."""
    h, w = depth.shape
    planes = _plane_depths(depth, num_planes) if planes is None else planes
    mpi_color = np.empty((3, num_planes, h, w), dtype=np.float32)
    mpi_depth, alpha = (np.empty((num_planes, h, w), dtype=np.float32) for _ in range(2))
    color, depth, bounds = np.ascontiguousarray(color), np.ascontiguousarray(depth), plane_bounds(planes)
    kernels.run_ranges(lambda r0, r1: kernels.one_hot_mpi(color[r0:r1], depth[r0:r1], bounds, mpi_color[:, :, r0:r1],
                                                          mpi_depth[:, r0:r1], alpha[:, r0:r1]),
                       kernels.split_rows(h, w * num_planes))
    return Mpi(mpi_color, mpi_depth, alpha, planes)


def build_mpi(color: np.ndarray, depth: np.ndarray, num_planes: int, plane_depths: Optional[np.ndarray] = None) -> Mpi:
    """One-hot MPI of an RGB-D frame: each pixel goes to the plane nearest in inverse depth.

    Args:
        color: (H, W, 3) linear RGB.
        depth: (H, W) planar depth, +inf for sky (sky goes to the farthest plane with depth +inf).
        num_planes: Z >= 1; planes from ``plane_depths(depth, Z)`` unless given.
        plane_depths: optional (Z,) planes to use instead (e.g. those of the same frame at another
            resolution): positive, non-decreasing, +inf only at the far end (all +inf for an all-sky frame).

    Returns:
        ``Mpi(color (3, Z, H, W), depth (Z, H, W), alpha (Z, H, W) in {0, 1}, plane_depths (Z,))``; colour
        and depth are 0 where alpha = 0, depth is the true (not the plane's) depth where alpha = 1.
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    color = checked_array(color, "color", ("H", "W", 3), sizes)
    z = _num_planes(num_planes)
    if plane_depths is not None:
        planes = np.asarray(plane_depths, dtype=np.float32)
        finite = np.isfinite(planes)
        if (planes.shape != (z,) or np.isnan(planes).any() or (planes <= 0).any()
                or (finite[1:] & ~finite[:-1]).any() or (np.diff(planes[finite]) < 0).any()):
            raise InputError(f"must be {z} non-decreasing positive depths (+inf only at the far end), got "
                             f"{planes.tolist()}", field="plane_depths")
        return _build_mpi(color, depth, z, planes)
    return _build_mpi(color, depth, z)


def downsample_factor(width: int, working_width: int) -> int:
    """Smallest integer block size that brings a frame ``width`` pixels wide to at most ``working_width``.

    >>> downsample_factor(1920, 480), downsample_factor(960, 480), downsample_factor(640, 480), downsample_factor(400, 480)
    (4, 2, 2, 1)
    """
    if int(working_width) < 1:
        raise InputError(f"must be >= 1, got {working_width}", field="working_width")
    return max(1, -(-int(width) // int(working_width)))


def downsampled_intrinsics(intrinsics: np.ndarray, factor: int) -> np.ndarray:
    """(3, 3) float64 intrinsics of a frame block-downsampled by ``factor`` (``downsample_frame``): pixel ``i`` spans
    source pixels ``[f i, f (i + 1))``, so with pixel centres at +0.5 the x- and y-rows of K are divided by f."""
    out = np.array(intrinsics, dtype=np.float64)
    out[:2] /= int(factor)
    return out


def downsample_frame(color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
                     factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block-downsample an RGB-D frame by an integer ``factor`` (the flow network's working resolution).

    Colour is the block mean, depth the block minimum (the nearest surface; +inf only where the whole block
    is sky), so every low-resolution pixel keeps a depth that exists in the frame. Rows and columns past the
    last whole block are dropped. Pixel ``i`` of the result spans source pixels ``[f i, f (i + 1))``, so with
    pixel centres at +0.5 the intrinsics scale as ``K' = diag(1/f, 1/f, 1) K`` (x-rows of K divided by f).
    Training (``models.flow.train``) and the engine's ``decomp`` predictor both call this function.

    Args:
        color: (H, W, 3) linear RGB; depth: (H, W) planar, +inf sky; intrinsics: (3, 3).
        factor: block size f >= 1 with f <= H and f <= W.

    Returns:
        color (H // f, W // f, 3) and depth (H // f, W // f) float32, intrinsics (3, 3) float64 (f = 1: copies).
    """
    sizes: dict = {}
    depth = checked_array(depth, "depth", ("H", "W"), sizes)
    color = checked_array(color, "color", ("H", "W", 3), sizes)
    k = checked_matrix(intrinsics, "intrinsics", 3)
    f = int(factor)
    if f < 1 or f > min(sizes["H"], sizes["W"]):
        raise InputError(f"must be between 1 and the frame's smaller side {min(sizes['H'], sizes['W'])}, got "
                         f"{factor}", field="factor")
    h, w = sizes["H"] // f, sizes["W"] // f
    if f == 1:
        return color.copy(), depth.copy(), np.array(k, dtype=np.float64)

    out_color = cv2.resize(np.ascontiguousarray(color[:h * f, :w * f]), (w, h), interpolation=cv2.INTER_AREA)
    out_depth = depth[0:h * f:f, 0:w * f:f].copy()  # block minimum: f x f strided minima (no reductions)
    for dy in range(f):
        for dx in range(f):
            if dy or dx:
                np.minimum(out_depth, depth[dy:h * f:f, dx:w * f:f], out=out_depth)
    return (out_color.astype(np.float32), np.ascontiguousarray(out_depth, dtype=np.float32),
            downsampled_intrinsics(k, f))


def downsample_flow(flow: np.ndarray, factor: int) -> np.ndarray:
    """Block-mean a (H, W, 2) pixel flow by ``factor`` into the grid of ``downsample_frame`` (its pixels).

    Rows and columns past the last whole block are dropped; the result is in downsampled pixels (divided
    by ``factor``), float32 (H // f, W // f, 2). The block sum runs over the block's rows, then its columns,
    in float32, then divides by f^2 and by f: numpy's ``mean(axis=(1, 3)) / f`` of the blocks to the bit
    (its order; tested), 6x faster than that strided reduction.
    """
    flow = checked_array(flow, "flow", ("H", "W", 2), {})
    f = int(factor)
    if f < 1:
        raise InputError(f"must be >= 1, got {factor}", field="factor")
    h, w = flow.shape[0] // f, flow.shape[1] // f
    blocks = flow[:h * f, :w * f].reshape(h, f, w, f, 2)
    out = blocks[:, 0, :, 0].copy()
    for dy in range(f):
        for dx in range(f):
            if dy or dx:
                out += blocks[:, dy, :, dx]
    out /= np.float32(f * f)
    out /= np.float32(f)
    return out


def visibility(mpi: Mpi) -> np.ndarray:
    """Transmittance in front of each plane (thesis Eq. 6.9), (Z, H, W): ``prod_{j < z} (1 - alpha_j)``."""
    return _visibility(checked_mpi(mpi, {}).alpha)


def _visibility(alpha: np.ndarray) -> np.ndarray:
    vis = np.empty_like(alpha)
    vis[0] = 1.0
    for z in range(1, alpha.shape[0]):
        vis[z] = vis[z - 1] * (np.float32(1.0) - alpha[z - 1])
    return vis


def _composite(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unvalidated ``composite``: ``engine.geometry.kernels.composite``, rows over the kernel threads (its oracle:
    ``composite_reference``)."""
    h, w = mpi.alpha.shape[1:]
    color, depth, acc = np.empty((h, w, 3), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    m_color, m_depth, m_alpha = (np.ascontiguousarray(a) for a in (mpi.color, mpi.depth, mpi.alpha))
    kernels.run_ranges(lambda r0, r1: kernels.composite(m_color[:, :, r0:r1], m_depth[:, r0:r1], m_alpha[:, r0:r1],
                                                        color[r0:r1], depth[r0:r1], acc[r0:r1]),
                       kernels.split_rows(h, w * mpi.alpha.shape[0]))
    return color, depth, acc


def composite(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render an MPI with the "over" operator (front-to-back: weight = alpha * visibility).

    Returns:
        color (H, W, 3) (premultiplied over black: 0 where nothing is covered), depth (H, W) (the
        weight-normalised depth of the visible surfaces; +inf where sky is visible or nothing is covered),
        accumulated alpha (H, W). Uncovered pixels are reported by ``disocclusion_mask``.
    """
    return _composite(checked_mpi(mpi, {}))


def disocclusion_mask(mpi: Mpi) -> np.ndarray:
    """(H, W) bool, True where no plane has alpha > 0 (a hole left by warping)."""
    return ~(checked_mpi(mpi, {}).alpha > 0).any(axis=0)
