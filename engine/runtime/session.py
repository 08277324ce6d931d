"""The game-engine integration API: a session that a game loop feeds without knowing the method.

A game renders every k-th frame. For each rendered frame it calls ``submit(color, depth, view,
projection, time)``; for each frame in between it calls ``predict(view, projection, time)`` and shows
the returned colour. ``reset()`` clears the history (level load, camera cut the game knows about).

Inputs are what the engine has, in the engine's own conventions (``SessionConfig.engine``); the session
converts them once, with the converters of ``engine/conventions/cameras.py``, into Interleave's convention
(``engine/core/frames.py``: OpenCV camera axes, rigid ``world_to_camera``, pixel centres at +0.5, planar
depth in metres with ``+inf`` for sky, linear-light Rec.709 colour):

==========  ===============================================  ==============================================
engine      ``view``                                         ``projection``
==========  ===============================================  ==============================================
opencv      ``world_to_camera`` (4, 4), OpenCV axes          K (3, 3), or (4, 4) with K in the top-left
opengl      world -> eye matrix (4, 4), eye looks down -z    perspective matrix (4, 4), ``clip = P @ eye``
unity       ``camera.worldToCameraMatrix``                   ``camera.projectionMatrix`` (or the GPU matrix
                                                             with ``ndc_y_down`` if it flips y)
godot       view matrix: ``camera.get_camera_transform()``   ``camera.get_camera_projection()``
            ``.affine_inverse()`` (world -> camera)
unreal      the camera's FMatrix (row vectors, translation   full horizontal FOV in degrees, or the
            in the bottom row, ``FRotationTranslationMatrix  FMatrix of ``FReversedZPerspectiveMatrix`` /
            (Rotation, Location)``), or 6 numbers            ``FPerspectiveMatrix`` (row vectors, "maintain
            (x, y, z, pitch, yaw, roll) in cm and degrees    X FOV", centred)
==========  ===============================================  ==============================================

Matrices are math matrices indexed ``[row, col]`` (``M[0, 3]`` is the x translation of a column-vector
matrix). Unity's ``Matrix4x4``, GLM and Godot store columns first in memory: pass ``M.T`` of a buffer
read as rows (the server has a flag for it). The output world is each converter's default (right-handed,
metres); every pose of one session goes through the same conversion, so the predicted frames are those
of the engine's cameras.

Depth is the engine's depth buffer in ``SessionConfig.depth_convention`` (decoded with
:func:`engine.conventions.decode_depth_buffer`, ``near``/``far`` in engine units); ``"linear"`` means
planar depth in engine units (``+inf`` or values >= ``far`` = sky). Colour is linear float, sRGB-encoded
float or sRGB-encoded uint8 (``color_in``), with 3 or 4 channels (alpha is ignored), row 0 at the top
unless ``flip_rows`` (bottom-up readbacks such as ``glReadPixels``: inputs are flipped on submit and
outputs flipped back, so the caller sees its own row order everywhere).

Motion vectors (optional, ``submit(..., motion_vectors=, motion_valid=)``) are the engine's own buffer in
its own conventions (``SessionConfig.motion_*``, with a default per engine); the session converts them into
``Frame.motion_vectors``: ``engine/runtime/motion.py`` has the conventions of each engine, with their
sources, and of the FSR / DLSS buffers.

Vectors point into the previous submitted frame, so a frame whose history was just reset (the first
frame, after ``reset()``, a camera cut, time going backwards) enters the history without vectors: they
would point into a frame the predictor does not have (``stats["motion_vectors"]["dropped"]``).

``method="auto"`` picks, per submitted frame, ``mvec`` (the renderer's motion vectors) when the frame
enters the history with motion vectors and ``flow2d`` when it does not (``engine.predict.resolve_auto``);
the choice can change at any submit (both keep the same two-frame history), and
``SessionPrediction.method`` says which one predicted.

Hard cases, and what the session does:

- **Camera cut**: a submitted frame whose pose differs from the previous one by more than
  ``cut_rotation_deg`` or by a camera-centre distance above ``cut_translation`` times the median scene
  depth resets the history (``SubmitResult.reset == "camera_cut"``); two-frame methods then fall back to
  ``reproject`` until a second frame arrives (``SessionPrediction.fallback == "history"``). A *predicted*
  pose that far from the newest frame is answered with that frame unchanged (``repeat``,
  ``fallback == "camera_cut"``): the game should render that frame instead. Never a smear across a cut.
- **Time going backwards / frames out of order**: a submit whose time is not after the newest frame's
  resets the history and starts again from that frame (``reset == "time_backwards"``), so a rewinding
  game and a late frame both give a valid, single-frame history; the predictor never sees a history out
  of time order. ``predict`` times are free (a two-frame method extrapolates to any time).
- **Resolution change**: a frame of another size is rejected with an :class:`~engine.core.errors.InputError`
  naming the frame and both sizes; ``reset(width=..., height=...)`` changes the size (and clears the
  history). A wrong-size buffer is far more often a bug than a deliberate change.
- **Bad values**: NaN or inf in colour, negative colour, NaN / out-of-range depth-buffer values,
  non-rigid or non-finite poses (each checked as the engine uses it: sRGB colour once decoded, where a
  finite 2e16 is inf; translations and depths once scaled by ``meters_per_unit``), infinite motion vectors
  (NaN is "no vector"), vectors longer than ``engine.core.frames.MAX_MOTION_DIAGONALS`` frame diagonals
  once converted (wrong units or scale), a vector buffer of the wrong shape, dtype or channel count or
  larger than the frame are rejected with an ``InputError`` naming the frame (the caller's ``frame``
  number, or the session's submit counter), the field and its time; the history is left as it was.
  Reversed-Z depth 0 (the far clear value) is sky (``+inf``), not an error.

Thread-safety: a ``Session`` may be called from several threads (e.g. ``submit`` from the render thread,
``predict`` from the present thread). Input conversion and validation run without a lock; one lock
serialises the history update + the predictor's ``prepare`` and each ``render``, so a ``predict`` that
arrives during a ``submit`` waits for it and then sees the new frame.

Zero-copy: ``submit`` keeps references to the caller's arrays, without copying, when nothing has to
change: colour ``float32`` (H, W, 3) or (H, W, 4) with ``color_in="linear"``, and depth ``float32``
(H, W) with ``depth_convention="linear"``, ``far=inf`` and a unit scale of 1 (the alpha channel is
dropped and ``flip_rows`` applied as views, also without a copy), and, on the ``gl`` backend, 8-bit colour
with ``color_in="srgb8"`` (its codes are uploaded as they are and decoded on the GPU). The session holds
them until they leave the history (at the next submit, or the one after for two-frame methods): do not
write into a submitted array before that, or pass ``copy=True``. Every other input (motion vectors always) is
converted into a new array. Returned arrays are always new.

Example:
    >>> import numpy as np
    >>> session = Session(SessionConfig(engine="opencv", width=8, height=6, method="reproject"))
    >>> K = [[8.0, 0, 4], [0, 8.0, 3], [0, 0, 1]]
    >>> _ = session.submit(np.full((6, 8, 3), 0.5, np.float32), np.full((6, 8), 2.0, np.float32), np.eye(4), K, 0.0)
    >>> out = session.predict(np.eye(4), K, 1 / 60)
    >>> out.color.shape, out.method, out.fallback
    ((6, 8, 3), 'reproject', None)
"""
from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field
from typing import Callable, Optional

