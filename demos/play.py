"""`interleave play`: a renderer draws every k-th frame, Interleave generates the rest, live or recorded.

The player core (:class:`Player`) needs no window. Each display tick it either has the renderer draw the
frame (every k-th tick: the built-in procedural scene through ``engine.scenegen.SceneRenderer``, or an
exported radiance field through ``engine.fields.gl.GlFieldRenderer``) and submits it to the one predictor
loop (``engine.runtime.stream.PredictionLoop``), or it generates the frame from what the loop prepared, for
the tick's camera and time. It measures the renderer's and the predictor's wall time per frame, keeps the
predictor's per-stage wall and GPU milliseconds (``Prediction.stages_ms`` and ``gpu_ms``), and composes
the displayed image: the frame, or the split view truth | generated | error (the truth of a generated tick
is the renderer's own frame at that pose, drawn only in split view), with an overlay of the numbers.

Conventions: frames are linear RGB (``engine.core.frames``); composed images are 8-bit sRGB-encoded RGB
(``engine.core.colorspace.display_encode``), rows top to bottom, shape (height, panels * width, 3). The
error panel is the mean absolute difference of the encoded images over the channels, times 4, in the
``magma`` colour map. Rendered fps is 1000 / the renderer's median wall ms per frame (draw and read-back),
generated fps 1000 / the predictor's median wall ms per generated frame (``PredictionLoop.predict``; the
per-rendered-frame ``prepare`` is shown apart), shown fps the ticks per wall second of the whole loop
(split view's truth renders included). Medians run over the last :data:`WINDOW` samples.

On the gl backend the player takes the gl path: the built-in scene is drawn by the live renderer
(:class:`LiveSceneSource`, ``engine.scenegen.live``) on the frame backend's GL context, its frames reach the
predictors without a copy, predictions stay on the GPU, and every shown frame is drawn from a texture into an
offscreen display (:class:`GlDisplay`); nothing is read back per shown frame but for a recording, the window or
the split view (docs/gpu.md, "The live loop on the GPU").

Four ways to run it: :func:`iter_frames` (composed frames, no window: tests, scripts), :func:`record`
(a video, ``cv2.VideoWriter`` with ``mp4v``), :func:`run_headless` (nothing shown: a benchmark) and
:func:`run_window` (a pyglet window; keys M, K, S, Q/Esc). :func:`play` is what the command runs: the window when
a display can be opened, else a recording.
"""
from __future__ import annotations

import dataclasses
import json
import os
import queue
import statistics
import sys
import threading
import time
from collections import deque
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Literal, Optional, Sequence

import cv2
import numpy as np

from engine.core.config import option
from engine.core.errors import InputError, InterleaveError
from engine.core.frames import Frame
from engine.geometry import encoding
from engine.geometry.motion import camera_motion_vectors
from engine.predict import Prediction, Predictor, Target, make_predictor, resolve_auto
from engine.predict.base import Timer
from engine.runtime.stream import PredictionLoop

__all__ = ["PlayConfig", "PlaySummary", "Player", "SceneSource", "LiveSceneSource", "FieldSource", "make_source",
           "GlDisplay", "overlay_canvas", "iter_frames", "record", "run_headless", "run_window", "play", "compose",
           "METHOD_CYCLE", "K_CYCLE", "GPU_COLOR_METHODS", "DEFAULT_RECORDING", "DEFAULT_FRAMES"]

#: The methods key M cycles through (the configured method joins them when it is not one of them).
METHOD_CYCLE = ("reproject", "flow2d", "mvec", "decomp")
#: The values of k key K cycles through (the configured k joins them when it is not one of them).
K_CYCLE = (2, 3, 4)
#: Samples the overlay's medians run over.
WINDOW = 30
#: Where ``play`` records when no window can be opened and no ``record`` path was given.
DEFAULT_RECORDING = Path("out/play/play.mp4")
#: Ticks a recording takes when ``frames`` is 0.
DEFAULT_FRAMES = 240
#: Scale of the error panel: |truth - generated| (sRGB-encoded, 0..1) times this, clipped to 1.
ERROR_GAIN = 4.0

_PRESETS = Literal["gentle", "medium", "fast", "extreme"]
_BACKENDS = Literal["auto", "cpu", "gl"]
_RENDERERS = Literal["auto", "live", "truth"]
#: Methods whose preparation on the gl backend reads only depth and motion vectors on the host: a live frame's
#: colour stays on the GPU for them (for the others it is read back once per rendered frame).
GPU_COLOR_METHODS = ("reproject", "mvec")


