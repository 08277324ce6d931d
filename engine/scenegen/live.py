"""The live mode of the scene renderer: a frame drawn as a game draws it, left on the GPU.

``SceneRenderer`` is the ground-truth mode (evaluation, training data): colour supersampled, a second pass
for the exact ground truth, motion vectors in float64 on the CPU, everything read back. ``LiveSceneRenderer``
draws what a real-time renderer hands a frame generator, on the frame backend's GL context
(``engine.geometry.backends.gl.shared_context``), with nothing read back unless asked:

1. the sun's shadow map (as the ground-truth mode);
2. ONE pass over the scene into two float32 render targets: the shaded colour and the planar depth
   (camera-space z), and the motion vector of each pixel. Each vertex is transformed by this frame's and by
   the previous frame's object and camera transforms (``u_prev_cam_from_obj``: camera(previous) from
   object(previous), composed in float64), and the fragment projects the interpolated previous point with
   the previous camera's intrinsics: the vector (pixels, x right, y down) from the pixel centre to where the
   same surface point was, camera motion included (``Frame.motion_vectors``, ``mvec``'s input). The sky is
   drawn behind in the same pass: its vector comes from the camera's rotation alone;
3. a compute pass (``frame_from_targets``) that copies the targets into the backend's frame layout (rows top
   to bottom): colour and depth buffers (a ``GlImage`` the predictors warp without an upload) and the
   vectors, +inf depth and NaN vectors where there is no surface / no vector.

It draws one sample per pixel (``supersample`` must be 1) and without the Monte Carlo-like noise of
``render_noise`` (a rasteriser has none; it must be 0). ``tests/scenegen/test_live.py`` holds its colour,
depth and vectors to the ground-truth mode's (``SceneRenderer.render_frame`` and its float64
``motion_vectors``) on frames of a moving scene on llvmpipe.
"""
from __future__ import annotations

import weakref
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from engine.core.errors import InputError
from engine.core.frames import MAX_MOTION_DIAGONALS, Camera, Frame
from engine.geometry.backends.gl.context import GlContext, shared_context
from engine.geometry.backends.gl.frame import GlImage
from engine.scenegen import glsl
from engine.scenegen.render import ScenePasses, clip_from_camera
from engine.scenegen.scene import Scene

__all__ = ["LiveFrame", "LiveSceneRenderer"]


@dataclass(eq=False)
class LiveFrame:
    """A frame the live renderer left on the GPU: ``image`` (colour (H, W, 3) and planar depth (H, W), float32
    buffers, rows top to bottom: what ``GlFrames.adopt`` hands to the predictors) and ``vectors``, a buffer of
    (H, W, 2) float32 motion vectors to frame ``previous`` (NaN: no vector), all freed with the object.
    ``frame()`` reads them back."""

    index: int
    time: float
    previous: int
    camera: Camera
    image: GlImage
    vectors: object = field(repr=False)

    def __post_init__(self) -> None:
        weakref.finalize(self, self.image.gl.discard, [self.vectors])

    @property
    def shape(self) -> tuple[int, int]:
        return self.image.shape

    def frame(self, color: bool = True) -> Frame:
        """The frame on the host: depth, motion vectors and (with ``color``) colour read back. Without ``color``
        the frame's ``color`` is None: its colour stays on the GPU (``image``), for a backend that has it there."""
        h, w = self.shape
        depth, vectors = np.empty((h, w), np.float32), np.empty((h, w, 2), np.float32)
        rgb = np.empty((h, w, 3), np.float32) if color else None

        def read() -> None:
            self.image.depth.read_into(depth, size=depth.nbytes)
            self.vectors.read_into(vectors, size=vectors.nbytes)
            if rgb is not None:
                self.image.color.read_into(rgb, size=rgb.nbytes)
        self.image.gl.call(read)
        return Frame(index=self.index, time=self.time, color=rgb, depth=depth, camera=self.camera,
                     motion_vectors=vectors)

    def read_color(self) -> np.ndarray:
        """The colour (H, W, 3) float32 on the host."""
        out = np.empty(self.shape + (3,), np.float32)
        self.image.gl.call(lambda: self.image.color.read_into(out, size=out.nbytes))
        return out


