"""Camera conventions of game engines (OpenGL, Unity, Unreal, Godot) -> OpenCV cameras; the conventions
of the whole ``engine.conventions`` package.

Interleave's own convention (the one every other module assumes, see ``engine/core/frames.py``):

- Camera axes are OpenCV's: x right, y down, z forward (into the scene). Right-handed.
- ``world_to_camera`` is a rigid 4x4 matrix (rotation with det +1, no scale) mapping world points,
  as column vectors, to camera points. The world frame is therefore right-handed.
- ``intrinsics`` is ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` in pixels; a camera point
  (x, y, z) lands at continuous image coordinates ``(fx x / z + cx, fy y / z + cy)`` whose origin is
  the top-left *corner* of the image, so pixel (u, v) (column, row) has its centre at
  (u + 0.5, v + 0.5). Image row 0 is the top row.
- Depth is planar (camera z), strictly positive, ``+inf`` for "no surface".

Game engines differ from this in handedness, up axis, units, the direction the camera looks, the
clip-space depth range, the direction of NDC y and of depth (reversed-Z). This module converts, once:

==========  ===========  ===============================  ===========  ======================
engine      world        camera looks along               units        usual depth buffer
==========  ===========  ===============================  ===========  ======================
OpenGL      right, y up  -z (x right, y up)               any          "opengl"
Unity       left, y up   local +z; -z in worldToCamera    metres       "reversed" (D3D/Metal)
Unreal      left, z up   +x (y right, z up)               centimetres  "reversed_infinite"
Godot 4     right, y up  -z (x right, y up)               metres       "reversed" (4.3+)
==========  ===========  ===============================  ===========  ======================

Every converter returns ``(intrinsics, world_to_camera)`` (float64) expressed in a right-handed
world obtained from the engine's world by a documented change of basis ``flip`` (a 4x4 matrix B,
``x_interleave = B @ x_engine``, after scaling engine units by ``meters_per_unit``). Because every
camera of one engine goes through the same B, relative poses between cameras are preserved.

Image coordinates from NDC (all engines): NDC x = -1 is the left edge, +1 the right edge; with NDC
y up (OpenGL, D3D, Unity, Unreal, Godot's API matrices) NDC y = +1 is the *top* edge, i.e. image row
0, and ``v = (1 - ndc_y) / 2 * H``; with NDC y down (Vulkan-style matrices, ``ndc_y_down=True``)
``v = (1 + ndc_y) / 2 * H``. Images read back bottom-up (``glReadPixels``, Unity ``Texture2D``)
must have their rows flipped before they reach Interleave.

All functions are pure: they never modify their inputs and return new float64 arrays.
"""
from __future__ import annotations

import math
from typing import Literal, Optional, Sequence

import numpy as np

from engine.conventions.values import frame_size, near_far, positive
from engine.core.checks import numeric_array
from engine.core.errors import InputError
from engine.core.frames import RIGID_TOLERANCE, rigid_inverse, validate_intrinsics, validate_pose

#: Clip-space z ranges understood by :func:`decode_from_projection` and
#: :func:`projection_from_intrinsics`: OpenGL's NDC z in [-1, 1], D3D/Vulkan/Metal's in [0, 1].
CLIP_RANGES = ("minus_one_to_one", "zero_to_one")

#: No change of basis: the engine world is already right-handed (OpenGL, Godot).
IDENTITY_FLIP = np.eye(4)

#: Unity's left-handed world (x right, y up, z forward) -> right-handed (x right, y up, z backward),
#: i.e. z is negated. This is the world OpenGL-style tools (and Unity's own worldToCameraMatrix
#: composed with it) use.
UNITY_FLIP = np.diag([1.0, 1.0, -1.0, 1.0])

#: Unreal's left-handed world (x forward, y right, z up) -> right-handed (x forward, y LEFT, z up),
#: i.e. y is negated (the ROS / REP-103 axes). Applied after scaling centimetres to metres.
UNREAL_FLIP = np.diag([1.0, -1.0, 1.0, 1.0])