@dataclass(frozen=True)
class PlayConfig:
    """What ``interleave play`` shows and where it goes; every field is a command-line option."""

    seed: int = option(7, "seed of the built-in procedural scene")
    preset: _PRESETS = option("gentle", "motion preset of the built-in scene: gentle, medium, fast or extreme "
                                        "(engine/scenegen/presets.py)")
    field: Optional[str] = option(None, "an exported radiance field (the folder 'interleave export field' wrote, "
                                        "or its run folder) to render instead of the built-in scene, along a camera "
                                        "path through its scene")
    width: int = option(640, "frame width in pixels")
    height: int = option(360, "frame height in pixels")
    supersample: int = option(1, "colour supersampling of the built-in scene per axis (1..4; the demo uses 2)")
    loop: int = option(240, "frames of the scene (or of the field's camera path) before it starts over")
    k: int = option(2, "one rendered frame every k ticks; the k - 1 in between are generated")
    method: str = option("auto", "the predictor: auto (mvec where the renderer gives motion vectors, which both "
                                 "sources do, else flow2d), or a method name as in 'interleave eval --methods'")
    backend: _BACKENDS = option("auto", "where the predictor's warps run: cpu, gl, or auto (gl on a hardware GPU)")
    split: bool = option(False, "start in the split view truth | generated | error")
    fps: float = option(30.0, "display rate: the window's pace and the video's frame rate (each tick shows the "
                              "next frame of the scene, whose own clock is its preset's)")
    frames: int = option(0, f"ticks to play, then stop (0: the window runs until closed, a recording takes "
                            f"{DEFAULT_FRAMES})")
    record: Optional[str] = option(None, "record headless to this video file (mp4v) instead of opening a window")
    screenshot: Optional[str] = option(None, "window mode: save the window's last frame, read back from its "
                                             "framebuffer, to this PNG when it closes")
    renderer: _RENDERERS = option("auto", "the built-in scene's renderer: live (colour, depth and motion vectors in "
                                          "one GPU pass, frames left on the GPU; one sample a pixel, no Monte Carlo "
                                          "noise), truth (the ground-truth renderer: supersampled colour, exact "
                                          "vectors in float64 on the CPU, read back), or auto (live on the gl "
                                          "backend with supersample 1, else truth)")
    headless: bool = option(False, "play without a window or a recording, then print the summary (a benchmark: "
                                   "on the gl backend the frames are drawn offscreen from textures and none is "
                                   "read back)")
    json: Optional[str] = option(None, "also write the summary, with the median GPU ms per stage, to this JSON file")

    def __post_init__(self) -> None:
        checks = [
            (self.width >= 16 and self.height >= 16, "width and height must be >= 16"),
            (1 <= self.supersample <= 4, "supersample must be 1..4"),
            (self.loop >= 2, "loop must be >= 2"),
            (self.k >= 1, "k must be >= 1"),
            (np.isfinite(self.fps) and self.fps > 0, "fps must be > 0"),
            (self.frames >= 0, "frames must be >= 0"),
            (not (self.headless and self.record), "headless plays without a recording: give --headless or --record"),
            (not (self.field and self.renderer == "live"), "the live renderer draws the built-in scene, not a field "
                                                           "(--renderer live with --field)"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="PlayConfig")


# ----------------------------------------------------------------------------------------------------
# Sources: the renderer that draws a tick's frame


class SceneSource:
    """The built-in procedural scene (``engine.scenegen``) drawn by the ground-truth renderer: frames
    ``0 .. loop - 1`` on the preset's clock, again and again.

    A tick ``t`` shows scene frame ``t % loop``; a wrap is a camera cut (:meth:`cut`). A rendered frame's
    motion vectors point to the previous rendered frame (what a renderer drawing every k-th frame writes),
    exact from the frame's depth, ids and the objects' rigid motion (``rigid_motion_vectors``).
    """

    has_motion_vectors = True
    live = False  # frames come as host arrays

    def __init__(self, config: PlayConfig) -> None:
        from engine.scenegen import SceneRenderer, make_scene
        from engine.scenegen.presets import preset_config

        self.scene = make_scene(preset_config(config.preset, seed=config.seed, width=config.width,
                                              height=config.height, num_frames=config.loop,
                                              supersample=config.supersample))
        self.objects = self.scene.scene_objects()
        self.length = config.loop
        self.name = f"scene {config.preset} seed {config.seed}"
        self.renderer = SceneRenderer(self.scene)

    def cut(self, tick: int) -> bool:
        """Whether ``tick`` starts the scene again (the first tick and every wrap)."""
        return tick % self.length == 0

    def frame(self, tick: int, previous: Optional[int]) -> Frame:
        """The rendered frame of ``tick``; its motion vectors point to tick ``previous`` (None: one frame back)."""
        index = tick % self.length
        frame = self.renderer.render_frame(index)
        if previous is not None and previous != tick - 1:
            frame.motion_vectors = self.renderer.motion_vectors(index, frame.depth, frame.object_id, frame.camera,
                                                                previous % self.length)
        return frame

    def target(self, tick: int) -> Target:
        """The camera and time of ``tick`` (what a game knows before drawing it)."""
        index = tick % self.length
        return Target(self.scene.camera_at(index), self.scene.time(index), index)

    def truth(self, tick: int) -> np.ndarray:
        """The renderer's colour of ``tick`` (linear RGB): the truth a generated frame is compared with."""
        return self.renderer.render_frame(tick % self.length).color

    def release(self) -> None:
        self.renderer.release()


class FieldSource:
    """An exported radiance field rendered by ``engine.fields.gl.GlFieldRenderer`` (static) or
    ``engine.fields.gldynamic.GlDynamicRenderer`` (dynamic) along ``field_camera_path`` (``loop`` cameras,
    walked forth and back so that the loop has no jump; a dynamic field's times go forth and back over its
    trained range with them).

    Time is ``tick / fps``; only the first tick is a cut. The motion vectors point to the previous rendered
    frame: a static field's are the camera's alone (``camera_motion_vectors`` from the rendered depth), a
    dynamic field's its own (the motion field inverted, ``GlDynamicRenderer.render(..., earlier_...)``, where it
    is steady: ``coherence=COHERENCE``, as the field demo's ``field_vector_source``).
    The path goes through the run's training cameras where torch can read them, else through the field's own
    scene description (as the field demo's).
    """

    has_motion_vectors = True
    live = False
    objects: Sequence = ()

    def __init__(self, config: PlayConfig) -> None:
        from demos.upsample import is_dynamic_export, resolve_field_dir, train_cameras
        from engine.fields.camera_path import field_camera_path

        export, run = resolve_field_dir(Path(config.field))
        self.dynamic = is_dynamic_export(export)
        if self.dynamic:
            from engine.fields.dynamic import load_dynamic_field
            from engine.fields.gldynamic import GlDynamicRenderer as Renderer

            assets = load_dynamic_field(export)
        else:
            from engine.fields.gl import GlFieldRenderer as Renderer
            from engine.fields.render import load_field

            assets = load_field(export)
        cameras, width, height = field_camera_path(assets, train_cameras(run, dynamic=self.dynamic), config.loop,
                                                   config.width, config.height)
        self.cameras = cameras + cameras[-2:0:-1]
        times = [0.0] * len(cameras)
        if self.dynamic:
            t0, t1 = assets.time_range
            times = list(t0 + (t1 - t0) * np.arange(len(cameras)) / max(len(cameras) - 1, 1))
        self.times = times + times[-2:0:-1]
        self.length = len(self.cameras)
        self.fps = config.fps
        self.name = f"{'dynamic ' if self.dynamic else ''}field {export}"
        self.renderer = Renderer(assets, width, height)

    def cut(self, tick: int) -> bool:
        return tick == 0

    def _render(self, tick: int, before: Optional[int] = None) -> dict:
        cam = self.cameras[tick % self.length]
        if not self.dynamic:
            return self.renderer.render(cam.intrinsics, cam.world_to_camera)
        time = self.times[tick % self.length]
        if before is None:
            return self.renderer.render(cam.intrinsics, cam.world_to_camera, time)
        from engine.fields.dynamic import COHERENCE  # the field's motion where it is steady, as the field demo's
        return self.renderer.render(cam.intrinsics, cam.world_to_camera, time,
                                    earlier_world_to_camera=self.cameras[before % self.length].world_to_camera,
                                    earlier_time=self.times[before % self.length], coherence=COHERENCE)

    def frame(self, tick: int, previous: Optional[int]) -> Frame:
        cam = self.cameras[tick % self.length]
        before = tick - 1 if previous is None else previous
        out = self._render(tick, before)
        if self.dynamic:
            return Frame(index=tick, time=tick / self.fps, color=out["color"], depth=out["depth"], camera=cam,
                         motion_vectors=out["motion_vectors"])
        return Frame(index=tick, time=tick / self.fps, color=out["color"], depth=out["depth"], camera=cam,
                     object_id=np.zeros(out["depth"].shape, np.int32),
                     motion_vectors=camera_motion_vectors(out["depth"], cam, self.cameras[before % self.length]))

    def target(self, tick: int) -> Target:
        return Target(self.cameras[tick % self.length], tick / self.fps, tick)

    def truth(self, tick: int) -> np.ndarray:
        return self._render(tick)["color"]

    def release(self) -> None:
        self.renderer.release()


class LiveSceneSource(SceneSource):
    """The built-in scene drawn by the live renderer (``engine.scenegen.live.LiveSceneRenderer``) on the frame
    backend's GL context: colour, depth and motion vectors to the previous rendered frame in one GPU pass.
    ``render`` leaves the frame there (a ``LiveFrame``: the player hands its colour and depth to the gl predictors
    without a copy and reads back only the depth and the vectors, for the preparation on the CPU). The preset's
    Monte Carlo noise is left out (a rasteriser has none)."""

    live = True

    def __init__(self, config: PlayConfig) -> None:
        from engine.scenegen import make_scene
        from engine.scenegen.live import LiveSceneRenderer
        from engine.scenegen.presets import preset_config

        self.scene = make_scene(preset_config(config.preset, seed=config.seed, width=config.width,
                                              height=config.height, num_frames=config.loop,
                                              supersample=config.supersample, render_noise=0.0))
        self.objects = self.scene.scene_objects()
        self.length = config.loop
        self.name = f"scene {config.preset} seed {config.seed} (live)"
        self.renderer = LiveSceneRenderer(self.scene)

    def render(self, tick: int, previous: Optional[int], gpu_ms: Optional[dict] = None):
        """The ``LiveFrame`` of ``tick``, its vectors to tick ``previous`` (None: one frame back), on the GPU."""
        index = tick % self.length
        return self.renderer.render(index, None if previous is None else previous % self.length, gpu_ms=gpu_ms)

    def frame(self, tick: int, previous: Optional[int]) -> Frame:
        return self.render(tick, previous).frame()

    def truth(self, tick: int) -> np.ndarray:
        return self.renderer.render(tick % self.length).read_color()


def _gl_display(config: PlayConfig) -> bool:
    """Whether ``config`` plays on the gl path (frames drawn from GPU textures): its backend resolves to gl."""
    from engine.geometry.backends import resolve_backend

    return resolve_backend(config.backend) == "gl"


def make_source(config: PlayConfig):
    """The renderer of ``config``: :class:`FieldSource` when ``config.field`` is set, else the built-in scene by
    :class:`LiveSceneSource` (``renderer`` live, or auto on the gl backend with supersample 1) or
    :class:`SceneSource`."""
    if config.field:
        return FieldSource(config)
    live = config.renderer == "live" or (config.renderer == "auto" and config.supersample == 1
                                         and _gl_display(config))
    return LiveSceneSource(config) if live else SceneSource(config)


# ----------------------------------------------------------------------------------------------------
# Composition: the displayed image


def _text(image: np.ndarray, text: str, origin: tuple[int, int], scale: float) -> None:
    """White text with a black shadow (cv2.putText), drawn into ``image`` in place. The shadow is the same text
    moved, not a thicker stroke: Hershey glyphs advance by their stroke width, so a thicker copy runs longer."""
    thick = max(1, int(round(1.5 * scale)))
    for dx, dy in ((1, 1), (-1, -1), (1, -1), (-1, 1)):
        cv2.putText(image, text, (origin[0] + dx, origin[1] + dy), cv2.FONT_HERSHEY_SIMPLEX, scale, (0, 0, 0), thick,
                    cv2.LINE_AA)
    cv2.putText(image, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), thick, cv2.LINE_AA)


