"""Benchmark of motion estimation without motion vectors, on fast held-out content and on the old gentle set.

``python -m tools.bench_motion [--out out/bench_motion] [--size 640x360] [--frames 16] [--k 2,4]
[--methods repeat,reproject,flow2d,decomp,oracle] [--sets gentle,fast,extreme,smooth] [--count 3] [--flip]
[--json FILE]``

Sets (rendered once, cached under ``--out``; ``tools.heldout``):

- ``gentle``: seeds 1001, 1002 at the generator's defaults (the README's held-out scenes);
- ``fast``: the first ``--count`` seeds from 7001 of the scene generator's ``fast`` preset
  (``engine.scenegen.presets``) whose moving pixels move a median 10-35 px a frame at 640 px width: the
  range of the path-traced scenes the engine is judged on (objects fast and spinning, fast camera yaw,
  thin structures always, Monte Carlo-like noise);
- ``extreme``: the same rule on the ``extreme`` preset (from seed 7101), a median 20-80 px a frame;
- ``smooth``: the same rule on the ``smooth`` preset (from seed 7901, a range no run used before), a median
  10-40 px a frame: as fast as ``fast`` but every object on a straight line at constant speed and spin (to 10
  degrees a frame), the camera without shake (turns to ~3 degrees a frame): content whose past motion
  predicts its future.

No network was trained on these seeds (training uses 5000-5031). For each set it prints the measured
speeds, then per (set, k, method): PSNR / SSIM / FLIP (``--flip``) over the whole frame and over moving
pixels, end-point error over moving pixels (the method's u(n -> n-k) extrapolated to frame n+1), median ms
per predicted frame and its ratio to ``reproject`` in the same run, and the share of the reproject ->
oracle gap the method recovers and the share of ``mvec``'s gain over ``reproject`` on moving pixels (where
``mvec``, the renderer's exact vectors, is among the methods). Scores are ``interleave eval``'s (sRGB,
DeCOMPnet's border crop).
"""
from __future__ import annotations

from pathlib import Path

from engine.eval.protocol import evaluate_sequence
from engine.io.rgbd import read_sequence
from engine.eval.protocol import score_cell
from tools.heldout import (bench_parser, gap, median_times, parse_common, render_set, report_speed, set_rows,
                           speed_set, table_lines, write_json)

#: set name -> (preset, first seed, median speed range in px per frame at 640 px width); None: fixed seeds
SETS = {
    "gentle": None,
    "fast": ("fast", 7001, (10.0, 35.0)),
    "extreme": ("extreme", 7101, (20.0, 80.0)),
    "smooth": ("smooth", 7901, (10.0, 40.0)),
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


def add_vector_gain(rows: list[dict]) -> None:
    """Each row's ``mvec_gain_moving``: the share of what ``mvec`` (the renderer's exact vectors) gains over
    ``reproject`` on moving pixels that the row's method gains, per set and k (NaN where mvec did not run)."""
    moving = {(r["set"], r["k"], r["method"]): r["psnr_moving"] for r in rows}
    for r in rows:
        base, bound = moving.get((r["set"], r["k"], "reproject")), moving.get((r["set"], r["k"], "mvec"))
        r["mvec_gain_moving"] = (float("nan") if base is None or bound is None
                                 else gap(r["psnr_moving"], base, bound))


def main(argv=None) -> None:
    parser = bench_parser(__doc__, "out/bench_motion", "2,4", "repeat,reproject,flow2d,decomp,oracle", list(SETS))
    parser.add_argument("--count", type=int, default=3, help="sequences per set")
    parser.add_argument("--flip", action="store_true", help="also score FLIP (slower)")
    args = parser.parse_args(argv)
    width, height, ks, methods = parse_common(args)
    rows, speeds, members = [], {}, {}
    for set_name in args.sets.split(","):
        if set_name not in SETS:
            parser.error(f"unknown set '{set_name}', expected some of {', '.join(SETS)}")
        results = []
        members[set_name] = []
        for seq_name, folder in set_sequences(args.out, set_name, args.count, width, height, args.frames):
            seq = read_sequence(folder)
            report_speed(set_name, seq_name, seq, speeds)
            members[set_name].append(seq_name)
            for k in ks:
                results += evaluate_sequence(seq, methods, k, with_flip=args.flip, max_groups=args.max_groups)
        rows += set_rows(set_name, results, methods, ks, tuple(c for c, _ in COLUMNS))
    add_vector_gain(rows)
    head = ["set", "k", "method", "PSNR", "SSIM", "FLIP", "PSNR mov", "SSIM mov", "FLIP mov", "EPE mov (px)",
            "ms/frame", "x reproject", "gap whole", "gap moving", "mvec gain moving"]
    print("\n| " + " | ".join(head) + " |\n|" + "---|" * len(head))
    print("\n".join(f"{line} {score_cell(100 * row['mvec_gain_moving'], 0)}% |"
                    for line, row in zip(table_lines(rows, COLUMNS), rows)))
    print("\n" + median_times(rows, methods))
    write_json(args.json, {"size": [width, height], "frames": args.frames, "k": ks, "sets": members,
                           "speeds": speeds, "rows": rows})


if __name__ == "__main__":
    main()
