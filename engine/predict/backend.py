"""Where a predictor's warp runs: the frame backends behind ``Predictor.frames``.

A predictor hands its frames to its backend once per rendered frame (``resident``: on ``gl`` the colour and
depth are uploaded to GPU buffers then) and, for every predicted frame, asks it to forward-warp and hole-fill
one of them to the target camera, optionally moved by an object flow times a scale (``warp_and_fill``).
``engine.predict.base.CpuFrames`` is ``warp_and_fill`` (numpy + numba); ``GlFrames`` runs the same passes as
OpenGL compute (``engine.geometry.backends.gl.GlFrameWarper``) and reads back only the predicted frame. A flow
made resident (``resident_flow``: uploaded once) is scaled on the GPU, so ``flow2d`` extrapolates to every
in-between frame without a new upload. ``gl`` adds the GPU milliseconds of its stages (GL timer queries) to
``timer.gpu``. Conventions: ``engine/predict/base.py``.
"""
from __future__ import annotations

import threading

import numpy as np

from engine.core.errors import InputError
from engine.core.frames import Frame
from engine.geometry.backends.gl.flow import GlOpticalFlow
from engine.geometry.backends.gl.frame import GlFlow, GlFrameWarper, GlMotion
from engine.geometry.backends.gl.trust import GlTrust
from engine.geometry.camera import reprojection_matrix
from engine.predict.base import PointMotion, ResidentFrame, Target, Timer
from engine.predict.dis import CONFIDENCE_MARGIN, CONFIDENCE_WINDOW, SMALL_MOTION

__all__ = ["GlFrames", "gl_flow_estimators"]


def gl_flow_estimators() -> tuple[GlOpticalFlow, GlTrust]:
    """The GPU's optical flow and its trust passes with ``flow2d``'s rules (``engine.predict.dis.trusted_motion``)
    on the shared context: what ``GlFrames.estimate_flow_back`` takes."""
    return GlOpticalFlow(), GlTrust(SMALL_MOTION, CONFIDENCE_MARGIN, CONFIDENCE_WINDOW)