def _font_scale(height: int) -> float:
    return float(np.clip(height / 600.0, 0.3, 0.8))


def _panel_label(image: np.ndarray, text: str) -> None:
    scale = _font_scale(image.shape[0])
    _text(image, text, (6, image.shape[0] - 8), scale)


def _overlay_box(lines: Sequence[str], height: int, width: int) -> tuple[float, int, int, int]:
    """(font scale, line step, box width, box height) of the overlay of ``lines`` on a height x width image."""
    scale = _font_scale(height)
    step = int(round(30 * scale)) + 4
    sizes = [cv2.getTextSize(s, cv2.FONT_HERSHEY_SIMPLEX, scale, max(1, int(round(1.5 * scale))))[0] for s in lines]
    return scale, step, min(width, max(w for w, _ in sizes) + 12), min(height, step * len(lines) + 8)


def _overlay(image: np.ndarray, lines: Sequence[str]) -> None:
    """``lines`` at the top left of ``image`` over a darkened box (in place)."""
    scale, step, box_w, box_h = _overlay_box(lines, *image.shape[:2])
    image[:box_h, :box_w] = (image[:box_h, :box_w] * 0.45).astype(np.uint8)
    for i, line in enumerate(lines):
        _text(image, line, (6, step * (i + 1)), scale)


def overlay_canvas(lines: Sequence[str], height: int, width: int) -> np.ndarray:
    """The overlay of ``lines`` on its own, (box height, box width, 4) uint8 RGBA (not premultiplied), rows top to
    bottom: blended over a frame (``mix(frame, rgb, alpha)``) it gives what ``_overlay`` draws there (the box
    darkened to 0.45, the text); the gl path blends it on the GPU (:class:`GlDisplay`)."""
    scale, step, box_w, box_h = _overlay_box(lines, height, width)
    # the text drawn over black and over white gives its coverage and colour (cv2's anti-aliasing does not
    # blend an alpha channel): over black b = t c, over white w = t c + (1 - t) 255
    over = [np.full((box_h, box_w, 3), v, np.uint8) for v in (0, 255)]
    for canvas in over:
        for i, line in enumerate(lines):
            _text(canvas, line, (6, step * (i + 1)), scale)
    black, white = (c.astype(np.float32) for c in over)
    text = np.clip(1.0 - (white - black).max(axis=2, keepdims=True) / 255.0, 0.0, 1.0)
    alpha = 1.0 - 0.45 * (1.0 - text)  # the darkened box under the text: the frame keeps 0.45 of itself there
    rgb = black / alpha
    return np.concatenate([rgb, 255.0 * alpha], axis=2).round().clip(0, 255).astype(np.uint8)


