"""In-memory frames and cameras, and the validation every public entry point runs once.

Conventions (the same everywhere in Interleave, see ``engine/conventions/cameras.py``):

- Camera axes are OpenCV's: x right, y down, z forward (into the scene).
- ``world_to_camera`` is a rigid 4x4 matrix mapping world points to camera points.
- ``intrinsics`` is a 3x3 matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``; pixel (u, v) (column,
  row) has its centre at (u + 0.5, v + 0.5) in the coordinates it maps to.
- ``depth`` is planar: the camera-space z of the surface seen at the pixel, in scene units, strictly
  positive; ``+inf`` marks "no surface" (sky).
- ``color`` is linear-light Rec.709 RGB (``linear-srgb``), float32, shape (H, W, 3). Loaders decode
  display-encoded input; metrics encode with the sRGB transfer function before comparing.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from engine.core.checks import numeric_array
from engine.core.errors import InputError

#: Largest deviation of R^T R from the identity, and of det(R) from 1, accepted as "rigid".
RIGID_TOLERANCE = 1e-4


@dataclass(frozen=True)
class Camera:
    """A pinhole camera: intrinsics (3, 3) and a rigid world-to-camera transform (4, 4), float64."""

    intrinsics: np.ndarray
    world_to_camera: np.ndarray

    @property
    def camera_to_world(self) -> np.ndarray:
        """Exact rigid inverse of ``world_to_camera``."""
        return rigid_inverse(self.world_to_camera)

    @property
    def position(self) -> np.ndarray:
        """Camera centre in world coordinates, shape (3,)."""
        return self.camera_to_world[:3, 3]


@dataclass
class Frame:
    """One rendered frame: colour, planar depth, camera and optional ground-truth channels.

    Attributes:
        index: frame number in its sequence.
        time: seconds since the start of the sequence.
        color: (H, W, 3) float32, linear RGB.
        depth: (H, W) float32, planar z, > 0, +inf for sky.
        camera: the camera that saw it.
        object_id: (H, W) int32, 0 for static background, or None.
        moving: (H, W) bool, True where the visible surface moves in world space before the next frame.
        flow: (H, W, 2) float32, total screen motion to the next frame in pixels (x right, y down).
        object_flow: (H, W, 2) float32, screen motion to the next frame from object motion alone.
        motion_vectors: (h, w, 2) float32 or None, a renderer's motion vectors, an INPUT of predictors
            (unlike the ground-truth ``flow`` / ``object_flow``): for each pixel, the screen displacement
            in pixels of this frame's full resolution (x right, y down) from the pixel centre to where the
            same surface point was in the previous frame of its stream (a sequence: the previous frame;
            a predictor's history: the previous rendered frame), camera motion included. NaN marks
            pixels without a vector (sky, particles). ``(h, w)`` may be smaller than ``(H, W)`` (vectors
            rendered at a lower resolution); the vector of output pixel (x, y) sits at
            ``((x + 0.5) w / W - 0.5, (y + 0.5) h / H - 0.5)`` in the small grid.
        color_codes: (H, W, 3|4) uint8 or None: the 8-bit sRGB codes ``color`` was decoded from
            (``engine.geometry.encoding.decode8``; alpha ignored), kept where the frame came so and the ``gl``
            backend runs: it uploads them (a third or a quarter of the float colour's bytes) and decodes on
            the GPU. They must decode to ``color``; ``with_color`` drops them.
    """

    index: int
    time: float
    color: np.ndarray
    depth: np.ndarray
    camera: Camera
    object_id: Optional[np.ndarray] = None
    moving: Optional[np.ndarray] = None
    flow: Optional[np.ndarray] = None
    object_flow: Optional[np.ndarray] = None
    motion_vectors: Optional[np.ndarray] = None
    color_codes: Optional[np.ndarray] = field(default=None, repr=False)

    @property
    def height(self) -> int:
        return int(self.depth.shape[0])

    @property
    def width(self) -> int:
        return int(self.depth.shape[1])

    def with_color(self, color: np.ndarray) -> "Frame":
        """A copy of this frame with another colour image (the arrays are shared, not copied; no codes)."""
        return replace(self, color=color, color_codes=None)


@dataclass
class SceneObject:
    """A rigid scene object with its per-frame world-from-object transforms, shape (N, 4, 4)."""

    id: int
    name: str
    moving: bool
    world_from_object: np.ndarray = field(repr=False)


def rigid_inverse(transform: np.ndarray) -> np.ndarray:
    """Inverse of a rigid 4x4 transform, computed as [R^T, -R^T t] (exact, no general inverse)."""
    rotation = transform[..., :3, :3]
    translation = transform[..., :3, 3]
    out = np.zeros_like(transform)
    out[..., :3, :3] = np.swapaxes(rotation, -1, -2)
    out[..., :3, 3] = -np.einsum("...ji,...j->...i", rotation, translation)
    out[..., 3, 3] = 1.0
    return out


def _finite_matrix(value: object, n: int, where: dict) -> np.ndarray:
    """``value`` as an (n, n) float64 matrix of finite numbers; InputError naming ``where`` otherwise."""
    m = numeric_array(value, **where)
    if m.shape != (n, n):
        raise InputError(f"must have shape ({n}, {n}), got {m.shape}", **where)
    if not np.all(np.isfinite(m)):
        raise InputError("has non-finite entries", **where)
    return m


def validate_intrinsics(intrinsics: object, *, file=None, frame=None, field_name="intrinsics") -> np.ndarray:
    """Check a 3x3 pinhole intrinsics matrix and return it as float64.

    Raises InputError for a wrong shape, non-finite values, a zero or negative focal length, or a last
    row other than [0, 0, 1] (a singular or non-pinhole matrix).
    """
    where = dict(file=file, frame=frame, field=field_name)
    k = _finite_matrix(intrinsics, 3, where)
    if not np.allclose(k[2], [0.0, 0.0, 1.0]):
        raise InputError(f"last row must be [0, 0, 1], got {k[2].tolist()}", **where)
    if k[0, 0] <= 0 or k[1, 1] <= 0:
        raise InputError(f"focal lengths must be positive, got fx={k[0, 0]}, fy={k[1, 1]}", **where)
    if abs(np.linalg.det(k)) < 1e-12:
        raise InputError("is singular", **where)
    return k


def validate_pose(world_to_camera: object, *, file=None, frame=None, field_name="world_to_camera") -> np.ndarray:
    """Check a rigid 4x4 world-to-camera matrix and return it as float64.

    Raises InputError for a wrong shape, non-finite values, a last row other than [0, 0, 0, 1], or a
    rotation block that is not orthonormal with determinant +1 (scale, shear, reflection).
    """
    where = dict(file=file, frame=frame, field=field_name)
    t = _finite_matrix(world_to_camera, 4, where)
    if not np.allclose(t[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"last row must be [0, 0, 0, 1], got {t[3].tolist()}", **where)
    rotation = t[:3, :3]
    orth_error = float(np.max(np.abs(rotation.T @ rotation - np.eye(3))))
    det = float(np.linalg.det(rotation))
    if orth_error > RIGID_TOLERANCE or abs(det - 1.0) > RIGID_TOLERANCE:
        raise InputError(
            f"is not rigid: |R^T R - I| = {orth_error:.3g}, det(R) = {det:.6g} "
            f"(scale, shear or reflection; tolerance {RIGID_TOLERANCE})", **where)
    return t


def validate_depth(depth: object, shape: tuple[int, int] | None = None, *, file=None, frame=None,
                   field_name="depth") -> np.ndarray:
    """Check a planar depth map (H, W) and return it as float32.

    NaN, -inf, zero and negative values are errors; +inf is legal ("no surface"). Nothing is clamped.
    """
    where = dict(file=file, frame=frame, field=field_name)
    d = np.asarray(depth)
    if d.ndim != 2:
        raise InputError(f"must have shape (H, W), got {d.shape}", **where)
    if shape is not None and d.shape != tuple(shape):
        raise InputError(f"has shape {d.shape}, expected {tuple(shape)}", **where)
    if not np.issubdtype(d.dtype, np.floating):
        raise InputError(f"must be a float array, got dtype {d.dtype}", **where)
    d = d.astype(np.float32, copy=False)
    nan = int(np.count_nonzero(np.isnan(d)))
    if nan:
        raise InputError(f"has {nan} NaN values", **where)
    neg_inf = int(np.count_nonzero(np.isneginf(d)))
    if neg_inf:
        raise InputError(f"has {neg_inf} -inf values (only +inf, meaning 'no surface', is legal)", **where)
    nonpos = int(np.count_nonzero(d <= 0))
    if nonpos:
        raise InputError(f"has {nonpos} zero or negative values (planar depth must be > 0)", **where)
    return d


def validate_color(color: object, shape: tuple[int, int] | None = None, *, file=None, frame=None,
                   field_name="color") -> np.ndarray:
    """Check a colour image (H, W, 3) of finite, non-negative floats and return it as float32."""
    where = dict(file=file, frame=frame, field=field_name)
    c = np.asarray(color)
    if c.ndim != 3 or c.shape[2] != 3:
        raise InputError(f"must have shape (H, W, 3), got {c.shape}", **where)
    if shape is not None and c.shape[:2] != tuple(shape):
        raise InputError(f"has size {c.shape[:2]}, expected {tuple(shape)}", **where)
    if not np.issubdtype(c.dtype, np.floating):
        raise InputError(f"must be a float array, got dtype {c.dtype}", **where)
    c = c.astype(np.float32, copy=False)
    bad = int(np.count_nonzero(~np.isfinite(c)))
    if bad:
        raise InputError(f"has {bad} non-finite values", **where)
    neg = int(np.count_nonzero(c < 0))
    if neg:
        raise InputError(f"has {neg} negative values", **where)
    return c


#: Largest motion vector accepted, in frame diagonals: a longer one is a unit or scale error, not motion.
MAX_MOTION_DIAGONALS = 64.0


def validate_motion_vectors(vectors: object, shape: tuple[int, int], *, file=None, frame=None,
                            field_name="motion_vectors") -> np.ndarray:
    """Check motion vectors (h, w, 2) in pixels for a frame of ``shape`` (H, W); returns float32.

    ``h <= H`` and ``w <= W`` (vectors may be rendered at a lower resolution). NaN marks a pixel without a
    vector and is legal; +-inf, and vectors longer than ``MAX_MOTION_DIAGONALS`` frame diagonals (a unit
    or scale error), are errors.
    """
    where = dict(file=file, frame=frame, field=field_name)
    v = np.asarray(vectors)
    if v.ndim != 3 or v.shape[2] != 2:
        raise InputError(f"must have shape (h, w, 2), got {v.shape}", **where)
    if not np.issubdtype(v.dtype, np.floating):
        raise InputError(f"must be a float array, got dtype {v.dtype}", **where)
    h, w = v.shape[:2]
    if not (1 <= h <= shape[0] and 1 <= w <= shape[1]):
        raise InputError(f"are {w}x{h}: must be at most the frame's {shape[1]}x{shape[0]} and not empty", **where)
    v = v.astype(np.float32, copy=False)
    inf = int(np.count_nonzero(np.isinf(v)))
    if inf:
        raise InputError(f"has {inf} infinite values (NaN marks a pixel without a vector; inf is an error)", **where)
    limit = MAX_MOTION_DIAGONALS * float(np.hypot(*shape))
    longest = float(np.nanmax(np.abs(v))) if np.isfinite(v).any() else 0.0
    if longest > limit:
        raise InputError(f"has a component of {longest:.4g} px, over {MAX_MOTION_DIAGONALS:g} frame diagonals "
                         f"({limit:.0f} px): wrong units or scale?", **where)
    return v


def validate_object_ids(ids: object, shape: tuple[int, int], *, file=None, frame=None,
                        field_name="object_id") -> np.ndarray:
    """Check an object id buffer (H, W) of a frame of ``shape``: non-negative integers (0: static background),
    integer or integral float dtype, at most int32's maximum; returns int32."""
    where = dict(file=file, frame=frame, field=field_name)
    ids = np.asarray(ids)
    if ids.shape != shape:
        raise InputError(f"must have shape {shape}, got {ids.shape}", **where)
    if ids.dtype.kind not in "iuf" or (ids.dtype.kind == "f" and not np.all(np.isfinite(ids))):
        raise InputError(f"must hold non-negative integers, got dtype {ids.dtype}", **where)
    if np.any(ids < 0) or np.any(ids != np.round(ids)) or np.any(ids > np.iinfo(np.int32).max):
        raise InputError("must hold non-negative integers (0: static background)", **where)
    return ids.astype(np.int32)


def validate_frame(frame: Frame, *, file=None) -> Frame:
    """Validate every array of a frame against the others; returns a frame with normalised dtypes."""
    idx = frame.index
    depth = validate_depth(frame.depth, file=file, frame=idx, field_name="Z")
    shape = depth.shape
    color = validate_color(frame.color, shape, file=file, frame=idx, field_name="RGB")
    camera = Camera(validate_intrinsics(frame.camera.intrinsics, file=file, frame=idx),
                    validate_pose(frame.camera.world_to_camera, file=file, frame=idx))
    if not np.isfinite(frame.time):
        raise InputError(f"time must be finite, got {frame.time}", file=file, frame=idx, field="time")
    out = replace(frame, color=color, depth=depth, camera=camera)
    for name, channels in (("flow", 2), ("object_flow", 2)):
        value = getattr(frame, name)
        if value is None:
            continue
        v = np.asarray(value, dtype=np.float32)
        if v.shape != shape + (channels,):
            raise InputError(f"must have shape {shape + (channels,)}, got {v.shape}", file=file, frame=idx, field=name)
        if not np.all(np.isfinite(v)):
            raise InputError("has non-finite values", file=file, frame=idx, field=name)
        out = replace(out, **{name: v})
    if frame.motion_vectors is not None:
        out = replace(out, motion_vectors=validate_motion_vectors(frame.motion_vectors, shape, file=file, frame=idx))
    if frame.object_id is not None:
        out = replace(out, object_id=validate_object_ids(frame.object_id, shape, file=file, frame=idx))
    if frame.moving is not None:
        m = np.asarray(frame.moving)
        if m.shape != shape:
            raise InputError(f"must have shape {shape}, got {m.shape}", file=file, frame=idx, field="moving")
        if not np.all(np.isin(m, (0, 1))):
            raise InputError("must hold only 0 and 1", file=file, frame=idx, field="moving")
        out = replace(out, moving=m.astype(bool))
    return out
