"""Reprojection, multi-plane images (MPI), forward splatting and compositing: the engine's numpy mirror.

The same functions, with the same names and semantics, exist in ``models/geometry.py`` (torch, batched,
differentiable: the reference that training uses). This module is the fast, unbatched path the engine
runs without torch; ``tests/test_geometry.py`` checks it against the torch reference. The design note is
``docs/geometry.md``.

Conventions (those of ``engine/frames.py``; every function below depends on them):

- Camera axes are OpenCV's: x right, y down, z forward. ``world_to_camera`` is a rigid 4x4 matrix;
  ``intrinsics`` is a 3x3 pinhole matrix whose last row is [0, 0, 1].
- Pixel (u, v) (column, row) has its centre at (u + 0.5, v + 0.5) in the coordinates ``intrinsics`` maps
  to; ``uv`` arrays hold (x, y) = (column, row) coordinates in that continuous frame.
- ``depth`` is planar (camera z), > 0, with ``+inf`` for "no surface" (sky). Sky points are points at
  infinity, homogeneous w = 0: only the rotation of a camera moves them, and nothing produces NaN.
- ``color`` is linear RGB float32 (H, W, 3).
- An MPI has Z planes ordered near (index 0) to far (index Z - 1), uniform in inverse depth between the
  frame's smallest and largest *finite* depth (no cap). Layouts here (torch adds a leading batch axis and
  a channel axis of 1 to depth and alpha): color (3, Z, H, W), depth (Z, H, W), alpha (Z, H, W),
  plane_depths (Z,).
- Alpha built from a frame is one-hot: each pixel goes to the plane nearest in inverse depth (ties go to
  the farther plane); sky pixels go to the farthest plane and keep depth +inf. The MPI depth channel holds
  the true depth where alpha = 1 and 0 elsewhere.

Values are float32; 4x4 compositions are made in float64 and splat sums accumulate in float64 (in
per-thread work buffers reused across calls, see ``_Scratch``). The forward warp, ``build_mpi`` and
``composite`` run as compiled kernels (``engine/kernels.py``); their numpy bodies (``*_reference``) are the
tests' oracle, and the kernels reproduce them bit for bit (compositing to 1e-6).
"""
from __future__ import annotations

import threading
from functools import lru_cache
from typing import NamedTuple, Optional, Sequence

import numpy as np

from engine.errors import InputError
from engine.frames import rigid_inverse

#: A projected point is valid (in front of the camera) when z > (|z u| + |z v|) / MAX_PIXEL_COORD +
#: TINY_DEPTH: relative to its own scale, and so that |u| + |v| < 1e7 px; other points get uv = 0, z = 0.
MAX_PIXEL_COORD = 1e7
#: Smallest camera z counted as "in front" (keeps 1 / z finite in float32).
TINY_DEPTH = 1e-30
#: A warped MPI pixel is covered (alpha = 1) when its summed bilinear splat weight exceeds this.
COVERAGE_THRESHOLD = 1e-3
#: Bilinear fractions within this many pixels of a pixel centre snap onto it (continuously), so round-off
#: of an exact landing cannot leak a tiny weight that the soft z-buffer would amplify by up to e^50.
SUBPIXEL_SNAP = 1.0 / 256.0
#: Floor of the soft z-buffer's log-weight: keeps float32 weights far from underflow (binds only when
#: sharpness > 60).
MIN_LOG_WEIGHT = -60.0
# Soft z-buffer weight of sky points (float64 sums): below any finite point's weight (>= e^-60 times a
# bilinear weight >= ~1e-9) by > e^100; a pixel whose summed weight is below _SKY_ONLY_WEIGHT saw only sky.
_SKY_WEIGHT = float(np.exp(-300.0))
_SKY_ONLY_WEIGHT = float(np.exp(-200.0))
#: Default soft z-buffer sharpness (the authors' 50).
DEFAULT_SHARPNESS = 50.0


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


# ----------------------------------------------------------------------------------------------------
# Validation (public entry points only)