def _encode8(linear: np.ndarray) -> np.ndarray:
    return encoding.encode8(linear)


def compose(shown: np.ndarray, lines: Sequence[str] = (), *, truth: Optional[np.ndarray] = None,
            labels: Sequence[str] = ("truth", "generated", "error")) -> np.ndarray:
    """The displayed image, (H, W, 3) uint8 RGB, or (H, 3 W, 3) as truth | shown | error when ``truth`` is
    given; ``lines`` overlaid at the top left, ``labels`` at the bottom of the panels of the split view.

    ``shown`` and ``truth`` are (H, W, 3) linear RGB; the error is ``ERROR_GAIN`` * mean |encoded difference|
    in the magma colour map, and its label gets the PSNR of the encoded images."""
    image = _encode8(shown)
    if truth is not None:
        t8 = _encode8(truth)
        diff = np.abs(t8.astype(np.float32) - image.astype(np.float32)).mean(axis=2) / 255.0
        err = cv2.applyColorMap((np.clip(ERROR_GAIN * diff, 0.0, 1.0) * 255.0).astype(np.uint8), cv2.COLORMAP_MAGMA)
        err = cv2.cvtColor(err, cv2.COLOR_BGR2RGB)
        mse = float(((t8.astype(np.float32) - image.astype(np.float32)) ** 2).mean()) / 255.0 ** 2
        psnr = "inf" if mse == 0 else f"{10 * np.log10(1.0 / mse):.1f}"
        panels = [t8, image, err]
        texts = [labels[0], labels[1], f"{labels[2]} x{ERROR_GAIN:g}, PSNR {psnr} dB"]
        for panel, text in zip(panels, texts):
            _panel_label(panel, text)
        image = np.concatenate(panels, axis=1)
    image = np.ascontiguousarray(image)
    if lines:
        _overlay(image, lines)
    return image


# ----------------------------------------------------------------------------------------------------
# The gl path's screen: frames drawn from GPU textures

_DISPLAY_VS = """
#version 330
in vec2 in_xy;
void main() { gl_Position = vec4(in_xy, 0.0, 1.0); }
"""

_DISPLAY_FS = """
#version 330
uniform sampler2D frame;     // display codes / 255 (a TextureRing's srgb8 texture), GL rows (row 0 at the bottom)
uniform sampler2D overlay;   // the overlay's RGBA (overlay_canvas), rows top to bottom as drawn
uniform ivec2 overlay_size;  // its (width, height); (0, 0): none
uniform int height;
out vec4 f_color;
void main() {
    ivec2 p = ivec2(gl_FragCoord.xy);
    vec3 col = texelFetch(frame, p, 0).rgb;
    ivec2 q = ivec2(p.x, height - 1 - p.y);
    if (q.x < overlay_size.x && q.y < overlay_size.y) {
        vec4 o = texelFetch(overlay, q, 0);
        col = mix(col, o.rgb, o.a);
    }
    f_color = vec4(col, 1.0);
}
"""


class GlDisplay:
    """The gl path's screen: an offscreen RGBA8 framebuffer on the frame backend's GL context into which each
    shown frame is drawn from its texture (a ``TextureRing`` texture of format ``srgb8``: the codes ``compose``
    makes) with the overlay (:func:`overlay_canvas`, uploaded when it changes: a few hundred kB) blended over its
    top left, then ``glFinish`` (what a swap waits for), so that the shown rate counts the GPU's work. Nothing is
    read back but by :meth:`read` (a recording, the window, the split view's comparison on the host)."""

    def __init__(self, gl=None) -> None:
        from engine.geometry.backends.gl import shared_context

        self.gl = shared_context() if gl is None else gl
        self.size: Optional[tuple[int, int]] = None
        self._fbo = self._target = self._overlay = self._host = None
        self._overlay_key: Optional[tuple] = None
        self.gl.call(self._build)

    def _build(self) -> None:
        ctx = self.gl.ctx
        self._program = ctx.program(vertex_shader=_DISPLAY_VS, fragment_shader=_DISPLAY_FS)
        self._vbo = ctx.buffer(np.array([[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]], np.float32).tobytes())
        self._vao = ctx.vertex_array(self._program, [(self._vbo, "2f", "in_xy")])

    def show(self, texture, lines: Sequence[str] = (), gpu_ms: Optional[dict] = None) -> None:
        """Draw ``texture`` (a ``FrameTexture`` of format ``srgb8``) with ``lines`` overlaid at the top left; with
        ``gpu_ms``, the GPU milliseconds of stage ``present`` are added."""
        w, h = texture.size
        canvas = overlay_canvas(lines, h, w) if lines else None

        def run() -> None:
            with self.gl.timing(gpu_ms), self.gl.gpu_stage("present"):
                self._draw(texture.texture, (w, h), canvas)
        self.gl.call(run)

    def show_image(self, image: np.ndarray) -> None:
        """Draw a composed host image (H, W, 3) uint8, rows top to bottom (the split view), uploaded once."""
        h, w = image.shape[:2]
        data = np.ascontiguousarray(image[::-1])

        def run() -> None:
            if self._host is None or self._host.size != (w, h):
                if self._host is not None:
                    self._host.release()
                self._host = self.gl.ctx.texture((w, h), 3)
            self._host.write(data)
            self._draw(self._host, (w, h), None)
        self.gl.call(run)

    def _draw(self, texture, size: tuple[int, int], canvas: Optional[np.ndarray]) -> None:
        import moderngl

        ctx = self.gl.ctx
        w, h = size
        if self.size != size:
            for obj in (self._fbo, self._target):
                if obj is not None:
                    obj.release()
            self._target = ctx.texture(size, 4)
            self._fbo = ctx.framebuffer(color_attachments=[self._target])
            self.size = size
        self._fbo.use()
        ctx.disable(moderngl.DEPTH_TEST | moderngl.CULL_FACE | moderngl.BLEND)
        texture.use(location=0)
        if canvas is not None:
            key = (canvas.shape, canvas.tobytes())
            if self._overlay is None or self._overlay.size != (canvas.shape[1], canvas.shape[0]):
                if self._overlay is not None:
                    self._overlay.release()
                self._overlay = ctx.texture((canvas.shape[1], canvas.shape[0]), 4)
                self._overlay_key = None
            if key != self._overlay_key:
                self._overlay.write(canvas)
                self._overlay_key = key
            self._overlay.use(location=1)
        else:
            texture.use(location=1)
        self._program["frame"].value = 0
        self._program["overlay"].value = 1
        self._program["overlay_size"].value = (0, 0) if canvas is None else (canvas.shape[1], canvas.shape[0])
        self._program["height"].value = h
        self._vao.render(moderngl.TRIANGLES)
        ctx.finish()

    def read(self) -> np.ndarray:
        """The last drawn image, (H, W, 3) uint8 RGB, rows top to bottom (a readback: the recording's)."""
        if self.size is None:
            raise InterleaveError("the display has shown no frame yet")
        w, h = self.size
        data = self.gl.call(lambda: self._fbo.read(components=3))
        return np.ascontiguousarray(np.frombuffer(data, np.uint8).reshape(h, w, 3)[::-1])

    def release(self) -> None:
        def free() -> None:
            for obj in (self._fbo, self._target, self._overlay, self._host, self._vao, self._vbo, self._program):
                if obj is not None:
                    obj.release()
            self._fbo = self._target = self._overlay = self._host = None
        self.gl.call(free)


