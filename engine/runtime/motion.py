"""The motion vectors a game submits, converted into ``Frame.motion_vectors``: each engine's conventions.

The motion vectors a game hands ``Session.submit(..., motion_vectors=, motion_valid=)``: the engine's own buffer,
(h, w, 2), or (h, w, 3) / (h, w, 4) of which only the first two channels (x, y) are read (the RG of an
RGB(A) texture), float16/32/64, at the frame's resolution or lower (h <= H, w <= W: vectors rendered at a
lower resolution, FSR/DLSS render resolution). Sample (i, j) of a lower-resolution buffer is the value at
its pixel's centre, the full-resolution point ((j + 0.5) W / w, (i + 0.5) H / h), whose depth is read there
(``engine.geometry.motion.sample_depths``; docs/motion-vectors.md, "Lower-resolution vectors"). ``flip_rows`` reverses their rows as it does
colour's. The session converts them with :func:`engine.conventions.motion_vectors_to_previous` into
``Frame.motion_vectors`` (pixels of the full resolution, x right, y down, from each pixel centre to where
its surface point was in the previous *submitted* frame): first ``motion_scale`` (x, y), then the units
(``"pixels"`` of the vector buffer, rescaled by (W / w, H / h); ``"uv"``: the viewport spans 1; ``"ndc"``:
it spans 2), then ``motion_y_up`` (y is negated when it points to the top of the picture; this describes
the picture, not the memory rows, so a bottom-up readback needs ``flip_rows`` and the same ``motion_y_up``)
and ``motion_direction`` (``"previous"``: from this pixel to where the point was; ``"next"``: the reverse,
previous -> current, the motion since the previous frame; negated, which is exact). With
``motion_includes_camera=False`` (object motion only) the session adds the motion the camera alone causes
(:func:`engine.geometry.motion.camera_motion_vectors` from this frame's depth, this camera and the previous
submitted frame's camera, at the vector samples' positions). A pixel without a vector (NaN in the buffer,
or False in ``motion_valid``, an (h, w) bool mask) stays NaN, or with ``motion_missing="camera"`` gets the
camera's motion (a static surface). Each engine's own buffer, as its renderer writes it (``""`` / ``None``
in a ``motion_*`` field means this default):

======  ======  =====  ===========  ======  ========  ==================================================
engine  units   y      direction    camera  missing   source
======  ======  =====  ===========  ======  ========  ==================================================
unity   uv      up     next         yes     none      ``_CameraMotionVectorsTexture`` /
                                                      ``_MotionVectorTexture`` (RGHalf, "encoded in
                                                      screen UV space"); the URP manual: "subtract the
                                                      motion vector ... from its current UV" to get last
                                                      frame's UV; URP ``CalcNdcMotionVectorFromCsPositions``
                                                      = (posNDC - prevPosNDC) * 0.5, y flipped back where
                                                      ``UNITY_UV_STARTS_AT_TOP``; camera pass + object pass
unreal  ndc     up     next         yes     camera    ``DecodeVelocityFromTexture(...).xy`` of the velocity
                                                      buffer (``Common.ush``; it undoes
                                                      ``EncodeVelocityToTexture``'s bias, scale and, SM5+,
                                                      ``VELOCITY_ENCODE_GAMMA``): ``Calculate3DVelocity`` =
                                                      ScreenPos now - ScreenPos before, jitter removed.
                                                      Static geometry is not written (the clear value 0,
                                                      which TAA/TSR fill with camera motion from depth):
                                                      mark those pixels False in ``motion_valid``
godot   uv      down   previous     yes     none      Godot 4 velocity texture (``scene_forward_clustered
                                                      .glsl``: ``motion_vector = prev_position_uv -
                                                      position_uv``, uv = clip.xy / w * 0.5 in
                                                      RenderingDevice clip space, y down); Godot hands it
                                                      to FSR 2 with ``motionVectorScale`` = render size
opencv  pixels  down   previous     yes     none      Interleave's own ``Frame.motion_vectors``
opengl  --      --     --           yes     none      no engine buffer: ``motion_units``, ``motion_y_up``
                                                      and ``motion_direction`` must be set
======  ======  =====  ===========  ======  ========  ==================================================

Upscaler-ready buffers: FSR 2/3 take "the motion from a pixel in the current frame to the position of
that same pixel in the previous frame" in render-resolution pixels, y down, after ``motionVectorScale``:
``motion_units="pixels"``, ``motion_direction="previous"``, ``motion_y_up=False``, ``motion_scale`` = the
``motionVectorScale`` the game gives FSR. DLSS (Streamline ``sl::Constants``): ``mvecScale`` "normalize[s]
motion vectors (so the values are in [-1,1] range)", i.e. into uv units: ``motion_units="uv"``,
``motion_scale`` = the ``mvecScale``, ``motion_includes_camera`` = ``cameraMotionIncluded``; set
``motion_direction`` and ``motion_y_up`` to what the game's buffer holds (not established here). Remove
TAA jitter from the vectors (engines and upscalers expect unjittered vectors). A vector buffer whose
values are encoded (UNORM, Unreal's velocity texture) must be decoded to floats first.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from engine import conventions
from engine.core.errors import InputError
from engine.core.frames import MAX_MOTION_DIAGONALS, Camera, validate_motion_vectors
from engine.geometry.motion import camera_motion_vectors, sample_depths

__all__ = ["MOTION_MISSING", "ENGINE_MOTION", "MotionConventions", "motion_mask", "engine_vectors",
           "camera_vectors_at", "with_camera_motion"]

#: What a pixel without a motion vector means: "none" (nothing known: NaN), "camera" (a static surface:
#: the camera's motion, as Unreal's unwritten velocity pixels).
MOTION_MISSING = ("none", "camera")
#: The motion-vector conventions of each engine's own buffer (module docstring: the table and its sources).
#: OpenGL has no engine buffer: units, y_up and direction must be set in SessionConfig.
ENGINE_MOTION = {
    "opencv": dict(units="pixels", y_up=False, direction="previous", includes_camera=True, missing="none"),
    "unity": dict(units="uv", y_up=True, direction="next", includes_camera=True, missing="none"),
    "unreal": dict(units="ndc", y_up=True, direction="next", includes_camera=True, missing="camera"),
    "godot": dict(units="uv", y_up=False, direction="previous", includes_camera=True, missing="none"),
    "opengl": dict(includes_camera=True, missing="none"),
}


@dataclass(frozen=True)
class MotionConventions:
    """Resolved motion-vector conventions of a session (``SessionConfig.motion_conventions()``).

    Attributes:
        units: "pixels" (of the vector buffer), "uv" (the viewport spans 1) or "ndc" (it spans 2).
        scale: (x, y) applied first.
        y_up: the vectors' y points to the top of the picture.
        direction: "previous" (pixel -> where its point was) or "next" (the reverse).
        includes_camera: False when the vectors hold object motion only.
        missing: "none" (a pixel without a vector stays NaN) or "camera" (it gets the camera's motion).
    """

    units: str
    scale: tuple[float, float]
    y_up: bool
    direction: str
    includes_camera: bool
    missing: str

    @property
    def needs_camera(self) -> bool:
        """Whether converting needs the camera-only vectors (object-only vectors, or missing = camera)."""
        return not self.includes_camera or self.missing == "camera"


def motion_mask(valid: object, shape: tuple[int, int], label: int) -> np.ndarray:
    """``motion_valid`` as a bool (h, w) mask: bool, or integers holding only 0 and 1."""
    where = dict(frame=label, field="motion_valid")
    m = np.asarray(valid)
    if m.shape != shape:
        raise InputError(f"must have the vectors' shape (h, w) = {shape}, got {m.shape}", **where)
    if m.dtype == bool:
        return m
    if not np.issubdtype(m.dtype, np.integer) or np.any((m != 0) & (m != 1)):
        raise InputError(f"must be a bool mask (or integers 0 / 1), got dtype {m.dtype}", **where)
    return m.astype(bool)


def engine_vectors(vectors: object, valid: object, motion: MotionConventions, size: tuple[int, int],
                    flip_rows: bool, label: int) -> np.ndarray:
    """The submitted motion vectors as (h, w, 2) float64 full-resolution pixels pointing to the previous
    frame (object motion only if the engine's are), NaN for no vector; InputError for bad input."""
    where = dict(frame=label, field="motion_vectors")
    mv = np.asarray(vectors)
    if mv.ndim != 3 or mv.shape[2] not in (2, 3, 4):
        raise InputError(f"must have shape (h, w, 2), or (h, w, 3) / (h, w, 4) whose first two channels are x, y "
                         f"(the RG of an RGB(A) texture), got {mv.shape}", **where)
    if not np.issubdtype(mv.dtype, np.floating):
        raise InputError(f"must be a float array (float16, float32 or float64), got dtype {mv.dtype}: decode "
                         "integer-encoded vectors first (Unreal: DecodeVelocityFromTexture)", **where)
    h, w = mv.shape[:2]
    big_h, big_w = size
    if not (1 <= h <= big_h and 1 <= w <= big_w):
        raise InputError(f"are {w}x{h}: must be at most the frame's {big_w}x{big_h} and not empty", **where)
    xy = mv[..., :2]
    mask = None if valid is None else motion_mask(valid, (h, w), label)
    if flip_rows:
        xy = xy[::-1]
        mask = None if mask is None else mask[::-1]
    out = conventions.motion_vectors_to_previous(xy, big_w, big_h, units=motion.units, direction=motion.direction,
                                                 y_up=motion.y_up, scale=motion.scale, buffer_size=(w, h),
                                                 frame=label, field_name="motion_vectors")
    if mask is not None:
        out[~mask] = np.nan
    limit = MAX_MOTION_DIAGONALS * math.hypot(big_h, big_w)
    longest = float(np.nanmax(np.abs(out))) if np.isfinite(out).any() else 0.0
    if longest > limit:  # checked in float64, before a float32 cast could turn it into inf
        raise InputError(f"has a component of {longest:.4g} px once converted, over {MAX_MOTION_DIAGONALS:g} frame "
                         f"diagonals ({limit:.0f} px): wrong motion_units or motion_scale?", **where)
    return out


def camera_vectors_at(depth: np.ndarray, camera: Camera, previous: Camera, shape: tuple[int, int]) -> np.ndarray:
    """(h, w, 2) float64 full-resolution pixel vectors of camera motion alone (a static scene) at the samples
    of an (h, w) vector buffer: sample (i, j) sits at full-resolution ((j + 0.5) W / w, (i + 0.5) H / h), with
    the depth there (``engine.geometry.motion.sample_depths``: interpolated between the nearest pixels,
    exact on a plane). Exact for that depth: the cameras' intrinsics are scaled by (w / W, h / H), which
    maps the sample points onto the small grid's pixel centres."""
    big_h, big_w = depth.shape
    h, w = shape
    if (h, w) == (big_h, big_w):
        return camera_motion_vectors(depth, camera, previous).astype(np.float64)
    shrink = np.diag([w / big_w, h / big_h, 1.0])
    small = camera_motion_vectors(sample_depths(depth, (h, w)),
                                  Camera(shrink @ camera.intrinsics, camera.world_to_camera),
                                  Camera(shrink @ previous.intrinsics, previous.world_to_camera))
    return small.astype(np.float64) * np.array([big_w / w, big_h / h])


def with_camera_motion(vectors: np.ndarray, motion: MotionConventions, depth: np.ndarray, camera: Camera,
                        previous: Camera, label: int) -> np.ndarray:
    """Total motion vectors (float32): object-only vectors plus the camera's motion, and/or pixels without a
    vector filled with the camera's motion (``motion.missing == "camera"``). Camera vectors longer than the
    validator's limit (points at the previous camera's plane) count as none."""
    out = vectors
    if motion.needs_camera:
        cam = camera_vectors_at(depth, camera, previous, vectors.shape[:2])
        cam[np.abs(cam).max(axis=-1) > MAX_MOTION_DIAGONALS * math.hypot(*depth.shape)] = np.nan
        if not motion.includes_camera:
            out = out + cam
        if motion.missing == "camera":
            none = np.isnan(out).any(axis=-1)
            out = np.where(none[..., None], cam, out)
    return validate_motion_vectors(out.astype(np.float32), depth.shape, frame=label, field_name="motion_vectors")