#: OpenGL eye space (x right, y up, looks down -z) <-> OpenCV camera (x right, y down, z forward): y and z
#: flip; its own inverse. The one definition of this flip (OpenGL, Blender, NeRF-synthetic cameras, GL clip
#: matrices of OpenCV cameras); ``OPENGL_EYE_TO_OPENCV`` is its 3x3 block.
OPENGL_TO_OPENCV = np.diag([1.0, -1.0, -1.0, 1.0])
OPENGL_EYE_TO_OPENCV = np.diag([1.0, -1.0, -1.0])

#: Unity camera local space (left-handed: x right, y up, z forward) -> OpenCV camera. det = -1.
UNITY_LOCAL_TO_OPENCV = np.diag([1.0, -1.0, 1.0])

#: Unreal camera local space (left-handed: x forward, y right, z up) -> OpenCV camera. det = -1.
#: OpenCV x = Unreal y, OpenCV y = -Unreal z, OpenCV z = Unreal x.
UNREAL_LOCAL_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [1.0, 0.0, 0.0]])

_ZERO_TOLERANCE = 1e-6  # relative size under which a projection entry counts as zero


# --------------------------------------------------------------------------------------------
# Small validators (one check per public entry point)
# --------------------------------------------------------------------------------------------

def _matrix(value: object, shape: tuple[int, ...], field: str) -> np.ndarray:
    m = numeric_array(value, copy=True, field=field)  # a copy: callers' arrays are never touched
    if m.shape != shape:
        raise InputError(f"must have shape {shape}, got {m.shape}", field=field)
    if not np.all(np.isfinite(m)):
        raise InputError(f"has {int(np.count_nonzero(~np.isfinite(m)))} non-finite entries", field=field)
    return m






def _rotation(r: np.ndarray, field: str, *, proper: bool) -> np.ndarray:
    """Check that a 3x3 block is orthonormal (det +1 when ``proper``, else +-1)."""
    err = float(np.max(np.abs(r.T @ r - np.eye(3))))
    det = float(np.linalg.det(r))
    if err > RIGID_TOLERANCE:
        raise InputError(f"rotation block is not orthonormal (|R^T R - I| = {err:.3g}): the matrix has "
                         "scale or shear; pass an unscaled camera transform", field=field)
    if proper and det < 0:
        raise InputError(f"rotation block has det {det:.6g} (a reflection)", field=field)
    return r