# ----------------------------------------------------------------------------------------------------
# The player core


def _median(values) -> float:
    return statistics.median(values) if values else float("nan")


def _fps(ms: float) -> float:
    return 1000.0 / ms if ms > 0 else float("nan")


def _stage_text(stages: dict[str, deque]) -> str:
    return " ".join(f"{name} {_median(v):.1f}" for name, v in stages.items() if v) or "-"


@dataclass
class PlaySummary:
    """What a run showed: ticks, how many the renderer drew, and medians over the whole run (wall ms): the
    renderer's per frame, the predictor's per generated frame and its ``prepare`` per rendered frame."""

    frames: int
    rendered: int
    generated: int
    method: str
    backend: str
    k: int
    render_ms: float
    generate_ms: float
    prepare_ms: float
    shown_fps: float
    size: tuple[int, int]
    path: Optional[str] = None
    #: ``live`` or ``truth`` for the built-in scene, ``field`` for a field
    renderer: str = ""
    #: True where the frames were drawn from GPU textures (the gl path), False where composed on the host
    gpu_display: bool = False
    #: median GPU ms per stage over the run: the renderer's (``render``, ``readout``: live renderer) and the
    #: predictor's per generated frame (``motion``, ``warp``, ``fill``, ...)
    gpu_ms: dict = dataclasses.field(default_factory=dict)
    #: the GL renderer the gl path ran on (``GL_RENDERER``; a software one such as llvmpipe times no GPU)
    device: str = ""

    @property
    def rendered_fps(self) -> float:
        """1000 / the renderer's median ms per frame."""
        return _fps(self.render_ms)

    @property
    def generated_fps(self) -> float:
        """1000 / the predictor's median ms per generated frame."""
        return _fps(self.generate_ms)

    def line(self) -> str:
        """The one-line summary the command prints."""
        where = f" to {self.path}" if self.path else ""
        return (f"played {self.frames} frames ({self.size[0]}x{self.size[1]}){where}: {self.rendered} rendered at "
                f"{self.rendered_fps:.1f} fps, {self.generated} generated at {self.generated_fps:.1f} fps (prepare "
                f"{self.prepare_ms:.1f} ms per rendered frame), shown at {self.shown_fps:.1f} fps; method "
                f"{self.method}, backend {self.backend}, k {self.k}"
                + (f"; renderer {self.renderer}" if self.renderer else "")
                + ("; frames drawn from GPU textures" if self.gpu_display else ""))

    def to_json(self) -> dict:
        """The summary as JSON-ready values, rates included."""
        out = dataclasses.asdict(self)
        out.update(rendered_fps=self.rendered_fps, generated_fps=self.generated_fps, size=list(self.size))
        return out


