"""Where the GL backend's GPU time goes, pass by pass: every compute dispatch timed with its own GL timer
query (``GlContext.pass_timing``).

``python -m tools.profile_gl_passes [--size 1920x1080] [--methods reproject,mvec,flow2d[estimator=gl]] [--k 2]
[--frames 6] [--repeats 2] [--out out/bench_backends] [--json FILE]``

The scene is ``tools.bench_backends``' (the fast held-out scene, rendered once and cached under ``--out``).
Each method runs on the ``gl`` backend, once to warm up, then ``--repeats`` passes over the rendered frames
with history, under ``pass_timing``. Per method and pass, it prints the dispatches and the GPU ms per predicted
frame. It also prints the stage total per predicted frame from the GL stage queries (``gpu_ms``), from the same
number of passes without per-pass queries. The stage total minus the sum of the passes is the GPU time spent
outside dispatches: clears, copies, readbacks, and waits between commands. A query per dispatch adds waits of
its own, so the pass times show shares, not a frame's time. On a software renderer (Mesa llvmpipe) the
queries do not time a GPU and the tool says so.
"""
from __future__ import annotations

import statistics

from engine.geometry.backends.gl import shared_context
from engine.io.rgbd import read_sequence
from engine.predict import make_predictor, split_methods
from tools.bench_backends import SCENE, gl_or_exit, gl_tool_parser, gpu_stages, parse_sizes
from tools.heldout import render_set, timing_cases, warm_runs, write_json


def profile_method(sequence, method: str, k: int, repeats: int) -> dict:
    """``{"passes": {name: (dispatches, GPU ms) per predicted frame}, "stage_gpu_ms": median per predicted
    frame, "predicted": frames}`` of one method on the ``gl`` backend."""
    predictors = {method: make_predictor(method, sequence.objects, backend="gl")}
    cases = timing_cases(sequence, k)
    for _ in warm_runs(predictors, cases, 1):  # warm-up: programs compiled, buffers grown
        pass
    totals = [sum(gpu_stages(state, preds).values()) for *_, state, preds, _ in warm_runs(predictors, cases, repeats)]
    passes: dict = {}
    with shared_context().pass_timing(passes):
        predicted = sum(len(preds) for *_, preds, _ in warm_runs(predictors, cases, repeats))
    per_frame = {name: (calls / predicted, ms / predicted) for name, (calls, ms) in sorted(passes.items())}
    return {"passes": per_frame, "stage_gpu_ms": float(statistics.median(totals)), "predicted": predicted}


def main(argv=None) -> None:
    parser = gl_tool_parser(__doc__, "reproject,mvec,flow2d[estimator=gl]", 2)
    parser.add_argument("--size", default="1920x1080")
    args = parser.parse_args(argv)
    sizes = parse_sizes(args.size)
    if len(sizes) != 1:
        raise SystemExit(f"error: --size takes one WIDTHxHEIGHT, got {args.size!r}")
    (width, height), = sizes
    hardware, renderer = gl_or_exit("profile_gl_passes")
    name, overrides, preset = SCENE
    sequence = read_sequence(render_set(args.out, name, overrides, width, height, args.frames, preset))
    doc = {"renderer": renderer, "hardware": hardware, "size": [width, height], "k": args.k, "methods": {}}
    for method in split_methods(args.methods):
        result = profile_method(sequence, method, args.k, args.repeats)
        doc["methods"][method] = result
        total = sum(ms for _, ms in result["passes"].values())
        print(f"\n{method} at {width}x{height}, k = {args.k}: GPU ms per predicted frame "
              f"(stage queries: {result['stage_gpu_ms']:.3f}; sum of the passes: {total:.3f})\n")
        print("| pass | dispatches | GPU ms | share of the passes |\n|---|---|---|---|")
        for pass_name, (calls, ms) in sorted(result["passes"].items(), key=lambda kv: -kv[1][1]):
            share = ms / total if total > 0 else float("nan")
            print(f"| {pass_name} | {calls:.1f} | {ms:.3f} | {100 * share:.1f} % |")
    write_json(args.json, doc)


if __name__ == "__main__":
    main()
