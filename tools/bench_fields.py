"""Speed / parity table of the field renderers: the GL compute shaders against the numpy / onnxruntime
references of ``engine.fields`` and (when torch is importable) the torch renderer of the trained run.

``python -m tools.bench_fields static EXPORT_DIR [--run RUN_DIR] [--sizes 512x512,960x540]`` (an exported
static field: ``engine.fields.gl``) and ``python -m tools.bench_fields dynamic EXPORT_DIR [--sizes 160x90]
[--view 0] [--time T]`` (an exported dynamic field: ``engine.fields.gldynamic``) print ms per frame, fps,
CPU ms and the PSNR / colour / depth differences of every renderer against the torch render (the numpy
one without torch) on one camera: a held-out view of the run, else (static) the first camera of the demo
path (``engine.fields.camera_path``). ``--json FILE`` also writes the records. The static bench also counts the field evaluations per pixel of
the default GL renderer and prints their multiply-add rate (GMAC/s in the MLPs), the figure to set against a
device's FP32 peak. When the export holds a baked field (``baked.json``, a field trained with deferred shading),
the static bench also times its GL renderer (``engine.fields.glbaked``: "gl baked", hardware and exact
filtering, and its early stop at the exact renderers' 1e-4 instead of 1/255) and its numpy reference ("baked
numpy"), scored against the same reference as the rest; so does the dynamic bench for a baked DeRF field
(``baked_dynamic.json``: ``GlBakedDynamicRenderer``, ``render_baked_dynamic``). The dynamic bench also times the
GL renderer with its motion-vector pass ("gl + motion vectors", what ``mvec`` is fed; wall time with readback).
"""
from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from engine.fields.camera_path import field_camera_path, scale_intrinsics
from engine.fields.dynamic import COHERENCE, load_dynamic_field, render_dynamic_field
from engine.fields.baked import (BakedDynamicAssets, load_baked, load_baked_dynamic, render_baked,
                                 render_baked_dynamic)
from engine.fields.gl import GlFieldRenderer
from engine.fields.glbaked import GlBakedDynamicRenderer, GlBakedRenderer
from engine.fields.gldynamic import GlDynamicRenderer
from engine.fields.render import TRANSMITTANCE_EPS, evaluation_macs, load_field, render_field

__all__ = ["DISPATCH_FRAMES", "DISPATCH_WARMUP_S", "DISPATCH_BUDGET_S", "dispatch_times", "run_static_bench",
           "run_dynamic_bench", "bench_records", "bench_table", "report_bench", "main"]


def _timed(fn):
    wall, cpu = time.perf_counter(), time.process_time()
    out = fn()
    return out, time.perf_counter() - wall, time.process_time() - cpu


def _psnr(reference: dict, test: dict) -> float:
    return psnr(display_encode(reference["color"]), display_encode(test["color"]))


def report_bench(records: list[dict], json_path: Optional[Path] = None) -> None:
    """Print the benchmark table; write the records as strict JSON (non-finite numbers as null) if asked."""
    print(bench_table(records))
    if json_path:
        json_path.write_text(json.dumps([{k: (None if isinstance(v, float) and not math.isfinite(v) else v)
                                          for k, v in r.items()} for r in records], indent=2) + "\n")