class Player:
    """The player without a window: :meth:`tick` draws or generates the next frame and composes it.

    Args:
        config: what to play (``config.method`` ``auto`` resolves with the source's motion vectors).
        source: the renderer (default :func:`make_source`); the player releases it in :meth:`close`.

    Keys (:meth:`press`): ``m`` the next method of :data:`METHOD_CYCLE`, ``k`` the next k of :data:`K_CYCLE`
    (from the next tick: a frame is rendered once k ticks have passed since the last), ``s`` split view on or
    off, ``q`` (or ``escape``) quit (:attr:`quit` turns True).
    """

    def __init__(self, config: PlayConfig, source=None) -> None:
        self.config = config
        self.source = make_source(config) if source is None else source
        #: the gl path (``_gl_display``): its screen and the ring of textures the shown frames are drawn from
        self.display: Optional[GlDisplay] = None
        self._ring = None
        self._gl_frames = None  # the gl predictors' shared frame backend (GlFrames)
        try:
            method = resolve_auto(config.method, self.source.has_motion_vectors)
            self.methods = list(METHOD_CYCLE) if method in METHOD_CYCLE else [method, *METHOD_CYCLE]
            self.ks = sorted(set(K_CYCLE) | {config.k})
            self._predictors: dict[str, Predictor] = {}
            self.method = method
            fallback = None
            if _gl_display(config):
                from engine.geometry.backends.gl.texture import TextureRing

                fallback = make_predictor("reproject", backend="gl")  # until a two-frame method has two frames
                self._gl_frames = fallback.frames
                self.display = GlDisplay()
                self._ring = TextureRing(self.display.gl)
            self.loop = PredictionLoop(self._predictor(method), fallback)
        except Exception:
            self.close()
            raise
        self.k = config.k
        self.split = config.split
        self.quit = False
        self.tick_index = 0
        self.keys_hint = False
        self._last_render: Optional[int] = None
        self._rendered: deque[Frame] = deque(maxlen=2)
        self._rendered_live: deque = deque(maxlen=2)  # their LiveFrames (live renderer), else None
        self._render_ms: deque[float] = deque(maxlen=WINDOW)
        self._prepare_ms: deque[float] = deque(maxlen=WINDOW)
        self._generate_ms: deque[float] = deque(maxlen=WINDOW)
        self._ticks: deque[float] = deque(maxlen=WINDOW + 1)
        self._stages: dict[str, deque] = {}
        self._gpu: dict[str, deque] = {}
        self._all_render: list[float] = []
        self._all_generate: dict[str, list[float]] = {}
        self._all_prepare: dict[str, list[float]] = {}
        self._all_gpu: dict[str, list[float]] = {}
        self.rendered = 0
        self.generated = 0
        self._start: Optional[float] = None
        #: the last tick's frame (linear RGB), its truth (split view only, else None), whether it was rendered
        self.last_color: Optional[np.ndarray] = None
        self.last_truth: Optional[np.ndarray] = None
        self.last_rendered = False
        #: the gl path: the texture the last tick was drawn from (a ``FrameTexture``)
        self.last_texture = None
        self._image: Optional[np.ndarray] = None

    # -------------------------------------------------------------------------------------- controls
    def _predictor(self, name: str) -> Predictor:
        if name not in self._predictors:
            self._predictors[name] = make_predictor(name, self.source.objects, backend=self.config.backend)
        return self._predictors[name]

    @property
    def backend(self) -> str:
        """Where the current predictor's warps run (``cpu`` or ``gl``)."""
        return self.loop.predictor.backend

    def set_method(self, name: str) -> None:
        """Switch the predictor now; what the new one needs is prepared from the kept rendered frames."""
        self.loop.predictor = self._predictor(name)
        self.method = name
        self._stages.clear()
        self._gpu.clear()
        self._generate_ms.clear()
        if self._rendered:
            if self._needs_host_color():  # live frames whose colour stayed on the GPU: read back once
                for frame, live in zip(self._rendered, self._rendered_live):
                    if frame.color is None:
                        frame.color = live.read_color()
            self.loop.load(list(self._rendered))

    def press(self, key: str) -> None:
        """Handle a key by name: ``m``, ``k``, ``s``, ``q`` / ``escape`` (others are ignored)."""
        key = key.lower()
        if key == "m":
            self.set_method(self.methods[(self.methods.index(self.method) + 1) % len(self.methods)])
        elif key == "k":
            self.k = self.ks[(self.ks.index(self.k) + 1) % len(self.ks)] if self.k in self.ks else self.ks[0]
        elif key == "s":
            self.split = not self.split
        elif key in ("q", "escape"):
            self.quit = True

    # -------------------------------------------------------------------------------------- ticks
    def _needs_host_color(self) -> bool:
        """Whether the current method needs a rendered frame's colour on the host (its preparation reads it, or
        it runs on the CPU); on the gl path ``reproject`` and ``mvec`` do not."""
        predictor = self.loop.predictor
        return not (self._gl_frames is not None and predictor.backend == "gl" and predictor.name in GPU_COLOR_METHODS)

    def _record_gpu(self, values: dict) -> None:
        for name, ms in values.items():
            self._gpu.setdefault(name, deque(maxlen=WINDOW)).append(ms)
            self._all_gpu.setdefault(name, []).append(ms)

    def _render(self, tick: int) -> tuple[Frame, object]:
        """Draw tick ``tick`` and submit it; (the frame, its ``LiveFrame`` on the GPU or None)."""
        cut = self.source.cut(tick)
        previous = None if cut else self._last_render
        start = time.perf_counter()
        live, gpu = None, {}
        if self.source.live:  # drawn on the GPU; depth and vectors (and colour where needed) read back
            live = self.source.render(tick, previous, gpu_ms=gpu)
            frame = live.frame(color=self._needs_host_color())
        else:
            frame = self.source.frame(tick, previous)
        self._render_ms.append(1e3 * (time.perf_counter() - start))
        self._all_render.append(self._render_ms[-1])
        self._record_gpu(gpu)
        if cut:
            self._rendered.clear()
            self._rendered_live.clear()
        self._rendered.append(frame)
        self._rendered_live.append(live)
        if live is not None and self._gl_frames is not None:
            self._gl_frames.adopt(frame, live.image)  # the predictors find it there: no upload
        start = time.perf_counter()
        self.loop.submit(frame, restart=cut)
        self._prepare_ms.append(1e3 * (time.perf_counter() - start))
        self._all_prepare.setdefault(self.method, []).append(self._prepare_ms[-1])
        self._last_render = tick
        self.rendered += 1
        return frame, live

    def _generate(self, tick: int) -> Prediction:
        target = self.source.target(tick)
        if self._gl_frames is not None:  # the gl path: the prediction stays on the GPU
            target = dataclasses.replace(target, resident=True)
        start = time.perf_counter()
        pred = self.loop.predict(target)
        self._generate_ms.append(1e3 * (time.perf_counter() - start))
        self._all_generate.setdefault(self.method, []).append(self._generate_ms[-1])
        for name, ms in pred.stages_ms.items():
            self._stages.setdefault(name, deque(maxlen=WINDOW)).append(ms)
        self._record_gpu(pred.gpu_ms)
        self.generated += 1
        return pred

    def step(self) -> None:
        """Draw or generate the next tick's frame and show it: composed on the host (:func:`compose`, kept for
        :meth:`image`), or on the gl path drawn from its GPU texture into the :class:`GlDisplay` with nothing read
        back (the split view compares on the host: it reads the frames back)."""
        tick = self.tick_index
        now = time.perf_counter()
        if self._start is None:
            self._start = now
        renders = (self.source.cut(tick) or self._last_render is None or tick - self._last_render >= self.k)
        frame = live = pred = None
        if renders:
            frame, live = self._render(tick)
            labels = ("truth", "rendered", "error")
        else:
            pred = self._generate(tick)
            labels = ("truth (rendered for comparison)", f"generated: {self.method}", "error")
        self.last_rendered = renders
        if self.display is None:
            color = frame.color if renders else pred.color
            truth = (color if renders else self.source.truth(tick)) if self.split else None
            self.last_color, self.last_truth = color, truth
            self._image = compose(color, self.overlay_lines(renders), truth=truth, labels=labels)
        else:
            self._show_on_gpu(tick, frame, live, pred, labels)
        self._ticks.append(time.perf_counter())
        self.tick_index += 1

    def _show_on_gpu(self, tick: int, frame: Optional[Frame], live, pred: Optional[Prediction],
                     labels: Sequence[str]) -> None:
        """The gl path: the tick's frame as a texture (a live frame's colour or the prediction's GPU buffer stored
        into it on the GPU; a frame that came as host arrays uploaded once, by the frame backend), drawn."""
        ring, gpu = self._ring, {}
        if frame is not None:
            image = live.image if live is not None else self._gl_frames.resident(frame, Timer()).image
            texture = ring.write(image.color, image.shape, "srgb8", gpu)
        elif pred.resident is not None:
            texture = ring.write(pred.resident.color, pred.resident.shape, "srgb8", gpu)
        else:  # a method that finished on the CPU (repeat, decomp's infill)
            texture = ring.upload(pred.color, "srgb8")
        self.last_texture = texture
        lines = self.overlay_lines(frame is not None)
        if not self.split:
            self.display.show(texture, lines, gpu)
            self._record_gpu(gpu)
            return
        if frame is not None:
            color = frame.color if frame.color is not None else live.read_color()
            truth = color
        else:
            color = pred.color if pred.resident is None else pred.resident.read()[0]
            truth = self.source.truth(tick)
        self.last_color, self.last_truth = color, truth
        self.display.show_image(compose(color, lines, truth=truth, labels=labels))

    def image(self) -> np.ndarray:
        """The last tick's composed image (H, W, 3) uint8 RGB (see :func:`compose`); on the gl path read back from
        the display (a recording's or the window's readback)."""
        return self._image if self.display is None else self.display.read()

    def tick(self) -> np.ndarray:
        """Draw or generate the next tick's frame and return the composed image (:meth:`step`, :meth:`image`)."""
        self.step()
        return self.image()

    def overlay_lines(self, rendered: bool) -> list[str]:
        """The overlay: method and backend, k, fps, per-stage wall and GPU ms, what this tick was."""
        render_ms, gen_ms = _median(self._render_ms), _median(self._generate_ms)
        shown = (len(self._ticks) - 1) / (self._ticks[-1] - self._ticks[0]) if len(self._ticks) > 1 else float("nan")
        fallback = self.loop.prepared.fallback if self.loop.prepared is not None else None
        method = self.method + (f" (reproject until {self.loop.predictor.history_needed} rendered)"
                                if fallback else "")
        lines = [f"{method} on {self.backend}, k={self.k}: tick {self.tick_index} "
                 f"{'rendered' if rendered else 'generated'}",
                 f"rendered {_fps(render_ms):.1f} fps ({render_ms:.1f} ms)  generated {_fps(gen_ms):.1f} fps "
                 f"({gen_ms:.1f} ms)  shown {shown:.1f} fps",
                 f"stage ms: {_stage_text(self._stages)}  prepare {_median(self._prepare_ms):.1f}",
                 f"gpu ms: {_stage_text(self._gpu) if self._gpu else '- (' + self.backend + ' backend)'}"]
        if self.keys_hint:
            lines.append("keys: M method  K k  S split  Q quit")
        return lines

    def summary(self, path: Optional[str] = None) -> PlaySummary:
        """Medians over the whole run so far (generated and prepare: of the current method)."""
        elapsed = (self._ticks[-1] - self._start) if self._ticks and self._start is not None else 0.0
        width = self.config.width * (3 if self.split else 1)
        renderer = "field" if isinstance(self.source, FieldSource) else ("live" if self.source.live else "truth")
        return PlaySummary(frames=self.tick_index, rendered=self.rendered, generated=self.generated,
                           method=self.method, backend=self.backend, k=self.k, render_ms=_median(self._all_render),
                           generate_ms=_median(self._all_generate.get(self.method, [])),
                           prepare_ms=_median(self._all_prepare.get(self.method, [])),
                           shown_fps=self.tick_index / elapsed if elapsed > 0 else float("nan"),
                           size=(width, self.config.height), path=path, renderer=renderer,
                           gpu_display=self.display is not None,
                           gpu_ms={name: _median(v) for name, v in self._all_gpu.items()},
                           device=self.display.gl.renderer if self.display is not None else "")

    def close(self) -> None:
        """Release the renderer, the textures and the display (safe to call twice)."""
        if self._ring is not None:
            self._ring.release_all()
            self._ring = None
        if self.display is not None:
            self.display.release()
            self.display = None
        if self.source is not None:
            self.source.release()
            self.source = None

    def __enter__(self) -> "Player":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def iter_frames(config: PlayConfig, count: int, keys: Optional[dict[int, str]] = None) -> Iterator[np.ndarray]:
    """``count`` composed frames of ``config``, no window; ``keys`` maps a tick to a key pressed before it."""
    with Player(config) as player:
        for tick in range(count):
            if keys and tick in keys:
                player.press(keys[tick])
            yield player.tick()