def check_shape(value, name: str, dims: Sequence, sizes: Optional[dict] = None, *, floating: bool = True):
    """Check that ``value`` (numpy array or torch tensor) has shape ``dims``; raise InputError naming it.

    ``dims`` holds ints (exact sizes) and names ("H", "W", ...); a name binds to the size it first meets in
    ``sizes`` and must match wherever it appears again. A leading "..." accepts any leading axes.
    With ``floating``, the dtype must be a floating-point one.
    """
    shape = getattr(value, "shape", None)
    if shape is None:
        raise InputError(f"must be an array, got {type(value).__name__}", field=name)
    shape = tuple(int(n) for n in shape)
    want = "(" + ", ".join(str(d) for d in dims) + ")"
    if dims and dims[0] == "...":
        dims = dims[1:]
        if len(shape) < len(dims):
            raise InputError(f"must have shape {want}, got {shape}", field=name)
        shape = shape[len(shape) - len(dims):]
    elif len(shape) != len(dims):
        raise InputError(f"must have shape {want}, got {shape}", field=name)
    sizes = {} if sizes is None else sizes
    for dim, n in zip(dims, shape):
        if isinstance(dim, int):
            if n != dim:
                raise InputError(f"must have shape {want}, got {tuple(getattr(value, 'shape'))}", field=name)
        elif dim in sizes and sizes[dim] != n:
            raise InputError(f"has {dim} = {n}, expected {dim} = {sizes[dim]} (shape {want}, got "
                             f"{tuple(getattr(value, 'shape'))})", field=name)
        else:
            sizes[dim] = n
    if floating:
        is_float = getattr(value, "is_floating_point", None)
        ok = is_float() if callable(is_float) else np.issubdtype(value.dtype, np.floating)
        if not ok:
            raise InputError(f"must be a floating-point array, got dtype {value.dtype}", field=name)
    return value


def _array(value, name, dims, sizes, dtype=np.float32, floating=True):
    arr = np.asarray(value)
    check_shape(arr, name, dims, sizes, floating=floating)
    return arr.astype(dtype, copy=False)


def _matrix(value, name, n):
    return _array(value, name, (n, n), None, np.float64, floating=False)


def _check_mpi(mpi, sizes) -> Mpi:
    if not isinstance(mpi, tuple) or len(mpi) != 4:
        raise InputError(f"must be an Mpi(color, depth, alpha, plane_depths), got {type(mpi).__name__}", field="mpi")
    color = _array(mpi[0], "mpi.color", (3, "Z", "H", "W"), sizes)
    depth = _array(mpi[1], "mpi.depth", ("Z", "H", "W"), sizes)
    alpha = _array(mpi[2], "mpi.alpha", ("Z", "H", "W"), sizes)
    planes = _array(mpi[3], "mpi.plane_depths", ("Z",), sizes)
    if sizes["Z"] < 1:
        raise InputError("has Z = 0 planes, need at least 1", field="mpi")
    return Mpi(color, depth, alpha, planes)


def _num_planes(num_planes) -> int:
    if isinstance(num_planes, bool) or not isinstance(num_planes, (int, np.integer)) or num_planes < 1:
        raise InputError(f"must be an integer >= 1, got {num_planes!r}", field="num_planes")
    return int(num_planes)


def _sharpness(sharpness) -> float:
    s = float(sharpness)
    if not np.isfinite(s) or s < 0:
        raise InputError(f"must be finite and >= 0, got {sharpness!r}", field="sharpness")
    return s


def _out_size(out_size, default):
    if out_size is None:
        return default
    try:
        h, w = (int(n) for n in out_size)
    except (TypeError, ValueError):
        raise InputError(f"must be (height, width), got {out_size!r}", field="out_size") from None
    if h < 1 or w < 1:
        raise InputError(f"must be positive, got {out_size!r}", field="out_size")
    return h, w


# ----------------------------------------------------------------------------------------------------
# Pixels, cameras, points


