"""A/B benchmark of the engine's thread settings, alternated within one process so that the VM's slow drifts
(about +-20 % between runs an hour apart on the 2-core machine) hit both sides alike.

``python -m tools.bench_threads SEQ_DIR [--pairs 20] [--repeats 3] [--k 2] [--json FILE]`` prints median
milliseconds of

- the one-plane full-resolution forward warp (``geometry.forward_warp_mpi``) with the warp's passes on
  one thread and split over ``engine.geometry.kernels.thread_count()`` threads (``$INTERLEAVE_KERNEL_THREADS``);
- ``decomp`` per predicted frame (prepare + renders of one group, divided by its k - 1 targets) with the
  same two kernel settings;
- ``decomp`` with onnxruntime's idle threads spinning (``INTERLEAVE_ORT_SPIN=1``) and not (the default).

Each frame pair runs every setting back to back, in alternating order; the first pass over the pairs
(compilation, buffer growth) is not counted.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

from engine import geometry
from engine.eval.protocol import evaluation_pairs
from engine.geometry import kernels
from engine.io.rgbd import read_sequence
from engine.predict import Target, make_predictor


def _with_env(name: str, value: str, fn):
    old = os.environ.get(name)
    os.environ[name] = value
    try:
        return fn()
    finally:
        if old is None:
            os.environ.pop(name, None)
        else:
            os.environ[name] = old


def _decomp_ms(pred, history, targets) -> float:
    start = time.perf_counter()
    state = pred.prepare(history)
    for t in targets:
        pred.render(state, Target(t.camera, t.time, t.index))
    return 1e3 * (time.perf_counter() - start) / max(1, len(targets))


def run(sequence: Path, pairs: int, repeats: int, k: int) -> dict:
    seq = read_sequence(sequence)
    threads = str(kernels.thread_count())
    groups = evaluation_pairs(len(seq), k)[::2][:pairs]
    data = [([seq[o], seq[n]], [seq[t] for t in ts]) for o, n, ts in groups]
    mpis = [geometry.build_mpi(h[0].color, h[0].depth, 1) for h, _ in data]
    spin = _with_env("INTERLEAVE_ORT_SPIN", "1", lambda: make_predictor("decomp", seq.objects))
    quiet = _with_env("INTERLEAVE_ORT_SPIN", "0", lambda: make_predictor("decomp", seq.objects))
    settings = {
        "warp, 1 thread": lambda i: _with_env(kernels.THREADS_ENV, "1", lambda: _warp_ms(data[i][0], mpis[i])),
        f"warp, {threads} threads": lambda i: _with_env(kernels.THREADS_ENV, threads,
                                                        lambda: _warp_ms(data[i][0], mpis[i])),
        "decomp, kernels on 1 thread": lambda i: _with_env(kernels.THREADS_ENV, "1",
                                                           lambda: _decomp_ms(quiet, *data[i])),
        f"decomp, kernels on {threads} threads": lambda i: _decomp_ms(quiet, *data[i]),
        "decomp, onnxruntime spinning": lambda i: _decomp_ms(spin, *data[i]),
    }
    times: dict[str, list[float]] = {name: [] for name in settings}
    names = list(settings)
    for rep in range(repeats + 1):
        for i in range(len(data)):
            order = names if (rep + i) % 2 == 0 else names[::-1]
            for name in order:
                ms = settings[name](i)
                if rep:
                    times[name].append(ms)
    return {"sequence": str(sequence), "k": k, "pairs": len(data), "repeats": repeats, "threads": int(threads),
            "median_ms": {name: statistics.median(v) for name, v in times.items()}}


def _warp_ms(history, mpi) -> float:
    older, newest = history
    start = time.perf_counter()
    geometry.forward_warp_mpi(mpi, older.camera.intrinsics, older.camera.world_to_camera, newest.camera.intrinsics,
                              newest.camera.world_to_camera)
    return 1e3 * (time.perf_counter() - start)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequence", type=Path)
    parser.add_argument("--pairs", type=int, default=20)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    result = run(args.sequence, args.pairs, args.repeats, args.k)
    print(f"{result['sequence']}, k = {args.k}, {result['pairs']} frame pairs x {args.repeats} (medians, ms):")
    print("| setting | ms |\n| --- | --- |")
    for name, ms in result["median_ms"].items():
        print(f"| {name} | {ms:.1f} |")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
