"""The GL backend: OpenGL 4.5 compute passes (``shaders/*.comp``, one per pass) on a headless EGL context.

``context`` (the context, its thread, programs, buffers, GPU timer queries), ``splat`` (the MPI forward
splat, ``GlSplatter``), ``frame`` (a frame uploaded once, warped and hole-filled on the GPU,
``GlFrameWarper``). Every pass has a CPU oracle (``engine.geometry``); the tests hold them to it on Mesa
llvmpipe.
"""
from engine.geometry.backends.gl.context import GlContext, available, shared_context
from engine.geometry.backends.gl.flow import GlFlowConfig, GlOpticalFlow
from engine.geometry.backends.gl.frame import GlFlow, GlFrameWarper, GlImage, GlMotion, GlPrediction
from engine.geometry.backends.gl.splat import GlSplatter

__all__ = ["GlContext", "available", "shared_context", "GlFlow", "GlFrameWarper", "GlImage", "GlMotion",
           "GlPrediction", "GlSplatter", "GlFlowConfig", "GlOpticalFlow"]