import numpy as np

from engine import conventions
from engine.conventions import MOTION_DIRECTIONS, MOTION_UNITS
from engine.core.checks import numeric_array
from engine.core.config import option
from engine.core.errors import InputError, InterleaveError
from engine.core.frames import (Camera, Frame, rigid_inverse, validate_color, validate_depth, validate_intrinsics,
                                validate_object_ids, validate_pose)
from engine.geometry import encoding
from engine.geometry.backends import resolve_backend
from engine.predict import Prediction, Predictor, Repeat, Target, make_predictor, use_backend
from engine.predict.registry import AUTO, resolve_auto
from engine.runtime.motion import ENGINE_MOTION, MOTION_MISSING, MotionConventions, engine_vectors, with_camera_motion
from engine.runtime.stream import PredictionLoop

__all__ = ["ENGINES", "COLOR_SPACES", "MOTION_MISSING", "ENGINE_MOTION", "SessionConfig", "MotionConventions",
           "Session", "SubmitResult", "SessionPrediction", "SessionTexture", "NotReadyError", "engine_camera"]

#: Engines whose view / projection ``Session`` understands (see the module docstring for each one's form).
ENGINES = ("opencv", "opengl", "unity", "unreal", "godot")
#: Colour encodings: linear-light float, sRGB-encoded float in [0, 1], sRGB-encoded uint8.
COLOR_SPACES = ("linear", "srgb", "srgb8")
#: Depth conventions decoded with ``SessionConfig.near`` / ``far`` (checked against a 4x4 projection).
PLANE_DEPTH_CONVENTIONS = ("opengl", "d3d", "reversed", "infinite", "reversed_infinite")
#: Engines whose ``projection`` is an OpenGL-style 4x4 matrix (eye looking down -z).
GL_PROJECTION_ENGINES = ("opengl", "unity", "godot")
#: Default ``meters_per_unit`` of each engine (Unreal works in centimetres).
DEFAULT_METERS_PER_UNIT = {"opencv": 1.0, "opengl": 1.0, "unity": 1.0, "unreal": 0.01, "godot": 1.0}
#: Why the history was reset before a submitted frame.
RESET_REASONS = ("camera_cut", "time_backwards")
#: Why a prediction did not come from the configured method.
FALLBACK_REASONS = ("history", "camera_cut")
#: Every ``_CUT_STRIDE``-th pixel in each direction estimates the median scene depth of a frame.
_CUT_STRIDE = 4


class NotReadyError(InterleaveError):
    """``predict`` was called before any frame was submitted (or right after ``reset``)."""