class GlFrames:
    """The GL backend: frames and flows in GPU buffers, the warp and the fill as compute passes. Wall stages:
    ``upload`` (a frame, flow or motion sent to the GPU) and ``warp`` (the dispatches, the hole fill and the
    readback of the predicted frame); GPU stages (``timer.gpu``): ``motion`` (extrapolating a ``PointMotion``),
    ``warp``, ``fill``, ``encode`` (a ``srgb8`` target), ``readback``."""

    name = "gl"

    def __init__(self, warper=None) -> None:
        self.warper = GlFrameWarper() if warper is None else warper
        self._kept: list[ResidentFrame] = []  # the two frames asked for last (``resident``)
        self._lock = threading.Lock()

    def resident(self, frame: Frame, timer: Timer) -> ResidentFrame:
        """The frame uploaded: its 8-bit codes decoded on the GPU where it has them (``Frame.color_codes``),
        else its float colour. Uploaded once: the two frames asked for last are kept (by identity: a frame's
        arrays must not change once it was handed over), so a method that asks for frame n-k before frame n
        finds frame n of its last preparation there."""
        with self._lock:
            kept = next((r for r in self._kept if r.frame is frame), None)
        if kept is None:
            with timer("upload"):
                if frame.color_codes is not None:
                    kept = ResidentFrame(frame, self.warper.upload_codes(frame.color_codes, frame.depth))
                else:
                    kept = ResidentFrame(frame, self.warper.upload(frame.color, frame.depth))
        with self._lock:
            self._kept = [r for r in self._kept if r is not kept][-1:] + [kept]
        return kept

    def adopt(self, frame: Frame, image) -> ResidentFrame:
        """Take ``frame`` as resident with ``image``, a ``GlImage`` of this backend's context that already holds
        its colour and depth (a renderer on the shared context drew it: ``engine.scenegen.live``), so that
        ``resident(frame)`` finds it instead of uploading. The frame's host ``color`` may then be None: the methods
        whose preparation reads only depth and vectors on the host (``reproject``, ``mvec``) never touch it."""
        if getattr(image, "gl", None) is not self.warper.gl or tuple(image.shape) != frame.depth.shape:
            raise InputError(f"must be a GlImage of this backend's context and of the frame's size "
                             f"{frame.depth.shape}", frame=frame.index, field="image")
        kept = ResidentFrame(frame, image)
        with self._lock:
            self._kept = [r for r in self._kept if r.frame is not frame][-1:] + [kept]
        return kept

    def resident_flow(self, flow, timer: Timer):
        """A flow (H, W, 2|3) uploaded as a ``GlFlow``, or a ``PointMotion`` as a ``GlMotion`` (its moving
        pixels only)."""
        with timer("upload"):
            if isinstance(flow, PointMotion):
                return self.warper.upload_motion(flow.velocity.shape[:2], flow.moving,
                                                 flow.velocity.reshape(-1, 3)[flow.moving], flow.acceleration)
            return self.warper.upload_flow(flow)

    def warp_and_fill(self, source: ResidentFrame, target: Target, timer: Timer, flow=None,
                      flow_scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
        """``CpuFrames.warp_and_fill`` on the GPU; a numpy ``flow`` or a ``PointMotion`` is uploaded for this
        call, a resident one (``resident_flow``) is not. The colour comes back in ``target.encoding``
        (``srgb8``: encoded on the GPU, GPU stage ``encode``)."""
        if source.image is None:
            source = self.resident(source.frame, timer)
        if isinstance(flow, (np.ndarray, PointMotion)):
            flow = self.resident_flow(flow, timer)
        motion = flow if isinstance(flow, GlMotion) else None
        src, dst = source.frame.camera, target.camera
        with timer("warp"):
            out = self.warper.warp_and_fill(source.image, src.intrinsics, src.world_to_camera, dst.intrinsics,
                                            dst.world_to_camera, None if motion else flow, flow_scale,
                                            gpu_ms=timer.gpu, motion=motion, encoding=target.encoding,
                                            readback=not target.resident)
        return (out, None) if target.resident else out  # resident: a GlPrediction, nothing read back

    def warp_fill_depth(self, source: ResidentFrame, target: Target,
                        timer: Timer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``CpuFrames.warp_fill_depth`` on the GPU: the filled depth comes from the same fill pass and is read
        back beside the colour. Returns (colour, depth, holes)."""
        if source.image is None:
            source = self.resident(source.frame, timer)
        src, dst = source.frame.camera, target.camera
        with timer("warp"):
            color, holes, depth = self.warper.warp_and_fill(source.image, src.intrinsics, src.world_to_camera,
                                                            dst.intrinsics, dst.world_to_camera, gpu_ms=timer.gpu,
                                                            with_depth=True)
        return color, depth, holes

    def estimate_flow_back(self, older: ResidentFrame, newest: ResidentFrame, estimator, trust, timer: Timer) -> GlFlow:
        """``flow2d``'s preparation on the GPU, nothing read back: frame n-k warped into frame n's view and
        filled (stage ``warp``), the flow u(n -> n-k) from frame n to it by ``estimator`` (a
        ``engine.geometry.backends.gl.GlOpticalFlow``; stage ``flow``), its untrusted motion zeroed by ``trust``
        (a ``GlTrust``; stage ``trust``). Returns the flow (H, W, 2) on the GPU."""
        if older.image is None:
            older = self.resident(older.frame, timer)
        if newest.image is None:
            newest = self.resident(newest.frame, timer)
        src, dst = older.frame.camera, newest.frame.camera
        with timer("warp"):
            warped = self.warper.warp_and_fill(older.image, src.intrinsics, src.world_to_camera, dst.intrinsics,
                                               dst.world_to_camera, gpu_ms=timer.gpu, readback=False)
        with timer("flow"):
            flow = estimator.estimate_buffers(newest.image.color, warped.color, newest.image.shape, gpu_ms=timer.gpu,
                                              as_gl=True)
        matrix = reprojection_matrix(dst.intrinsics, dst.world_to_camera, src.intrinsics, src.world_to_camera)
        gl = self.warper.gl

        def apply():
            with gl.timing(timer.gpu), gl.gpu_stage("trust"):
                trust.apply_buffers(*estimator.lumas(), flow.buffer, newest.image.depth, newest.image.shape, matrix,
                                    older.frame.depth.shape)
        with timer("trust"):
            gl.call(apply)
        return flow
