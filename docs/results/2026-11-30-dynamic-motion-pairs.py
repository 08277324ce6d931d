"""The flow prior's pairs and the motion field's hidden units, per trained dynamic run (2026-11-30 page).

``PYTHONPATH=. python docs/results/2026-11-30-dynamic-motion-pairs.py timing RIG`` times the prior's matching on
RIG's training views (cam0, cam1, cam3) for SIFT and DIS at time offsets 10 and 1 (SIFT features cached first).

``PYTHONPATH=. python docs/results/2026-11-30-dynamic-motion-pairs.py OUT.json RUN:RIG[:nomodel] ...`` (each RUN
trained on RIG with cam0, cam1, cam3 and exported to ``RUN.export`` or ``RUN/export``; RIG ``-``: scores and units
only; ``nomodel``: skip the figures that load the
run's model in torch, for a run trained by patched code that this checkout's model does not rebuild). Per run:

- its scores (held-out PSNR on cam2, objects / background, moving mass, depth MAE);
- ``tools.field_motion_truth.flow_units`` on its export: the flow MLP's hidden units and those never active;
- its verified matches (``RUN/priors/sparse_flow.npz``) by group: same time / across time, still / on an object
  (``object_id`` at pixel a), and how many have a truth error of 2 px or more (the ``...-prior-residuals`` script's
  truth error: pixel a at the rig's true depth projected into view b, a still point assumed; across time on an
  object it is the object's motion);
- on the across-time object matches with a truth error of 2 px or more, rendered by the trained model without
  jitter: the distance between the two rays' expected (contracted) points before the flow (the motion the model's
  geometry shows), the distance of their expected flows, and the median share of the first that the flow difference
  carries (1: the flow maps both rays to one canonical point, 0: no motion).
"""
from __future__ import annotations

import dataclasses
import importlib.util
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch

from engine.fields.dynamic import load_dynamic_field
from models.fields.data.timed import load_rig_video, split_by_camera
from models.fields.priors.flow import SparseFlowPrior, sparse_flow_matches
from tools.field_motion_truth import flow_units

_spec = importlib.util.spec_from_file_location(
    "residuals", Path(__file__).with_name("2026-11-30-dynamic-prior-residuals.py"))
residuals = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(residuals)
expected_ends = residuals.expected_ends


def flow_share(run: str, rig: str, matches: dict) -> dict:
    """The shown motion, the flow difference and the flow's share of the shown motion over ``matches`` (dict of
    arrays), from the expected points and flows of their two ends (``residuals.expected_ends``)."""
    ends = expected_ends(run, rig, matches)
    point = {end: canonical - flow for end, (canonical, flow) in ends.items()}
    motion, carried = point["b"] - point["a"], ends["a"][1] - ends["b"][1]
    share = (carried * motion).sum(1) / np.maximum((motion * motion).sum(1), 1e-12)
    return {"model_motion_median": float(np.median(np.linalg.norm(motion, axis=1))),
            "flow_difference_median": float(np.median(np.linalg.norm(carried, axis=1))),
            "flow_share_median": float(np.median(share))}


def one_run(run: str, rig: str, use_model: bool) -> dict:
    torch.set_num_threads(1)
    scores = json.loads(Path(run, "scores.json").read_text())
    out = {"run": run, "rig": rig, **{k: scores.get(k) for k in (
        "steps", "psnr", "psnr_objects", "psnr_background", "flow_moving_fraction", "depth_mae", "train_seconds")}}
    export = f"{run}.export" if Path(f"{run}.export").is_dir() else f"{run}/export"
    out["flow_units"], out["flow_units_never_active"] = flow_units(load_dynamic_field(export))
    if rig == "-":  # not a rig (lego): scores and units only
        print(json.dumps(out), flush=True)
        return out
    matches = dict(np.load(f"{run}/priors/sparse_flow.npz"))
    names = json.loads(Path(run, "priors", "sparse_flow.json").read_text())["key"]["views"]
    error, on_object = residuals.truth_errors(matches, names, rig)
    across = matches["across_time"].astype(bool)
    out["matches"] = int(len(error))
    for name, group in (("same_still", ~across & ~on_object), ("same_object", ~across & on_object),
                        ("across_still", across & ~on_object), ("across_object", across & on_object)):
        out[name] = {"n": int(group.sum()), "truth_error_ge_2px": int((group & (error >= 2)).sum())}
    moving = across & on_object & (error >= 2) & np.isfinite(error)
    if use_model and moving.any():
        out["across_object_ge_2px"] = flow_share(run, rig, {k: v[moving] for k, v in matches.items()})
    print(json.dumps(out), flush=True)
    return out


def timing(rig: str) -> None:
    views, _ = split_by_camera(load_rig_video(rig), ["cam0", "cam1", "cam3"], ["cam2"])
    for name, options in (("sift, offset 10", {}), ("sift, offset 1", {"time_offset": 1}),
                          ("dis, offset 10", {"source": "dis"}),
                          ("dis, offset 1", {"source": "dis", "time_offset": 1})):
        prior = dataclasses.replace(SparseFlowPrior(enabled=True), **options)
        sparse_flow_matches(views, prior)  # SIFT features cached
        start = time.perf_counter()
        matches = sparse_flow_matches(views, prior)
        print(json.dumps({"prior": name, "seconds": round(time.perf_counter() - start, 2), "matches": len(matches),
                          "pairs": len(matches.pairs)}), flush=True)


def main(out_json: str, *specs: str) -> None:
    if out_json == "timing":
        return timing(*specs)
    rows = []
    for spec in specs:
        run, rig, *flags = spec.split(":")
        rows.append(one_run(run, rig, "nomodel" not in flags))
    Path(out_json).write_text(json.dumps(rows, indent=1) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:])