# ----------------------------------------------------------------------------------------------------
# Headless recording and the window


def record(config: PlayConfig, path: Optional[str] = None) -> PlaySummary:
    """Play ``config.frames`` ticks (0: :data:`DEFAULT_FRAMES`) headless into the video ``path`` (default
    ``config.record``; mp4v at ``config.fps``) and return the summary."""
    path = Path(path or config.record or DEFAULT_RECORDING)
    if path.is_dir():
        raise InputError("is a folder, not a video file", file=path, field="record")
    path.parent.mkdir(parents=True, exist_ok=True)
    count = config.frames or DEFAULT_FRAMES
    writer = None
    with Player(config) as player:
        try:
            for _ in range(count):
                image = player.tick()
                if writer is None:
                    size = (image.shape[1], image.shape[0])
                    writer = cv2.VideoWriter(str(path), cv2.VideoWriter_fourcc(*"mp4v"), float(config.fps), size)
                    if not writer.isOpened():
                        raise InputError("cannot be written as an mp4v video", file=path, field="record")
                writer.write(cv2.cvtColor(image, cv2.COLOR_RGB2BGR))
        finally:
            if writer is not None:
                writer.release()
        return player.summary(str(path))


def run_headless(config: PlayConfig) -> PlaySummary:
    """Play ``config.frames`` ticks (0: :data:`DEFAULT_FRAMES`) with no window and no recording and return the
    summary: a benchmark of the loop as shown. On the gl path every frame is drawn from its texture into the
    offscreen display and nothing is read back; elsewhere the frames are composed on the host."""
    with Player(config) as player:
        for _ in range(config.frames or DEFAULT_FRAMES):
            player.step()
        return player.summary()