def bench_records(outs: dict, width: int, height: int) -> list[dict]:
    """One benchmark record per renderer: ``outs`` maps a renderer name to (render, wall seconds, CPU
    seconds, compile seconds); scores are against the torch render (else numpy's, else the first).
    A GL render carries ``dispatch_seconds`` (``_gl_outs``): its ``dispatch_ms`` is their median, NaN for the
    others."""
    ref_name = "torch" if "torch" in outs else "numpy" if "numpy" in outs else next(iter(outs))
    ref = outs[ref_name][0]
    records = []
    for name, (out, walls, cpus, compile_s) in outs.items():
        ms = 1e3 * float(np.median(walls))
        frames = out.get("dispatch_seconds", [])
        finite = np.isfinite(ref["depth"]) & np.isfinite(out["depth"])
        records.append({
            "size": f"{width}x{height}", "renderer": name, "ms": ms, "fps": 1e3 / ms,
            "cpu_ms": 1e3 * float(np.median(cpus)), "runs": len(walls), "compile_s": compile_s,
            "dispatch_ms": 1e3 * float(np.median(frames)) if frames else float("nan"),
            "dispatch_frames": len(frames),
            "reference": ref_name, "psnr": _psnr(ref, out) if name != ref_name else float("inf"),
            "max_abs_color": float(np.abs(out["color"] - ref["color"]).max()),
            "depth_median_abs": float(np.median(np.abs(out["depth"][finite] - ref["depth"][finite])))
            if finite.any() else float("nan"),
            "depth_finite_agree": float(np.mean(np.isfinite(ref["depth"]) == np.isfinite(out["depth"]))),
        })
        print(f"{width}x{height} {name}: {ms:.1f} ms", file=sys.stderr, flush=True)
    return records