@dataclass(frozen=True)
class SessionConfig:
    """How the game hands over its frames and what it wants back. Checked when created."""

    engine: str = option("opencv", f"engine whose view/projection matrices are passed: {', '.join(ENGINES)}")
    width: int = option(640, "frame width in pixels (the viewport the projection maps to)")
    height: int = option(360, "frame height in pixels")
    depth_convention: str = option("linear", "depth buffer convention, one of engine.conventions.DEPTH_CONVENTIONS; "
                                             "'linear' = planar depth in engine units")
    near: float = option(0.1, "near plane, engine units (decodes non-linear depth buffers)")
    far: float = option(math.inf, "far plane, engine units; inf for an infinite far plane")
    meters_per_unit: float = option(0.0, "engine length unit in metres; 0 = the engine's default (0.01 for "
                                         "Unreal, 1 otherwise)")
    ndc_y_down: bool = option(False, "the projection's NDC y points down (Vulkan-style, projection[1,1] < 0)")
    flip_rows: bool = option(False, "images are bottom-up (glReadPixels, Unity Texture2D): flip inputs and outputs")
    color_in: str = option("linear", f"encoding of submitted colour: {', '.join(COLOR_SPACES)}")
    color_out: str = option("linear", f"encoding of predicted colour: {', '.join(COLOR_SPACES)}")
    method: str = option("reproject", "predictor (engine.predict), options in brackets, e.g. "
                                      "decomp[gate.enabled=false]; auto: mvec for frames with motion vectors, "
                                      "flow2d for frames without")
    cut_translation: float = option(0.5, "camera cut when the camera centre moves more than this times the "
                                          "median scene depth")
    cut_rotation_deg: float = option(45.0, "camera cut when the camera turns by more than this many degrees")
    motion_units: str = option("", f"units of submitted motion vectors: {', '.join(MOTION_UNITS)} (pixels of the "
                                   "vector buffer; uv: the viewport spans 1; ndc: it spans 2); '' = the engine's")
    motion_scale: tuple[float, float] = option((1.0, 1.0), "x, y multipliers applied to the vectors first (FSR "
                                                           "motionVectorScale, DLSS mvecScale)")
    motion_y_up: Optional[bool] = option(None, "the vectors' y points to the top of the picture; None = the "
                                               "engine's")
    motion_direction: str = option("", "previous: from the pixel to where its point was in the previous frame; "
                                       "next: the reverse (previous -> current); '' = the engine's")
    motion_includes_camera: Optional[bool] = option(None, "the vectors include camera motion (False: object "
                                                          "motion only, the session adds the camera's); None = "
                                                          "the engine's")
    motion_missing: str = option("", "a pixel without a vector (NaN, motion_valid False): none (no vector) or "
                                     "camera (static: the camera's motion); '' = the engine's")

    def __post_init__(self) -> None:
        for name, allowed in (("engine", ENGINES), ("depth_convention", conventions.DEPTH_CONVENTIONS),
                              ("color_in", COLOR_SPACES), ("color_out", COLOR_SPACES)):
            if getattr(self, name) not in allowed:
                raise InputError(f"must be one of {', '.join(allowed)}, got {getattr(self, name)!r}", field=name)
        for name in ("width", "height"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"must be a positive integer, got {value!r}", field=name)
        if not (math.isfinite(self.near) and self.near > 0):
            raise InputError(f"must be a positive finite number, got {self.near}", field="near")
        if math.isnan(self.far) or self.far <= self.near:
            raise InputError(f"must be greater than near ({self.near}), or inf, got {self.far}", field="far")
        if self.depth_convention in ("infinite", "reversed_infinite") and math.isfinite(self.far):
            raise InputError(f"must be inf for depth convention {self.depth_convention!r}, got {self.far}",
                             field="far")
        if self.depth_convention == "linear01" and not math.isfinite(self.far):
            raise InputError("must be finite for depth convention 'linear01'", field="far")
        if not (math.isfinite(self.meters_per_unit) and self.meters_per_unit >= 0):
            raise InputError(f"must be >= 0 (0 = engine default), got {self.meters_per_unit}", field="meters_per_unit")
        for name in ("cut_translation", "cut_rotation_deg"):
            if not getattr(self, name) > 0:
                raise InputError(f"must be positive (inf disables the check), got {getattr(self, name)}", field=name)
        if self.method.partition("[")[0] == "oracle":
            raise InputError("'oracle' needs ground-truth object motion, which a game session does not have",
                             field="method")
        if self.method.partition("[")[0].strip() == AUTO and self.method.strip() != AUTO:
            raise InputError(f"'auto' takes no options (it picks mvec or flow2d per frame), got {self.method!r}",
                             field="method")
        for name, allowed in (("motion_units", MOTION_UNITS), ("motion_direction", MOTION_DIRECTIONS),
                              ("motion_missing", MOTION_MISSING)):
            if getattr(self, name) not in ("",) + allowed:
                raise InputError(f"must be one of {', '.join(allowed)}, or '' for the engine's, got "
                                 f"{getattr(self, name)!r}", field=name)
        for name in ("motion_y_up", "motion_includes_camera"):
            if getattr(self, name) not in (None, True, False):
                raise InputError(f"must be true, false or None (the engine's), got {getattr(self, name)!r}",
                                 field=name)
        scale = self.motion_scale
        if (not isinstance(scale, (tuple, list)) or len(scale) != 2
                or not all(isinstance(x, (int, float, np.integer, np.floating)) and not isinstance(x, bool)
                           and math.isfinite(x) and x != 0 for x in scale)):
            raise InputError(f"must be two finite non-zero numbers (x, y), got {scale!r}", field="motion_scale")

    @property
    def unit_scale(self) -> float:
        """Metres per engine unit actually used (``meters_per_unit`` or the engine's default)."""
        return self.meters_per_unit or DEFAULT_METERS_PER_UNIT[self.engine]

    def motion_conventions(self) -> "MotionConventions":
        """The motion-vector conventions actually used: each ``motion_*`` field, or the engine's default
        (``ENGINE_MOTION``). InputError naming the field where the engine has none (OpenGL: set
        ``motion_units``, ``motion_y_up`` and ``motion_direction``)."""
        engine = ENGINE_MOTION[self.engine]
        values = {}
        for key, given in (("units", self.motion_units), ("y_up", self.motion_y_up),
                           ("direction", self.motion_direction), ("includes_camera", self.motion_includes_camera),
                           ("missing", self.motion_missing)):
            if given not in ("", None):
                values[key] = given
            elif key in engine:
                values[key] = engine[key]
            else:
                raise InputError(f"engine {self.engine!r} has no motion-vector convention of its own: set "
                                 f"SessionConfig.motion_{key} to what the submitted vectors hold",
                                 field=f"motion_{key}")
        return MotionConventions(scale=(float(self.motion_scale[0]), float(self.motion_scale[1])), **values)


