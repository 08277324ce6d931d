"""Benchmark of the two backends side by side: ``cpu`` (numpy + numba) and ``gl`` (OpenGL compute, frames kept on the
GPU), per frame size and method.

``python -m tools.bench_backends [--sizes 640x360,960x540,1920x1080,3840x2160] [--methods reproject,mvec,flow2d]
[--k 2] [--frames 6] [--repeats 3] [--encoding linear|srgb8] [--out out/bench_backends] [--json FILE]``
(methods: any names ``make_predictor`` takes, e.g. ``flow2d[estimator=gl]``, ``decomp``)

Renders (once, cached under ``--out``) the fast held-out scene (preset ``fast``, seed 7003: objects moving a median
12 px a frame at 640x360) at each size. For every rendered frame n with history, each method on each backend
prepares once and predicts the k-1 frames after n, on histories held in memory (with the motion vectors ``mvec``
needs), methods and backends in rotating order, ``--repeats`` passes. Per (size, method, backend) it prints the
median wall ms per predicted frame (preparation divided by k-1, uploads and the readback included), the GPU ms the
GL timer queries measured (``-`` on a software renderer such as Mesa llvmpipe, whose queries do not time a GPU; on
a GPU a second table splits it by stage), the ratio to ``reproject`` on the CPU in the same run, the PSNR against
the truth, and the parity of ``gl`` with ``cpu``: the largest colour difference and the share of pixels within 1e-3
of max(1, value) (the tests' tolerance). ``--encoding srgb8`` runs 8-bit frames in and out, as a ``Session`` with
``color_in="srgb8", color_out="srgb8"`` does: the rendered frames are their 8-bit codes (``gl`` uploads the codes and
decodes them on the GPU), and the predictions 8-bit display codes (``gl`` encodes on the GPU and reads back a quarter
of the float bytes; ``cpu`` encodes on the host, inside the timing); PSNR is then of the decoded codes, parity the
largest code difference and the share of pixels whose codes are equal.
"""
from __future__ import annotations

import argparse
import statistics
from dataclasses import replace

import numpy as np

from engine.eval.metrics import score_frame
from engine.geometry.backends import gl_renderer
from engine.io.rgbd import read_sequence
from engine.geometry.encoding import FRAME_ENCODINGS, decode8, encode8
from engine.predict import make_predictor, split_methods
from tools.heldout import render_set, timing_cases, warm_runs, write_json

SCENE = ("fast7003", dict(seed=7003), "fast")
BACKENDS = ("cpu", "gl")


def parse_sizes(text: str) -> list[tuple[int, int]]:
    """``"640x360,1920x1080"`` -> [(640, 360), (1920, 1080)]; anything else exits with a one-line error."""
    sizes = []
    for part in (p.strip().lower() for p in text.split(",") if p.strip()):
        values = part.split("x")
        if len(values) != 2 or not all(v.isdigit() and int(v) > 0 for v in values):
            raise SystemExit(f"error: size {part!r}: expected WIDTHxHEIGHT, positive integers (e.g. 1920x1080)")
        sizes.append((int(values[0]), int(values[1])))
    if not sizes:
        raise SystemExit("error: no size given (e.g. 1920x1080)")
    return sizes


def gpu_stages(state, predictions: list) -> dict[str, float]:
    """GPU ms per stage of one preparation (``state``) and its renders, per predicted frame."""
    per_stage: dict = {}
    for part in [state.gpu_ms] + [p.gpu_ms for p in predictions]:
        for name, value in part.items():
            per_stage[name] = per_stage.get(name, 0.0) + value / len(predictions)
    return per_stage


def stage_medians(runs: list[dict]) -> dict:
    """Per stage name, the median GPU ms over ``runs`` (a stage missing from a run counts 0)."""
    names = sorted({name for run in runs for name in run})
    return {name: float(statistics.median(run.get(name, 0.0) for run in runs)) for name in names}


def eight_bit(frame):
    """``frame`` as it arrives in 8-bit sRGB: its codes, and the colour decoded from them (``Frame.color_codes``)."""
    codes = encode8(frame.color)
    return replace(frame, color=decode8(codes), color_codes=codes)


