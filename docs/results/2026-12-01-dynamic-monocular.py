"""A monocular capture cut from an rgbd-rig: each frame seen by one train camera, the cameras taken in turn (D-NeRF's
"teleporting" camera), the rig's test cameras held out at every frame. Trains one variant of the dynamic field on it
and scores it, as ``interleave train dynamic`` would (its priors choice included).

    PYTHONPATH=. python docs/results/2026-12-01-dynamic-monocular.py train RIG RUN STEPS SEED [KEY=VALUE,...]
    PYTHONPATH=. python docs/results/2026-12-01-dynamic-monocular.py collect OUT.json RUN...

``KEY=VALUE`` are DynamicTrainConfig options (``field.kind=kplanes``, ``field.canonical_time=false``); ``train``
writes ``RUN/scores.json``, ``collect`` gathers the runs' scores and configs into one JSON.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path

import numpy as np
import torch

from engine.core.config import config_from_text
from models.fields.data.select import select_dynamic_views
from models.fields.train_dynamic import (DynamicTrainConfig, choose_canonical_time, choose_dynamic_priors,
                                         evaluate_dynamic, train_dynamic, views_per_time)


def monocular(views):
    """One view a frame: frame position i of the sorted times is taken from train camera i mod (cameras)."""
    times = np.unique(views.times)
    cams = np.unique(views.camera_ids)
    keep = []
    for i, t in enumerate(times):
        cam = cams[i % len(cams)]
        keep += np.flatnonzero((views.times == t) & (views.camera_ids == cam)).tolist()
    return views.subset(keep)


def train(rig: str, run: str, steps: str, seed: str, options: str = "") -> None:
    torch.set_num_threads(1)
    full, test, record = select_dynamic_views("rig", rig, 1, test_every=2)
    views = monocular(full)
    config = config_from_text(DynamicTrainConfig, f"steps={int(steps)},seed={int(seed)}" +
                              (f",{options}" if options else ""))
    explicit = "field.canonical_time" in options
    config = choose_dynamic_priors(config)
    config = choose_canonical_time(config, views, explicit=explicit)
    out = Path(run)
    train_dynamic(views, config, out, device="cpu")
    scores = evaluate_dynamic(out, test, with_flip=False, context_views=views, renderer="torch")
    keep = ("psnr", "ssim", "depth_mae", "train_seconds", "flow_moving_fraction", "kind", "num_views")
    result = {"rig": rig, "options": options, "steps": int(steps), "seed": int(seed), "train_views": len(views),
              "train_cameras": sorted({views.camera_names[c] for c in views.camera_ids}),
              "views_per_time": views_per_time(views),
              "canonical_time": config.field.canonical_time, "canonical_time_choice": config.canonical_time_choice,
              "priors_choice": config.priors_choice, "test": record.get("test_cameras"),
              **{k: scores.get(k) for k in keep},
              "psnr_objects": scores.get("psnr_objects"), "psnr_background": scores.get("psnr_background")}
    (out / "scores.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    print(json.dumps(result, default=float))


def collect(out: str, *runs: str) -> None:
    rows = [json.loads((Path(r) / "scores.json").read_text()) | {"run": Path(r).name} for r in runs]
    Path(out).write_text(json.dumps({"runs": rows}, indent=2) + "\n")


if __name__ == "__main__":
    {"train": train, "collect": collect}[sys.argv[1]](*sys.argv[2:])