@dataclass(frozen=True)
class SubmitResult:
    """What ``submit`` did with a frame.

    Attributes:
        frame: the session's number of the frame (0, 1, ... in submit order, not reset by ``reset``).
        reset: why the history was cleared before this frame ("camera_cut", "time_backwards"), or None.
        history: rendered frames the next predictions use (1 after a reset, up to what the method needs).
    """

    frame: int
    reset: Optional[str]
    history: int


@dataclass
class SessionPrediction:
    """A predicted frame.

    Attributes:
        color: (H, W, 3) in ``SessionConfig.color_out`` (float32, or uint8 for "srgb8"), rows in the
            caller's order.
        holes: (H, W) bool, True where no rendered pixel landed (disocclusions, filled by the hole fill):
            the pixels to trust least.
        method: the predictor that made it ("reproject", "repeat", ...).
        fallback: why that is not the configured method ("history": the method needs more rendered frames
            than there are since the start or the last reset; "camera_cut": the target pose is too far from
            the newest frame's, so the newest frame is shown unchanged), or None.
        frame: the session number of the newest rendered frame it was predicted from.
        stages_ms: wall-clock milliseconds of the predictor's stages.
    """

    color: np.ndarray
    holes: np.ndarray
    method: str
    fallback: Optional[str]
    frame: int
    stages_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class SessionTexture:
    """A predicted frame handed out as a texture (``Session.predict_texture``).

    Attributes:
        texture: an ``engine.geometry.backends.gl.texture.FrameTexture``: the texture (``texture.texture``, GL name
            ``texture.glo``) of the session's GL context, its size, format and colour space, ``valid`` and
            ``read()``; owned by the session, valid until two more texture predictions or ``release()``.
        method, fallback, frame, stages_ms: as ``SessionPrediction``'s.
        gpu_ms: GPU milliseconds of the predictor's stages (GL timer queries).
    """

    texture: object
    method: str
    fallback: Optional[str]
    frame: int
    stages_ms: dict[str, float] = field(default_factory=dict)
    gpu_ms: dict[str, float] = field(default_factory=dict)


# --------------------------------------------------------------------------------------------
# Engine poses -> OpenCV cameras
# --------------------------------------------------------------------------------------------

def _unreal_hfov(projection: object, width: int, height: int) -> float:
    """Full horizontal FOV (degrees) from a scalar or from Unreal's projection FMatrix (row vectors)."""
    p = numeric_array(projection, field="projection")
    if p.ndim == 0:
        if not math.isfinite(float(p)):  # None reads as NaN; the range is from_unreal's to check
            raise InputError(f"must be a horizontal FOV in degrees, got {projection!r}", field="projection")
        return float(p)
    if p.shape != (4, 4) or not np.all(np.isfinite(p)):
        raise InputError(f"must be a horizontal FOV in degrees or a finite 4x4 FMatrix, got shape {p.shape}",
                         field="projection")
    scale = max(abs(p[0, 0]), 1e-300)
    if abs(p[2, 3] - 1.0) > 1e-6 or abs(p[3, 3]) > 1e-6 or abs(p[0, 3]) > 1e-6 or abs(p[1, 3]) > 1e-6:
        raise InputError("is not Unreal's perspective FMatrix (row vectors: column 3 must be [0, 0, 1, 0]); "
                         "pass the matrix as Unreal stores it, or the horizontal FOV", field="projection")
    if abs(p[2, 0]) > 1e-6 * scale or abs(p[2, 1]) > 1e-6 * scale or abs(p[0, 1]) > 1e-6 * scale \
            or abs(p[1, 0]) > 1e-6 * scale:
        raise InputError("is off-centre or skewed; only centred 'maintain X FOV' projections are supported",
                         field="projection")
    if not p[0, 0] > 0 or abs(p[1, 1] - p[0, 0] * width / height) > 1e-4 * p[1, 1]:
        raise InputError(f"projection[1,1] = {p[1, 1]:.6g} is not projection[0,0] * W / H = "
                         f"{p[0, 0] * width / height:.6g}: only 'maintain X FOV' with square pixels is supported",
                         field="projection")
    return math.degrees(2.0 * math.atan(1.0 / p[0, 0]))


def engine_camera(config: SessionConfig, view: object, projection: object,
                  width: Optional[int] = None, height: Optional[int] = None) -> Camera:
    """The OpenCV :class:`~engine.core.frames.Camera` of an engine pose, as a ``Session`` converts it.

    ``view`` and ``projection`` take the forms of the table in this module's docstring for
    ``config.engine``; ``width``/``height`` default to the config's. Raises InputError for bad matrices,
    naming the session's field: ``view`` (whatever the converter calls it: Unity's ``matrix``, Unreal's
    ``transform``, ``location``, ``rotation``) or ``projection``.
    """
    try:
        return _engine_camera(config, view, projection, width, height)
    except InputError as exc:
        if exc.field not in _VIEW_FIELDS:
            raise
        raise InputError(exc.problem, file=exc.file, frame=exc.frame, field="view") from None


