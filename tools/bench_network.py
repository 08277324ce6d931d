"""A/B benchmark of exported flow graphs on the inputs the engine really gives them.

``python -m tools.bench_network SEQ_DIR... --models A.onnx,B.onnx [--k 2] [--groups 6] [--repeats 5]
[--threads 2] [--json FILE]`` runs the default ``decomp`` predictor on ``--groups`` rendered frames per
sequence (spread evenly) and records every input the flow network receives (one per gate box). Then each
graph runs all recorded inputs, the graphs alternated within each of ``--repeats`` passes (the first pass,
warm-up, not counted) so that the VM's slow drifts hit all alike, and it prints per graph:

- the median ms per box and per rendered frame (the sum over the frame's boxes),
- the largest |du|, |dv| difference from the first graph's flow over all boxes (pixels of the network's
  grid): graphs exported from the same weights must agree; dz is not compared (graphs exported with
  ``--no-depth-flow`` return 0).

The graphs must take the same inputs (plane count, initial flow). No torch needed.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path
from typing import Sequence

import numpy as np

from engine.core.errors import InputError
from engine.eval.protocol import evaluation_pairs
from engine.io.rgbd import read_sequence
from engine.predict.decomp import DEFAULT_MODEL, DecompConfig, DecompPredictor, FlowNetwork


class _Recorder:
    """Stands in for an onnxruntime session: runs it and keeps a copy of every feed, tagged with the frame."""

    def __init__(self, session) -> None:
        self.session = session
        self.frame = -1
        self.feeds: list[tuple[int, dict[str, np.ndarray]]] = []

    def run(self, names, feeds):
        self.feeds.append((self.frame, {k: v.copy() for k, v in feeds.items()}))
        return self.session.run(names, feeds)


def record_inputs(sequences: Sequence[Path], k: int, groups: int, threads: int = 2,
                  model: Path = DEFAULT_MODEL) -> list[tuple[int, dict[str, np.ndarray]]]:
    """(frame number, network feed) for every network call of ``decomp`` (``model``) on the sequences."""
    out: list[tuple[int, dict[str, np.ndarray]]] = []
    frame = 0
    for path in sequences:
        seq = read_sequence(path)
        network = FlowNetwork(model, threads)
        recorder = _Recorder(network.session)
        network.session = recorder
        pred = DecompPredictor(DecompConfig(model=str(model)), network=network, objects=seq.objects)
        pairs = evaluation_pairs(len(seq), k)
        step = max(1, len(pairs) // groups)
        for older, newest, _ in pairs[::step][:groups]:
            recorder.frame = frame
            pred.prepare([seq[older], seq[newest]])
            frame += 1
        out += recorder.feeds
    return out


def run(sequences: Sequence[Path], models: Sequence[Path], k: int = 2, groups: int = 6, repeats: int = 5,
        threads: int = 2) -> dict:
    if not models:
        raise InputError("needs at least one graph", field="models")
    feeds = record_inputs(sequences, k, groups, threads, models[0])
    if not feeds:
        raise InputError("the gate found no object motion on these frames: the network never ran",
                         field="sequences")
    nets = [FlowNetwork(m, threads) for m in models]
    first = nets[0]
    for net in nets[1:]:
        if (net.num_planes, net.needs_initial_flow) != (first.num_planes, first.needs_initial_flow):
            raise InputError(f"takes {net.num_planes} planes (initial flow: {net.needs_initial_flow}), the first "
                             f"graph {first.num_planes} ({first.needs_initial_flow})", file=net.path)
    flows = [[net.session.run(None, f)[0][:, :2] for _, f in feeds] for net in nets]
    diff = [max(float(np.abs(a - b).max()) for a, b in zip(flows[i], flows[0])) for i in range(len(nets))]
    box_ms: list[list[float]] = [[] for _ in nets]
    frame_ms: list[list[float]] = [[] for _ in nets]
    for rep in range(repeats + 1):
        order = list(range(len(nets))) if rep % 2 == 0 else list(range(len(nets)))[::-1]
        for i in order:
            per_frame: dict[int, float] = {}
            for frame, f in feeds:
                start = time.perf_counter()
                nets[i].session.run(None, f)
                ms = 1e3 * (time.perf_counter() - start)
                per_frame[frame] = per_frame.get(frame, 0.0) + ms
                if rep:
                    box_ms[i].append(ms)
            if rep:
                frame_ms[i] += list(per_frame.values())
    sizes = sorted({tuple(int(s) for s in f["alpha_n"].shape[-2:]) for _, f in feeds}, key=lambda s: s[0] * s[1])
    return {"sequences": [str(s) for s in sequences], "k": k, "frames": len({fr for fr, _ in feeds}),
            "boxes": len(feeds), "box_sizes": [sizes[0], sizes[-1]], "repeats": repeats, "threads": threads,
            "graphs": [{"model": str(m), "median_ms_per_box": statistics.median(b),
                        "median_ms_per_frame": statistics.median(fr), "max_flow_difference_px": d}
                       for m, b, fr, d in zip(models, box_ms, frame_ms, diff)]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m tools.bench_network", description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", type=Path, nargs="+", help="rgbd-seq folders")
    parser.add_argument("--models", required=True, help="comma-separated ONNX flow graphs (the first is the reference)")
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--groups", type=int, default=6, help="rendered frames per sequence (default 6)")
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--threads", type=int, default=2, help="onnxruntime intra-op threads (default 2)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    if args.k < 2 or args.groups < 1 or args.repeats < 1 or args.threads < 1:
        raise InputError("needs k >= 2 and groups, repeats, threads >= 1", field="arguments")
    models = [Path(m) for m in args.models.split(",") if m.strip()]
    result = run(args.sequences, models, args.k, args.groups, args.repeats, args.threads)
    lo, hi = result["box_sizes"]
    print(f"{result['boxes']} network inputs from {result['frames']} rendered frames (k = {args.k}, boxes "
          f"{lo[0]}x{lo[1]} to {hi[0]}x{hi[1]} px), {args.repeats} passes, {args.threads} threads (medians):")
    print("| graph | ms / box | ms / frame | max abs d(du, dv) from the first (px) |\n| --- | --- | --- | --- |")
    for g in result["graphs"]:
        print(f"| {g['model']} | {g['median_ms_per_box']:.1f} | {g['median_ms_per_frame']:.1f} | "
              f"{g['max_flow_difference_px']:.1e} |")
    if args.json:
        args.json.write_text(json.dumps(result, indent=1))
        print(f"wrote {args.json}")


if __name__ == "__main__":
    main()
