"""The frame-upsampling demo: render the built-in scene, keep every k-th frame, predict the rest.

``upsample_stream`` is the loop a renderer would run: rendered frames go in, and for every tick a frame
comes out, either the rendered one or one predicted from the last two rendered frames and the camera of
that tick. ``run_demo`` renders the built-in procedural scene, evaluates every method on it, and writes a
side-by-side video (truth | prediction | error) of the best method, the table, the JSON and the plot.
``run_field_demo`` does the same with a trained radiance field (``interleave export field``) rendered by
``engine.fields.gl`` along a camera path through its scene.
"""
from __future__ import annotations

import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Optional, Sequence

import cv2
import numpy as np
from tqdm import tqdm

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.core.frames import Frame
from engine.eval.metrics import flip_map
from engine.eval.protocol import (VectorSource, evaluate_sequence, evaluation_pairs, history_motion_vectors,
                                  make_predictors, markdown_table, plot, stage_table, summarize, write_json)
from engine.fields.camera_path import field_camera_path
from engine.fields.gl import GlFieldRenderer
from engine.fields.render import load_field
from engine.fields.dynamic import COHERENCE, field_motion_vectors, field_object_flow
from engine.geometry.motion import camera_motion_vectors
from engine.io.rgbd import RgbdSequence, read_sequence, write_sequence
from engine.predict import Oracle, Predictor, Target, make_predictor, use_backend
from engine.runtime.stream import PredictionLoop
from engine.scenegen import SceneConfig, generate_sequence, make_scene


#: A dynamic field's pixel is ``moving`` where its motion moves it more than this (px) to the next frame.
MOVING_PX = 0.25


@dataclass
class OutputFrame:
    """One displayed tick: its index, linear colour, whether it was predicted, and the true frame of the tick."""

    index: int
    color: np.ndarray
    predicted: bool
    truth: Frame


