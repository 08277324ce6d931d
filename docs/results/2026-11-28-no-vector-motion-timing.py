"""Warm ms per predicted frame at 960x540, k = 2, on the CPU backend (2026-11-28-no-vector-motion.md): one smooth
sequence (seed 7901, 10 frames), 3 passes over its evaluation pairs, the first dropped, medians.

    python docs/results/2026-11-28-no-vector-motion-timing.py OUT_DIR "reproject;flow2d;..." OUT.json
"""
import json
import statistics
import sys
from pathlib import Path

from engine.io.rgbd import read_sequence
from engine.predict import make_predictor
from tools.heldout import render_set, timing_cases, warm_runs

folder = render_set(Path(sys.argv[1]), "smooth7901", {"seed": 7901}, 960, 540, 10, "smooth")
seq = read_sequence(folder)
methods = sys.argv[2].split(";")
predictors = {m: make_predictor(m, seq.objects, backend="cpu") for m in methods}
times = {m: [] for m in methods}
for r, _, key, _, _, ms in warm_runs(predictors, timing_cases(seq, 2), 3):
    if r > 0:
        times[key].append(ms)
medians = {m: statistics.median(v) for m, v in times.items()}
for m in methods:
    print(f"{m}: {medians[m]:.1f} ms, x{medians[m] / medians['reproject']:.2f} reproject")
Path(sys.argv[3]).write_text(json.dumps(medians, indent=1))
