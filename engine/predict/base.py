"""The predictor interface: targets, predictions, the prepared state, stage timing and the ``Predictor`` base.

Every method sits behind one interface so the evaluation, the demo and the game-engine API call them alike:

- ``prepare(history)`` does the work that depends only on the rendered frames (e.g. estimating motion
  between frame n-k and frame n) once per rendered frame;
- ``render(state, target)`` predicts one in-between frame from that state;
- ``predict(history, target)`` is both in one call.

``history`` lists rendered frames oldest first and ends with frame n (the newest); methods that need
motion use ``history[-2]`` as frame n-k. Timings of each stage are returned in milliseconds.
Conventions are those of ``engine/core/frames.py`` (OpenCV cameras, planar depth, linear RGB).
"""
from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, field
from typing import Any, Iterator, Optional, Sequence

import numpy as np

from engine import geometry
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, rigid_inverse
from engine.geometry.encoding import FRAME_ENCODINGS
from engine.geometry.holefill import fill_holes

__all__ = ["MAX_EXTRAPOLATION", "Target", "Prediction", "PreparedState", "Timer", "Predictor", "warp_and_fill",
           "extrapolation_factor", "true_object_flow", "ResidentFrame", "PointMotion", "CpuFrames", "warp_fill_depth"]


@dataclass(frozen=True)
class Target:
    """The frame to predict: its camera, its time in seconds, its index in the stream, and the colour encoding
    the caller will use (``engine.geometry.encoding.FRAME_ENCODINGS``). A backend that can encode where the
    frame is (``gl``: on the GPU, so a quarter of the bytes is read back) returns that encoding; the others
    return linear colour, and the caller encodes it: ``Prediction.encoding`` says which one came back."""

    camera: Camera
    time: float
    index: int = -1
    encoding: str = "linear"
    #: leave the predicted frame on the GPU: a backend that has it there (``gl``) returns it as
    #: ``Prediction.resident`` (a ``GlPrediction``, linear) with no readback; the others return host arrays
    resident: bool = False

    def __post_init__(self) -> None:
        if self.encoding not in FRAME_ENCODINGS:
            raise InputError(f"must be one of {', '.join(FRAME_ENCODINGS)}, got {self.encoding!r}",
                             field="encoding")
        if self.resident and self.encoding != "linear":
            raise InputError(f"a frame left on the GPU is linear: encoding {self.encoding!r} needs resident=False",
                             field="encoding")


@dataclass
class Prediction:
    """A predicted frame: colour (H, W, 3) in ``encoding`` (linear RGB float32, or the ``srgb8`` uint8 codes a
    ``Target`` asked for and the backend made), the holes the method had to fill, stage timings (wall
    milliseconds; ``gpu_ms``: GPU milliseconds of the stages the ``gl`` backend timed with GL queries)."""

    color: Optional[np.ndarray]
    holes: Optional[np.ndarray]
    stages_ms: dict[str, float] = field(default_factory=dict)
    gpu_ms: dict[str, float] = field(default_factory=dict)
    #: the frame left on the GPU (``Target.resident`` on ``gl``: an ``engine.geometry.backends.gl.GlPrediction``,
    #: colour and packed holes in buffers of the shared context); ``color`` and ``holes`` are None then
    resident: Any = None

    @property
    def encoding(self) -> str:
        """``srgb8`` for uint8 codes, else ``linear`` (the colour's dtype says which; a resident frame is linear)."""
        return "srgb8" if self.color is not None and self.color.dtype == np.uint8 else "linear"


@dataclass
class PreparedState:
    """What ``prepare`` computed from the rendered frames, reused for every predicted frame until the next:
    ``data`` is the method's own typed per-frame state (a dataclass, e.g. ``Flow2DState``; None when the
    method keeps none)."""

    history: Sequence[Frame]
    data: Any = None
    stages_ms: dict[str, float] = field(default_factory=dict)
    gpu_ms: dict[str, float] = field(default_factory=dict)


class Timer:
    """Collects wall-clock milliseconds of named stages: ``with timer("stage"): ...`` adds the block's time
    to ``into["stage"]`` (a stage entered several times accumulates). ``gpu`` collects GPU milliseconds,
    written by the ``gl`` backend."""

    def __init__(self, into: Optional[dict[str, float]] = None, gpu: Optional[dict[str, float]] = None) -> None:
        self.into = {} if into is None else into
        self.gpu = {} if gpu is None else gpu

    @contextmanager
    def __call__(self, name: str) -> Iterator[None]:
        start = time.perf_counter()
        try:
            yield
        finally:
            self.into[name] = self.into.get(name, 0.0) + 1e3 * (time.perf_counter() - start)


