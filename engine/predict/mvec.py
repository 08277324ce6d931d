"""``mvec``: frame extrapolation from the renderer's own motion vectors (no motion estimation).

A renderer that knows its motion writes motion vectors (``Frame.motion_vectors``: per pixel, the screen
displacement in pixels to where the surface point was in the previous rendered frame, camera motion
included). ``mvec`` turns them into 3D motion and extrapolates it, in passes over a typed state:

1. ``vectors``: the newest frame's vectors at full resolution (``upsample_motion_vectors``, depth-guided
   nearest, when they come smaller) and, with ``undilate``, without FSR-style edge dilation;
2. ``velocity``: each pixel's 3D displacement since frame n-k in frame n's camera axes
   (``engine.geometry.motion.scene_velocity``: frame n's depth, frame n-k's depth at the vector's end,
   both cameras), zero for static surfaces, sky and pixels without a vector;
3. ``acceleration`` (when frame n-2k was rendered and frame n-k came with its vectors, to n-2k): the
   change of each moving point's velocity since the interval before (``velocity_change``), kept only where
   it is small against the velocity (smooth motion; a bounce, start or stop keeps constant velocity);
   ``rigid`` (with ``extrapolation=rigid`` or ``fallback``; ``engine.geometry.rigid``): the
   moving pixels in rigid parts, each part on the path (a screw, or a spin about its centre) that its last
   two intervals support, where that path explained the last interval at least as well as the points' own
   lines (with two frames: the lines), written as each point's V and A; with ``fallback``, regions whose
   earlier motion did not explain the last interval dropped (they take the camera-only warp);
4. ``render``: ``P(n + k') = P(n) + s V + s (s + 1) / 2 A`` with s = k'/k from the frame times
   (``extrapolation_factor``): constant velocity, or the parabola through the last three positions, in 3D,
   so camera motion and object motion toward the camera both come out right; frame n is forward-splatted
   by that 3D flow to the target camera and hole-filled exactly like ``reproject`` (the backend's
   ``warp_and_fill`` of the ``PointMotion``: on ``gl`` the motion is uploaded once and extrapolated on the GPU).
   Where nothing moves the result is ``reproject``'s, bit for bit.

Vectors of frame n must point to frame n-k, the previous rendered frame (what an engine that renders every
k-th frame writes; ``interleave eval`` derives them from a sequence's per-frame vectors). Conventions:
``engine/core/frames.py``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any, Optional

import numpy as np

from engine.core.config import option
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.rigid import (PartPaths, apply_parts, find_parts, hindcast_keeps, kept_part_motion,
                                   motion_components, moving_points, part_paths, previous_positions, refined_before)
from engine.geometry.motion import (DEFAULT_DEPTH_BAND, DEFAULT_STATIC_TOLERANCE, extrapolated_flow, scene_velocity,
                                    undilate_motion_vectors, upsample_motion_vectors, velocity_change,
                                    velocity_change_args)
from engine.predict.base import (PointMotion, Predictor, PreparedState, ResidentFrame, Timer,
                                 extrapolation_factor)

__all__ = ["MvecConfig", "MvecState", "Mvec", "EXTRAPOLATIONS", "GROUPINGS"]

#: the values of ``MvecConfig.extrapolation`` and ``MvecConfig.grouping``
EXTRAPOLATIONS = ("linear", "rigid")
GROUPINGS = ("motion", "ids")
#: the rigid fits and the fall-back's check read at most about this many moving pixels (a grid of them)
SAMPLES = 4096
#: a pixel joins its group's rigid part where the part's transform explains it within this many times
#: ``rigid_threshold`` (its previous depth was read at one pixel, the fitted sample's between pixels)
ASSIGN = 3.0


@dataclass(frozen=True)
class MvecConfig:
    """Options of ``mvec`` (``mvec[undilate=true]``)."""

    undilate: bool = option(False, "undo FSR-style edge dilation of the vectors (a background pixel handed "
                                   "the nearer neighbour's vector loses it)")
    static_tolerance: float = option(DEFAULT_STATIC_TOLERANCE, "pixels: a vector this close to the camera's own "
                                                               "motion marks a static surface")
    depth_band: float = option(DEFAULT_DEPTH_BAND, "ratio > 1 within which frame n-k's depth at a vector's end "
                                                   "is trusted as the point's previous depth")
    acceleration: bool = option(True, "with frame n-k's vectors too, extrapolate a smooth change of velocity "
                                      "(the parabola through the last three positions)")
    acceleration_limit: float = option(0.5, "largest change of velocity, relative to the velocity, taken as "
                                            "smooth motion (larger: constant velocity)")
    extrapolation: str = option("rigid", "linear: each moving pixel on its own line (or parabola); rigid: moving "
                                          "pixels grouped into rigid parts by their 3D motion, each part turned "
                                          "and moved on a screw or a spin where the interval before supports it")
    grouping: str = option("motion", "with extrapolation=rigid, the groups the rigid parts are fitted in: motion "
                                     "(pixels that move alike, from vectors and depths alone) or ids (the frame's "
                                     "object ids, channel object_id, where the renderer gives them; motion where not)")
    fallback: bool = option(True, "with frame n-k's vectors too: a region whose motion, extrapolated from the "
                                   "interval before, explained the last interval worse than no object motion "
                                   "takes the camera-only warp")
    fallback_ratio: float = option(1.5, "a region falls back when its motion's error over the last interval "
                                        "exceeds this many times the error of no object motion (a reversal: "
                                        "2, a stop: more; a turn by 90 degrees: 1.41, kept)")
    rigid_threshold: float = option(1.0, "pixels: largest residual of a point that moves with its rigid part")

    def __post_init__(self) -> None:
        if not (self.static_tolerance >= 0 and np.isfinite(self.static_tolerance)):
            raise InputError(f"must be finite and >= 0, got {self.static_tolerance}", field="static_tolerance")
        if not (self.depth_band > 1 and np.isfinite(self.depth_band)):
            raise InputError(f"must be finite and > 1, got {self.depth_band}", field="depth_band")
        if not (self.acceleration_limit >= 0 and np.isfinite(self.acceleration_limit)):
            raise InputError(f"must be finite and >= 0, got {self.acceleration_limit}", field="acceleration_limit")
        if self.extrapolation not in EXTRAPOLATIONS:
            raise InputError(f"must be one of {', '.join(EXTRAPOLATIONS)}, got {self.extrapolation!r}",
                             field="extrapolation")
        if self.grouping not in GROUPINGS:
            raise InputError(f"must be one of {', '.join(GROUPINGS)}, got {self.grouping!r}", field="grouping")
        if not (self.fallback_ratio > 0 and np.isfinite(self.fallback_ratio)):
            raise InputError(f"must be finite and > 0, got {self.fallback_ratio}", field="fallback_ratio")
        if not (self.rigid_threshold > 0 and np.isfinite(self.rigid_threshold)):
            raise InputError(f"must be finite and > 0, got {self.rigid_threshold}", field="rigid_threshold")


@dataclass
class MvecState:
    """``mvec``'s per-frame state: ``velocity`` (H, W, 3) scene units per frame interval n-k -> n in frame
    n's camera axes, ``moving`` the flat indices of the pixels with a non-zero velocity, ``acceleration``
    (len(moving), 3) their change of velocity per interval, or None (constant velocity; and with pass ``rigid``,
    which computes it for the pixels that keep their own motion only, into ``motion``)."""

    velocity: np.ndarray
    moving: np.ndarray
    acceleration: Optional[np.ndarray] = None
    frame: Optional[ResidentFrame] = None
    #: rigid parts found (``extrapolation=rigid``) and moving pixels held to the camera-only warp (``fallback``)
    parts: int = 0
    held: int = 0
    #: the motion where the backend computes (``PointMotion``; on ``gl`` uploaded once, extrapolated there)
    motion: Any = None


class Mvec(Predictor):
    """Constant-velocity 3D extrapolation of the renderer's motion vectors (module docstring)."""

    name = "mvec"
    history_needed = 2
    backends = ("cpu", "gl")
    history_wanted = 3  # frame n-2k, when there, gives the change of velocity

    def __init__(self, config: Optional[MvecConfig] = None) -> None:
        self.config = MvecConfig() if config is None else config
        # the last prepared frame's velocity, keyed by the pair of frames it came from (``_key``): frame n's
        # preparation reuses it as frame n-k's (a stream prepares every rendered frame in turn)
        self._last: tuple[tuple, np.ndarray] = ((), np.zeros((0, 0, 3), np.float32))
        self._previous = self._last

    @staticmethod
    def _key(newest, older) -> tuple:
        """Which pair of frames a velocity belongs to: indices, times and a sample of depth and vectors."""
        sample = tuple(hash(np.ascontiguousarray(a[::17, ::13]).tobytes()) for a in (newest.depth, older.depth))
        vectors = newest.motion_vectors
        return (newest.index, newest.time, older.index, older.time, newest.depth.shape, sample,
                None if vectors is None else hash(np.ascontiguousarray(vectors[::17, ::13]).tobytes()))

    def _vectors(self, frame) -> np.ndarray:
        """Pass 1: ``frame``'s vectors at its full resolution, undilated if configured."""
        vectors = upsample_motion_vectors(frame.motion_vectors, frame.depth)
        return undilate_motion_vectors(vectors, frame.depth) if self.config.undilate else vectors

    def _velocity(self, newest, older, vectors: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Pass 2: ``newest``'s 3D velocity since ``older`` and its moving pixels (``scene_velocity``)."""
        return scene_velocity(newest.depth, vectors, older.depth, newest.camera, older.camera,
                              static_tolerance=self.config.static_tolerance, band=self.config.depth_band)

    def _prepare(self, state: PreparedState, timer: Timer) -> MvecState:
        older, newest = state.history[-2], state.history[-1]
        if newest.motion_vectors is None:
            raise InputError("method 'mvec' needs the renderer's motion vectors of the newest frame (rgbd-seq "
                             "channels motion.X/Y, Session.submit(motion_vectors=...)); use 'flow2d' or 'auto'",
                             frame=newest.index, field="motion_vectors")
        self._previous = self._last
        cfg = self.config
        with timer("vectors"):
            vectors = self._vectors(newest)
        with timer("velocity"):
            velocity, moving = self._velocity(newest, older, vectors)
        self._last = (self._key(newest, older), velocity)
        data = MvecState(velocity, moving, frame=self.frames.resident(newest, timer))
        before, change, shaped = None, None, False
        if moving.size and len(state.history) >= 3 and (cfg.acceleration or cfg.fallback):
            with timer("acceleration"):
                before = self._before(state.history[-3:])
                shaped = before is not None and (cfg.extrapolation == "rigid" or cfg.fallback)  # pass ``rigid`` runs
                if cfg.acceleration and before is not None:
                    args = (newest.depth, vectors, velocity)
                    rest = (newest.camera, older.camera, older.depth, before[0], before[1])
                    if shaped:  # computed in pass ``rigid``, for the pixels that keep their own motion only
                        change = velocity_change_args(*args, *rest, band=cfg.depth_band, limit=cfg.acceleration_limit)
                    else:
                        data.acceleration = velocity_change(*args, moving, *rest, band=cfg.depth_band,
                                                            limit=cfg.acceleration_limit)
        if moving.size:
            motion = PointMotion(velocity, moving, data.acceleration)
            if shaped:  # else: nothing to decide
                with timer("rigid"):
                    motion = self._shaped(state.history, vectors, data, before, change, timer)
            if motion.moving.size:
                data.motion = self.frames.resident_flow(motion, timer)
        return data

    def _before(self, frames) -> Optional[tuple[np.ndarray, float]]:
        """Frame n-k's velocity (since n-2k, its camera's axes) and the ratio of the last interval to the one
        before, from frames n-2k, n-k, n; None when frame n-k has no vectors or the three do not line up. A
        stream prepares every rendered frame in turn: the velocity of the last preparation is reused."""
        first, older, newest = frames
        if (older.motion_vectors is None or first.depth.shape != older.depth.shape
                or not first.time < older.time < newest.time):
            return None
        key, before = self._previous
        if key != self._key(older, first):
            before, _ = self._velocity(older, first, self._vectors(older))
        return before, (newest.time - older.time) / (older.time - first.time)

    def _shaped(self, history, vectors: np.ndarray, data: MvecState, before: tuple[np.ndarray, float],
                change: Optional[tuple], timer: Timer) -> PointMotion:
        """Pass ``rigid``: the moving pixels' motion as the warp extrapolates it. With ``extrapolation=rigid``
        the pixels of each rigid part (``engine.geometry.rigid``: ``find_parts``) move on their part's path
        (``part_paths``: the screw, or the spin about the part's centre where the interval before says so, with
        its change where the three frames agree) where that path explained the last interval at least as well as
        the points' own lines; the others keep their line or parabola. With ``fallback``, each region (a rigid
        part, or the rest of a group of pixels that move alike) whose motion of the interval before, continued,
        explained the last interval worse than ``fallback_ratio`` times no object motion is left out: it takes
        the camera-only warp. Fits and checks read a grid sample. Needs frame n-2k (``before``: frame n-k's
        velocity and the ratio of the intervals, ``_before``). ``change`` (``velocity_change_args``, with
        ``acceleration``): the change of velocity is computed here, for the kept pixels that keep their own
        motion only (``kept_part_motion``). Its steps are timed as stages ``rigid.groups`` (the moving points and
        their groups), ``rigid.parts`` (the sample's history, the parts and their paths; with ``fallback`` alone,
        the history) and ``rigid.keep`` (the fall-back's check, every pixel's motion)."""
        cfg = self.config
        older, newest = history[-2], history[-1]
        k = np.asarray(newest.camera.intrinsics, np.float64)
        moving = data.moving
        h, w = newest.depth.shape
        # fits and checks run on a sample: the moving pixels on a grid of ``stride`` pixels
        with timer("rigid.groups"):
            stride = max(1, math.ceil(math.sqrt(moving.size / SAMPLES)))
            now, speed, z, sample = moving_points(newest.depth, data.velocity, moving, k, stride)
            if cfg.grouping == "ids" and newest.object_id is not None and newest.object_id.shape == (h, w):
                _, labels = np.unique(newest.object_id.reshape(-1)[moving], return_inverse=True)  # numbered by id
                labels = labels.astype(np.int64).reshape(-1)
                count = int(labels.max()) + 1
            else:
                labels, count = motion_components((h, w), moving, now, speed)
        with timer("rigid.parts"):
            now_s, then_s, scale_s = now[sample], now[sample] - speed[sample], k[0, 0] / z[sample]
            relative = older.camera.world_to_camera @ newest.camera.camera_to_world
            first = (history[-3].depth, history[-3].camera.intrinsics,
                     history[-3].camera.world_to_camera @ newest.camera.camera_to_world)
            # serial steps, two at a time: the sample's positions at n-2k, then the zeroing of pass ``rigid``'s
            # velocity, on a kernel thread (``run_beside``), while this thread fits the parts (they read the same
            # inputs and write their own outputs: the same bits)
            earlier_valid = kernels.run_beside(lambda: previous_positions(
                newest.depth, vectors, moving[sample], then_s, relative, older.depth, before[0], before[1],
                band=cfg.depth_band, first=first))
            out = np.empty((h, w, 3), np.float32)
            zeroed = kernels.run_beside(lambda: kernels.fill_zeros(out.reshape(-1)))
            paths = PartPaths.stack([], [])
            if cfg.extrapolation == "rigid":
                fitted = refined_before(then_s, vectors, moving[sample], relative, older.depth, older.camera.intrinsics)
                table = find_parts(labels[sample], count, now_s, fitted, scale_s, threshold=cfg.rigid_threshold,
                                   min_points=max(8, 32 // stride ** 2))
            earlier, valid = earlier_valid()
            predicted = 2.0 * then_s - earlier  # the interval before, extrapolated: constant velocity
            if cfg.extrapolation == "rigid":
                # a part turning faster than MAX_TURN keeps its lines (faster turns alias); the others take their path
                # only where it, continued from the interval before, explained the last interval at least as well as
                # its points' own lines did (else: a wobble, a deformation, or too few points seen at n-2k to tell)
                paths = part_paths(table, now_s, fitted, earlier, valid, scale_s, predicted, k,
                                   threshold=cfg.rigid_threshold,
                                   limit=cfg.acceleration_limit if cfg.acceleration else -1.0)
        with timer("rigid.keep"):
            # every pixel of a part's group that the part's transform explains takes its path (the sample's depths
            # were read between pixels, the others' at one: a looser threshold); the others keep their own motion
            data.parts = len(paths.group)
            keep = np.ones(count + data.parts, dtype=bool)
            limit = ASSIGN * cfg.rigid_threshold
            if cfg.fallback:  # the sample's regions (their rigid part, else their group) keep or drop their motion
                _, _, regions = apply_parts(now_s, speed[sample], z[sample], labels[sample], count, paths, k[0, 0],
                                            limit)
                keep = hindcast_keeps(regions, count + data.parts, now_s, then_s, predicted, valid, k,
                                      ratio=cfg.fallback_ratio)
            zeroed()
            velocity, moving, acceleration = kept_part_motion((h, w), moving, now, speed, z, labels, count, paths,
                                                              k[0, 0], limit, None, keep, change, out)
            data.held = int(data.moving.size - moving.size)
        return PointMotion(velocity, moving, acceleration if data.parts or change is not None else None)

    def object_flow(self, state: PreparedState) -> np.ndarray:
        """The u(n -> n-k) of frame n implied by its vectors, (H, W, 2) pixels (object motion alone, seen
        from frame n's camera: the 3D velocity reversed and projected), for the end-point error."""
        newest = state.history[-1]
        return extrapolated_flow(newest.depth, state.data.velocity, newest.camera.intrinsics, -1.0,
                                 state.data.moving)[..., :2]

    def _render(self, state, target, timer):
        if state.data.motion is None:  # nothing moves: reproject's warp
            return self.frames.warp_and_fill(state.data.frame, target, timer)
        return self.frames.warp_and_fill(state.data.frame, target, timer, state.data.motion,
                                         extrapolation_factor(state, target))