def bench_size(sequence, methods: list[str], k: int, repeats: int, encoding: str = "linear") -> list[dict]:
    """Rows (method, backend, wall ms, GPU ms, PSNR, parity) of one sequence (see the module docstring)."""
    predictors = {(m, b): make_predictor(m, sequence.objects, backend=b) for m in methods for b in BACKENDS}
    cases = timing_cases(sequence, k)
    if encoding == "srgb8":  # frames come as 8-bit codes too, as a Session's with color_in="srgb8" on gl
        cases = [([eight_bit(f) for f in history], targets) for history, targets in cases]
    keys = list(predictors)
    wall: dict = {key: [] for key in keys}
    gpu: dict = {key: [] for key in keys}
    stages: dict = {key: [] for key in keys}
    outputs: dict = {}
    for r, c, key, state, preds, ms in warm_runs(predictors, cases, repeats, encoding):
        wall[key].append(ms)
        per_stage = gpu_stages(state, preds)
        stages[key].append(per_stage)
        gpu[key].append(sum(per_stage.values()))
        if r == 0:
            outputs[key, c] = [p.color for p in preds]
    truths = [[sequence[t.index] for t in targets] for _, targets in cases]  # read once, scored per method
    rows = []
    for method, backend in keys:
        scores, worst, within = [], 0.0, []
        for c, frames in enumerate(truths):
            for i, truth in enumerate(frames):
                color, ref = outputs[(method, backend), c][i], outputs[(method, "cpu"), c][i]
                if encoding == "srgb8":  # scored decoded; parity in codes: equal codes
                    scores.append(score_frame(truth.color, decode8(color), truth.moving, with_flip=False))
                    diff, tolerance = np.abs(color.astype(np.int16) - ref), 0
                else:
                    scores.append(score_frame(truth.color, color, truth.moving, with_flip=False))
                    diff, tolerance = np.abs(color - ref), 1e-3 * np.maximum(1.0, np.abs(ref))
                worst = max(worst, float(diff.max()))
                within.append(float(np.mean((diff <= tolerance).all(axis=-1))))
        rows.append({"method": method, "backend": predictors[method, backend].backend,
                     "wall_ms": float(statistics.median(wall[method, backend])),
                     "gpu_ms": float(statistics.median(gpu[method, backend])),
                     "gpu_stage_ms": stage_medians(stages[method, backend]),
                     "psnr": float(np.mean([s.psnr for s in scores])),
                     "psnr_moving": float(np.nanmean([s.psnr_moving for s in scores])),
                     "parity_max_diff": worst, "parity_within": float(np.mean(within))})
    return rows


def gl_tool_parser(doc: str, methods: str, repeats: int) -> argparse.ArgumentParser:
    """The options the GL tools share: --methods, --k, --frames, --repeats, --out (the scene cache), --json."""
    parser = argparse.ArgumentParser(description=doc, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--methods", default=methods)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=repeats)
    parser.add_argument("--out", default="out/bench_backends")
    parser.add_argument("--json", default=None)
    return parser


def gl_or_exit(prog: str) -> tuple[bool, str]:
    """(on a hardware GPU, the GL renderer's name), printed; exits naming ``prog`` where the gl backend cannot
    run."""
    runs, hardware, renderer = gl_renderer()
    if not runs:
        raise SystemExit(f"{prog}: the gl backend cannot run here: {renderer}")
    print(f"GL renderer: {renderer} ({'hardware' if hardware else 'software: GPU ms are not measured'})")
    return hardware, renderer


def main(argv=None) -> None:
    parser = gl_tool_parser(__doc__, "reproject,mvec,flow2d,flow2d[estimator=gl],decomp", 3)
    parser.add_argument("--sizes", default="640x360,960x540,1920x1080,3840x2160")
    parser.add_argument("--encoding", choices=FRAME_ENCODINGS, default="linear")
    args = parser.parse_args(argv)
    hardware, renderer = gl_or_exit("bench_backends")
    methods = split_methods(args.methods)
    doc = {"renderer": renderer, "hardware": hardware, "encoding": args.encoding, "k": args.k, "frames": args.frames,
           "repeats": args.repeats, "scene": SCENE[0], "sizes": []}
    print("\n| size | method | backend | wall ms | GPU ms | x cpu reproject | PSNR | PSNR moving | parity max diff | "
          "parity within 1e-3 |\n|---|---|---|---|---|---|---|---|---|---|")
    stage_lines = []
    for width, height in parse_sizes(args.sizes):
        name, overrides, preset = SCENE
        sequence = read_sequence(render_set(args.out, name, overrides, width, height, args.frames, preset))
        rows = bench_size(sequence, methods, args.k, args.repeats, args.encoding)
        base = next((r["wall_ms"] for r in rows if r["method"] == "reproject" and r["backend"] == "cpu"), float("nan"))
        for r in rows:
            gpu = f"{r['gpu_ms']:.2f}" if hardware and r["backend"] == "gl" else "-"
            print(f"| {width}x{height} | {r['method']} | {r['backend']} | {r['wall_ms']:.1f} | {gpu} | "
                  f"{r['wall_ms'] / base:.2f} | {r['psnr']:.2f} | {r['psnr_moving']:.2f} | "
                  f"{r['parity_max_diff']:.2e} | {100 * r['parity_within']:.2f} % |", flush=True)
            if hardware and r["backend"] == "gl":
                stage_lines.append(f"| {width}x{height} | {r['method']} | " + ", ".join(
                    f"{n} {v:.3f}" for n, v in r["gpu_stage_ms"].items()) + " |")
        doc["sizes"].append({"size": [width, height], "rows": rows})
    if stage_lines:
        print("\nGPU ms per predicted frame by stage (GL timer queries, medians):\n\n| size | method | stages |\n"
              "|---|---|---|\n" + "\n".join(stage_lines))
    write_json(args.json, doc)


if __name__ == "__main__":
    main()
