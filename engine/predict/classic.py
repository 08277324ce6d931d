"""The classic predictors: ``repeat``, ``reproject`` (timewarp), ``flow2d`` (2D optical-flow extrapolation)
and ``oracle`` (true object motion, the upper bound). Conventions: ``engine/predict/base.py``."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Optional, Sequence

import numpy as np

from engine import geometry
from engine.core.errors import InputError
from engine.core.frames import Frame, SceneObject
from engine.predict.base import (Predictor, PreparedState, ResidentFrame, Target, Timer, extrapolation_factor,
                                 true_object_flow)
from engine.predict.backend import gl_flow_estimators
from engine.predict.corrflow import CorrFlowNetwork, corr_dis_flow
from engine.predict.dis import dis_calc, dis_estimator, drop_untrusted, fall_back, luma8

__all__ = ["Repeat", "Reproject", "Flow2D", "Flow2DState", "Oracle", "ESTIMATORS"]

#: ``flow2d``'s optical-flow estimators: OpenCV DIS on the CPU, the GPU's (``engine.geometry.backends.gl.flow``),
#: or DIS started from the correlation network's estimate (``engine.predict.corrflow``)
ESTIMATORS = ("dis", "gl", "corr")


class Repeat(Predictor):
    """The last rendered frame, unchanged (what a game shows without frame generation)."""

    name = "repeat"

    def _render(self, state, target, timer):
        frame = state.history[-1]
        return frame.color.copy(), np.zeros(frame.depth.shape, dtype=bool)


class Reproject(Predictor):
    """Camera-only depth reprojection of the last frame (timewarp), with the background-biased hole fill."""

    name = "reproject"
    backends = ("cpu", "gl")

    def _prepare(self, state: PreparedState, timer: Timer) -> ResidentFrame:
        return self.frames.resident(state.history[-1], timer)

    def _render(self, state, target, timer):
        return self.frames.warp_and_fill(state.data, target, timer)


@dataclass
class Flow2DState:
    """``flow2d``'s per-frame state: ``flow_back`` (H, W, 2), the estimated u(n -> n-k) in pixels (None when it
    was estimated on the GPU and stays there); ``frame`` and ``flow`` are frame n and that flow where the
    backend computes (on ``gl``: uploaded once, or made there)."""

    flow_back: Optional[np.ndarray]
    frame: ResidentFrame
    flow: Any


class Flow2D(Predictor):
    """2D optical-flow extrapolation in the spirit of spacewarp.

    Frame n-k is warped into frame n's view (camera motion cancelled, holes filled); an optical flow
    estimates the remaining (object) motion from frame n to the warped n-k on 8-bit sRGB luma (``estimator``:
    ``dis``, OpenCV's DIS with a ``preset``, or ``gl``, the pyramidal DIS-style flow of
    ``engine.geometry.backends.gl.flow`` on the GPU: on the ``gl`` backend the whole preparation, trust rules
    included, then runs there without a readback; docs/results/2026-11-25-gl-flow.md; or ``corr``, DIS started
    from the correlation network's estimate, ``engine.predict.corrflow``: the committed network or ``network``,
    an exported one, which reads both frames' depths too when it was trained on RGB-D); the
    flow is extrapolated linearly, u(n -> n+k') = -(k'/k) u(n -> n-k) (thesis Eq. 6.13), and frame n is
    forward-warped by that 2D flow plus the target camera's motion. The flow is 0 (the camera-only warp)
    where frame n-k did not see the surface and where a motion under a pixel does not explain frame n better
    than none (``engine.predict.dis.trusted_motion``); with ``fallback``, also on every region whose motion
    explains frame n from n-k worse than none (``engine.predict.dis.explained_motion``; on the ``gl`` backend
    with ``estimator=gl`` the flow is then read back for it).
    """

    name = "flow2d"
    history_needed = 2
    backends = ("cpu", "gl")

    def __init__(self, preset: str = "medium", estimator: str = "dis", network: str = "",
                 fallback: bool = False) -> None:
        if estimator not in ESTIMATORS:
            raise InputError(f"must be one of {', '.join(ESTIMATORS)}, got {estimator!r}", field="estimator")
        if network and estimator != "corr":
            raise InputError(f"a network is read by estimator=corr only, got estimator={estimator}", field="network")
        self.estimator = estimator
        self.fallback = fallback
        self._dis = dis_estimator(preset)
        self._gl: Optional[tuple] = None
        self._corr: Optional[CorrFlowNetwork] = None
        if estimator == "corr":
            self._corr = CorrFlowNetwork(network or None)

    def _gl_estimators(self) -> tuple:
        """(GlOpticalFlow, GlTrust) of this predictor, made on first use."""
        if self._gl is None:
            self._gl = gl_flow_estimators()
        return self._gl

    def _prepare(self, state: PreparedState, timer: Timer) -> Flow2DState:
        older, newest = state.history[-2], state.history[-1]
        if self.estimator == "gl" and self.frames.name == "gl" and not self.fallback:  # all on the GPU
            previous = self.frames.resident(older, timer)  # n-k first: it is frame n of the last preparation
            frame = self.frames.resident(newest, timer)
            flow = self.frames.estimate_flow_back(previous, frame, *self._gl_estimators(), timer)
            return Flow2DState(None, frame, flow)
        target = Target(newest.camera, newest.time, newest.index)
        depth_w = None
        if (self._corr is not None and self._corr.depth) or self.fallback:  # RGB-D networks, fallback read its depth
            warped, depth_w, _ = self.frames.warp_fill_depth(self.frames.resident(older, timer), target, timer)
        else:
            warped, _ = self.frames.warp_and_fill(self.frames.resident(older, timer), target, timer)
        luma_n, luma_w = luma8(newest.color), luma8(warped)
        with timer("flow"):
            if self.estimator == "gl":
                flow = self._gl_estimators()[0].estimate(newest.color, warped)
            elif self._corr is not None:
                flow = corr_dis_flow(self._corr, self._dis, newest.color, warped, luma_n, luma_w, newest.depth, depth_w)
            else:
                flow = dis_calc(self._dis, luma_n, luma_w)
        with timer("trust"):
            src, dst = older.camera, newest.camera
            seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics,
                                        src.world_to_camera, older.depth.shape)
            drop_untrusted(flow, luma_n, luma_w, seen)
        if self.fallback:
            with timer("fallback"):
                fall_back(flow, luma_n, luma_w, newest.depth, dst.intrinsics, (newest.color, warped), depth_w)
        return self.state_of(newest, flow, timer)

    def state_of(self, newest, flow_back: np.ndarray, timer: Timer) -> Flow2DState:
        """The state of frame ``newest`` with its estimated u(n -> n-k) ``flow_back``, made resident on the
        backend."""
        return Flow2DState(flow_back, self.frames.resident(newest, timer), self.frames.resident_flow(flow_back, timer))

    def object_flow(self, state: PreparedState) -> np.ndarray:
        """The estimated u(n -> n-k) of frame n, (H, W, 2) pixels (read back when it was made on the GPU)."""
        data = state.data
        return data.flow.read() if data.flow_back is None else data.flow_back

    def _render(self, state, target, timer):
        return self.frames.warp_and_fill(state.data.frame, target, timer, state.data.flow,
                                         -extrapolation_factor(state, target))


class Oracle(Predictor):
    """Upper bound: moves every pixel of frame n by its object's TRUE rigid motion, then by the camera's.

    Uses the ``object_id`` channel and the sequence's per-frame object transforms; times between frames
    are not interpolated, so the target must be a frame of the sequence (``target.index``).
    """

    name = "oracle"
    backends = ("cpu", "gl")

    def __init__(self, objects: Sequence[SceneObject]) -> None:
        self.objects = {o.id: o for o in objects}

    def _prepare(self, state: PreparedState, timer: Timer) -> ResidentFrame:
        return self.frames.resident(state.history[-1], timer)

    def _true_flow(self, frame: Frame, target: Target) -> np.ndarray:
        """Frame n's true object flow to the target frame (what subclasses that know another truth replace)."""
        return true_object_flow(frame, self.objects, target.index)

    def _render(self, state, target, timer):
        with timer("motion"):
            flow = self._true_flow(state.history[-1], target)
        return self.frames.warp_and_fill(state.data, target, timer, flow)
