"""Benchmark of ``mvec`` (the renderer's motion vectors) against ``oracle``, ``reproject`` and ``decomp``.

``python -m tools.bench_mvec [--out out/bench_mvec] [--size 640x360] [--frames 16] [--k 2,3,4]
[--methods reproject,decomp,mvec[extrapolation=linear,fallback=false],mvec,oracle]
[--sets gentle,fast,fast2,faster,glide,camera,spin] [--json FILE]``

Renders (once, cached under ``--out``) held-out sequences that no network was trained on, with the scene
generator's exact motion vectors:

- ``gentle``: seeds 1001, 1002 at the generator's default speeds;
- ``fast``: seeds 3202, 3203 at 10 fps (3x the motion per frame), objects 3x and camera 1.5x faster, Monte
  Carlo noise 0.05 (a median 10-20 px a frame over moving pixels);
- ``fast2``: seeds 3204-3207 as ``fast`` (the four seeds after it, fixed before they were first scored: a check
  that a rule chosen on ``fast`` generalises);
- ``faster``: the same scenes with objects 6x faster (tens of pixels a frame, fast spins and bounces);
- ``glide``: seeds 3302, 3303 at 30 fps, objects travelling 3x farther at 2.5x the rates (fast but smooth
  paths, spins to ~15 degrees a frame), camera 2x;
- ``camera``: seed 1004 without objects at 10 fps, camera 3x faster (fast yaw); ``oracle`` is ``reproject``
  there (nothing but the camera moves) and is not run.
- ``spin``: ``tools.spin_set``'s seeds 4101-4103 (issue 42): objects spinning 5-15 degrees a frame about
  off-centre axes, the camera yawing up to 3 degrees a frame, thin structures.

For each set it prints the measured screen speed of the moving pixels (median and 90th percentile of the
true object flow, px per frame), then per (set, k, method): PSNR over the whole frame and over moving
pixels, end-point error over moving pixels, median ms per predicted frame and its ratio to ``reproject``
in the same run, and the share of the reproject -> oracle gap the method recovers (whole frame and moving
pixels). Scores are those of ``interleave eval`` (sRGB PSNR with DeCOMPnet's border crop), FLIP off.

The evaluation times each frame once, methods in a fixed order, which favours the later ones by a few
milliseconds. ``--timing-size 960x540`` adds a fair timing: the gentle and glide scenes rendered at that
size, each method's preparation plus its k-1 renders (k = 2 and 4) on the same frames in memory, methods in
rotating order, repeated ``--repeats`` times; medians per predicted frame and the ratio to ``reproject``
(the first gentle, glide and spin scenes).
"""
from __future__ import annotations

import statistics

from engine.eval.protocol import evaluate_sequence
from engine.io.rgbd import read_sequence
from engine.predict import make_predictor
from tools.heldout import (bench_parser, median_times, parse_common, render_set, report_speed, set_rows, table_lines,
                           timing_cases, warm_runs, write_json)
from tools.spin_set import SPIN_SEEDS, render_spin

#: set name -> [(sequence name, SceneConfig overrides)]
SETS = {
    "gentle": [("seed1001", dict(seed=1001)), ("seed1002", dict(seed=1002))],
    "fast": [(f"fast{s}", dict(seed=s, fps=10.0, object_speed=3.0, camera_speed=1.5, render_noise=0.05))
             for s in (3202, 3203)],
    # a second fast set (issue 42's fall-back rule, 2026-11-29): the four seeds after the fast set's, its overrides
    "fast2": [(f"fast{s}", dict(seed=s, fps=10.0, object_speed=3.0, camera_speed=1.5, render_noise=0.05))
              for s in (3204, 3205, 3206, 3207)],
    "faster": [(f"faster{s}", dict(seed=s, fps=10.0, object_speed=6.0, camera_speed=1.5)) for s in (3202, 3203)],
    "glide": [(f"glide{s}", dict(seed=s, object_travel=3.0, object_speed=2.5, camera_speed=2.0)) for s in (3302, 3303)],
    "camera": [("camera1004", dict(seed=1004, num_objects=(0, 0), fps=10.0, camera_speed=3.0))],
    "spin": [(f"spin{s}", dict(spin_seed=s)) for s in SPIN_SEEDS],
}


