"""Frame predictors: given past rendered frames and a target camera, predict the frame seen from it.

Every method sits behind one interface so the evaluation, the demo and (later) the game-engine API call
them alike:

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
from dataclasses import dataclass, field
from functools import lru_cache
from typing import Any, Callable, Optional, Sequence

import numpy as np

from engine import geometry
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, SceneObject, rigid_inverse
from engine.geometry.holefill import fill_holes
from engine.core.colorspace import ENCODE8_BUCKETS, encode8_table


@dataclass(frozen=True)
class Target:
    """The frame to predict: its camera, its time in seconds, and its index in the stream."""

    camera: Camera
    time: float
    index: int = -1


@dataclass
class Prediction:
    """A predicted frame: colour (H, W, 3) linear RGB, the holes the method had to fill, stage timings."""

    color: np.ndarray
    holes: np.ndarray
    stages_ms: dict[str, float] = field(default_factory=dict)


@dataclass
class PreparedState:
    """What ``prepare`` computed from the rendered frames, reused for every predicted frame until the next."""

    history: Sequence[Frame]
    data: dict[str, Any] = field(default_factory=dict)
    stages_ms: dict[str, float] = field(default_factory=dict)


class _Timer:
    """Collects wall-clock milliseconds of named stages."""

    def __init__(self, into: dict[str, float]) -> None:
        self.into = into

    def __call__(self, name: str, fn: Callable, *args, **kwargs):
        start = time.perf_counter()
        out = fn(*args, **kwargs)
        self.into[name] = self.into.get(name, 0.0) + 1e3 * (time.perf_counter() - start)
        return out


class Predictor:
    """Base class: subclasses set ``name``, ``history_needed`` and implement ``_prepare``/``_render``."""

    name = "base"
    #: number of rendered frames the method needs (1: frame n only, 2: frames n-k and n)
    history_needed = 1

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
        self._prepare(state, _Timer(state.stages_ms))
        return state

    def render(self, state: PreparedState, target: Target) -> Prediction:
        stages: dict[str, float] = {}
        color, holes = self._render(state, target, _Timer(stages))
        return Prediction(color=color, holes=holes, stages_ms=stages)

    def predict(self, history: Sequence[Frame], target: Target) -> Prediction:
        """Prepare and render in one call (stage timings include the preparation)."""
        state = self.prepare(history)
        out = self.render(state, target)
        out.stages_ms = {**state.stages_ms, **out.stages_ms}
        return out

    def _prepare(self, state: PreparedState, timer: _Timer) -> None:
        pass

    def _render(self, state: PreparedState, target: Target, timer: _Timer) -> tuple[np.ndarray, np.ndarray]:
        raise NotImplementedError


def _warp_and_fill(frame: Frame, target: Target, timer: _Timer, flow: Optional[np.ndarray] = None):
    """Forward-warp ``frame`` to the target camera (optionally moving points by ``flow``) and fill holes."""
    src, dst = frame.camera, target.camera
    color, depth, holes = timer("warp", geometry.forward_warp_frame, frame.color, frame.depth,
                                src.intrinsics, src.world_to_camera, dst.intrinsics, dst.world_to_camera, flow)
    color, _ = timer("fill", fill_holes, color, depth, holes, frame.color)
    return color, holes


class Repeat(Predictor):
    """The last rendered frame, unchanged (what a game shows without frame generation)."""

    name = "repeat"

    def _render(self, state, target, timer):
        frame = state.history[-1]
        return frame.color.copy(), np.zeros(frame.depth.shape, dtype=bool)


class Reproject(Predictor):
    """Camera-only depth reprojection of the last frame (timewarp), with the background-biased hole fill."""

    name = "reproject"

    def _render(self, state, target, timer):
        return _warp_and_fill(state.history[-1], target, timer)


def extrapolation_factor(state: PreparedState, target: Target) -> float:
    """k'/k of thesis Eq. 6.13 from the frame times: how far past frame n the target lies, per step n-k -> n."""
    older, newest = state.history[-2], state.history[-1]
    return (target.time - newest.time) / (newest.time - older.time)