#: The names ``engine.conventions``' converters give the argument that is a session's ``view``.
_VIEW_FIELDS = ("matrix", "transform", "location", "rotation")


def _engine_camera(config: SessionConfig, view: object, projection: object, width: Optional[int],
                   height: Optional[int]) -> Camera:
    w = config.width if width is None else width
    h = config.height if height is None else height
    scale = config.unit_scale
    engine = config.engine
    if engine == "opencv":
        k = numeric_array(projection, field="projection")
        if k.shape == (4, 4):
            k = k[:3, :3]
        pose = validate_pose(view, field_name="view").copy()
        translation = pose[:3, 3].copy()
        with np.errstate(over="ignore"):
            pose[:3, 3] = translation * scale
        if not np.isfinite(pose[:3, 3]).all():  # validated as used, as the other engines' converters do
            raise InputError(f"translation ({', '.join(f'{t:.6g}' for t in translation)}) times meters_per_unit "
                             f"{scale:g} is not finite", field="view")
        return Camera(validate_intrinsics(k, field_name="projection"), pose)
    if engine == "opengl":
        k, pose = conventions.from_opengl(w, h, view=view, projection=projection, ndc_y_down=config.ndc_y_down,
                                          meters_per_unit=scale)
    elif engine == "unity":
        k, pose = conventions.from_unity(w, h, matrix=view, matrix_is_world_to_camera=True, projection=projection,
                                         ndc_y_down=config.ndc_y_down, meters_per_unit=scale)
    elif engine == "godot":
        camera_to_world = rigid_inverse(validate_pose(view, field_name="view"))
        k, pose = conventions.from_godot(w, h, basis=camera_to_world[:3, :3], origin=camera_to_world[:3, 3],
                                         projection=projection, ndc_y_down=config.ndc_y_down,
                                         meters_per_unit=scale)
    else:  # unreal
        v = numeric_array(view, field="view")
        hfov = _unreal_hfov(projection, w, h)
        if v.shape == (6,):
            k, pose = conventions.from_unreal(w, h, location=v[:3], rotation=v[3:], horizontal_fov_deg=hfov,
                                              meters_per_unit=scale)
        else:
            k, pose = conventions.from_unreal(w, h, transform=view, horizontal_fov_deg=hfov, meters_per_unit=scale)
    return Camera(k, pose)


# --------------------------------------------------------------------------------------------
# Pixels in and out
# --------------------------------------------------------------------------------------------

def _rgb(color: object, where: dict) -> np.ndarray:
    c = np.asarray(color)
    if c.ndim != 3 or c.shape[2] not in (3, 4):
        raise InputError(f"must have shape (H, W, 3) or (H, W, 4), got {c.shape}", **where)
    return c[..., :3]


def _decode_color(color: np.ndarray, space: str, where: dict) -> np.ndarray:
    """Linear float32 (H, W, 3) from the submitted encoding; no copy for float32 linear input."""
    if space == "srgb8":
        if color.dtype != np.uint8:
            raise InputError(f"must be uint8 for color_in 'srgb8', got dtype {color.dtype}", **where)
        return encoding.decode8(color)
    linear = validate_color(color, frame=where["frame"], field_name=where["field"])
    if space == "linear":
        return linear
    decoded = encoding.srgb_to_linear(linear)  # float32: overflows to inf from about 1.2e16
    bad = int(np.count_nonzero(~np.isfinite(decoded)))
    if bad:
        raise InputError(f"has {bad} values that are not finite once decoded from sRGB (largest "
                         f"{float(linear.max()):.3g}; sRGB-encoded colour is about 0..1)", **where)
    return decoded


def _encode_color(linear: np.ndarray, space: str) -> np.ndarray:
    """The predicted frame in the session's ``color_out`` encoding (compiled: ``engine.geometry.encoding``)."""
    if space == "linear":
        return linear
    return encoding.display_encode(linear) if space == "srgb" else encoding.encode8(linear)


def _scene_depth(depth: np.ndarray) -> float:
    """Median finite depth of a strided subsample (metres), inf for an all-sky frame."""
    sample = depth[::_CUT_STRIDE, ::_CUT_STRIDE]
    finite = sample[np.isfinite(sample)]
    return float(np.median(finite)) if finite.size else math.inf


def _cut(a: Camera, b: Camera, scene_depth: float, config: SessionConfig) -> bool:
    """True when the pose change a -> b is a camera cut (see ``SessionConfig.cut_*``)."""
    ra, rb = a.world_to_camera[:3, :3], b.world_to_camera[:3, :3]
    cos_angle = (float(np.sum(ra * rb)) - 1.0) / 2.0  # trace(rb @ ra.T) = 1 + 2 cos(angle)
    if math.degrees(math.acos(min(1.0, max(-1.0, cos_angle)))) > config.cut_rotation_deg:
        return True
    centre_a, centre_b = -ra.T @ a.world_to_camera[:3, 3], -rb.T @ b.world_to_camera[:3, 3]
    distance = float(np.linalg.norm(centre_a - centre_b))
    return math.isfinite(scene_depth) and distance > config.cut_translation * scene_depth


def _located(exc: InputError, frame: int, time: object, what: str) -> InputError:
    return InputError(f"{exc.problem} ({what} at time {time})", file=exc.file, frame=frame, field=exc.field)