@lru_cache(maxsize=16)
def _grid(height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
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
    u, v = _grid(height, width)
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
    depth = _array(depth, "depth", ("...", "H", "W"), None)
    k = _matrix(intrinsics, "intrinsics", 3)
    h, w = depth.shape[-2:]
    u, v = _grid(h, w)
    lead = depth.shape[:-2]
    pixels = _pixel_points(np.broadcast_to(u, lead + (h * w,)), np.broadcast_to(v, lead + (h * w,)),
                           depth.reshape(lead + (h * w,)))
    points = _transform(_block(_pinhole_inverse(k)), *pixels)
    return np.stack(points, axis=-1).reshape(depth.shape + (4,))


def relative_transform(src_world_to_camera: np.ndarray, dst_world_to_camera: np.ndarray) -> np.ndarray:
    """``T_dst @ inv(T_src)`` (float64, exact rigid inverse): maps source-camera points to destination-camera.

    Both are rigid world-to-camera (..., 4, 4) matrices; leading axes broadcast.
    """
    src = _array(src_world_to_camera, "src_world_to_camera", ("...", 4, 4), None, np.float64, floating=False)
    dst = _array(dst_world_to_camera, "dst_world_to_camera", ("...", 4, 4), None, np.float64, floating=False)
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
    pts = _array(points_h, "points_h", ("...", 4), None)
    k = _matrix(intrinsics, "intrinsics", 3)
    u, v, z, valid = _project_pixels(*_transform(_block(k), pts[..., 0], pts[..., 1], pts[..., 2], pts[..., 3]))
    return np.stack([u, v], axis=-1), z, valid


def _reprojection_matrix(k_src, t_src, k_dst, t_dst) -> np.ndarray:
    """Eq. 6.2 as one float64 4x4 matrix on pixel points: [[K_dst, 0], [0, 1]] T_dst T_src^-1 [[K_src^-1, 0], [0, 1]]."""
    return _block(k_dst) @ t_dst @ rigid_inverse(t_src) @ _block(_pinhole_inverse(k_src))


def _reproject_points(u, v, depth, matrix):
    """Source pixel coordinates + depth -> destination (u, v, z, valid) (see ``_reprojection_matrix``)."""
    return _project_pixels(*_transform(matrix, *_pixel_points(u, v, depth)))


def _flow3(flow, sizes, name="flow"):
    flow = _array(flow, name, ("H", "W", "C"), sizes)
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
    depth = _array(depth, "depth", ("H", "W"), sizes)
    k_src, k_dst = _matrix(K_src, "K_src", 3), _matrix(K_dst, "K_dst", 3)
    matrix = _reprojection_matrix(k_src, _matrix(T_src, "T_src", 4), k_dst, _matrix(T_dst, "T_dst", 4))
    h, w = depth.shape
    u, v = _grid(h, w)
    d = depth.reshape(-1)
    if flow is not None:
        flow = _flow3(flow, sizes).reshape(h * w, -1)
        u, v = u + flow[:, 0], v + flow[:, 1]
        if flow.shape[1] == 3:
            d = d + flow[:, 2]
    uo, vo, z, valid = _reproject_points(u, v, d, matrix)
    return np.stack([uo, vo], axis=-1).reshape(h, w, 2), z.reshape(h, w), valid.reshape(h, w)


# ----------------------------------------------------------------------------------------------------
# MPI


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
    depth = _array(depth, "depth", ("H", "W"), None)
    return _plane_depths(depth, _num_planes(num_planes))


def _half_inverse(planes: np.ndarray) -> np.ndarray:
    """The Z - 1 mid-points between consecutive planes' inverse depths, float32: a point's plane is the number
    of them its inverse depth is <= to (``_nearest_plane``; the compiled kernels read the same bounds)."""
    inv_planes = np.float32(1.0) / planes
    return ((inv_planes[:-1] + inv_planes[1:]) * np.float32(0.5)).astype(np.float32)


def _nearest_plane(inv_depth: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """Index of the plane nearest in inverse depth (ties to the farther plane); ``inv_depth`` = 1 / z."""
    index = np.zeros(inv_depth.shape, dtype=np.intp)
    for bound in _half_inverse(planes):
        index += inv_depth <= bound
    return index


def plane_index(depth: np.ndarray, planes: np.ndarray) -> np.ndarray:
    """(H, W) index of the plane each pixel of a planar ``depth`` map goes to in ``build_mpi`` (the plane
    nearest in inverse depth; sky (+inf) -> the farthest plane). ``planes`` (Z,) as ``build_mpi`` takes them."""
    return _nearest_plane(np.float32(1.0) / depth, planes)


def _build_mpi(color: np.ndarray, depth: np.ndarray, num_planes: int, planes: Optional[np.ndarray] = None) -> Mpi:
    """Unvalidated ``build_mpi``: ``engine.kernels.one_hot_mpi`` (its oracle: ``_build_mpi_reference``)."""
    from engine import kernels

    h, w = depth.shape
    planes = _plane_depths(depth, num_planes) if planes is None else planes
    mpi_color = np.empty((3, num_planes, h, w), dtype=np.float32)
    mpi_depth, alpha = (np.empty((num_planes, h, w), dtype=np.float32) for _ in range(2))
    kernels.one_hot_mpi(np.ascontiguousarray(color), np.ascontiguousarray(depth), _half_inverse(planes), mpi_color,
                        mpi_depth, alpha)
    return Mpi(mpi_color, mpi_depth, alpha, planes)


def _build_mpi_reference(color: np.ndarray, depth: np.ndarray, num_planes: int,
                         planes: Optional[np.ndarray] = None) -> Mpi:
    h, w = depth.shape
    planes = _plane_depths(depth, num_planes) if planes is None else planes
    index = plane_index(depth, planes)
    alpha = np.zeros((num_planes, h, w), dtype=np.float32)
    np.put_along_axis(alpha, index[None], np.float32(1.0), axis=0)
    on = alpha > 0
    mpi_depth = np.where(on, depth[None], np.float32(0.0))
    mpi_color = np.where(on[None], np.moveaxis(color, -1, 0)[:, None], np.float32(0.0))
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
    depth = _array(depth, "depth", ("H", "W"), sizes)
    color = _array(color, "color", ("H", "W", 3), sizes)
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


def downsample_frame(color: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
                     factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Block-downsample an RGB-D frame by an integer ``factor`` (the flow network's working resolution).

    Colour is the block mean, depth the block minimum (the nearest surface; +inf only where the whole block
    is sky), so every low-resolution pixel keeps a depth that exists in the frame. Rows and columns past the
    last whole block are dropped. Pixel ``i`` of the result spans source pixels ``[f i, f (i + 1))``, so with
    pixel centres at +0.5 the intrinsics scale as ``K' = diag(1/f, 1/f, 1) K`` (x-rows of K divided by f).
    Training (``models.train_flow``) and the engine's ``decomp`` predictor both call this function.

    Args:
        color: (H, W, 3) linear RGB; depth: (H, W) planar, +inf sky; intrinsics: (3, 3).
        factor: block size f >= 1 with f <= H and f <= W.

    Returns:
        color (H // f, W // f, 3) and depth (H // f, W // f) float32, intrinsics (3, 3) float64 (f = 1: copies).
    """
    sizes: dict = {}
    depth = _array(depth, "depth", ("H", "W"), sizes)
    color = _array(color, "color", ("H", "W", 3), sizes)
    k = _matrix(intrinsics, "intrinsics", 3)
    f = int(factor)
    if f < 1 or f > min(sizes["H"], sizes["W"]):
        raise InputError(f"must be between 1 and the frame's smaller side {min(sizes['H'], sizes['W'])}, got "
                         f"{factor}", field="factor")
    h, w = sizes["H"] // f, sizes["W"] // f
    if f == 1:
        return color.copy(), depth.copy(), np.array(k, dtype=np.float64)
    import cv2  # INTER_AREA with an integer factor is the exact block mean, several times faster than numpy's

    out_color = cv2.resize(np.ascontiguousarray(color[:h * f, :w * f]), (w, h), interpolation=cv2.INTER_AREA)
    out_depth = depth[0:h * f:f, 0:w * f:f].copy()  # block minimum: f x f strided minima (no reductions)
    for dy in range(f):
        for dx in range(f):
            if dy or dx:
                np.minimum(out_depth, depth[dy:h * f:f, dx:w * f:f], out=out_depth)
    out_k = np.array(k, dtype=np.float64)
    out_k[:2] /= f
    return out_color.astype(np.float32), np.ascontiguousarray(out_depth, dtype=np.float32), out_k


def downsample_flow(flow: np.ndarray, factor: int) -> np.ndarray:
    """Block-mean a (H, W, 2) pixel flow by ``factor`` into the grid of ``downsample_frame`` (its pixels).

    Rows and columns past the last whole block are dropped; the result is in downsampled pixels (divided
    by ``factor``), float32 (H // f, W // f, 2).
    """
    flow = _array(flow, "flow", ("H", "W", 2), {})
    f = int(factor)
    if f < 1:
        raise InputError(f"must be >= 1, got {factor}", field="factor")
    h, w = flow.shape[0] // f, flow.shape[1] // f
    return (flow[:h * f, :w * f].reshape(h, f, w, f, 2).mean(axis=(1, 3)) / f).astype(np.float32)


def visibility(mpi: Mpi) -> np.ndarray:
    """Transmittance in front of each plane (thesis Eq. 6.9), (Z, H, W): ``prod_{j < z} (1 - alpha_j)``."""
    return _visibility(_check_mpi(mpi, {}).alpha)


def _visibility(alpha: np.ndarray) -> np.ndarray:
    vis = np.empty_like(alpha)
    vis[0] = 1.0
    for z in range(1, alpha.shape[0]):
        vis[z] = vis[z - 1] * (np.float32(1.0) - alpha[z - 1])
    return vis


def _composite(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Unvalidated ``composite``: ``engine.kernels.composite`` (its oracle: ``_composite_reference``)."""
    from engine import kernels

    h, w = mpi.alpha.shape[1:]
    color, depth, acc = np.empty((h, w, 3), np.float32), np.empty((h, w), np.float32), np.empty((h, w), np.float32)
    kernels.composite(np.ascontiguousarray(mpi.color), np.ascontiguousarray(mpi.depth),
                      np.ascontiguousarray(mpi.alpha), color, depth, acc)
    return color, depth, acc


def _composite_reference(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    weight = mpi.alpha * _visibility(mpi.alpha)
    color = np.einsum("czhw,zhw->hwc", mpi.color, weight, optimize=False)
    acc = weight.sum(axis=0)
    seen = weight > 0
    sky = (seen & np.isinf(mpi.depth)).any(axis=0)
    depth_sum = (np.where(seen & ~np.isinf(mpi.depth), mpi.depth, np.float32(0.0)) * weight).sum(axis=0)
    covered = (acc > 0) & ~sky
    depth = np.where(covered, depth_sum / np.where(covered, acc, np.float32(1.0)), np.float32(np.inf))
    return color, depth.astype(np.float32, copy=False), acc


def composite(mpi: Mpi) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Render an MPI with the "over" operator (front-to-back: weight = alpha * visibility).

    Returns:
        color (H, W, 3) (premultiplied over black: 0 where nothing is covered), depth (H, W) (the
        weight-normalised depth of the visible surfaces; +inf where sky is visible or nothing is covered),
        accumulated alpha (H, W). Uncovered pixels are reported by ``disocclusion_mask``.
    """
    return _composite(_check_mpi(mpi, {}))


def disocclusion_mask(mpi: Mpi) -> np.ndarray:
    """(H, W) bool, True where no plane has alpha > 0 (a hole left by warping)."""
    return ~(_check_mpi(mpi, {}).alpha > 0).any(axis=0)


# ----------------------------------------------------------------------------------------------------
# Forward warping (bilinear splatting with a soft z-buffer)


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
    Sky points get _SKY_WEIGHT = e^-300, so any finite point outweighs them by > e^200 (the torch reference
    keeps sky in a separate layer instead: the results agree to ~1e-100).
    """
    lo, hi = log_range
    log_z = np.log1p(np.where(sky, np.float32(0.0), z), dtype=np.float64)
    if lo != np.inf:  # else no finite point is splatted at all
        log_z -= lo
    log_z *= -sharpness / max(hi, 1e-30)
    np.clip(log_z, MIN_LOG_WEIGHT, 0.0, out=log_z)
    weight = np.exp(log_z, out=log_z)
    weight[sky] = _SKY_WEIGHT
    return weight


def _bilinear_fraction(x: np.ndarray, limit: int):
    """Integer left/top tap (padded coordinates, 1 = first pixel) and snapped fraction of the right/bottom tap."""
    x = np.clip(x - np.float32(0.5), np.float32(-2.0), np.float32(limit + 1))
    left = np.floor(x)
    frac = np.clip((x - left - np.float32(SUBPIXEL_SNAP)) * np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP)),
                   np.float32(0.0), np.float32(1.0))
    return left.astype(np.intp) + 1, frac


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


_SCRATCH = _Scratch()
#: Smallest share of a split warp pass per thread (smaller warps run on one thread: a hand-off costs ~0.1 ms).
_MIN_POINTS_PER_THREAD = 1 << 16
_MIN_ROWS_PER_THREAD = 8
#: Points per chunk of the numpy warp (work arrays of 32k values stay in the L2 cache).
_CHUNK = 1 << 15
#: The splat pass skips the points that do not land (alpha 0 or outside the output) when fewer than this
#: fraction land: e.g. a box-sized output of a whole frame costs in proportion to the box, not the frame.
_COMPACT_BELOW = 0.94


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


def _forward_warp_mpi(mpi: Mpi, k_src, t_src, k_dst, t_dst, object_flow, out_size, sharpness):
    """Unvalidated body of ``forward_warp_mpi`` (inputs already float32 / float64 arrays): the compiled
    kernels of ``engine.kernels``, held to ``_forward_warp_mpi_reference`` by the tests."""
    from engine import kernels

    color, depth, alpha, planes = mpi
    num_z, h, w = alpha.shape
    ho, wo = out_size
    n = num_z * h * w
    half_inv = _half_inverse(planes)
    flow = np.zeros((3, 1, 1, 1), np.float32) if object_flow is None else np.ascontiguousarray(object_flow)
    matrix = np.ascontiguousarray(_reprojection_matrix(k_src, t_src, k_dst, t_dst).astype(np.float32))
    base = _SCRATCH.get("base", n, np.intp)
    fx, fy, z, a = (_SCRATCH.get(name, n, np.float32) for name in ("fx", "fy", "z", "a"))
    log_z = _SCRATCH.get("log_z", n)
    depth, alpha, color = (np.ascontiguousarray(v) for v in (depth, alpha, color))
    constants = (np.float32(1.0 / (1.0 - 2.0 * SUBPIXEL_SNAP)), np.float32(SUBPIXEL_SNAP),
                 np.float32(1.0 / MAX_PIXEL_COORD), np.float32(TINY_DEPTH))
    # each pass split over threads (engine.kernels.run_ranges): pass 1 by source rows, pass 2 by points into
    # one padded sum volume per part, the normalisation by output rows (it adds the parts in order)
    ranges = kernels.split_ranges(h, max(_MIN_ROWS_PER_THREAD, -(-_MIN_POINTS_PER_THREAD // max(1, num_z * w))))
    extents = kernels.run_ranges(lambda r0, r1: kernels.project_points(
        depth, alpha, flow, object_flow is not None, matrix, half_inv, ho, wo, *constants, r0, r1, base, fx, fy, z,
        a, log_z), ranges)
    lo, hi = min(e[0] for e in extents), max(e[1] for e in extents)
    hp, wp = ho + 2, wo + 2
    ranges = kernels.split_ranges(n, _MIN_POINTS_PER_THREAD)
    sums = _SCRATCH.get("sums", len(ranges) * 6 * num_z * hp * wp).reshape(len(ranges), -1, 6)  # six sums a pixel
    flat_color = color.reshape(3, -1)
    kernels.run_ranges(lambda p0, p1: kernels.splat_points(
        flat_color, base, fx, fy, z, a, log_z, lo, hi, float(sharpness), wp, MIN_LOG_WEIGHT, _SKY_WEIGHT, p0, p1,
        sums[ranges.index((p0, p1))]), ranges)
    out_color = np.empty((3, num_z, ho, wo), dtype=np.float32)
    out_depth, out_alpha, cov = (np.empty((num_z, ho, wo), dtype=np.float32) for _ in range(3))
    kernels.run_ranges(lambda r0, r1: kernels.normalize(
        sums, num_z, ho, wo, COVERAGE_THRESHOLD, _SKY_ONLY_WEIGHT, r0, r1, out_color, out_depth, out_alpha, cov),
        kernels.split_ranges(ho, _MIN_ROWS_PER_THREAD))
    return Mpi(out_color, out_depth, out_alpha, planes), cov


def _forward_warp_mpi_reference(mpi: Mpi, k_src, t_src, k_dst, t_dst, object_flow, out_size, sharpness):
    """numpy body of ``forward_warp_mpi``: the oracle of the compiled ``_forward_warp_mpi`` (same arguments).

    Points are processed in chunks of _CHUNK so every temporary stays in cache and is recycled by the
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
    gu, gv = _grid(h, w)
    flat_depth, flat_alpha = depth.reshape(-1), alpha.reshape(-1)
    flat_flow = None if object_flow is None else object_flow.reshape(3, -1)
    flat_color = color.reshape(3, -1)
    matrix = _reprojection_matrix(k_src, t_src, k_dst, t_dst)
    point_base = _SCRATCH.get("base", n, np.intp)
    point_fx, point_fy, point_z, point_alpha = (_SCRATCH.get(name, n, np.float32) for name in ("fx", "fy", "z", "a"))
    log_range = (np.inf, 0.0)
    # pass 1: reproject, pick the pixel taps and the destination plane of every point
    for start in range(0, n, _CHUNK):
        part = slice(start, min(start + _CHUNK, n))
        src = part if index is None else index[part]
        pixel = src if index is None else src % (h * w)
        u, v, d = gu[pixel], gv[pixel], flat_depth[src]
        if flat_flow is not None:
            u, v, d = u + flat_flow[0, src], v + flat_flow[1, src], d + flat_flow[2, src]  # sky stays +inf
        uo, vo, z, valid = _reproject_points(u, v, d, matrix)
        x0, point_fx[part] = _bilinear_fraction(uo, wo)
        y0, point_fy[part] = _bilinear_fraction(vo, ho)
        keep = valid & (x0 >= 0) & (x0 <= wo) & (y0 >= 0) & (y0 <= ho)  # else dropped: weight 0
        a = point_alpha[part]
        np.multiply(flat_alpha[src], keep, out=a)
        plane = _nearest_plane(np.float32(1.0) / np.where(valid, z, np.float32(1.0)), planes)  # sky: far
        base = point_base[part]
        np.multiply(plane * hp + y0, wp, out=base)
        base += x0
        base[~keep] = 0
        point_z[part] = z
        log_range = _log_depth_range(z, (a > 0) & np.isfinite(z), log_range)
    # pass 2: splat [coverage, weight, weight * (r, g, b, z)] with the soft z-buffer, only the points that
    # land (alpha > 0 inside the output): a box-sized output of a full frame splats the box's points only
    kept = np.flatnonzero(point_alpha[:n])
    compact = kept.size < _COMPACT_BELOW * n
    m = kept.size if compact else n
    sums = _SCRATCH.get("sums", 6 * num_z * hp * wp).reshape(6, -1)
    sums.fill(0.0)
    for start in range(0, m, _CHUNK):
        part = kept[start:start + _CHUNK] if compact else slice(start, min(start + _CHUNK, n))
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
    out_depth[covered & (wsum < _SKY_ONLY_WEIGHT)] = np.inf
    warped = Mpi(out_color, out_depth, covered.astype(np.float32), planes)
    return warped, cov.astype(np.float32)


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
    mpi = _check_mpi(mpi, sizes)
    if object_flow is not None:
        object_flow = _array(object_flow, "object_flow", (3, "Z", "H", "W"), sizes)
    out = _out_size(out_size, (sizes["H"], sizes["W"]))
    return _forward_warp_mpi(mpi, _matrix(K_src, "K_src", 3), _matrix(T_src, "T_src", 4),
                             _matrix(K_dst, "K_dst", 3), _matrix(T_dst, "T_dst", 4), object_flow, out,
                             _sharpness(sharpness))


def forward_warp_frame(color: np.ndarray, depth: np.ndarray, K_src: np.ndarray, T_src: np.ndarray,
                       K_dst: np.ndarray, T_dst: np.ndarray, flow: Optional[np.ndarray] = None,
                       sharpness: float = DEFAULT_SHARPNESS) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Forward-warp an RGB-D frame: a one-plane ``build_mpi`` + ``forward_warp_mpi`` + ``composite``.

    Args:
        color: (H, W, 3) linear RGB; depth: (H, W) planar, +inf for sky.
        K_src, T_src, K_dst, T_dst: intrinsics (3, 3) and world-to-camera (4, 4) of both views.
        flow: optional (H, W, 3) (du, dv, dz) or (H, W, 2) (dz = 0) object flow in the source view.
        sharpness: soft z-buffer sharpness.

    Returns:
        color (H, W, 3), depth (H, W) (+inf on sky and holes), holes (H, W) bool (nothing landed).
    """
    sizes: dict = {}
    depth = _array(depth, "depth", ("H", "W"), sizes)
    color = _array(color, "color", ("H", "W", 3), sizes)
    object_flow = None
    if flow is not None:
        flow = _flow3(flow, sizes)
        object_flow = np.zeros((3, 1) + depth.shape, dtype=np.float32)
        object_flow[:flow.shape[2], 0] = np.moveaxis(flow, -1, 0)
    mpi = _build_mpi(color, depth, 1)
    warped, _ = _forward_warp_mpi(mpi, _matrix(K_src, "K_src", 3), _matrix(T_src, "T_src", 4),
                                  _matrix(K_dst, "K_dst", 3), _matrix(T_dst, "T_dst", 4), object_flow,
                                  depth.shape, _sharpness(sharpness))
    out_color, out_depth, _ = _composite(warped)
    return out_color, out_depth, warped.alpha[0] <= 0