def bench_table(records: list[dict]) -> str:
    """Markdown table of benchmark records."""
    lines = ["| size | renderer | ms / frame | fps | ms, no readback | CPU ms / frame | PSNR vs reference (dB) "
             "| max abs colour | median abs depth | depth inf agree | evaluations / px | GMAC/s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in records:
        value = "ref." if math.isinf(r["psnr"]) else f"{r['psnr']:.1f}"
        evals = f"{r['evaluations_per_pixel']:.2f}" if "evaluations_per_pixel" in r else "-"
        rate = f"{r['gmac_per_s']:.1f}" if "gmac_per_s" in r else "-"
        gpu = f"{r['dispatch_ms']:.2f}" if math.isfinite(r.get("dispatch_ms", float("nan"))) else "-"
        lines.append(f"| {r['size']} | {r['renderer']} | {r['ms']:.0f} | {r['fps']:.2f} | {gpu} | {r['cpu_ms']:.0f} "
                     f"| {value} ({r['reference']}) "
                     f"| {r['max_abs_color']:.1e} | {r['depth_median_abs']:.1e} "
                     f"| {100 * r['depth_finite_agree']:.2f}% | {evals} | {rate} |")
    return "\n".join(lines)


def _torch_renderer(model, near: float, far: float):
    """``(K, world_to_camera, height, width) -> render`` of a torch model (``render_image``)."""
    from models.fields.components.render import render_image  # torch: optional here

    return lambda k, w2c, height, width: render_image(model, k, w2c, height, width, near, far)


def _static_camera(export: Path, run: Optional[Path]):
    """(K, world_to_camera, width, height, where) of a held-out view of the run, else of the demo path."""
    if run is not None and (run / "data.json").is_file():
        try:
            from models.fields.data.select import load_run_views  # torch: optional here
        except ImportError:
            pass
        else:
            _, test = load_run_views(run)
            cam = test.cameras[0]
            return cam.intrinsics, cam.world_to_camera, test.width, test.height, f"held-out view {test.names[0]}"
    cams, width, height = field_camera_path(load_field(export), None, 8)
    return cams[0].intrinsics, cams[0].world_to_camera, width, height, "first camera of the demo path"


def _size_outs(width: int, height: int, k, w2c, extra: tuple, *, assets, torch_render, gl_renderer, variants,
               reference, skip: tuple[str, ...], repeat: int) -> dict:
    """``{renderer: (render, wall seconds, CPU seconds, compile seconds)}`` at one size: the torch render
    (one timed run after a 16 x 16 warm-up), every GL variant (``repeat`` timed runs after a warm-up) and
    the numpy / onnx references; ``extra`` follows the camera in every render call (a dynamic field's time)."""
    outs: dict[str, tuple[dict, list[float], list[float], float]] = {}
    if torch_render is not None:
        torch_render(k, w2c, 16, 16)  # warm-up
        out, wall, cpu = _timed(lambda: torch_render(k, w2c, height, width))
        outs["torch"] = (out, [wall], [cpu], 0.0)
    if "gl" not in skip:
        outs.update(_gl_outs(gl_renderer, assets, variants, width, height, k, w2c, extra, repeat))
    for query in ("numpy", "onnx"):
        if query not in skip:
            out, wall, cpu = _timed(lambda: reference(assets, k, w2c, height, width, *extra, query=query))
            outs[query] = (out, [wall], [cpu], 0.0)
    return outs


#: Frames each GL variant draws back to back, dispatch to ``finish`` and nothing read back, for its
#: ``dispatch_ms`` (``GlFieldRenderer.dispatch_seconds``): the renderer's own time, at the clocks a steady stream
#: of frames keeps. They follow DISPATCH_WARMUP_S seconds of untimed frames: a GPU left idle drops its clocks
#: (an H200's SM clock sat at 345 of 1980 MHz through the 2026-11-30 field benchmark, which timed single frames
#: with their readback; docs/results/2026-11-30-gpu-h200-fields.md).
#: The timed frames stop early once they add up to DISPATCH_BUDGET_S (at least one is timed), so that a software
#: renderer's seconds-long 1080p frames do not multiply the benchmark's time.
DISPATCH_FRAMES = 20
DISPATCH_WARMUP_S = 0.5
DISPATCH_BUDGET_S = 2.0


def dispatch_times(renderer, k, w2c, frames: int = DISPATCH_FRAMES, warmup_s: float = DISPATCH_WARMUP_S,
                   budget_s: float = DISPATCH_BUDGET_S) -> list[float]:
    """Seconds of up to ``frames`` frames of a GL field renderer drawn back to back without the readback (fewer
    once they add up to ``budget_s``; at least one), after at least ``warmup_s`` seconds of the same frames
    untimed (at most 1000 of them). Frames are drawn in calls of doubling size, so they stay back to back."""
    def draw(until_seconds: float, most: int) -> list[float]:
        seconds: list[float] = []
        while len(seconds) < most and (not seconds or sum(seconds) < until_seconds):
            seconds += renderer.dispatch_seconds(k, w2c, max(1, min(50, len(seconds), most - len(seconds))))
        return seconds

    if warmup_s > 0:
        draw(warmup_s, 1000)
    return draw(budget_s, frames)


def _gl_outs(gl_renderer, assets, variants, width: int, height: int, k, w2c, extra: tuple, repeat: int) -> dict:
    """``{variant: (render, wall seconds, CPU seconds, compile seconds)}`` of GL renderers (a warm-up render,
    then ``repeat`` timed ones with the readback); each render holds ``dispatch_seconds``, the seconds of
    :data:`DISPATCH_FRAMES` frames drawn back to back without it (:func:`dispatch_times`, after the timed
    renders, at their time)."""
    outs = {}
    for name, kwargs in variants:
        with gl_renderer(assets, width, height, **kwargs) as r:
            out = r.render(k, w2c, *extra)  # warm-up
            runs = [_timed(lambda: r.render(k, w2c, *extra)) for _ in range(repeat)]
            out["dispatch_seconds"] = dispatch_times(r, k, w2c)
            outs[name] = (out, [x[1] for x in runs], [x[2] for x in runs], r.compile_seconds)
    return outs


STATIC_GL_VARIANTS = [("gl float", {}), ("gl float, exact filtering", {"filtering": "exact"}),
                      ("gl uint8", {"quantized": True}),
                      ("gl float, no early stop / colour skip", {"transmittance_eps": 0.0, "color_eps": 0.0}),
                      ("gl float, weights in a UBO", {"weights": "buffer"}),
                      ("gl float, colour once per pixel (approx.)", {"color_mode": "latent"}),
                      ("gl float, 1 tile per invocation", {"tiles_per_invocation": 1}),
                      ("gl float, 8 tiles per invocation", {"tiles_per_invocation": 8})]
#: The baked field's GL renderer (``engine.fields.glbaked``), timed when the export holds ``baked.json``.
BAKED_GL_VARIANTS = [("gl baked", {}), ("gl baked, exact filtering", {"filtering": "exact"}),
                     ("gl baked, early stop at 1e-4", {"transmittance_eps": TRANSMITTANCE_EPS})]
DYNAMIC_GL_VARIANTS = [("gl", {}), ("gl, exact filtering", {"filtering": "exact"}),
                       ("gl, no early stop / colour skip", {"transmittance_eps": 0.0, "color_eps": 0.0})]


def run_static_bench(export: Path, sizes: list[tuple[int, int]], *, run: Optional[Path] = None, repeat: int = 3,
                     skip: tuple[str, ...] = (), threads: int = 0) -> list[dict]:
    """Time every renderer of the static field at every size on one camera; PSNR of each against the torch
    render (or the numpy one when torch is not importable). Returns one record per (size, renderer)."""
    export = Path(export)
    if not (export / "field.json").is_file() and (export / "export" / "field.json").is_file():
        export = export / "export"
    if run is None and (export.parent / "checkpoint.pt").is_file():
        run = export.parent
    k0, w2c, w0, h0, where = _static_camera(export, run)
    assets = load_field(export)
    baked = load_baked(export) if (export / "baked.json").is_file() and "baked" not in skip else None
    torch_render = None
    if "torch" not in skip and run is not None:
        try:
            import torch  # optional: the bench runs without it

            from models.fields.train_static import load_model
        except ImportError:
            pass
        else:
            if threads:
                torch.set_num_threads(threads)
            model = load_model(run)
            torch_render = _torch_renderer(model, model.scene.near, model.scene.far)
    # a deferred field is shaded once per pixel exactly: the per-sample field's approximation does not apply
    variants = [(name, kw) for name, kw in STATIC_GL_VARIANTS if not (assets.deferred and "color_mode" in kw)]
    records = []
    for width, height in sizes:
        k = scale_intrinsics(k0, w0, h0, width, height)
        outs = _size_outs(width, height, k, w2c, (), assets=assets, torch_render=torch_render,
                          gl_renderer=GlFieldRenderer, variants=variants, reference=render_field, skip=skip,
                          repeat=repeat)
        if baked is not None:
            outs.update(_baked_outs(baked, width, height, k, w2c, skip, repeat))
        size_records = bench_records(outs, width, height)
        if "gl" not in skip:
            _add_arithmetic(size_records, assets, k, w2c, width, height)
        if baked is not None and "baked" not in skip:
            _add_baked_evaluations(size_records, baked, k, w2c, width, height)
        records.extend(size_records)
    for r in records:
        r["camera"] = where
    return records


def _baked_outs(baked, width: int, height: int, k, w2c, skip: tuple[str, ...], repeat: int, extra: tuple = ()
                ) -> dict:
    """The baked field's renders at one size: its GL variants and (unless numpy is skipped) its numpy reference;
    a baked dynamic field's (``extra``: its time) with ``GlBakedDynamicRenderer`` and ``render_baked_dynamic``."""
    dynamic = isinstance(baked, BakedDynamicAssets)
    gl_renderer = GlBakedDynamicRenderer if dynamic else GlBakedRenderer
    reference = render_baked_dynamic if dynamic else render_baked
    outs = {}
    if "gl" not in skip:
        outs.update(_gl_outs(gl_renderer, baked, BAKED_GL_VARIANTS, width, height, k, w2c, extra, repeat))
    if "numpy" not in skip:
        out, wall, cpu = _timed(lambda: reference(baked, k, w2c, height, width, *extra))
        outs["baked numpy"] = (out, [wall], [cpu], 0.0)
    return outs


def _add_baked_evaluations(records: list[dict], baked, k, w2c, width: int, height: int) -> None:
    """Samples read per pixel (in occupied bricks, up to early termination) by the default baked GL renderer."""
    with GlBakedRenderer(baked, width, height, count_evaluations=True) as r:
        evaluations = r.render(k, w2c)["evaluations"]
    for rec in records:
        if rec["renderer"] == BAKED_GL_VARIANTS[0][0]:
            rec["evaluations_per_pixel"] = float(evaluations.mean())


def _add_arithmetic(records: list[dict], assets, k, w2c, width: int, height: int) -> None:
    """Field evaluations per pixel (counted by the GL renderer at its defaults) and what they cost: GMAC a
    frame in the MLPs (``evaluation_macs``) and, at the default renderer's time, GMAC/s (to set against the
    device's FP32 multiply-add peak), added to the default GL record."""
    with GlFieldRenderer(assets, width, height, count_evaluations=True) as r:
        evaluations = r.render(k, w2c)["evaluations"]
    gmac = float(evaluations.sum(dtype=np.float64)) * evaluation_macs(assets) / 1e9
    for rec in records:
        if rec["renderer"] == STATIC_GL_VARIANTS[0][0]:
            rec.update(evaluations_per_pixel=float(evaluations.mean()), macs_per_evaluation=evaluation_macs(assets),
                       gmac_per_frame=gmac, gmac_per_s=gmac / (rec["ms"] / 1e3))


#: The earlier time of the timed motion vectors: this fraction of the trained range before the view's time (after
#: it at the range's start), about one frame of a 30-frame capture.
VECTOR_TIME_STEP = 1 / 30


def _vector_outs(assets, width: int, height: int, k, w2c, t: float, repeat: int) -> dict:
    """``{"gl + motion vectors": (render, wall seconds, CPU seconds, compile seconds)}``: the default GL renderer
    drawing the frame and its motion vectors (the second pass, ``coherence=COHERENCE`` as ``mvec`` is fed) to a
    time ``VECTOR_TIME_STEP`` of the range earlier, the camera the same (a warm-up render, then ``repeat`` timed
    ones with both readbacks)."""
    t0, t1 = assets.time_range
    step = VECTOR_TIME_STEP * (t1 - t0)
    earlier = t - step if t - step >= t0 else min(t + step, t1)
    with GlDynamicRenderer(assets, width, height) as r:
        def draw():
            return r.render(k, w2c, t, earlier_world_to_camera=w2c, earlier_time=earlier, coherence=COHERENCE)
        out = draw()  # warm-up
        runs = [_timed(draw) for _ in range(repeat)]
        return {"gl + motion vectors": (out, [x[1] for x in runs], [x[2] for x in runs], r.compile_seconds)}


def run_dynamic_bench(export: Path, sizes: list[tuple[int, int]], *, run: Optional[Path] = None, repeat: int = 3,
                      skip: tuple[str, ...] = (), view: int = 0, time_value: Optional[float] = None,
                      threads: int = 0) -> list[dict]:
    """Time every renderer of the dynamic field at every size on one held-out view of the run (at its time,
    or ``time_value``); PSNR of each against the torch render (or the numpy one without torch). When the export
    holds a baked field (``baked_dynamic.json``) its GL renderer and numpy oracle are timed too."""
    import torch  # the held-out views come from the run's data (models.fields): torch is needed here

    from models.fields.data.select import load_dynamic_run_views
    from models.fields.dynamic.model import AtTime
    from models.fields.train_dynamic import load_dynamic_model

    export = Path(export)
    if not (export / "dynamic.json").is_file() and (export / "export" / "dynamic.json").is_file():
        export = export / "export"
    run = run or export.parent
    if not (run / "data.json").is_file():
        raise InputError("has no data.json: pass --run RUN_DIR (the held-out camera comes from it)", file=run)
    if threads:
        torch.set_num_threads(threads)
    _, test = load_dynamic_run_views(run)
    cam = test.cameras[view]
    t = float(test.times[view]) if time_value is None else float(time_value)
    assets = load_dynamic_field(export)
    baked = (load_baked_dynamic(export) if (export / "baked_dynamic.json").is_file() and "baked" not in skip
             else None)
    torch_render = None
    if "torch" not in skip:
        model = AtTime(load_dynamic_model(run), t)
        torch_render = _torch_renderer(model, model.model.scene.near, model.model.scene.far)
    records = []
    for width, height in sizes:
        k = scale_intrinsics(cam.intrinsics, test.width, test.height, width, height)
        outs = _size_outs(width, height, k, cam.world_to_camera, (t,), assets=assets, torch_render=torch_render,
                          gl_renderer=GlDynamicRenderer, variants=DYNAMIC_GL_VARIANTS, reference=render_dynamic_field,
                          skip=skip, repeat=repeat)
        if "gl" not in skip:
            outs.update(_vector_outs(assets, width, height, k, cam.world_to_camera, t, repeat))
        if baked is not None:
            outs.update(_baked_outs(baked, width, height, k, cam.world_to_camera, skip, repeat, (t,)))
        for record in bench_records(outs, width, height):
            records.append({**record, "time": t, "camera": f"held-out view {test.names[view]}"})
    return records


def _sizes(text: str) -> list[tuple[int, int]]:
    try:
        out = [tuple(int(v) for v in item.lower().split("x")) for item in text.split(",") if item.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WxH[,WxH...], got {text!r}") from None
    if not out or any(len(s) != 2 or min(s) < 1 for s in out):
        raise argparse.ArgumentTypeError(f"expected WxH[,WxH...], got {text!r}")
    return out


def main(argv: Optional[list[str]] = None) -> int:
    """``python -m tools.bench_fields {static,dynamic} EXPORT_DIR``: the speed / parity table."""
    parser = argparse.ArgumentParser(prog="python -m tools.bench_fields", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="kind", required=True)
    static = sub.add_parser("static", help="an exported static field (engine.fields.gl)")
    dynamic = sub.add_parser("dynamic", help="an exported dynamic field (engine.fields.gldynamic)")
    static.add_argument("export", type=Path, metavar="EXPORT_DIR",
                        help="folder with field.json (or a run directory holding export/)")
    static.add_argument("--run", type=Path, default=None,
                        help="the run directory (torch renderer and held-out camera; default: EXPORT_DIR/..)")
    static.add_argument("--sizes", type=_sizes, default=[(512, 512), (960, 540)],
                        help="WxH,... (default 512x512,960x540)")
    dynamic.add_argument("export", type=Path, metavar="EXPORT_DIR",
                         help="folder with dynamic.json (or a run directory holding export/)")
    dynamic.add_argument("--run", type=Path, default=None, help="the run directory (default: EXPORT_DIR/..)")
    dynamic.add_argument("--sizes", type=_sizes, default=[(160, 90), (512, 512)],
                         help="WxH,... (default 160x90,512x512)")
    dynamic.add_argument("--view", type=int, default=0, help="index of the held-out view (default 0)")
    dynamic.add_argument("--time", type=float, default=None, help="render time (default: the view's own)")
    for p in (static, dynamic):
        p.add_argument("--repeat", type=int, default=3, help="timed GL renders per variant (median; default 3)")
        p.add_argument("--skip", default="", help="comma-separated renderers to skip: gl,numpy,onnx,torch and "
                                                  "baked (the baked field of an export that has one)")
        p.add_argument("--threads", type=int, default=0, help="torch threads (0: torch's default)")
        p.add_argument("--json", type=Path, default=None, help="also write the records to this JSON file")
    args = parser.parse_args(argv)
    skip = tuple(s.strip() for s in args.skip.split(",") if s.strip())
    try:
        if args.kind == "static":
            records = run_static_bench(args.export, args.sizes, run=args.run, repeat=max(1, args.repeat), skip=skip,
                                       threads=args.threads)
        else:
            records = run_dynamic_bench(args.export, args.sizes, run=args.run, repeat=max(1, args.repeat),
                                        skip=skip, view=args.view, time_value=args.time, threads=args.threads)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    report_bench(records, args.json)
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