def sequence_folder(out, name: str, overrides: dict, width: int, height: int, frames: int):
    """A set's sequence, rendered once under ``out``: ``tools.spin_set``'s scene for ``spin_seed``, else the
    generator's scene of ``overrides``."""
    if "spin_seed" in overrides:
        return render_spin(out, overrides["spin_seed"], width, height, frames)
    return render_set(out, name, overrides, width, height, frames)


#: table columns (summary name, digits)
COLUMNS = (("psnr", 2), ("psnr_moving", 2), ("epe_moving", 2), ("ms_per_frame", 1), ("time_vs_reproject", 2))


def warm_timing(sequence, methods: list[str], k: int, repeats: int) -> dict[str, float]:
    """Median ms per predicted frame of each method: prepare once + render the k-1 frames, on histories held
    in memory (with the vectors ``mvec`` needs), methods in rotating order, ``repeats`` passes."""
    predictors = {m: make_predictor(m, sequence.objects) for m in methods}
    times: dict[str, list[float]] = {m: [] for m in methods}
    for _, _, method, _, _, ms in warm_runs(predictors, timing_cases(sequence, k), repeats):
        times[method].append(ms)
    return {m: float(statistics.median(v)) for m, v in times.items()}


def main(argv=None) -> None:
    parser = bench_parser(__doc__, "out/bench_mvec", "2,3,4",
                          "reproject,decomp,mvec[extrapolation=linear,fallback=false],mvec,oracle", list(SETS))
    parser.add_argument("--timing-size", default=None, help="e.g. 960x540: add the fair timing at that size")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args(argv)
    width, height, ks, methods = parse_common(args)
    rows, speeds = [], {}
    for set_name in args.sets.split(","):
        results = []
        for seq_name, overrides in SETS[set_name]:
            seq = read_sequence(sequence_folder(args.out, seq_name, overrides, width, height, args.frames))
            report_speed(set_name, seq_name, seq, speeds)
            run = [m for m in methods if m != "oracle" or seq.objects]  # no objects: the bound is reproject
            for k in ks:
                results += evaluate_sequence(seq, run, k, with_flip=False, max_groups=args.max_groups)
        rows += set_rows(set_name, results, methods, ks, tuple(name for name, _ in COLUMNS))

    print("\n| set | k | method | PSNR | PSNR moving | EPE moving (px) | ms/frame | x reproject | gap whole | "
          "gap moving |\n|---|---|---|---|---|---|---|---|---|---|")
    print("\n".join(table_lines(rows, COLUMNS)))
    timing = []
    if args.timing_size:
        tw, th = (int(v) for v in args.timing_size.lower().split("x"))
        timed = [m for m in methods if m != "oracle"]
        print(f"\nwarm timing at {tw}x{th}, median ms per predicted frame (x reproject):")
        for seq_name, overrides in SETS["gentle"][:1] + SETS["glide"][:1] + SETS["spin"][:1]:
            seq = read_sequence(sequence_folder(args.out, seq_name, overrides, tw, th, args.frames))
            for k in (2, 4):
                ms = warm_timing(seq, timed, k, args.repeats)
                timing.append({"sequence": seq_name, "size": [tw, th], "k": k, "ms": ms})
                print(f"  {seq_name} k={k}: " + ", ".join(f"{m} {v:.1f} (x{v / ms['reproject']:.2f})"
                                                        for m, v in ms.items()))
    print("\n" + median_times(rows, methods))
    write_json(args.json, {"size": [width, height], "frames": args.frames, "k": ks, "speeds": speeds, "rows": rows,
                           "timing": timing})


if __name__ == "__main__":
    main()