def _flip(flip: object, default: np.ndarray) -> np.ndarray:
    if flip is None:
        return default.copy()
    b = _matrix(flip, (4, 4), "flip")
    if not np.allclose(b[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"last row must be [0, 0, 0, 1], got {b[3].tolist()}", field="flip")
    _rotation(b[:3, :3], "flip", proper=False)
    return b


def _finish(camera_from_engine: np.ndarray, flip: np.ndarray, engine: str) -> np.ndarray:
    """world_to_camera = camera_from_engine_world @ flip^-1, checked to be rigid (det +1).

    ``camera_from_engine`` maps (scaled) engine-world points to OpenCV camera points; ``flip`` maps
    (scaled) engine-world points to the right-handed output world.
    """
    world_to_camera = camera_from_engine @ rigid_inverse(flip)
    if np.linalg.det(world_to_camera[:3, :3]) < 0:
        raise InputError(
            f"the {engine} world and the chosen `flip` differ in handedness, so world_to_camera would be a "
            "reflection; pass a `flip` with det -1 (e.g. UNITY_FLIP / UNREAL_FLIP) for a left-handed world, "
            "or det +1 for a right-handed one", field="flip")
    return validate_pose(world_to_camera)


def _rigid_camera(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = rotation
    out[:3, 3] = translation
    return out


def opengl_to_opencv_world_to_camera(camera_to_world_gl: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera (4, 4) from an OpenGL/Blender camera-to-world matrix (y up, looking down -z).

    ``camera_to_world_cv = camera_to_world_gl @ OPENGL_TO_OPENCV`` (flip the camera's y and z axes), then the
    rigid inverse.
    """
    return rigid_inverse(np.asarray(camera_to_world_gl, dtype=np.float64) @ OPENGL_TO_OPENCV)


def look_at(eye: np.ndarray, target: np.ndarray, up: Sequence[float] = (0.0, 0.0, 1.0)) -> np.ndarray:
    """OpenCV rotation (3, 3) of a camera at ``eye`` facing ``target`` without roll: world -> camera rows
    x right, y down, z forward, with the world's ``up`` direction (default z up) pointing up in the image.
    Looking along ``up`` itself, the right vector is taken against the world y axis instead.

    >>> look_at(np.zeros(3), np.array([0.0, 1.0, 0.0])).tolist()
    [[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]]
    """
    forward = np.asarray(target, np.float64) - np.asarray(eye, np.float64)
    forward = forward / np.linalg.norm(forward)
    right = np.cross(forward, np.asarray(up, np.float64))
    if np.linalg.norm(right) < 1e-6:  # looking straight along up: any right vector will do
        right = np.cross(forward, np.array([0.0, 1.0, 0.0]))
    right = right / np.linalg.norm(right)
    down = np.cross(forward, right)
    return np.stack([right, down, forward])


# --------------------------------------------------------------------------------------------
# Projection matrices and intrinsics
# --------------------------------------------------------------------------------------------

def _perspective_problem(p: np.ndarray) -> Optional[str]:
    """Why ``p`` is not a -z-looking perspective matrix (K-compatible, depth independent of x, y), or None."""
    scale = max(abs(p[0, 0]), abs(p[1, 1]), 1e-300)
    tol = _ZERO_TOLERANCE * scale
    last = p[3]
    if abs(last[0]) > tol or abs(last[1]) > tol or abs(last[3]) > tol or abs(last[2]) <= tol:
        return f"is not a perspective projection: its last row must be [0, 0, -1, 0] up to scale, got {last.tolist()}"
    if last[2] > 0:
        return ("has last row [0, 0, +1, 0]: a camera looking down +z (left-handed D3D style); "
                "this converter expects the OpenGL/Unity/Godot style that looks down -z")
    if abs(p[0, 1]) > tol or abs(p[1, 0]) > tol:
        return "has skew terms (projection[0,1] or [1,0] non-zero), which K cannot represent"
    if abs(p[0, 3]) > tol or abs(p[1, 3]) > tol:
        return "has translation terms in x or y (projection[0,3] or [1,3] non-zero)"
    if abs(p[2, 0]) > tol or abs(p[2, 1]) > tol:
        return "has an oblique near plane (projection[2,0] or [2,1] non-zero); depth would depend on x and y"
    return None


def perspective_matrix(projection: object, field: str = "projection") -> np.ndarray:
    """A right-handed, -z-looking perspective matrix normalised so that its last row is [0, 0, -1, 0]."""
    p = _matrix(projection, (4, 4), field)
    problem = _perspective_problem(p)
    if problem is not None:
        if _perspective_problem(p.T) is None:
            problem += " (it looks transposed: pass the math matrix, clip = P @ eye, not a column-major buffer)"
        raise InputError(problem, field=field)
    return p / -p[3, 2]


def intrinsics_from_projection(projection: object, width: int, height: int, *,
                               ndc_y_down: bool = False) -> np.ndarray:
    """OpenCV intrinsics K (3, 3) from an OpenGL-style perspective projection and the viewport size.

    ``projection`` is the 4x4 math matrix (``clip = projection @ eye``, column vectors) of a camera whose
    eye space is x right, y up, looking down -z, so its last row is ``[0, 0, -1, 0]`` (any positive
    multiple is accepted). The clip z range ([-1, 1] or [0, 1], standard or reversed) does not matter
    here. Off-centre projections (``projection[0, 2]``, ``projection[1, 2]`` non-zero, e.g. glFrustum
    with l != -r, TAA jitter, lens shift) move the principal point.

    With an OpenCV camera point (x, y, z) = (x_eye, -y_eye, -z_eye):
    ``ndc_x = P00 x / z - P02`` and ``ndc_y = -P11 y / z - P12``; with window pixels
    ``u = (1 + ndc_x) W / 2`` and ``v = (1 - ndc_y) H / 2`` (NDC y up, row 0 at the top):

        fx = P00 W / 2,  cx = (1 - P02) W / 2,  fy = P11 H / 2,  cy = (1 + P12) H / 2.

    With ``ndc_y_down=True`` (Vulkan-style matrices whose NDC y points down, so P11 < 0 and
    ``v = (1 + ndc_y) H / 2``): ``fy = -P11 H / 2``, ``cy = (1 - P12) H / 2``.

    Example:
        >>> p = projection_from_intrinsics([[500, 0, 320], [0, 500, 240], [0, 0, 1]], 640, 480, 0.1, 100)
        >>> intrinsics_from_projection(p, 640, 480).round(6).tolist()
        [[500.0, 0.0, 320.0], [0.0, 500.0, 240.0], [0.0, 0.0, 1.0]]
    """
    w, h = frame_size(width, height)
    p = perspective_matrix(projection)
    if ndc_y_down:
        if p[1, 1] > 0:
            raise InputError("projection[1,1] > 0 with ndc_y_down=True: the image would be upside down; "
                             "NDC-y-down (Vulkan-style) matrices have projection[1,1] < 0", field="projection")
        fy, cy = -p[1, 1] * h / 2.0, (1.0 - p[1, 2]) * h / 2.0
    else:
        if p[1, 1] < 0:
            raise InputError("projection[1,1] < 0: the matrix flips y (Vulkan-style, or a Unity render-texture "
                             "GPU matrix); pass ndc_y_down=True if NDC y = -1 is image row 0",
                             field="projection")
        fy, cy = p[1, 1] * h / 2.0, (1.0 + p[1, 2]) * h / 2.0
    fx, cx = p[0, 0] * w / 2.0, (1.0 - p[0, 2]) * w / 2.0
    return validate_intrinsics([[fx, 0.0, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]], field_name="projection")


def intrinsics_from_fov(width: int, height: int, *, vertical_fov_deg: Optional[float] = None,
                        horizontal_fov_deg: Optional[float] = None) -> np.ndarray:
    """Centred pinhole intrinsics with square pixels from one full field-of-view angle, in degrees.

    ``fy = (H / 2) / tan(vfov / 2)`` or ``fx = (W / 2) / tan(hfov / 2)``; the other focal length equals
    it; ``cx = W / 2``, ``cy = H / 2`` (the image centre in the +0.5 pixel-centre convention).
    Give exactly one of the two angles.

    Example:
        >>> intrinsics_from_fov(640, 480, horizontal_fov_deg=90.0).round(6).tolist()
        [[320.0, 0.0, 320.0], [0.0, 320.0, 240.0], [0.0, 0.0, 1.0]]
    """
    w, h = frame_size(width, height)
    if (vertical_fov_deg is None) == (horizontal_fov_deg is None):
        raise InputError("give exactly one of vertical_fov_deg and horizontal_fov_deg", field="fov")
    name = "vertical_fov_deg" if vertical_fov_deg is not None else "horizontal_fov_deg"
    fov = positive(vertical_fov_deg if vertical_fov_deg is not None else horizontal_fov_deg, name)
    if fov >= 180.0:
        raise InputError(f"must be below 180 degrees, got {fov}", field=name)
    half_extent = h / 2.0 if vertical_fov_deg is not None else w / 2.0
    f = half_extent / math.tan(math.radians(fov) / 2.0)
    return np.array([[f, 0.0, w / 2.0], [0.0, f, h / 2.0], [0.0, 0.0, 1.0]])


def _window_depth_coefficients(near: float, far: float, reversed_z: bool) -> tuple[float, float]:
    """(A, B) with window depth d = A + B / z."""
    ratio = near / far  # 0 for an infinite far plane
    if reversed_z:
        return -ratio / (1.0 - ratio), near / (1.0 - ratio)
    return 1.0 / (1.0 - ratio), -near / (1.0 - ratio)


def projection_from_intrinsics(intrinsics: object, width: int, height: int, near: float, far: float, *,
                               clip_range: Literal["minus_one_to_one", "zero_to_one"] = "minus_one_to_one",
                               reversed_z: bool = False, ndc_y_down: bool = False) -> np.ndarray:
    """The OpenGL-style 4x4 projection (eye x right, y up, looking down -z) that renders K exactly.

    The inverse of :func:`intrinsics_from_projection`. ``far`` may be ``inf`` (infinite far plane).
    ``clip_range`` is the NDC z range of the API ("minus_one_to_one" for OpenGL, "zero_to_one" for
    D3D/Vulkan/Metal); the window depth it produces is that of :func:`encode_depth_buffer` with
    convention "opengl"/"d3d" (standard) or "reversed" (``reversed_z=True``), infinite when far=inf.
    """
    k = validate_intrinsics(intrinsics)
    w, h = frame_size(width, height)
    near, far = near_far(near, far, allow_inf=True)
    if clip_range not in CLIP_RANGES:
        raise InputError(f"must be one of {CLIP_RANGES}, got {clip_range!r}", field="clip_range")
    a_win, b_win = _window_depth_coefficients(near, far, reversed_z)
    if clip_range == "zero_to_one":
        a_ndc, b_ndc = a_win, b_win
    else:
        a_ndc, b_ndc = 2.0 * a_win - 1.0, 2.0 * b_win
    fx, fy, cx, cy = k[0, 0], k[1, 1], k[0, 2], k[1, 2]
    p = np.zeros((4, 4))
    p[0, 0], p[0, 2] = 2.0 * fx / w, 1.0 - 2.0 * cx / w
    if ndc_y_down:
        p[1, 1], p[1, 2] = -2.0 * fy / h, 1.0 - 2.0 * cy / h
    else:
        p[1, 1], p[1, 2] = 2.0 * fy / h, 2.0 * cy / h - 1.0
    p[2, 2], p[2, 3] = -a_ndc, b_ndc  # ndc_z = -P22 + P23 / z  with  z = -z_eye = w_clip
    p[3, 2] = -1.0
    return p


# --------------------------------------------------------------------------------------------
# Rotations
# --------------------------------------------------------------------------------------------

def unreal_rotation_matrix(pitch: float, yaw: float, roll: float) -> np.ndarray:
    """Unreal's FRotationMatrix(FRotator(Pitch, Yaw, Roll)) (degrees), as a 3x3 numpy matrix.

    Unreal uses row vectors: row 0 is the rotated forward (X) axis, row 1 right (Y), row 2 up (Z),
    all in Unreal world coordinates (x forward, y right, z up, left-handed). Roll is applied first
    (about X), then pitch (about Y; positive looks up), then yaw (about Z; positive turns from +X
    towards +Y). The column-vector camera-to-world rotation is the transpose.
    """
    sp, cp = math.sin(math.radians(pitch)), math.cos(math.radians(pitch))
    sy, cy = math.sin(math.radians(yaw)), math.cos(math.radians(yaw))
    sr, cr = math.sin(math.radians(roll)), math.cos(math.radians(roll))
    return np.array([
        [cp * cy, cp * sy, sp],
        [sr * sp * cy - cr * sy, sr * sp * sy + cr * cy, -sr * cp],
        [-(cr * sp * cy + sr * sy), cy * sr - cr * sp * sy, cr * cp],
    ])


def quaternion_to_matrix(quaternion: Sequence[float], *, field: str = "rotation") -> np.ndarray:
    """3x3 rotation matrix (column vectors) of a unit quaternion given as (x, y, z, w), Unity's order.

    The numeric formula does not depend on handedness: Unity's left-handed ``Matrix4x4.Rotate(q)``
    yields the same numbers. Quaternions further than 1e-3 from unit norm are an InputError.
    """
    q = _matrix(quaternion, (4,), field)
    norm = float(np.linalg.norm(q))
    if abs(norm - 1.0) > 1e-3:
        raise InputError(f"must be a unit quaternion (x, y, z, w), got norm {norm:.6g}", field=field)
    x, y, z, w = q / norm
    return np.array([
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ])


# --------------------------------------------------------------------------------------------
# Engine camera converters
# --------------------------------------------------------------------------------------------

def from_opengl(width: int, height: int, *, view: object, projection: object, ndc_y_down: bool = False,
                flip: object = None, meters_per_unit: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(intrinsics, world_to_camera)`` from an OpenGL-style view and projection matrix.

    Args:
        width, height: viewport size in pixels.
        view: 4x4 world -> eye matrix (column vectors); eye space is right-handed, x right, y up, the
            camera looks down -z. A view of a left-handed world (det of its rotation -1, e.g. Unity's
            ``worldToCameraMatrix``) needs a ``flip`` with det -1.
        projection: 4x4 perspective matrix, last row [0, 0, -1, 0]; OpenGL clip z in [-1, 1] or
            D3D/Vulkan/reversed clip z in [0, 1] (irrelevant for K). NDC y up and image row 0 at the
            top unless ``ndc_y_down`` (see :func:`intrinsics_from_projection`).
        ndc_y_down: the engine's NDC y points down (Vulkan-style matrices, projection[1,1] < 0).
        flip: 4x4 change of basis B from the (scaled) engine world to the output world,
            ``x_out = B @ x_engine``; orthonormal, det +-1, translation in metres. Default identity.
        meters_per_unit: engine length unit in metres; the output world is in metres.

    Returns:
        ``(K, world_to_camera)``: K (3, 3) and a rigid (4, 4), float64, OpenCV axes,
        ``world_to_camera = diag(1, -1, -1, 1) @ view_scaled @ B^-1``.
    """
    w, h = frame_size(width, height)
    scale = positive(meters_per_unit, "meters_per_unit")
    v = _matrix(view, (4, 4), "view")
    if not np.allclose(v[3], [0.0, 0.0, 0.0, 1.0]):
        raise InputError(f"last row must be [0, 0, 0, 1], got {v[3].tolist()}", field="view")
    _rotation(v[:3, :3], "view", proper=False)
    k = intrinsics_from_projection(projection, w, h, ndc_y_down=ndc_y_down)
    camera_from_engine = _rigid_camera(OPENGL_EYE_TO_OPENCV @ v[:3, :3], OPENGL_EYE_TO_OPENCV @ (scale * v[:3, 3]))
    return k, _finish(camera_from_engine, _flip(flip, IDENTITY_FLIP), "OpenGL")


def from_unity(width: int, height: int, *, position: object = None, rotation: object = None,
               matrix: object = None, matrix_is_world_to_camera: bool = False,
               vertical_fov_deg: Optional[float] = None, projection: object = None, ndc_y_down: bool = False,
               flip: object = None, meters_per_unit: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(intrinsics, world_to_camera)`` from a Unity camera.

    Unity's world is left-handed: x right, y up, z forward; a camera looks along its local +z
    (``transform.forward``) with local +y up. Give the pose as either
    ``position`` (3,) + ``rotation`` (quaternion x, y, z, w) of ``camera.transform``, or
    ``matrix``: ``transform.localToWorldMatrix`` (4x4, column vectors, no scale), or, with
    ``matrix_is_world_to_camera=True``, ``camera.worldToCameraMatrix`` (OpenGL convention: right-handed
    eye space looking down -z, ``= diag(1, 1, -1, 1) @ worldToLocal``).

    Give the lens as either ``vertical_fov_deg`` (``Camera.fieldOfView``, centred, square pixels) or
    ``projection`` (``Camera.projectionMatrix``, OpenGL-style; handles lens shift / off-centre; a
    ``GL.GetGPUProjectionMatrix`` result works too, with ``ndc_y_down=True`` if it flips y).

    The default ``flip`` is :data:`UNITY_FLIP` (negate z): the output world is right-handed with
    x right, y up, z backward, in metres (``meters_per_unit`` 1). Image row 0 is the top row (Unity
    readbacks into Texture2D are bottom-up: flip them).
    """
    w, h = frame_size(width, height)
    scale = positive(meters_per_unit, "meters_per_unit")
    if (matrix is None) == (position is None and rotation is None):
        raise InputError("give either position + rotation or matrix", field="pose")
    if matrix is None:
        if position is None or rotation is None:
            raise InputError("position and rotation must be given together", field="pose")
        r = quaternion_to_matrix(rotation)
        t = _matrix(position, (3,), "position")
        camera_from_engine = _rigid_camera(UNITY_LOCAL_TO_OPENCV @ r.T, -UNITY_LOCAL_TO_OPENCV @ r.T @ (scale * t))
    else:
        m = _matrix(matrix, (4, 4), "matrix")
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0]):
            raise InputError(f"last row must be [0, 0, 0, 1], got {m[3].tolist()}", field="matrix")
        if matrix_is_world_to_camera:
            _rotation(m[:3, :3], "matrix", proper=False)
            camera_from_engine = _rigid_camera(OPENGL_EYE_TO_OPENCV @ m[:3, :3],
                                               OPENGL_EYE_TO_OPENCV @ (scale * m[:3, 3]))
        else:
            r = _rotation(m[:3, :3], "matrix", proper=True)
            camera_from_engine = _rigid_camera(UNITY_LOCAL_TO_OPENCV @ r.T,
                                               -UNITY_LOCAL_TO_OPENCV @ r.T @ (scale * m[:3, 3]))
    k = _lens(w, h, vertical_fov_deg, None, projection, ndc_y_down, "vertical_fov_deg")
    return k, _finish(camera_from_engine, _flip(flip, UNITY_FLIP), "Unity")


def from_unreal(width: int, height: int, *, location: object = None, rotation: object = None,
                transform: object = None, horizontal_fov_deg: float, meters_per_unit: float = 0.01,
                flip: object = None) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(intrinsics, world_to_camera)`` from an Unreal Engine camera.

    Unreal's world is left-handed: x forward, y right, z up, in centimetres; a camera looks along its
    local +x with local +y right and +z up. Give the pose as either ``location`` (x, y, z) in world
    units + ``rotation`` = (pitch, yaw, roll) in degrees, the FRotator order and rotation order of
    :func:`unreal_rotation_matrix`, or ``transform``: the camera's 4x4 FMatrix as Unreal stores it
    (row vectors, translation in the bottom row, e.g. ``FTransform::ToMatrixNoScale()``).
    ``horizontal_fov_deg`` is the full horizontal FOV (``FMinimalViewInfo::FOV``, aspect ratio axis
    constraint "maintain X FOV"); pixels are square and the principal point is centred.

    World units are scaled by ``meters_per_unit`` (default 0.01: cm -> m); the default ``flip`` is
    :data:`UNREAL_FLIP` so the output world is right-handed x forward, y left, z up, in metres.
    Unreal's depth buffer is reversed-Z with an infinite far plane: decode it with
    ``decode_depth_buffer(buf, near_cm * meters_per_unit, None, convention="reversed_infinite")``.
    """
    w, h = frame_size(width, height)
    scale = positive(meters_per_unit, "meters_per_unit")
    if (transform is None) == (location is None and rotation is None):
        raise InputError("give either location + rotation or transform", field="pose")
    if transform is None:
        if location is None or rotation is None:
            raise InputError("location and rotation must be given together", field="pose")
        angles = _matrix(rotation, (3,), "rotation")
        rows = unreal_rotation_matrix(*angles)
        origin = _matrix(location, (3,), "location")
    else:
        m = _matrix(transform, (4, 4), "transform")
        if not np.allclose(m[:, 3], [0.0, 0.0, 0.0, 1.0]):
            raise InputError("last column must be [0, 0, 0, 1]: expected Unreal's FMatrix layout (row vectors, "
                             "translation in the bottom row); pass transform.T for a column-vector matrix",
                             field="transform")
        rows = _rotation(m[:3, :3], "transform", proper=True)
        origin = m[3, :3]
    # rows = camera axes (forward, right, up) in world; camera_from_world (column vectors) = rows @ (x - o).
    camera_from_engine = _rigid_camera(UNREAL_LOCAL_TO_OPENCV @ rows, -UNREAL_LOCAL_TO_OPENCV @ rows @ (scale * origin))
    k = intrinsics_from_fov(w, h, horizontal_fov_deg=horizontal_fov_deg)
    return k, _finish(camera_from_engine, _flip(flip, UNREAL_FLIP), "Unreal")


def from_godot(width: int, height: int, *, basis: object, origin: object, fov_deg: Optional[float] = None,
               keep_aspect: Literal["height", "width"] = "height", projection: object = None,
               ndc_y_down: bool = False, flip: object = None,
               meters_per_unit: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """OpenCV ``(intrinsics, world_to_camera)`` from a Godot 4 Camera3D.

    Godot's world is right-handed, y up; a camera looks down its local -z with +y up (OpenGL-like).
    ``basis`` (3x3) and ``origin`` (3,) are the camera's ``global_transform`` (camera-to-world): the
    basis *columns* are ``basis.x``, ``basis.y``, ``basis.z`` (``np.column_stack([b.x, b.y, b.z])``).

    Give the lens as ``fov_deg`` (``Camera3D.fov``; vertical with ``keep_aspect="height"``, Godot's
    default KEEP_HEIGHT, horizontal with ``"width"``) or as ``projection``
    (``Camera3D.get_camera_projection()``, OpenGL-style). Godot 4.3+ renders reversed-Z with a finite
    far plane: decode with ``convention="reversed"``; Godot 4.0-4.2 with ``"d3d"``.
    Default ``flip``: identity (the output world is Godot's).
    """
    w, h = frame_size(width, height)
    scale = positive(meters_per_unit, "meters_per_unit")
    r = _rotation(_matrix(basis, (3, 3), "basis"), "basis", proper=True)
    o = _matrix(origin, (3,), "origin")
    camera_from_engine = _rigid_camera(OPENGL_EYE_TO_OPENCV @ r.T, -OPENGL_EYE_TO_OPENCV @ r.T @ (scale * o))
    if keep_aspect not in ("height", "width"):
        raise InputError(f"must be 'height' or 'width', got {keep_aspect!r}", field="keep_aspect")
    if keep_aspect == "height":
        k = _lens(w, h, fov_deg, None, projection, ndc_y_down, "fov_deg")
    else:
        k = _lens(w, h, None, fov_deg, projection, ndc_y_down, "fov_deg")
    return k, _finish(camera_from_engine, _flip(flip, IDENTITY_FLIP), "Godot")


def _lens(w: int, h: int, vfov: Optional[float], hfov: Optional[float], projection: object,
          ndc_y_down: bool, name: str) -> np.ndarray:
    if (projection is None) == (vfov is None and hfov is None):
        raise InputError(f"give either {name} or projection", field="lens")
    if projection is not None:
        return intrinsics_from_projection(projection, w, h, ndc_y_down=ndc_y_down)
    fov = positive(vfov if vfov is not None else hfov, name)
    if fov >= 180.0:
        raise InputError(f"must be below 180 degrees, got {fov}", field=name)
    return intrinsics_from_fov(w, h, vertical_fov_deg=vfov, horizontal_fov_deg=hfov)


