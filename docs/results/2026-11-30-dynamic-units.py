"""Figures of 2026-11-30-dynamic-units.md (issue 45): the flow MLP's units at initialisation, onnxruntime's parity
spread against torch's float32, and the runs' scores.

    PYTHONPATH=. python docs/results/2026-11-30-dynamic-units.py init                  # units at step 0, 5 seeds
    PYTHONPATH=. python docs/results/2026-11-30-dynamic-units.py parity RUN EXPORT     # 20 sets of 8192 points
    PYTHONPATH=. python docs/results/2026-11-30-dynamic-units.py parity-static RUN EXPORT   # a static field's
    PYTHONPATH=. python docs/results/2026-11-30-dynamic-units.py collect OUT.json RUN...   # scores, truth, traces

``collect`` reads each run's ``scores.json`` and ``config.json``, ``RUN.truth.txt`` (``python -m
tools.field_motion_truth RUN.export RIG/cam2 > RUN.truth.txt``) and ``RUN.trace.txt`` where present (lines ``step
dead_units active_fraction`` written by the page's patched training code).
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

SAMPLES = 65536


def _points(count: int = SAMPLES, seed: int = 1) -> tuple[torch.Tensor, torch.Tensor]:
    """Random contracted points over the cube and normalised times, as the page counts units."""
    g = torch.Generator().manual_seed(seed)
    return torch.rand(count, 3, generator=g) * 2 - 1, torch.rand(count, generator=g) * 2 - 1


def unit_counts(pre: torch.Tensor) -> dict:
    """First-layer pre-activations (N, H) -> units never active, always active, and the spreads."""
    on = pre > 0
    return {"dead": int((~on.any(0)).sum()), "always_on": int(on.all(0).sum()), "units": int(pre.shape[1]),
            "pre_std_over_points": float(pre.std(0).mean())}


def init_figures(seeds: int = 5, time_resolution: int = 12) -> list[dict]:
    """The default flow MLP's and canonical density MLP's first layers at step 0, for training seeds 0..seeds-1."""
    from models.fields.dynamic.model import CanonicalField, MotionConfig, MotionField
    from models.fields.static.field import FieldConfig

    coords, times = _points()
    rows = []
    for seed in range(seeds):
        torch.manual_seed(seed)
        motion = MotionField(MotionConfig(), time_resolution)
        torch.manual_seed(seed)
        canonical = CanonicalField(FieldConfig(), 2, time_resolution)
        with torch.no_grad():
            feats = motion.encoding(coords, times)
            flow = unit_counts(motion.flow_mlp.net[0](feats))
            canon = unit_counts(canonical.density_mlp.net[0](canonical.encoding(coords, times)))
        flow.update(features_min=float(feats.min()), features_mean=float(feats.mean()),
                    features_max=float(feats.max()), bias_std=float(motion.flow_mlp.net[0].bias.detach().std()))
        rows.append({"seed": seed, "flow_mlp": flow, "canonical_density_mlp": canon})
    return rows


def parity_spread(run: str, export: str, sets: int = 20) -> dict:
    """onnxruntime's and torch's float32 largest errors against float64 over ``sets`` sets of 8192 random queries
    (``export.dynamic.example_queries``, seeds 1..sets), and their ratio."""
    from export.dynamic import _model, check_parity, example_queries

    model = _model(run)
    rows = [check_parity(f"{export}/dynamic.onnx", model, *example_queries(model, 8192, seed=s))
            for s in range(1, sets + 1)]
    return _spread(rows)


def parity_spread_static(run: str, export: str, sets: int = 20) -> dict:
    """As :func:`parity_spread` for a static field (``export.field.example_points``)."""
    from export.field import _model, check_parity, example_points

    model = _model(run)
    rows = [check_parity(f"{export}/field.onnx", model, *example_points(model, 8192, seed=s))
            for s in range(1, sets + 1)]
    return _spread(rows)


def _spread(rows: list[dict]) -> dict:
    out = {}
    for q in ("density", "color"):
        ort = np.array([r[q] for r in rows])
        t32 = np.array([r[f"{q}_float32"] for r in rows])
        ratio = ort / np.maximum(t32, 1e-30)
        out[q] = {"onnxruntime_median": float(np.median(ort)), "onnxruntime_max": float(ort.max()),
                  "torch32_median": float(np.median(t32)), "torch32_max": float(t32.max()),
                  "ratio_median": float(np.median(ratio)), "ratio_min": float(ratio.min()),
                  "ratio_max": float(ratio.max())}
    return out


def _truth(path: Path) -> dict:
    out = {}
    for line in path.read_text().splitlines():
        value, _, key = line.strip().partition(" ")
        try:
            out[key.strip()] = float(value)
        except ValueError:
            continue
    return out


def collect(runs: list[str]) -> list[dict]:
    rows = []
    for run in runs:
        r = Path(run)
        scores = json.loads((r / "scores.json").read_text())
        row = {"run": r.name, "psnr": scores["psnr"], "ssim": scores["ssim"], "depth_mae": scores["depth_mae"],
               "flow_moving_fraction": scores.get("flow_moving_fraction"), "train_seconds": scores.get("train_seconds"),
               "config": json.loads((r / "config.json").read_text())}
        truth, trace = Path(f"{run}.truth.txt"), Path(f"{run}.trace.txt")
        if truth.is_file():
            row["motion_truth"] = _truth(truth)
        if trace.is_file():
            row["unit_trace"] = [[float(x) for x in line.split()] for line in trace.read_text().splitlines()]
        rows.append(row)
    return rows


def main(argv: list[str]) -> None:
    if argv[:1] == ["init"]:
        print(json.dumps(init_figures(), indent=1))
    elif argv[:1] == ["parity"] and len(argv) == 3:
        print(json.dumps(parity_spread(argv[1], argv[2]), indent=1))
    elif argv[:1] == ["parity-static"] and len(argv) == 3:
        print(json.dumps(parity_spread_static(argv[1], argv[2]), indent=1))
    elif argv[:1] == ["collect"] and len(argv) >= 3:
        Path(argv[1]).write_text(json.dumps(collect(argv[2:]), indent=1) + "\n")
    else:
        raise SystemExit(__doc__)


if __name__ == "__main__":
    main(sys.argv[1:])