class Predictor:
    """Base class: subclasses set ``name``, ``history_needed`` and implement ``_prepare``/``_render``."""

    name = "base"
    #: number of rendered frames the method needs (1: frame n only, 2: frames n-k and n)
    history_needed = 1
    #: rendered frames the method uses when they exist (0: ``history_needed``); the loop keeps this many
    history_wanted = 0
    #: the backends the method runs on (``engine.geometry.backends``); ``frames`` is where its warps run
    backends: tuple[str, ...] = ("cpu",)
    frames: "CpuFrames"

    @property
    def backend(self) -> str:
        """The backend this predictor runs on (``cpu`` or ``gl``)."""
        return self.frames.name

    def prepare(self, history: Sequence[Frame]) -> PreparedState:
        if len(history) < self.history_needed:
            raise InputError(f"method '{self.name}' needs {self.history_needed} rendered frames, got {len(history)}",
                             field="history")
        newest = history[-1]
        for f in history[-self.history_needed:]:
            if f.depth.shape != newest.depth.shape:
                raise InputError(f"frame size {f.depth.shape} differs from the newest frame's {newest.depth.shape}",
                                 frame=f.index, field="history")
        if self.history_needed > 1 and not history[-2].time < newest.time:
            raise InputError(f"frames must be in time order: frame {history[-2].index} at t={history[-2].time} "
                             f"is not before frame {newest.index} at t={newest.time}", field="history")
        state = PreparedState(history=history)
        state.data = self._prepare(state, Timer(state.stages_ms, state.gpu_ms))
        return state

    def render(self, state: PreparedState, target: Target) -> Prediction:
        stages: dict[str, float] = {}
        gpu: dict[str, float] = {}
        color, holes = self._render(state, target, Timer(stages, gpu))
        if target.resident and not isinstance(color, np.ndarray):  # the backend left it on the GPU
            return Prediction(color=None, holes=None, stages_ms=stages, gpu_ms=gpu, resident=color)
        return Prediction(color=color, holes=holes, stages_ms=stages, gpu_ms=gpu)

    def predict(self, history: Sequence[Frame], target: Target) -> Prediction:
        """Prepare and render in one call (stage timings include the preparation)."""
        state = self.prepare(history)
        out = self.render(state, target)
        out.stages_ms = {**state.stages_ms, **out.stages_ms}
        out.gpu_ms = {**state.gpu_ms, **out.gpu_ms}
        return out

    def _prepare(self, state: PreparedState, timer: Timer) -> Any:
        """The method's per-frame state (``state.data``) from ``state.history``; None by default."""
        return None

    def _render(self, state: PreparedState, target: Target, timer: Timer) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


@dataclass(eq=False)
class ResidentFrame:
    """A rendered frame where its backend computes: ``image`` is its GPU copy on ``gl`` (None on ``cpu``)."""

    frame: Frame
    image: Any = None


@dataclass(eq=False)
class PointMotion:
    """The 3D motion of a frame's moving pixels (``mvec``'s estimate), which a backend extrapolates s frame
    intervals ahead into an object flow (``engine.geometry.motion.extrapolated_flow``): ``velocity`` (H, W, 3)
    scene units per interval in the frame's camera axes (0 where nothing moves), ``moving`` (M,) the flat
    indices of the pixels with a velocity, ``acceleration`` (M, 3) their change of velocity per interval, or
    None (constant velocity)."""

    velocity: np.ndarray
    moving: np.ndarray
    acceleration: Optional[np.ndarray] = None