def upsample_stream(frames: Sequence[Frame], k: int, predictor: Predictor,
                    vectors: Optional[VectorSource] = None) -> Iterator[OutputFrame]:
    """Show frames 0, k, 2k, ... as rendered and predict the others from the last rendered frames.

    Only each predicted tick's camera and time are read from the frames in between (what a game knows
    before rendering). Until two frames are rendered, a two-frame method falls back to `reproject`. The
    motion vectors of a rendered frame of a sequence are re-derived to point k frames back, to the previous
    rendered frame (``engine.eval.protocol.history_motion_vectors``, from ``vectors`` when given).
    """
    loop = PredictionLoop(predictor)
    for position, frame in enumerate(frames):
        if frame.index % k == 0:
            if frame.motion_vectors is not None and isinstance(frames, RgbdSequence):
                # a renderer drawing every k-th frame writes vectors to its previous rendered frame
                frame.motion_vectors = (history_motion_vectors(frames, position - k, position, frame, vectors)
                                        if position >= k else None)
            loop.submit(frame)
            yield OutputFrame(frame.index, frame.color, False, frame)
        elif loop.prepared is not None:
            pred = loop.predict(Target(frame.camera, frame.time, frame.index))
            yield OutputFrame(frame.index, pred.color, True, frame)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    cv2.putText(image, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def side_by_side(truth: np.ndarray, shown: np.ndarray, predicted: bool, index: int, method: str) -> np.ndarray:
    """truth | shown frame | FLIP error (magma), as one 8-bit BGR image with labels."""
    import matplotlib

    a, b = display_encode(truth), display_encode(shown)
    err = flip_map(a, b) if predicted else np.zeros(a.shape[:2], np.float32)
    err_rgb = matplotlib.colormaps["magma"](err)[..., :3]
    tiles = [(a, f"truth {index}"), (b, f"{method} (predicted)" if predicted else "rendered"),
             (err_rgb, f"FLIP error {err.mean():.3f}")]
    out = [_label(cv2.cvtColor((t * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR), s) for t, s in tiles]
    return np.concatenate(out, axis=1)


def run_demo(out_dir: Path, *, k: int = 2, seed: int = 7, frames: int = 48, width: int = 640,
             height: int = 360, methods: Sequence[str] = ("repeat", "reproject", "flow2d", "decomp", "mvec", "oracle"),
             progress: bool = True, backend: str = "auto") -> dict:
    """Render the built-in scene into ``out_dir/scene``, evaluate ``methods``, write video and reports.

    Returns the evaluation summary; prints the table.
    """

    config = SceneConfig(width=width, height=height, num_frames=frames, seed=seed)
    check_before_rendering(frames, k, methods, make_scene(config).scene_objects(), backend)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene_dir = generate_sequence(config, out_dir / "scene", progress=progress)
    return report_sequence(read_sequence(scene_dir), out_dir, k=k, methods=methods, progress=progress,
                           command=f"interleave demo --k {k} --seed {seed} --backend {backend}", backend=backend)


def check_before_rendering(frames: int, k: int, methods: Sequence[str], objects: Sequence, backend: str) -> None:
    """InputError for a k, a frame count or a method the evaluation would refuse, raised before the seconds
    of rendering that precede it (the rendered frames carry motion vectors)."""
    if not evaluation_pairs(frames, k):
        raise InputError(f"{frames} frames are too few for k = {k} (needs at least {2 * k})", field="frames")
    make_predictors(methods, objects, has_vectors=True, backend=backend)


def report_sequence(sequence, out_dir: Path, *, k: int, methods: Sequence[str], progress: bool = True,
                    command: str = "interleave demo", extra: Optional[dict] = None, note: str = "",
                    backend: str = "auto", vectors: Optional[VectorSource] = None,
                    predictors: Optional[dict] = None) -> dict:
    """Evaluate ``methods`` on a loaded sequence and write the demo's outputs into ``out_dir``: ``table.md``
    (with ``note`` under it), ``results.json`` (with ``extra``), ``speed_vs_error.png``, ``side_by_side.mp4``
    (truth | prediction | FLIP error of the best non-oracle method) and three stills. Prints the table.
    ``vectors``, ``predictors``: the renderer's own motion vectors between rendered frames and predictors made
    by the caller (``evaluate_sequence``)."""

    results = evaluate_sequence(sequence, list(methods), k, progress=progress, backend=backend, vectors=vectors,
                                predictors=predictors)
    table = markdown_table(results) + "\n\nStage breakdown, median ms per predicted frame:\n\n" + stage_table(results)
    if note:
        table += "\n\n" + note
    (out_dir / "table.md").write_text(table + "\n")
    write_json(results, out_dir / "results.json", {"command": command, **(extra or {})})
    plot(results, out_dir / "speed_vs_error.png")
    print(table)

    candidates = [r for r in results if r.method != "oracle"] or list(results)
    best = max(candidates, key=lambda r: r.psnr).method
    predictor = make_predictor(best, sequence.objects, backend=backend)
    writer = cv2.VideoWriter(str(out_dir / "side_by_side.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                             float(sequence.fps), (3 * sequence.width, sequence.height))
    stills = 0
    for shown in tqdm(upsample_stream(sequence, k, predictor, vectors), total=len(sequence), desc="video",
                      disable=not progress, unit="frame"):
        image = side_by_side(shown.truth.color, shown.color, shown.predicted, shown.index, best)
        writer.write(image)
        if shown.predicted and stills < 3 and shown.index >= len(sequence) // 2:
            cv2.imwrite(str(out_dir / f"still_{shown.index:04d}.png"), image)
            stills += 1
    writer.release()
    print(f"best non-oracle method: {best}; wrote {out_dir / 'side_by_side.mp4'}, {out_dir / 'table.md'}, "
          f"{out_dir / 'results.json'}, {out_dir / 'speed_vs_error.png'}")
    return summarize(results)


# ----------------------------------------------------------------------------------------------------
# The same demo on a trained radiance field: `interleave demo --field RUN_OR_EXPORT_DIR`


def resolve_field_dir(path: Path) -> tuple[Path, Optional[Path]]:
    """(export folder with ``field.json`` or ``dynamic.json``, run folder or None) for an export folder or a run
    folder holding ``export/``; the run folder is the export's parent when that holds ``data.json`` (the run's
    cameras)."""

    path = Path(path)
    for export in (path, path / "export"):
        if (export / "field.json").is_file() or (export / "dynamic.json").is_file():
            break
    else:
        raise InputError("holds no field.json or dynamic.json (nor export/...): export the trained field first with "
                         f"'interleave export field|dynamic {path}'", file=path)
    run = export.parent if (export.parent / "data.json").is_file() else None
    return export, run


def is_dynamic_export(export: Path) -> bool:
    """Whether an export folder of :func:`resolve_field_dir` holds a dynamic field."""
    return (Path(export) / "dynamic.json").is_file()


def train_cameras(run: Optional[Path], dynamic: bool = False):
    """The run's training cameras and image size (needs torch and the run's scene folder), else None."""
    if run is None:
        return None
    try:
        if dynamic:
            from models.fields.data.select import load_dynamic_run_views as load_run_views
        else:
            from models.fields.train_static import load_run_views
    except ImportError:  # no torch: the path is derived from the manifest alone
        return None

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        train, _ = load_run_views(run)
    return list(train.cameras), train.width, train.height


def render_field_frames(renderer, cameras, fps: float, timings: Optional[list] = None) -> Iterator[Frame]:
    """Frames (colour, planar depth, camera, motion vectors) of a static field rendered along ``cameras``, one
    at a time; each render's seconds are appended to ``timings``. A static field's motion vectors are the
    camera's alone, exact from the rendered depth (``camera_motion_vectors``; zero on the first frame), and
    every pixel belongs to the static background (``object_id`` 0), so the evaluation can derive the
    vectors to any earlier frame exactly."""
    for i, cam in enumerate(cameras):
        out = renderer.render(cam.intrinsics, cam.world_to_camera)
        if timings is not None:
            timings.append(out["seconds"])
        vectors = camera_motion_vectors(out["depth"], cam, cameras[max(i - 1, 0)])
        yield Frame(index=i, time=i / fps, color=out["color"], depth=out["depth"], camera=cam,
                    object_id=np.zeros(out["depth"].shape, np.int32), motion_vectors=vectors)


def render_dynamic_frames(renderer, cameras, times: np.ndarray, fps: float,
                          timings: Optional[list] = None) -> Iterator[Frame]:
    """Frames of a dynamic field (``engine.fields.gldynamic.GlDynamicRenderer``) rendered along ``cameras`` at
    ``times`` (the field's units): colour, depth, its own motion vectors to the previous frame (the motion
    field inverted where it is steady, ``field_motion_vectors(coherence=COHERENCE)``; the camera's alone on the
    first frame; the demo gives ``mvec`` the vectors between rendered frames from the field directly,
    :func:`field_vector_source`) and, as the truth the scores read, the
    flow to the next frame (the same computation forward in time), its part from the
    field's motion (``object_flow``: flow minus the camera's) and ``moving`` where that part exceeds
    ``MOVING_PX``."""
    for i, cam in enumerate(cameras):
        before = cameras[max(i - 1, 0)]
        out = renderer.render(cam.intrinsics, cam.world_to_camera, float(times[i]),
                              earlier_world_to_camera=before.world_to_camera, earlier_time=float(times[max(i - 1, 0)]),
                              coherence=COHERENCE)
        if timings is not None:
            timings.append(out["seconds"])
        after = cameras[min(i + 1, len(cameras) - 1)]
        flow = field_motion_vectors(renderer.assets, cam.intrinsics, cam.world_to_camera, out["depth"],
                                    float(times[i]), after.world_to_camera, float(times[min(i + 1, len(times) - 1)]))
        object_flow = flow - camera_motion_vectors(out["depth"], cam, after)
        moving = np.nan_to_num(np.abs(object_flow).max(axis=-1), nan=0.0) > MOVING_PX
        yield Frame(index=i, time=i / fps, color=out["color"], depth=out["depth"], camera=cam,
                    motion_vectors=out["motion_vectors"], flow=np.nan_to_num(flow),
                    object_flow=np.nan_to_num(object_flow), moving=moving)


def run_field_demo(field_dir: Path, out_dir: Path, *, k: int = 2, frames: int = 48, width: Optional[int] = 640,
                   height: Optional[int] = 360, fps: float = 30.0,
                   methods: Sequence[str] = ("repeat", "reproject", "flow2d", "decomp"), quantized: bool = False,
                   orbit_degrees: float = 90.0, progress: bool = True, backend: str = "auto") -> dict:
    """The frame-upsampling demo with a trained field as the renderer.

    The field (``engine.fields.gl.GlFieldRenderer``, or ``engine.fields.gldynamic.GlDynamicRenderer`` for a
    dynamic export, at times spread evenly over its trained range) renders colour and planar depth along
    :func:`field_camera_path` into ``out_dir/field`` (an rgbd-seq, with the field's own motion vectors);
    every k-th frame is "rendered", the predictors predict the others, and each prediction is scored against
    the field's own render at that pose and time. Writes what :func:`run_demo` writes; the field's render time
    is in ``table.md`` and ``results.json``. ``oracle`` is dropped from ``methods`` for a static field (it has
    no object motion); a dynamic field's is :class:`FieldOracle`.
    """

    export, run = resolve_field_dir(field_dir)
    if is_dynamic_export(export):
        return _run_dynamic_field_demo(export, run, out_dir, k=k, frames=frames, width=width, height=height, fps=fps,
                                       methods=methods, orbit_degrees=orbit_degrees, progress=progress,
                                       backend=backend, command=f"interleave demo --field {field_dir} --k {k} "
                                                                 f"--backend {backend}")
    methods, out_dir = _field_demo_start(methods, frames, k, backend, out_dir)
    assets = load_field(export)
    cameras, width, height = field_camera_path(assets, train_cameras(run), frames, width, height,
                                               orbit_degrees=orbit_degrees)
    timings: list[float] = []
    with GlFieldRenderer(assets, width, height, quantized=quantized) as renderer:
        seq_dir = write_sequence(out_dir / "field", render_field_frames(renderer, cameras, fps, timings), fps=fps,
                                 progress=progress)
        compile_s = renderer.compile_seconds
    render_ms = 1e3 * float(np.median(timings))
    note = (f"Field renderer (engine.fields.gl, {'uint8' if quantized else 'float'} planes, {width}x{height}): "
            f"{render_ms:.1f} ms per rendered frame (median of {len(timings)}; shader compiled in {compile_s:.2f} s). "
            f"Truth for the predicted frames is the field's own render at their pose.")
    extra = {"field": {"export": str(export), "run": None if run is None else str(run),
                       "kind": assets.scene["kind"], "render_ms_per_frame": render_ms, "width": width,
                       "height": height, "quantized": quantized}}
    return report_sequence(read_sequence(seq_dir), out_dir, k=k, methods=methods, progress=progress,
                           command=f"interleave demo --field {field_dir} --k {k} --backend {backend}", extra=extra,
                           note=note, backend=backend)


class FieldOracle(Oracle):
    """``oracle`` of a dynamic field's frames: frame n moved by the field's own motion from frame n's time to
    the target's (``engine.fields.dynamic.field_object_flow``: the field knows its future), then by the
    camera's. The target must be a frame of the rendered path (``target.index``), whose field time is
    ``times[index]``."""

    def __init__(self, assets, times: Sequence[float]) -> None:
        self.assets, self.times = assets, np.asarray(times, np.float64)

    def _true_flow(self, frame: Frame, target: Target) -> np.ndarray:
        return field_object_flow(self.assets, frame.camera.intrinsics, frame.camera.world_to_camera, frame.depth,
                                 float(self.times[frame.index]), float(self.times[target.index]))


def field_vector_source(assets, cameras: Sequence, times: Sequence[float]) -> VectorSource:
    """The motion vectors a dynamic field's renderer writes for ``mvec`` when it draws only frames ``older`` and
    ``newest`` of a path (``cameras``, field ``times``): the field's own motion
    (``engine.fields.dynamic.field_motion_vectors`` from the newest frame's depth), kept where it is steady over
    the interval before (``coherence=COHERENCE``: a trained field's motion jitters in time, and ``mvec``
    extrapolates it), else the camera's."""
    def vectors(older: int, newest: int, frame: Frame) -> np.ndarray:
        return field_motion_vectors(assets, frame.camera.intrinsics, frame.camera.world_to_camera, frame.depth,
                                    float(times[newest]), cameras[older].world_to_camera, float(times[older]),
                                    coherence=COHERENCE)
    return vectors


def _field_demo_start(methods: Sequence[str], frames: int, k: int, backend: str, out_dir: Path
                      ) -> tuple[list[str], Path]:
    """A field demo's methods (``oracle`` dropped: it needs rigid objects), checked before anything renders, and
    its output folder (created)."""
    methods = [m for m in methods if m != "oracle"]
    if not methods:
        raise InputError("no method left to evaluate (oracle needs rigid objects)", field="methods")
    check_before_rendering(frames, k, methods, (), backend)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    return methods, out_dir


def _run_dynamic_field_demo(export: Path, run: Optional[Path], out_dir: Path, *, k: int, frames: int,
                            width: Optional[int], height: Optional[int], fps: float, methods: Sequence[str],
                            orbit_degrees: float, progress: bool, backend: str, command: str) -> dict:
    """:func:`run_field_demo` for a dynamic export: the field's own vectors feed ``mvec``, and ``oracle`` moves
    frame n by the field's own motion to the target's time (:class:`FieldOracle`)."""
    from engine.fields.dynamic import load_dynamic_field
    from engine.fields.gldynamic import GlDynamicRenderer

    with_oracle = "oracle" in methods
    methods, out_dir = _field_demo_start(methods, frames, k, backend, out_dir)
    methods = methods + ["oracle"] if with_oracle else methods
    assets = load_dynamic_field(export)
    cameras, width, height = field_camera_path(assets, train_cameras(run, dynamic=True), frames, width, height,
                                               orbit_degrees=orbit_degrees)
    t0, t1 = assets.time_range
    times = t0 + (t1 - t0) * np.arange(frames) / max(frames - 1, 1)
    timings: list[float] = []
    with GlDynamicRenderer(assets, width, height) as renderer:
        seq_dir = write_sequence(out_dir / "field", render_dynamic_frames(renderer, cameras, times, fps, timings),
                                 fps=fps, progress=progress)
        compile_s = renderer.compile_seconds
    sequence = read_sequence(seq_dir)

    render_ms = 1e3 * float(np.median(timings))
    note = (f"Dynamic field renderer (engine.fields.gldynamic, {assets.kind}, {width}x{height}): {render_ms:.1f} ms "
            f"per rendered frame with its motion vectors (median of {len(timings)}; shader compiled in "
            f"{compile_s:.2f} s), times {t0:g}..{t1:g}. Truth for the predicted frames is the field's own render at "
            "their pose and time; 'moving' pixels are those the field's motion moves by more than "
            f"{MOVING_PX} px to the next frame.")
    extra = {"field": {"export": str(export), "run": None if run is None else str(run), "kind": assets.kind,
                       "scene": assets.scene["kind"], "render_ms_per_frame": render_ms, "width": width,
                       "height": height, "time_range": [t0, t1]}}
    oracle = {"oracle": use_backend(FieldOracle(assets, times), backend)} if with_oracle else None
    return report_sequence(sequence, out_dir, k=k, methods=methods, progress=progress, command=command, extra=extra,
                           note=note, backend=backend, vectors=field_vector_source(assets, cameras, times),
                           predictors=oracle)
