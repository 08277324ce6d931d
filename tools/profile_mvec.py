"""Where ``mvec``'s time goes against ``reproject``'s, pass by pass, on the CPU backend (issue 42's cost target).

``python -m tools.profile_mvec [--out out/bench_mvec] [--size 960x540] [--frames 16] [--k 2,4]
[--methods reproject,mvec[extrapolation=linear,fallback=false],mvec] [--sequences seed1001,glide3302,spin4101]
[--repeats 5] [--json FILE]``

The sequences are ``tools.bench_mvec``'s (rendered once and cached under ``--out``). Per sequence and k, each
method prepares every evaluation pair's history and renders its k-1 targets, warm, methods in rotating order
(``tools.heldout.warm_runs``), ``--repeats`` passes after one warm-up pass. It prints per method, in ms per
predicted frame (medians over the runs): the wall time and its ratio to ``reproject``; the CPU time of all the
process's threads and its ratio (steadier than wall time on a shared machine; not the target, which is wall
time); the CPU time of the calling thread alone and its ratio (``main``: the serial passes plus the calling
thread's share of the split kernels, what a quiet machine with a core per kernel thread waits for when the
shares are even; steady under load); and each pass's wall time: ``prepare:<stage>`` (the preparation's stages,
divided over the predicted frames; ``rigid.groups``, ``rigid.parts`` and ``rigid.keep`` are the steps of
``rigid``) and ``render:<stage>`` (``warp``: on the CPU backend with the extrapolation of the motion inside;
``fill``). Pairs without frame n-2k (the first of each sequence) have no ``acceleration`` or ``rigid`` stage; a
pass's median counts them as 0 ms.
"""
from __future__ import annotations

import argparse
import statistics
import time
from collections import defaultdict
from pathlib import Path
from typing import Iterator

from engine.io.rgbd import read_sequence
from engine.predict import make_predictor, split_methods
from tools.bench_mvec import SETS, sequence_folder
from tools.heldout import timing_cases, warm_runs, write_json

#: every set's sequences by name
SEQUENCES = {name: overrides for members in SETS.values() for name, overrides in members}


def stage_ms(state, predictions) -> dict[str, float]:
    """Each pass's wall ms per predicted frame of one run: the preparation's stages divided over the
    predictions, and the renders' own stages (a prediction's ``stages_ms`` holds its preparation's too)."""
    count = len(predictions)
    out: dict[str, float] = defaultdict(float)
    for name, ms in state.stages_ms.items():
        out[f"prepare:{name}"] += ms / count
    for prediction in predictions:
        for name, ms in prediction.stages_ms.items():
            if state.stages_ms.get(name) != ms:  # a render stage (the preparation's are copied as they are)
                out[f"render:{name}"] += ms / count
    return out


def profile(sequence, methods: list[str], k: int, repeats: int) -> dict[str, dict]:
    """Per method: ``wall_ms``, ``cpu_ms`` (medians per predicted frame) and ``passes`` (median wall ms per
    predicted frame of each pass)."""
    predictors = {m: make_predictor(m, sequence.objects) for m in methods}
    cases = timing_cases(sequence, k)
    for _ in warm_runs(predictors, cases, 1):  # warm-up: kernels compiled, caches filled
        pass
    wall, cpu = defaultdict(list), defaultdict(list)
    passes: dict[str, list[dict]] = defaultdict(list)
    for *_, method, state, predictions, ms in warm_runs(predictors, cases, repeats):
        wall[method].append(ms)
        passes[method].append(stage_ms(state, predictions))
    for *_, method, _, _, ms in warm_runs(predictors, cases, repeats, clock=time.process_time):
        cpu[method].append(ms)
    main = defaultdict(list)
    for *_, method, _, _, ms in warm_runs(predictors, cases, repeats, clock=time.thread_time):
        main[method].append(ms)
    out = {}
    for m in methods:
        names = sorted({name for run in passes[m] for name in run})
        out[m] = {"wall_ms": statistics.median(wall[m]), "cpu_ms": statistics.median(cpu[m]),
                  "main_ms": statistics.median(main[m]),
                  "passes": {name: statistics.median(run.get(name, 0.0) for run in passes[m]) for name in names}}
    return out


def sequences_parser(doc: str, size: str, k: str, sequences: str) -> argparse.ArgumentParser:
    """The options of the tools that run on ``tools.bench_mvec``'s sequences by name, with their defaults:
    --out, --size, --frames, --k, --sequences, --json."""
    parser = argparse.ArgumentParser(description=doc.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/bench_mvec"))
    parser.add_argument("--size", default=size)
    parser.add_argument("--frames", type=int, default=16)
    parser.add_argument("--k", default=k)
    parser.add_argument("--sequences", default=sequences)
    parser.add_argument("--json", type=Path, default=None)
    return parser


def named_sequences(args) -> Iterator[tuple[str, object, list[int]]]:
    """(name, the loaded sequence, ks) of each of ``sequences_parser``'s --sequences, rendered once at --size
    with --frames frames and cached under --out."""
    width, height = (int(v) for v in args.size.lower().split("x"))
    for name in args.sequences.split(","):
        sequence = read_sequence(sequence_folder(args.out, name, SEQUENCES[name], width, height, args.frames))
        yield name, sequence, [int(v) for v in args.k.split(",")]


def main(argv=None) -> None:
    parser = sequences_parser(__doc__, "960x540", "2,4", "seed1001,glide3302,spin4101")
    parser.add_argument("--methods", default="reproject,mvec[extrapolation=linear,fallback=false],mvec")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    width, height = (int(v) for v in args.size.lower().split("x"))
    methods = split_methods(args.methods)
    if "reproject" not in methods:
        methods.insert(0, "reproject")
    rows = []
    for name, sequence, ks in named_sequences(args):
        for k in ks:
            result = profile(sequence, methods, k, args.repeats)
            base = result["reproject"]
            print(f"\n{name} k={k} ({width}x{height}), ms per predicted frame:")
            for m, r in result.items():
                print(f"  {m}: wall {r['wall_ms']:.1f} (x{r['wall_ms'] / base['wall_ms']:.2f}), cpu {r['cpu_ms']:.1f} "
                      f"(x{r['cpu_ms'] / base['cpu_ms']:.2f}), main thread {r['main_ms']:.1f} "
                      f"(x{r['main_ms'] / base['main_ms']:.2f}); " +
                      ", ".join(f"{p} {v:.2f}" for p, v in r["passes"].items()))
            rows.append({"sequence": name, "k": k, "size": [width, height], "methods": result})
    write_json(args.json, {"repeats": args.repeats, "rows": rows})


if __name__ == "__main__":
    main()