def dis_estimator(preset: str = "medium", finest_scale: Optional[int] = None):
    """An OpenCV DIS optical-flow object for a preset name ('ultrafast', 'fast', 'medium'; others raise),
    with its finest pyramid scale replaced by ``finest_scale`` when given (0: the input's own resolution)."""
    import cv2

    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    if preset not in presets:
        raise InputError(f"unknown DIS preset '{preset}', expected one of {sorted(presets)}", field="preset")
    estimator = cv2.DISOpticalFlow_create(presets[preset])
    if finest_scale is not None:
        estimator.setFinestScale(int(finest_scale))
    return estimator


#: Smallest side OpenCV's DIS is given: on smaller images (e.g. 12 x 200, 3 x 200) it raises or crashes the
#: process (OpenCV 5.0, measured for every preset, finest scale 0 included); 32 px a side never did.
DIS_MIN_SIDE = 32


def dis_calc(estimator, luma_a: np.ndarray, luma_b: np.ndarray) -> np.ndarray:
    """``estimator.calc(luma_a, luma_b)``, (H, W, 2) float32 flow from a to b, for any size: images with a
    side under ``DIS_MIN_SIDE`` are padded by repeating their edge pixels (no motion there) and the flow is
    cropped back. Same-size uint8 (H, W) images."""
    import cv2

    h, w = luma_a.shape
    if luma_b.shape != (h, w):
        raise InputError(f"DIS images of shapes {luma_a.shape} and {luma_b.shape}: expected the same", field="luma")
    pad_h, pad_w = max(0, DIS_MIN_SIDE - h), max(0, DIS_MIN_SIDE - w)
    if not (pad_h or pad_w):
        return estimator.calc(luma_a, luma_b, None)
    a, b = (cv2.copyMakeBorder(x, 0, pad_h, 0, pad_w, cv2.BORDER_REPLICATE) for x in (luma_a, luma_b))
    return np.ascontiguousarray(estimator.calc(a, b, None)[:h, :w])


def dis_block(preset: str = "medium") -> int:
    """Block size 2^s of a DIS preset's finest pyramid scale s (medium: 2, fast and ultrafast: 4). DIS
    computes nothing finer: its flow on a full-size image is its flow on the image's ``cv2.INTER_AREA``
    block means (finest scale 0), bilinearly upsampled and scaled by the block size."""
    return 2 ** int(dis_estimator(preset).getFinestScale())


def luma8(color: np.ndarray) -> np.ndarray:
    """(H, W) uint8 luma of display-encoded linear RGB (H, W, 3): what DIS optical flow reads."""
    import cv2

    return cv2.cvtColor(encode8(color), cv2.COLOR_RGB2GRAY)


def encode8(color: np.ndarray) -> np.ndarray:
    """(H, W, 3) uint8 display encoding of linear RGB (H, W, 3), equal to ``colorspace.encode8_reference``
    (compiled: ``engine.geometry.kernels.encode8``)."""
    from engine.geometry import kernels
    level, step = _encode8_table()
    out = np.empty(color.shape, dtype=np.uint8)
    kernels.encode8(np.ascontiguousarray(color, dtype=np.float32), level, step, ENCODE8_BUCKETS, out)
    return out


@lru_cache(maxsize=1)
def _encode8_table() -> tuple[np.ndarray, np.ndarray]:
    return encode8_table()


class Flow2D(Predictor):
    """2D optical-flow extrapolation in the spirit of spacewarp.

    Frame n-k is warped into frame n's view (camera motion cancelled, holes filled); OpenCV's DIS optical
    flow estimates the remaining (object) motion from frame n to the warped n-k on 8-bit sRGB luma; the
    flow is extrapolated linearly, u(n -> n+k') = -(k'/k) u(n -> n-k) (thesis Eq. 6.13), and frame n is
    forward-warped by that 2D flow plus the target camera's motion.
    """

    name = "flow2d"
    history_needed = 2

    def __init__(self, preset: str = "medium") -> None:
        self._dis = dis_estimator(preset)

    def _prepare(self, state, timer):
        older, newest = state.history[-2], state.history[-1]
        warped, _ = _warp_and_fill(older, Target(newest.camera, newest.time, newest.index), timer)
        state.data["flow_back"] = timer("flow", dis_calc, self._dis, luma8(newest.color), luma8(warped))

    def object_flow(self, state: PreparedState) -> np.ndarray:
        """The estimated u(n -> n-k) of frame n, (H, W, 2) pixels."""
        return state.data["flow_back"]

    def _render(self, state, target, timer):
        flow = -extrapolation_factor(state, target) * state.data["flow_back"]
        return _warp_and_fill(state.history[-1], target, timer, flow)


