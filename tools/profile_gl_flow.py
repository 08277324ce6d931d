"""The GPU's optical flow alone (``GlOpticalFlow.estimate``): dispatches and GPU ms per stage (and with
``--passes`` per pass), configurations side by side (``tools.bench_gl_flow`` scores its accuracy against DIS).

``python -m tools.profile_gl_flow [--sizes 960x540,1920x1080] [--configs "sor=passes,coarse_pixels=0;search=thread;"]
[--passes] [--k 2] [--frames 6] [--repeats 5] [--idle 0] [--out out/bench_backends] [--json FILE]``

The frames are ``tools.bench_backends``' scene (the fast held-out scene, rendered once and cached under
``--out``): the flow from frame n to frame n-k, over every rendered frame n with history. ``--configs`` is a
``;``-separated list of ``GlFlowConfig`` changes (``name=value,...``; empty: the defaults), each a row; the
default compares the passes as they were before ``flow_coarse`` and ``flow_refine_tile`` (every level by its
passes, SOR as red and black dispatches), each of the two alone, ``flow_coarse`` on the levels of at most 2048
pixels, the one-invocation search, and the defaults. Per size and
configuration, one warm-up pass, then ``--repeats`` passes back to back. It prints the settings the estimator
ran (search / SOR / coarse pixels, ``auto`` resolved), the compute dispatches of one estimate
(``dispatch_counts``), the median GPU ms per stage (``luma``, ``pyramid``, ``search``, ``readback``; GL timer
queries), the median wall ms, and the flow's difference from the first configuration's (the same search with
its sums in another order, or rounded another way: a few near-ties differ). With ``--passes`` one more pass
runs with a timer query per dispatch (``GlContext.pass_timing``) and a table gives each pass's dispatches and
GPU ms per estimate (a query per dispatch adds waits of its own: shares, not a frame's time; on a software
renderer the CPU's ms of each dispatch, a proxy). With ``--idle
S`` each estimate waits S seconds first, as a GPU waits between rendered frames: a GPU that lowers its clocks
when idle then shows it in the GPU ms. On a software renderer the queries do not time a GPU and the tool
prints ``-`` for them.
"""
from __future__ import annotations

import argparse
import statistics
import time
from dataclasses import replace

import numpy as np

from engine.geometry.backends.gl import shared_context
from engine.geometry.backends.gl.flow import GlOpticalFlow, dispatch_counts
from engine.io.rgbd import read_sequence
from tools.bench_backends import SCENE, gl_or_exit, parse_sizes, stage_medians
from tools.bench_gl_flow import parse_config
from tools.heldout import render_set, write_json

STAGES = ("luma", "pyramid", "search", "readback")
#: the configurations compared by default: the passes before flow_coarse and flow_refine_tile, each of the two
#: alone, flow_coarse on fewer levels (at 1920x1080 levels 5 and 6), the one-invocation search, the defaults
CONFIGS = "sor=passes,coarse_pixels=0;sor=passes;coarse_pixels=0;coarse_pixels=2048;search=thread;"


def time_config(pairs: list, estimator: GlOpticalFlow, repeats: int, idle: float) -> tuple[dict, float, list]:
    """(median GPU ms per stage, median wall ms, the flows of the last pass) of one estimator over ``pairs``
    ((first, second) colour arrays)."""
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
    return stage_medians(runs), float(statistics.median(walls)), flows


def time_passes(pairs: list, estimator: GlOpticalFlow) -> dict:
    """{pass: (dispatches, GPU ms) per estimate} over one pass of ``pairs``, a query per dispatch."""
    passes: dict = {}
    with shared_context().pass_timing(passes):
        for first, second in pairs:
            estimator.estimate(first, second)
    return {name: (calls / len(pairs), ms / len(pairs)) for name, (calls, ms) in passes.items()}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="960x540,1920x1080")
    parser.add_argument("--configs", default=CONFIGS)
    parser.add_argument("--passes", action="store_true")
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--idle", type=float, default=0.0)
    parser.add_argument("--out", default="out/bench_backends")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    if args.k < 1 or args.repeats < 1 or args.idle < 0 or args.frames <= args.k:
        raise SystemExit("error: --k and --repeats must be >= 1, --idle >= 0 and --frames > --k")
    try:
        configs = [parse_config(text) for text in args.configs.split(";")]
    except (SystemExit, ValueError, TypeError) as err:  # parse_config names a field it does not know
        raise SystemExit(f"error: --configs {args.configs!r}: {err}") from None
    hardware, renderer = gl_or_exit("profile_gl_flow")
    name, overrides, preset = SCENE
    doc = {"renderer": renderer, "hardware": hardware, "k": args.k, "idle_s": args.idle, "rows": []}
    print("| size | search / SOR / coarse pixels | dispatches | GPU ms: luma | pyramid | search | readback | total | "
          "wall ms | flow vs first: median / p99 / max px |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    tables = []
    for width, height in parse_sizes(args.sizes):
        sequence = read_sequence(render_set(args.out, name, overrides, width, height, args.frames, preset))
        frames = list(sequence)
        pairs = [(frames[n].color, frames[n - args.k].color) for n in range(args.k, len(frames), args.k)]
        first_flows = None
        for config in configs:
            estimator = GlOpticalFlow(config=config)
            ran = replace(config, search=estimator.search, sor=estimator.sor, coarse_pixels=estimator.coarse_pixels)
            label = f"{ran.search} / {ran.sor} / {ran.coarse_pixels}"
            dispatches = dispatch_counts((height, width), ran)
            gpu, wall, flows = time_config(pairs, estimator, args.repeats, args.idle)
            passes = time_passes(pairs, estimator) if args.passes else None
            estimator.release()
            if first_flows is None:
                first_flows = flows
            diff = np.concatenate([np.abs(a - b).max(axis=-1).ravel() for a, b in zip(flows, first_flows)])
            row = {"size": [width, height], "search": ran.search, "sor": ran.sor,
                   "coarse_pixels": ran.coarse_pixels, "dispatches": dispatches,
                   "gpu_ms": gpu if hardware else None, "wall_ms": wall, "pairs": len(pairs),
                   "passes": passes,
                   "diff_px": {"median": float(np.median(diff)), "p99": float(np.percentile(diff, 99)),
                               "max": float(diff.max())}}
            doc["rows"].append(row)
            cells = [f"{gpu.get(s, 0.0):.2f}" if hardware else "-" for s in STAGES]
            total = f"{sum(gpu.values()):.2f}" if hardware else "-"
            d = row["diff_px"]
            print(f"| {width}x{height} | {label} | {sum(dispatches.values())} | {' | '.join(cells)} | {total} | "
                  f"{wall:.1f} | {d['median']:.3g} / {d['p99']:.3g} / {d['max']:.3g} |")
            if passes is not None:
                tables.append((f"{width}x{height}, {label}", passes))
    unit = "GPU ms (a query each)" if hardware else "CPU ms of the software renderer (a finish around each)"
    for title, passes in tables:
        print(f"\nper pass, {title}: dispatches and {unit} per estimate\n")
        print("| pass | dispatches | ms |\n|---|---|---|")
        for pass_name, (calls, ms) in sorted(passes.items(), key=lambda kv: (-kv[1][1], -kv[1][0])):
            print(f"| {pass_name} | {calls:.0f} | {ms:.3f} |")
    write_json(args.json, doc)


if __name__ == "__main__":
    main()
