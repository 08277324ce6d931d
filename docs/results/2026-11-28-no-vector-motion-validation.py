"""The fall-back's validation (2026-11-28-no-vector-motion.md): flow2d against flow2d[fallback=true] at k = 2 on
sequences that are not the benchmark's (gentle seeds 1005-1006, fast 7204-7205, the first two smooth seeds from
7951 moving a median 10-40 px a frame), with the hidden-surface rule as committed and without it.

    python docs/results/2026-11-28-no-vector-motion-validation.py OUT_DIR
"""
import sys
from pathlib import Path

import engine.predict.dis as dis
from engine.eval.protocol import evaluate_sequence, summarize
from engine.io.rgbd import read_sequence
from tools.heldout import render_set, speed_set

out = Path(sys.argv[1])
committed = dis.HIDDEN_BAND
sets = {"gentle": [render_set(out, f"seed{s}", {"seed": s}, 640, 360, 16) for s in (1005, 1006)],
        "fast": [render_set(out, f"valfast{s}", {"seed": s}, 640, 360, 16, "fast") for s in (7204, 7205)],
        "smooth": [f for _, f in speed_set(out, "valsmooth", "smooth", 7951, 2, (10.0, 40.0), 640, 360, 16)]}
for name, folders in sets.items():
    sequences = [read_sequence(f) for f in folders]
    line = name
    for band in (committed, float("inf")):
        dis.HIDDEN_BAND = band  # inf: no surface counts as hidden
        results = []
        for seq in sequences:
            results += evaluate_sequence(seq, ["flow2d", "flow2d[fallback=true]"], 2, with_flip=False, max_groups=4)
        s = summarize(results)
        a, b = s["flow2d/k=2"], s["flow2d[fallback=true]/k=2"]
        line += (f" | hidden band {band}: flow2d {a['psnr']:.2f} / {a['psnr_moving']:.2f}, fallback "
                 f"{b['psnr']:.2f} / {b['psnr_moving']:.2f}")
    print(line, flush=True)
