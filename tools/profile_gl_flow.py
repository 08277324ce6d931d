"""The GPU's optical flow alone (``GlOpticalFlow.estimate``): GPU ms per stage, its inverse searches side by
side (``tools.bench_gl_flow`` scores its accuracy against DIS).

``python -m tools.profile_gl_flow [--sizes 960x540,1920x1080] [--searches thread,group] [--k 2] [--frames 6]
[--repeats 5] [--idle 0] [--out out/bench_backends] [--json FILE]``

The frames are ``tools.bench_backends``' scene (the fast held-out scene, rendered once and cached under
``--out``): the flow from frame n to frame n-k, over every rendered frame n with history. Per size and search
(``GlFlowConfig.search``), one warm-up pass, then ``--repeats`` passes back to back. It prints the median GPU
ms per stage (``luma``, ``pyramid``, ``search``, ``readback``; GL timer queries), the median wall ms, and the
flow's difference from the first search named (the same search with its sums in another order: a few
near-ties differ). With ``--idle S`` each estimate waits S seconds first, as a GPU waits between rendered
frames: a GPU that lowers its clocks when idle then shows it in the GPU ms. On a software renderer the
queries do not time a GPU and the tool prints ``-`` for them.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from engine.geometry.backends.gl.flow import SEARCHES, GlFlowConfig, GlOpticalFlow
from engine.io.rgbd import read_sequence
from tools.bench_backends import SCENE, gl_or_exit, parse_sizes, stage_medians
from tools.heldout import render_set, write_json

STAGES = ("luma", "pyramid", "search", "readback")


def time_search(pairs: list, search: str, repeats: int, idle: float) -> tuple[dict, float, list]:
    """(median GPU ms per stage, median wall ms, the flows of the last pass) of one search over ``pairs``
    ((first, second) colour arrays)."""
    estimator = GlOpticalFlow(config=GlFlowConfig(search=search))
    for first, second in pairs:  # warm-up: programs compiled, buffers grown
        estimator.estimate(first, second)
    runs, walls, flows = [], [], []
    for _ in range(repeats):
        flows = []
        for first, second in pairs:
            if idle:
                time.sleep(idle)
            gpu: dict = {}
            start = time.perf_counter()
            flows.append(estimator.estimate(first, second, gpu_ms=gpu))
            walls.append(1e3 * (time.perf_counter() - start))
            runs.append(gpu)
    estimator.release()
    return stage_medians(runs), float(statistics.median(walls)), flows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="960x540,1920x1080")
    parser.add_argument("--searches", default="thread,group")
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--idle", type=float, default=0.0)
    parser.add_argument("--out", default="out/bench_backends")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    searches = [s.strip() for s in args.searches.split(",") if s.strip()]
    bad = [s for s in searches if s not in SEARCHES or s == "auto"]
    if bad or not searches:
        raise SystemExit(f"error: --searches takes thread and/or group, got {args.searches!r}")
    if args.k < 1 or args.repeats < 1 or args.idle < 0 or args.frames <= args.k:
        raise SystemExit("error: --k and --repeats must be >= 1, --idle >= 0 and --frames > --k")
    hardware, renderer = gl_or_exit("profile_gl_flow")
    name, overrides, preset = SCENE
    doc = {"renderer": renderer, "hardware": hardware, "k": args.k, "idle_s": args.idle, "rows": []}
    print("| size | search | GPU ms: luma | pyramid | search | readback | total | wall ms | "
          "flow vs first: median / p99 / max px |")
    print("|---|---|---|---|---|---|---|---|---|")
    for width, height in parse_sizes(args.sizes):
        sequence = read_sequence(render_set(args.out, name, overrides, width, height, args.frames, preset))
        frames = list(sequence)
        pairs = [(frames[n].color, frames[n - args.k].color) for n in range(args.k, len(frames), args.k)]
        first_flows = None
        for search in searches:
            gpu, wall, flows = time_search(pairs, search, args.repeats, args.idle)
            if first_flows is None:
                first_flows = flows
            diff = np.concatenate([np.abs(a - b).max(axis=-1).ravel() for a, b in zip(flows, first_flows)])
            row = {"size": [width, height], "search": search, "gpu_ms": gpu if hardware else None,
                   "wall_ms": wall, "pairs": len(pairs), "diff_px": {
                       "median": float(np.median(diff)), "p99": float(np.percentile(diff, 99)),
                       "max": float(diff.max())}}
            doc["rows"].append(row)
            cells = [f"{gpu.get(s, 0.0):.2f}" if hardware else "-" for s in STAGES]
            total = f"{sum(gpu.values()):.2f}" if hardware else "-"
            d = row["diff_px"]
            print(f"| {width}x{height} | {search} | {' | '.join(cells)} | {total} | {wall:.1f} | "
                  f"{d['median']:.3g} / {d['p99']:.3g} / {d['max']:.3g} |")
    write_json(args.json, doc)


if __name__ == "__main__":
    main()