# --------------------------------------------------------------------------------------------
# The session
# --------------------------------------------------------------------------------------------

class Session:
    """Feed rendered frames, get in-between frames. See the module docstring for conventions and hard cases.

    Args:
        config: a :class:`SessionConfig` (or None for the defaults).
        make_method: how a method name becomes a predictor (default :func:`engine.predict.make_predictor`;
            the server passes one that adds its own network files). ``"auto"`` makes both of its methods
            here, so a bad name fails now, not at a later submit.
        backend: where the predictors' warps run: ``auto`` (``gl`` on a hardware OpenGL context, else
            ``cpu``), ``cpu`` or ``gl`` (``engine.predict.use_backend``; ``decomp``'s preparation runs on the
            CPU but for ``decomp[estimator=gl]``'s initial flow).
    """

    def __init__(self, config: Optional[SessionConfig] = None, *,
                 make_method: Optional[Callable[[str], Predictor]] = None, backend: str = "auto") -> None:
        self.config = config or SessionConfig()
        chosen = resolve_backend(backend)
        #: where the predictors' warps run (``cpu`` or ``gl``); ``predict_texture`` needs ``gl``
        self.backend = chosen
        self._textures = None  # the TextureRing of predict_texture, made on first use
        # 8-bit frames keep their codes for the gl backend, which uploads them and decodes on the GPU
        self._keep_codes = chosen == "gl" and self.config.color_in == "srgb8"

        def make(name: str) -> Predictor:
            try:
                predictor = (make_predictor if make_method is None else make_method)(name)
            except InputError as exc:  # the registry names the command line's --methods
                if exc.field != "methods":
                    raise
                raise InputError(exc.problem, file=exc.file, field="method") from None
            return use_backend(predictor, chosen)

        if self.config.method.strip() == AUTO:
            # predictor for frames with (True) and without (False) motion vectors
            self._auto: Optional[dict[bool, Predictor]] = {
                has: make(resolve_auto(self.config.method, has)) for has in (False, True)}
            self._loop = PredictionLoop(self._auto[False])
        else:
            self._auto = None
            self._loop = PredictionLoop(make(self.config.method))
        self._repeat = Repeat()
        self._scene_depth = math.inf  # of the newest rendered frame
        self._lock = threading.Lock()
        self._size = (self.config.height, self.config.width)
        self._frames_submitted = 0
        self._predictions = 0
        self._resets = {reason: 0 for reason in RESET_REASONS + ("reset",)}
        self._vectors = {"kept": 0, "dropped": 0}

    @property
    def width(self) -> int:
        return self._size[1]

    @property
    def height(self) -> int:
        return self._size[0]

    @property
    def stats(self) -> dict:
        """Counts so far: frames submitted, predictions made, history resets by reason, submitted motion
        vectors kept and dropped (the frame's history had just been reset: the first frame, after a reset)."""
        with self._lock:
            return {"submitted": self._frames_submitted, "predicted": self._predictions, "resets": dict(self._resets),
                    "history": 0 if self._loop.prepared is None else len(self._loop.prepared.frames),
                    "motion_vectors": dict(self._vectors)}

    def camera(self, view: object, projection: object) -> Camera:
        """The OpenCV camera the session makes of an engine pose (for checks and debugging)."""
        return engine_camera(self.config, view, projection, self.width, self.height)

    def submit(self, color: object, depth: object, view: object, projection: object, time: float, *,
               frame: Optional[int] = None, copy: bool = False, motion_vectors: object = None,
               motion_valid: object = None, object_ids: object = None) -> SubmitResult:
        """Hand over one rendered frame.

        Args:
            color: (H, W, 3) or (H, W, 4) in ``config.color_in``; alpha is ignored.
            depth: (H, W) depth buffer in ``config.depth_convention``.
            view, projection: the frame's camera in ``config.engine``'s form.
            time: seconds (any origin), must be finite; not after the newest frame's -> history reset.
            frame: the caller's frame number, used in error messages (default: the session's counter).
            copy: never keep references to ``color`` / ``depth`` (see "Zero-copy").
            motion_vectors: the engine's motion vectors of this frame, pointing into the previously
                submitted frame: (h, w, 2..4) float, h <= H, w <= W, in ``config.motion_conventions()``
                (module docstring); NaN = no vector. Dropped when the history restarts at this frame.
            motion_valid: optional (h, w) bool mask of the pixels that have a vector (False -> NaN).
            object_ids: optional (H, W) non-negative integer ids of the object seen at each pixel (0: static
                background; rows as ``color``'s): ``mvec[grouping=ids]`` fits its rigid parts per object
                (``docs/motion-vectors.md``). Always copied.

        Returns:
            a :class:`SubmitResult`. Raises InputError (naming the frame, the field and the time) for bad
            input; the history is then unchanged.
        """
        with self._lock:
            size = self._size
            label = self._frames_submitted if frame is None else int(frame)  # for error messages
        where = dict(frame=label, field="color")
        try:
            if not isinstance(time, (int, float, np.floating, np.integer)) or not math.isfinite(time):
                raise InputError(f"must be a finite number of seconds, got {time!r}", field="time")
            rgb = _rgb(color, where)
            depth_in = np.asarray(depth)
            if self.config.flip_rows:
                rgb, depth_in = rgb[::-1], depth_in[::-1]
            if rgb.shape[:2] != size or depth_in.shape != size:
                raise InputError(f"frame size is color {rgb.shape[:2]}, depth {depth_in.shape}; the session expects "
                                 f"(H, W) = {size}: call reset(width=..., height=...) to change the resolution",
                                 field="size")
            linear = _decode_color(rgb, self.config.color_in, where)
            planar = self._decode_depth(depth_in, label)
            codes = None
            if self._keep_codes:  # all channels (uploaded as they are; the GPU skips alpha), rows as rgb's
                codes = np.asarray(color)[::-1] if self.config.flip_rows else np.asarray(color)
            if copy:
                linear = linear.copy() if np.may_share_memory(linear, color) else linear
                planar = planar.copy() if np.may_share_memory(planar, depth) else planar
                codes = None if codes is None else codes.copy()
            camera = engine_camera(self.config, view, projection, size[1], size[0])
            self._check_planes(projection)
            vectors, motion = None, None
            if motion_vectors is not None:
                motion = self.config.motion_conventions()
                vectors = engine_vectors(motion_vectors, motion_valid, motion, size, self.config.flip_rows, label)
            elif motion_valid is not None:
                raise InputError("is given without motion_vectors", field="motion_valid")
            ids = None if object_ids is None else validate_object_ids(object_ids, size, field_name="object_ids")
            if ids is not None and self.config.flip_rows:  # rows as colour's
                ids = np.ascontiguousarray(ids[::-1])
        except InputError as exc:
            raise _located(exc, label, time, "submitted frame") from None
        scene_depth = _scene_depth(planar)
        with self._lock:
            if self._size != size:
                raise InputError(f"the session was reset to (H, W) = {self._size} during this submit",
                                 frame=label, field="size")
            number = self._frames_submitted  # numbered under the lock: concurrent submits never share one
            old = self._loop.prepared
            reset = None
            if old is not None:
                newest = old.frames[-1]
                if not float(time) > newest.time:
                    reset = "time_backwards"
                elif _cut(newest.camera, camera, min(scene_depth, self._scene_depth), self.config):
                    reset = "camera_cut"
            kept = None
            if vectors is not None and old is not None and reset is None:  # else they point into a lost frame
                try:
                    kept = with_camera_motion(vectors, motion, planar, camera, old.frames[-1].camera, label)
                except InputError as exc:
                    raise _located(exc, label, time, "submitted frame") from None
            new = Frame(index=number, time=float(time), color=linear, depth=planar, camera=camera,
                        motion_vectors=kept, color_codes=codes, object_id=ids)
            predictor = None if self._auto is None else self._auto[kept is not None]
            try:  # a predictor that refuses the frames (mvec without vectors) leaves the history as it was
                frames = self._loop.submit(new, restart=reset is not None, predictor=predictor).frames
            except InputError as exc:
                raise _located(exc, label, time, "submitted frame") from None
            self._scene_depth = scene_depth
            self._frames_submitted += 1
            if reset is not None:
                self._resets[reset] += 1
            if vectors is not None:
                self._vectors["kept" if kept is not None else "dropped"] += 1
            return SubmitResult(frame=number, reset=reset, history=len(frames))

    def _check_planes(self, projection: object) -> None:
        """A depth buffer decoded with near/far other than the projection's is wrong everywhere (21.9 ->
        15.3 dB in one case): where the engine passes an OpenGL-style 4x4 projection and the depth
        convention decodes with near/far, they must be planes of that projection (1 %)."""
        cfg = self.config
        if (cfg.depth_convention not in PLANE_DEPTH_CONVENTIONS or cfg.engine not in GL_PROJECTION_ENGINES
                or np.shape(projection) != (4, 4)):
            return
        problem = conventions.near_far_problem(cfg.near, cfg.far, projection)
        if problem is not None:
            name, why = problem
            raise InputError(f"SessionConfig.{why}: the depth buffer would decode to wrong depths", field=name)

    def _decode_depth(self, buffer: np.ndarray, label: int) -> np.ndarray:
        cfg = self.config
        where = dict(frame=label, field_name="depth")
        scale = cfg.unit_scale
        if cfg.depth_convention == "linear" and math.isinf(cfg.far) and scale == 1.0:
            return validate_depth(buffer, **where)  # no copy for float32
        far = None if math.isinf(cfg.far) else cfg.far
        planar = conventions.decode_depth_buffer(buffer, cfg.near, far, convention=cfg.depth_convention, **where)
        if scale == 1.0:
            return validate_depth(planar, **where)
        surface = np.isfinite(planar)
        with np.errstate(over="ignore"):
            planar *= scale
            planar = validate_depth(planar, **where)  # float32
        overflow = int(np.count_nonzero(surface & ~np.isfinite(planar)))
        if overflow:  # a surface must not become sky
            raise InputError(f"has {overflow} values that are not finite once scaled by meters_per_unit {scale:g}",
                             frame=label, field="depth")
        return planar

    def predict(self, view: object, projection: object, time: float, *,
                frame: Optional[int] = None) -> SessionPrediction:
        """Predict the frame seen from ``view``/``projection`` at ``time`` (seconds).

        Raises NotReadyError before the first submit (and after ``reset``), InputError (naming the frame
        and time) for a bad pose, or for a time more than ``engine.predict.MAX_EXTRAPOLATION`` steps of the
        rendered frames from the newest one where the method extrapolates motion. ``frame`` is the caller's
        number for the predicted frame, for errors.
        """
        camera, label, size = self._predicted_camera(view, projection, time, frame)
        out, predictor, fallback, newest = self._render_at(camera, time, label, size)
        color = out.color if out.encoding == self.config.color_out else _encode_color(out.color, self.config.color_out)
        holes = out.holes
        if self.config.flip_rows:
            color, holes = color[::-1], holes[::-1]
        return SessionPrediction(color=color, holes=holes, method=predictor.name, fallback=fallback,
                                 frame=newest.index, stages_ms=out.stages_ms)

    def _predicted_camera(self, view: object, projection: object, time: float,
                          frame: Optional[int]) -> tuple[Camera, int, tuple[int, int]]:
        """The checked camera of a predicted frame, the frame's label for errors and the session's (H, W) now;
        InputError naming the frame and time for a bad time or pose."""
        with self._lock:
            size = self._size
            label = self._predictions if frame is None else int(frame)
        try:
            if not isinstance(time, (int, float, np.floating, np.integer)) or not math.isfinite(time):
                raise InputError(f"must be a finite number of seconds, got {time!r}", field="time")
            camera = engine_camera(self.config, view, projection, size[1], size[0])
        except InputError as exc:
            raise _located(exc, label, time, "predicted frame") from None
        return camera, label, size

    def _render_at(self, camera: Camera, time: float, label: int, size: tuple[int, int],
                   resident: bool = False) -> tuple[Prediction, Predictor, Optional[str], Frame]:
        """Render the prediction for ``camera`` at ``time`` from the history, under the lock: (the predictor's
        output, the predictor, the fallback reason, the newest rendered frame). ``resident``: ask the backend to
        leave the frame on the GPU (``Target.resident``)."""
        with self._lock:
            history = self._loop.prepared
            if history is None:
                raise NotReadyError("predict before any frame was submitted since the start or the last reset")
            if self._size != size:
                raise InputError(f"the session was reset to (H, W) = {self._size} during this predict",
                                 frame=label, field="size")
            newest = history.frames[-1]
            # srgb8 is encoded where the frame is (on gl: on the GPU, a quarter of the bytes read back)
            encoding = "srgb8" if self.config.color_out == "srgb8" and not resident else "linear"
            target = Target(camera, float(time), label, encoding, resident=resident)
            if _cut(newest.camera, camera, self._scene_depth, self.config):
                predictor, fallback = self._repeat, "camera_cut"
            else:
                predictor, fallback = history.predictor, history.fallback
            try:
                out = predictor.render(history.state, target)
            except InputError as exc:  # a time too far from the rendered frames
                raise _located(exc, label, time, "predicted frame") from None
            self._predictions += 1
        return out, predictor, fallback, newest

    def predict_texture(self, view: object, projection: object, time: float, *, frame: Optional[int] = None,
                        format: str = "rgba16f") -> "SessionTexture":
        """``predict``, with the frame handed out as a texture of the session's GL context instead of host arrays
        (nothing read back; docs/gpu.md, "Frames handed out as textures"). Needs the ``gl`` backend.

        The session owns the texture (``engine.geometry.backends.gl.texture``): it stays valid until two more
        texture predictions were made or ``release()``; ``format`` is ``rgba16f`` (linear, default),
        ``rgba32f`` (linear) or ``srgb8`` (8-bit sRGB codes in an RGBA8 texture), whatever ``color_out`` says;
        rows are GL's (texel row 0 at the bottom), whatever ``flip_rows`` says. A frame a method made on the CPU
        (``repeat`` after a camera cut, methods without GL passes) is uploaded once.

        Raises InputError (one line) on the ``cpu`` backend and for an unknown format; else as ``predict``.
        """
        from engine.geometry.backends.gl.texture import TEXTURE_FORMATS

        if self.backend != "gl":
            raise InputError(f"textures need the gl backend: this session runs on {self.backend} (make it with "
                             f"Session(..., backend='gl'), or call predict for host arrays)", field="backend")
        if format not in TEXTURE_FORMATS:
            raise InputError(f"must be one of {', '.join(TEXTURE_FORMATS)}, got {format!r}", field="format")
        camera, label, size = self._predicted_camera(view, projection, time, frame)
        out, predictor, fallback, newest = self._render_at(camera, time, label, size, resident=True)
        with self._lock:
            if self._textures is None:
                from engine.geometry.backends.gl import shared_context
                from engine.geometry.backends.gl.texture import TextureRing

                self._textures = TextureRing(shared_context())
            ring = self._textures
        if out.resident is not None:
            texture = ring.write(out.resident.color, out.resident.shape, format)
        else:
            texture = ring.upload(out.color, format)
        return SessionTexture(texture=texture, method=predictor.name, fallback=fallback, frame=newest.index,
                              stages_ms=out.stages_ms, gpu_ms=out.gpu_ms)

    def release_textures(self) -> None:
        """Free the textures ``predict_texture`` handed out (every handle turns invalid; the next call makes new
        ones)."""
        with self._lock:
            ring, self._textures = self._textures, None
        if ring is not None:
            ring.release_all()

    def reset(self, width: Optional[int] = None, height: Optional[int] = None) -> None:
        """Forget every rendered frame (camera cut, level load); optionally change the frame size.

        The next ``predict`` needs a ``submit`` first. ``width``/``height`` default to the current size.
        """
        w = self.width if width is None else width
        h = self.height if height is None else height
        for name, value in (("width", w), ("height", h)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 1:
                raise InputError(f"must be a positive integer, got {value!r}", field=name)
        with self._lock:
            self._loop.restart()
            self._size = (int(h), int(w))
            self._resets["reset"] += 1