def _no_display_reason() -> Optional[str]:
    """Why no window can be opened here, or None when a display may exist."""
    if sys.platform.startswith("linux") and not (os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY")):
        return "no display (DISPLAY is not set)"
    try:
        import pyglet  # noqa: F401
    except ImportError:
        return "pyglet is not installed (pip install -e '.[play]')"
    return None


class _Worker(threading.Thread):
    """Runs the :class:`Player` on its own thread: the renderers' EGL contexts stay current there and never
    meet the window's GL context. Composed frames go out through ``frames`` (at most two ahead), keys come in
    through ``keys``."""

    def __init__(self, config: PlayConfig) -> None:
        super().__init__(daemon=True, name="interleave-play")
        self.config = config
        self.frames: queue.Queue = queue.Queue(maxsize=2)
        self.keys: queue.Queue = queue.Queue()
        self.stop = threading.Event()
        self.error: Optional[Exception] = None
        self.summary: Optional[PlaySummary] = None

    def run(self) -> None:
        try:
            with Player(self.config) as player:
                player.keys_hint = True
                limit = self.config.frames or None
                while not self.stop.is_set() and not player.quit and player.tick_index != limit:
                    while not self.keys.empty():
                        player.press(self.keys.get())
                    if player.quit:
                        break
                    image = player.tick()
                    while not self.stop.is_set():
                        try:
                            self.frames.put(image, timeout=0.1)
                            break
                        except queue.Full:
                            continue
                self.summary = player.summary()
        except Exception as exc:  # handed to the window's thread, which raises it
            self.error = exc
        finally:
            self.stop.set()


def run_window(config: PlayConfig, keys: Optional[dict[int, str]] = None) -> PlaySummary:
    """Show ``config`` in a pyglet window at ``config.fps`` until it is closed (Q, Esc, the close button) or
    ``config.frames`` ticks were shown; save ``config.screenshot`` (the last frame read back from the window's
    framebuffer) on the way out. ``keys`` maps a count of frames shown to a key (``M``, ``K``, ``S``, ``Q``,
    ``ESCAPE``) sent through the window's key handler after that frame, as if typed. The player runs up to
    two frames ahead of the window, so a key shows from two or three frames later.
    Raises InterleaveError when the window cannot be opened."""
    try:
        import pyglet
    except ImportError as exc:
        raise InterleaveError("the window needs pyglet: pip install -e '.[play]'") from exc
    width = config.width * (3 if config.split else 1)
    try:
        from pyglet.window import key  # the import already opens the display (pyglet's shadow window)

        window = pyglet.window.Window(width, config.height, caption="interleave play", vsync=False)
    except Exception as exc:  # NoSuchDisplayException, no GL config, ...: one line for the caller
        raise InterleaveError(f"cannot open a window: {exc}") from exc
    worker = _Worker(config)
    names = {key.M: "m", key.K: "k", key.S: "s", key.Q: "q", key.ESCAPE: "escape"}

    @window.event
    def on_key_press(symbol, modifiers):  # pyglet's signature
        if symbol in names:
            worker.keys.put(names[symbol])
        return pyglet.event.EVENT_HANDLED  # Esc closes through the player, after its last frame

    worker.start()
    shown, last, first, latest = 0, None, None, None
    period = 1.0 / config.fps
    try:
        while not window.has_exit and not (worker.stop.is_set() and worker.frames.empty()):
            start = time.perf_counter()
            window.dispatch_events()
            try:
                image = worker.frames.get(timeout=0.1)
            except queue.Empty:
                continue
            height, width = image.shape[:2]
            if (window.width, window.height) != (width, height):
                window.set_size(width, height)
            window.switch_to()
            window.clear()
            flipped = np.ascontiguousarray(image[::-1])  # GL rows run bottom to top
            pyglet.image.ImageData(width, height, "RGB", flipped.tobytes(), pitch=3 * width).blit(0, 0)
            shown += 1
            latest = time.perf_counter()
            first = latest if first is None else first
            if config.screenshot:  # read before the flip: the back buffer holds what is about to show
                last = _read_window(pyglet, width, height)
            window.flip()
            if keys and shown in keys:
                window.dispatch_event("on_key_press", getattr(key, keys[shown].upper()), 0)
            if config.frames and shown >= config.frames:
                break
            time.sleep(max(0.0, period - (time.perf_counter() - start)))
    finally:
        worker.stop.set()
        worker.join(timeout=30)
        window.close()
    if worker.error is not None:
        raise worker.error
    if config.screenshot:
        if last is None:
            raise InterleaveError("the window showed no frame to save")
        Path(config.screenshot).parent.mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(config.screenshot), cv2.cvtColor(last, cv2.COLOR_RGB2BGR))
    summary = worker.summary
    if summary is None:
        raise InterleaveError("the player stopped before its first frame")
    elapsed = latest - first if first is not None else 0.0  # the window's own rate, first to last frame shown
    return dataclasses.replace(summary, frames=shown,
                               shown_fps=(shown - 1) / elapsed if shown > 1 and elapsed > 0 else float("nan"))


def _read_window(pyglet, width: int, height: int) -> np.ndarray:
    """(H, W, 3) uint8 RGB, rows top to bottom, of the window's colour buffer."""
    buffer = pyglet.image.get_buffer_manager().get_color_buffer().get_image_data()
    data = np.frombuffer(buffer.get_data("RGB", 3 * buffer.width), np.uint8)
    return np.ascontiguousarray(data.reshape(buffer.height, buffer.width, 3)[::-1][:height, :width])


def play(config: PlayConfig, *, err=sys.stderr) -> PlaySummary:
    """What ``interleave play`` runs, then writes ``config.json`` (the summary) when given. With ``config.record``
    it records headless, with ``config.headless`` it plays without showing anything (:func:`run_headless`).
    Otherwise it opens the window; when no window can be opened (no DISPLAY, no pyglet, pyglet fails), it says
    why in one line on ``err`` and records to :data:`DEFAULT_RECORDING` instead."""
    summary = _play(config, err)
    if config.json:
        path = Path(config.json)
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(summary.to_json(), indent=2) + "\n")
    return summary


def _play(config: PlayConfig, err) -> PlaySummary:
    if config.headless:
        return run_headless(config)
    if config.record:
        return record(config)
    reason = _no_display_reason()
    if reason is None:
        try:
            return run_window(config)
        except InterleaveError as exc:
            if not str(exc).startswith("cannot open a window"):
                raise
            reason = str(exc)
    print(f"interleave play: {reason}: recording {config.frames or DEFAULT_FRAMES} frames to {DEFAULT_RECORDING} "
          f"instead", file=err)
    return record(config, str(DEFAULT_RECORDING))