class CpuFrames:
    """The CPU backend: numpy + numba (``engine.geometry``), the oracle of ``engine.predict.backend.GlFrames``."""

    name = "cpu"

    def resident(self, frame: Frame, timer: Timer) -> ResidentFrame:
        return ResidentFrame(frame)

    def resident_flow(self, flow, timer: Timer):
        """A flow (H, W, 2|3) or a ``PointMotion`` where this backend computes (here: as it is)."""
        return flow

    def warp_fill_depth(self, source: ResidentFrame, target: Target,
                        timer: Timer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``warp_fill_depth`` of ``source.frame`` (no object motion): (colour, depth, holes)."""
        return warp_fill_depth(source.frame, target, timer)

    def warp_and_fill(self, source: ResidentFrame, target: Target, timer: Timer, flow=None,
                      flow_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """``warp_and_fill`` of ``source.frame`` moved by ``flow_scale * flow``, or for a ``PointMotion`` by
        its motion extrapolated ``flow_scale`` intervals ahead (``geometry.forward_warp_moved_frame``: the
        extrapolation runs in the warp, stage ``warp``); stages ``warp``, ``fill``."""
        if not isinstance(flow, PointMotion):
            if flow is not None and flow_scale != 1.0:
                flow = flow_scale * flow
            return warp_and_fill(source.frame, target, timer, flow)
        frame = source.frame
        src, dst = frame.camera, target.camera
        with timer("warp"):  # the motion extrapolated point by point in the warp's first pass: no flow buffer
            color, depth, holes = geometry.forward_warp_moved_frame(
                frame.color, frame.depth, src.intrinsics, src.world_to_camera, dst.intrinsics, dst.world_to_camera,
                flow.velocity, flow.moving, flow_scale, flow.acceleration)
        return _filled(frame, timer, color, depth, holes)[::2]


def warp_and_fill(frame: Frame, target: Target, timer: Timer,
                  flow: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray]:
    """Forward-warp ``frame`` to the target camera (optionally moving points by ``flow`` (H, W, 2 or 3)) and fill
    the holes (``engine.geometry.holefill``); stages ``warp`` and ``fill``. Returns (colour, holes)."""
    color, _, holes = warp_fill_depth(frame, target, timer, flow)
    return color, holes


def warp_fill_depth(frame: Frame, target: Target, timer: Timer,
                    flow: Optional[np.ndarray] = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``warp_and_fill`` that also returns the warped planar depth (H, W), filled as the colour is (+inf where
    nothing was left to fill from): (colour, depth, holes). For frame n-k and frame n's camera this is the
    camera-compensated frame n-k that the flow estimators match frame n against."""
    src, dst = frame.camera, target.camera
    with timer("warp"):
        color, depth, holes = geometry.forward_warp_frame(frame.color, frame.depth, src.intrinsics,
                                                          src.world_to_camera, dst.intrinsics, dst.world_to_camera,
                                                          flow)
    return _filled(frame, timer, color, depth, holes)


def _filled(frame: Frame, timer: Timer, color: np.ndarray, depth: np.ndarray,
            holes: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The warp of ``frame`` hole-filled (stage ``fill``): (colour, depth, holes)."""
    with timer("fill"):
        color, depth = fill_holes(color, depth, holes, frame.color)
    return color, depth, holes


#: The farthest a target may lie from frame n, in steps n-k -> n (``extrapolation_factor``): a renderer late by
#: a few steps is served; beyond this the extrapolated motion carries every point far out of view (and
#: overflows float32 long before 1e38), so the request is refused rather than answered with a wrong frame.
MAX_EXTRAPOLATION = 64.0


def extrapolation_factor(state: PreparedState, target: Target) -> float:
    """k'/k of thesis Eq. 6.13 from the frame times: how far past frame n the target lies, per step n-k -> n.
    InputError (field ``time``) beyond ``MAX_EXTRAPOLATION`` steps either way."""
    older, newest = state.history[-2], state.history[-1]
    factor = (target.time - newest.time) / (newest.time - older.time)
    if not abs(factor) <= MAX_EXTRAPOLATION:  # also NaN
        raise InputError(f"lies {factor:.3g} steps of the rendered frames (t = {older.time!r} -> {newest.time!r}) "
                         f"from the newest frame; at most {MAX_EXTRAPOLATION:g} are predicted", field="time")
    return factor


def true_object_flow(frame: Frame, objects: dict, target_index: int) -> np.ndarray:
    """(H, W, 3) flow in frame n's view from TRUE object motion to frame ``target_index``: pixel displacement
    (du, dv) and planar depth change dz of every pixel whose object moves (0 elsewhere and for sky).

    ``objects`` maps object id -> ``SceneObject`` (per-frame world-from-object transforms); the frame must
    carry its ``object_id`` channel.
    """
    if frame.object_id is None or not objects:
        raise InputError("true object motion needs the object_id channel and the sequence's objects",
                         frame=frame.index, field="object_id")
    k, t = frame.camera.intrinsics, frame.camera.world_to_camera
    flow = np.zeros(frame.depth.shape + (3,), dtype=np.float32)
    ids = frame.object_id
    points_all = geometry.unproject(frame.depth, k)  # (H, W, 4) homogeneous
    pixels_all = geometry.pixel_centers(*frame.depth.shape)
    for oid in np.unique(ids):
        obj = objects.get(int(oid))
        if obj is None or not obj.moving:
            continue
        if not 0 <= target_index < len(obj.world_from_object):
            raise InputError(f"no transform of object {oid} for frame {target_index}", frame=frame.index,
                             field="objects")
        motion = obj.world_from_object[target_index] @ rigid_inverse(obj.world_from_object[frame.index])
        camera_motion = t @ motion @ rigid_inverse(t)  # object motion expressed in frame n's camera
        mask = (ids == oid) & np.isfinite(frame.depth)
        moved = points_all[mask] @ camera_motion.T  # (N, 4), w = 1 (finite depth only)
        uv, z, valid = geometry.project(moved, k)
        pix = pixels_all[mask]
        d = np.where(valid[:, None], np.concatenate([uv - pix, (z - frame.depth[mask])[:, None]], axis=1), 0.0)
        flow[mask] = d
    return flow


Predictor.frames = CpuFrames()  # the default backend of every predictor (stateless, shared)