class Oracle(Predictor):
    """Upper bound: moves every pixel of frame n by its object's TRUE rigid motion, then by the camera's.

    Uses the ``object_id`` channel and the sequence's per-frame object transforms; times between frames
    are not interpolated, so the target must be a frame of the sequence (``target.index``).
    """

    name = "oracle"

    def __init__(self, objects: Sequence[SceneObject]) -> None:
        self.objects = {o.id: o for o in objects}

    def _render(self, state, target, timer):
        frame = state.history[-1]
        flow = timer("motion", true_object_flow, frame, self.objects, target.index)
        return _warp_and_fill(frame, target, timer, flow)


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


#: Registry of method names -> factory(objects) for the CLI and the evaluation.
METHODS: dict[str, Callable[[Sequence[SceneObject]], Predictor]] = {
    "repeat": lambda objects: Repeat(),
    "reproject": lambda objects: Reproject(),
    "flow2d": lambda objects: Flow2D(),
    "oracle": lambda objects: Oracle(objects),
    "decomp": lambda objects: _decomp(objects=objects),
    "decomp2d": lambda objects: _decomp("flow2d.onnx", objects=objects),
}


def _decomp(weights: str = "flow3d.onnx", options: str = "", objects: Sequence[SceneObject] = ()) -> Predictor:
    """The DeCOMPnet predictor (``engine.predict.decomp.predictor``) with committed weights from ``engine/weights``."""
    from engine.predict.decomp.predictor import DEFAULT_MODEL, DecompPredictor, config_from_options

    return DecompPredictor(config_from_options(options, model=str(DEFAULT_MODEL.with_name(weights))),
                           objects=objects)


def split_methods(text: str) -> list[str]:
    """Comma-separated method names, where a name may carry options in brackets with commas inside:
    ``"reproject,decomp[gate=0,flow_width=240]"`` -> ``["reproject", "decomp[gate=0,flow_width=240]"]``."""
    out, depth, current = [], 0, ""
    for ch in text:
        depth += (ch == "[") - (ch == "]")
        if ch == "," and depth == 0:
            out.append(current.strip())
            current = ""
        else:
            current += ch
    out.append(current.strip())
    return [m for m in out if m]


def make_predictor(name: str, objects: Sequence[SceneObject] = ()) -> Predictor:
    """Build a predictor by name (see ``METHODS``); unknown names raise InputError listing the known ones.

    ``decomp`` and ``decomp2d`` take options of ``engine.predict.decomp.predictor.DecompConfig`` in brackets, e.g.
    ``decomp[gate=0,flow_width=240]``; ``flow2d`` its DIS preset, ``flow2d[preset=fast]``.
    """
    base, _, rest = name.partition("[")
    if base not in METHODS:
        raise InputError(f"unknown method '{name}', expected one of {', '.join(METHODS)}", field="methods")
    if not rest:
        return METHODS[base](objects)
    if base == "flow2d" and rest.endswith("]"):
        key, _, value = rest[:-1].partition("=")
        if key.strip() != "preset":
            raise InputError(f"method '{name}': flow2d takes one option, preset (ultrafast, fast, medium)",
                             field="methods")
        return Flow2D(value.strip())
    if base not in ("decomp", "decomp2d") or not rest.endswith("]"):
        raise InputError(f"method '{name}': only decomp, decomp2d (options of engine.predict.decomp.predictor.DecompConfig) and "
                         f"flow2d (preset=...) take options, as decomp[key=value,...]", field="methods")
    return _decomp("flow3d.onnx" if base == "decomp" else "flow2d.onnx", rest[:-1], objects)