class LiveSceneRenderer(ScenePasses):
    """Draws frames of ``scene`` in one pass with colour, depth and motion vectors, on ``gl`` (default: the frame
    backend's shared context, so that the frames reach the predictors without a copy); every GL call runs on
    the context's thread. Release it when done (the context stays).

    >>> renderer = LiveSceneRenderer(make_scene(SceneConfig(width=64, height=48, supersample=1)))  # doctest: +SKIP
    >>> live = renderer.render(5, previous=3)                       # vectors to frame 3, on the GPU  # doctest: +SKIP
    >>> frame = live.frame()                                        # read back  # doctest: +SKIP
    """

    SOURCES = {"live": (glsl.GEOMETRY_VS, glsl.LIVE_FS), "shadow": (glsl.SHADOW_VS, glsl.SHADOW_FS),
               "sky_live": (glsl.FULLSCREEN_VS, glsl.SKY_LIVE_FS)}

    def __init__(self, scene: Scene, gl: Optional[GlContext] = None) -> None:
        cfg = scene.config
        if cfg.supersample != 1:
            raise InputError(f"the live renderer draws one sample a pixel: supersample must be 1, got "
                             f"{cfg.supersample}", field="supersample")
        if cfg.render_noise > 0:
            raise InputError(f"the live renderer draws without Monte Carlo noise: render_noise must be 0, got "
                             f"{cfg.render_noise}", field="render_noise")
        self._released = False
        if gl is None:
            try:
                gl = shared_context()
            except RuntimeError as exc:  # no EGL, no GL 4.5: one line, as for --backend gl
                raise InputError(f"the live renderer draws on the GL backend's context, which cannot run here "
                                 f"({exc}); use the ground-truth renderer", field="renderer") from None
        self.gl = gl
        try:
            self.gl.call(super().__init__, scene, self.gl.ctx)
        except Exception:
            self.release()
            raise

    def _targets(self, w: int, h: int, s: int) -> None:
        """The live pass's targets: (r, g, b, planar depth) and (vector x, y, has a vector, -), float32."""
        self.rgbd, self.motion = self._texture((w, h)), self._texture((w, h))
        self.fbo_live = self._framebuffer([self.rgbd, self.motion], self._texture((w, h), depth=True))

    def render(self, index: int, previous: Optional[int] = None, *, gpu_ms: Optional[dict] = None) -> LiveFrame:
        """Draw frame ``index`` (0 <= index < num_frames) with its motion vectors to frame ``previous`` (default
        ``index - 1``: a renderer drawing every k-th frame points to ``index - k``; any integer: the paths are
        defined for all times). With ``gpu_ms``, the GPU milliseconds of stages ``render`` (shadow map and the
        live pass) and ``readout`` (the copy into the frame layout) are added (GL timer queries)."""
        self._check_index(index)
        previous = index - 1 if previous is None else int(previous)
        return self.gl.call(self._render, index, previous, gpu_ms)

    def _render(self, index: int, previous: int, gpu_ms: Optional[dict]) -> LiveFrame:
        gl, scene = self.gl, self.scene
        cam, before = scene.camera_at(index), scene.camera_at(previous)
        with gl.timing(gpu_ms):
            with gl.gpu_stage("render"):
                self._live_pass(cam, before, self._object_transforms(index), self._object_transforms(previous))
            with gl.gpu_stage("readout"):
                image, vectors = self._readout()
        return LiveFrame(index=index, time=scene.time(index), previous=previous,
                         camera=Camera(cam.intrinsics, cam.world_to_camera), image=image, vectors=vectors)

    def _live_pass(self, cam: Camera, before: Camera, now: np.ndarray, then: np.ndarray) -> None:
        """Shadow map, then the scene and the sky behind it into ``fbo_live`` (``now``, ``then``: the objects'
        transforms of this and of the previous frame, ``_object_transforms``)."""
        mgl, ctx, cfg = self._moderngl, self.ctx, self.scene.config
        w, h = cfg.width, cfg.height
        self._shadow_pass(now)
        ctx.enable(mgl.DEPTH_TEST | mgl.CULL_FACE)
        self.fbo_live.use()
        self.fbo_live.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        ctx.depth_func = "<"
        k, kp = cam.intrinsics, before.intrinsics
        view, view_before = cam.world_to_camera, before.world_to_camera
        for prog in ("live", "sky_live"):
            self._set(prog, "u_prev_k0", np.asarray(kp[0], np.float64))
            self._set(prog, "u_prev_k1", np.array([kp[1, 1], kp[1, 2]]))
            self._set(prog, "u_max_vector", float(MAX_MOTION_DIAGONALS * np.hypot(h, w)))
            self._set(prog, "u_height", float(h))
        self._set("live", "u_proj", clip_from_camera(k, w, h))
        self._set("live", "u_eye", cam.position)
        if self.shadow_map is not None:
            self.shadow_map.use(location=0)
        slot = self._slots()
        for b in self.batches:
            i = slot[b.obj]
            self._set_material(b.material, "live")
            self._set("live", "u_model", now[i])
            self._set("live", "u_cam_from_obj", view @ now[i])
            self._set("live", "u_prev_cam_from_obj", view_before @ then[i])
            b.vaos["live"].render(mgl.TRIANGLES)
        ctx.depth_func = "<="
        k_inv = np.linalg.inv(k)
        self._set("sky_live", "u_world_from_pixel", view[:3, :3].T @ k_inv)
        self._set("sky_live", "u_prev_from_pixel", view_before[:3, :3] @ view[:3, :3].T @ k_inv)
        self._set("sky_live", "u_sky_visible", int(self.scene.sky.visible))
        self.fullscreen["sky_live"].render(mgl.TRIANGLES)
        ctx.depth_func = "<"

    def _readout(self) -> tuple[GlImage, object]:
        """Pass ``frame_from_targets``: new colour, depth and vector buffers in the frame layout."""
        gl, cfg = self.gl, self.scene.config
        h, w = cfg.height, cfg.width
        n = h * w
        color, depth, vectors = gl.new_buffer(12 * n), gl.new_buffer(4 * n), gl.new_buffer(8 * n)
        self.rgbd.use(location=0)
        self.motion.use(location=1)
        for binding, buf in enumerate((color, depth, vectors)):
            buf.bind_to_storage_buffer(binding)
        gl.dispatch(gl.program("frame_from_targets"), n, {"rgbd_target": 0, "motion_target": 1, "size": (h, w)})
        return GlImage((h, w), color, depth, gl), vectors

    def release(self) -> None:
        """Free the renderer's GL objects (safe to call twice); the shared context stays."""
        if self._released:
            return
        self._released = True
        if getattr(self, "_owned", None) is not None:
            self.gl.call(self.release_objects)

    def __enter__(self) -> "LiveSceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()
