"""Benchmark of motion estimation without motion vectors, on fast held-out content and on the old gentle set.

``python -m tools.bench_motion [--out out/bench_motion] [--size 640x360] [--frames 16] [--k 2,4]
[--methods repeat,reproject,flow2d,decomp,oracle] [--sets gentle,fast,extreme] [--count 3] [--flip]
[--json FILE]``

Sets (rendered once, cached under ``--out``; ``tools.heldout``):

- ``gentle``: seeds 1001, 1002 at the generator's defaults (the README's held-out scenes);
- ``fast``: the first ``--count`` seeds from 7001 of the scene generator's ``fast`` preset
  (``engine.scenegen.presets``) whose moving pixels move a median 10-35 px a frame at 640 px width: the
  range of the path-traced scenes the engine is judged on (objects fast and spinning, fast camera yaw,
  thin structures always, Monte Carlo-like noise);
- ``extreme``: the same rule on the ``extreme`` preset (from seed 7101), a median 20-80 px a frame.

No network was trained on these seeds (training uses 5000-5031). For each set it prints the measured
speeds, then per (set, k, method): PSNR / SSIM / FLIP (``--flip``) over the whole frame and over moving
pixels, end-point error over moving pixels (the method's u(n -> n-k) extrapolated to frame n+1), median ms
per predicted frame and its ratio to ``reproject`` in the same run, and the share of the reproject ->
oracle gap the method recovers. Scores are ``interleave eval``'s (sRGB, DeCOMPnet's border crop).
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
from pathlib import Path

from engine.eval.protocol import evaluate_sequence, json_safe, summarize
from engine.io.rgbd import read_sequence
from engine.predict import split_methods
from tools.heldout import gap, motion_speed, render_set, speed_set

#: set name -> (preset, first seed, median speed range in px per frame at 640 px width); None: fixed seeds
SETS = {
    "gentle": None,
    "fast": ("fast", 7001, (10.0, 35.0)),
    "extreme": ("extreme", 7101, (20.0, 80.0)),
}
GENTLE_SEEDS = (1001, 1002)

COLUMNS = (("psnr", 2), ("ssim", 4), ("flip", 4), ("psnr_moving", 2), ("ssim_moving", 4), ("flip_moving", 4),
           ("epe_moving", 2), ("ms_per_frame", 1), ("time_vs_reproject", 2))


def set_sequences(out: Path, name: str, count: int, width: int, height: int, frames: int) -> list[tuple[str, Path]]:
    """[(sequence name, folder)] of a set (rendered on first use)."""
    if SETS[name] is None:
        return [(f"seed{s}", render_set(out, f"seed{s}", {"seed": s}, width, height, frames))
                for s in GENTLE_SEEDS[:count]]
    preset, first, speeds = SETS[name]
    return speed_set(out, name, preset, first, count, speeds, width, height, frames)


def cell(v, digits: int = 2) -> str:
    return "-" if v is None or (isinstance(v, float) and math.isnan(v)) else f"{v:.{digits}f}"


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_motion"))
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--methods", default="repeat,reproject,flow2d,decomp,oracle")
    parser.add_argument("--sets", default=",".join(SETS))
    parser.add_argument("--count", type=int, default=3, help="sequences per set")
    parser.add_argument("--flip", action="store_true", help="also score FLIP (slower)")
    parser.add_argument("--max-groups", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    ks = [int(v) for v in args.k.split(",")]
    methods = split_methods(args.methods)
    for needed in ("oracle", "reproject"):
        if needed not in methods:
            methods.insert(0, needed)
    rows, speeds, members = [], {}, {}
    for set_name in args.sets.split(","):
        if set_name not in SETS:
            parser.error(f"unknown set '{set_name}', expected some of {', '.join(SETS)}")
        results = []
        members[set_name] = []
        for seq_name, folder in set_sequences(args.out, set_name, args.count, width, height, args.frames):
            seq = read_sequence(folder)
            speeds[seq_name] = motion_speed(seq)
            members[set_name].append(seq_name)
            print(f"{set_name}/{seq_name}: moving pixels move a median {speeds[seq_name][0]:.1f} px/frame "
                  f"(90th percentile {speeds[seq_name][1]:.1f})", flush=True)
            for k in ks:
                results += evaluate_sequence(seq, methods, k, with_flip=args.flip, max_groups=args.max_groups)
        summary = summarize(results)
        for k in ks:
            base, bound = summary[f"reproject/k={k}"], summary[f"oracle/k={k}"]
            for method in methods:
                row = summary.get(f"{method}/k={k}")
                if row is None:
                    continue
                by_sequence = {r.sequence: {"psnr": r.psnr, "psnr_moving": r.psnr_moving, "epe_moving": r.epe_moving}
                               for r in results if r.method == method and r.k == k}
                rows.append({"set": set_name, "k": k, "method": method, **{c: row.get(c) for c, _ in COLUMNS},
                             "gap_whole": gap(row["psnr"], base["psnr"], bound["psnr"]),
                             "gap_moving": gap(row["psnr_moving"], base["psnr_moving"], bound["psnr_moving"]),
                             "sequences": by_sequence})
    head = ["set", "k", "method", "PSNR", "SSIM", "FLIP", "PSNR mov", "SSIM mov", "FLIP mov", "EPE mov (px)",
            "ms/frame", "x reproject", "gap whole", "gap moving"]
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    for r in rows:
        values = [cell(r[c], d) for c, d in COLUMNS]
        print(f"| {r['set']} | {r['k']} | {r['method']} | " + " | ".join(values)
              + f" | {cell(100 * r['gap_whole'], 0)}% | {cell(100 * r['gap_moving'], 0)}% |")
    print("\nmedian ms per frame over all sets and k: " + ", ".join(
        f"{m} {statistics.median(r['ms_per_frame'] for r in rows if r['method'] == m):.1f}" for m in methods
        if any(r["method"] == m for r in rows)))
    if args.json:
        args.json.parent.mkdir(parents=True, exist_ok=True)
        args.json.write_text(json.dumps(json_safe({"size": [width, height], "frames": args.frames, "k": ks,
                                                   "sets": members, "speeds": speeds, "rows": rows}), indent=1))


if __name__ == "__main__":
    main()
