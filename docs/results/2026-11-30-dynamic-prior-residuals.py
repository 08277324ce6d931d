"""The sparse flow prior's residuals in a trained dynamic run, split by how wrong each match is (2026-11-30 page).

``PYTHONPATH=. python docs/results/2026-11-30-dynamic-prior-residuals.py RUN RIG OUT.json`` (RUN trained on RIG with
cam0, cam1, cam3; its verified matches in ``RUN/priors/sparse_flow.npz``):

- truth error of a match: pixel a unprojected with the rig's true planar depth (the best of its 3x3
  neighbourhood, so that an edge's depth does not count as a wrong match) and projected into view b, against the
  match's pixel b, assuming a still point. Across time on a moving object it is the object's motion, not an error.
- residual: ``|sum_i w_i c'_i(a) - sum_i w_i c'_i(b)|`` (Eq. 5.7's distance, contracted units) of the two rays
  rendered without jitter by the trained model.
- groups: same time / across time, still (``object_id`` 0 at pixel a) / object, truth error in [0, 1), [1, 2),
  [2, 5), >= 5 px; per group the residual's median and mean and its share of the summed squared residuals (the loss).
"""
from __future__ import annotations

import json
import sys

import numpy as np
import torch

from engine.io.rgbd import read_sequence
from models.fields.data.timed import load_rig_video, split_by_camera
from models.fields.priors.depth import keypoint_rays
from models.fields.train_dynamic import load_dynamic_model

BINS = ((0.0, 1.0), (1.0, 2.0), (2.0, 5.0), (5.0, np.inf))


def truth_errors(matches, names: list[str], rig: str) -> tuple[np.ndarray, np.ndarray]:
    """(M,) truth error in px (inf where pixel a has no finite depth) and (M,) bool: pixel a is on an object."""
    sequences, frames = {}, {}

    def frame(view: int):
        if view not in frames:
            camera, index = names[view].split("@")
            sequences.setdefault(camera, read_sequence(f"{rig}/{camera}"))
            frames[view] = sequences[camera][int(index)]
        return frames[view]

    errors, on_object = [], []
    for va, xa, vb, xb in zip(matches["view_a"], matches["xy_a"], matches["view_b"], matches["xy_b"]):
        fa, fb = frame(int(va)), frame(int(vb))
        h, w = fa.depth.shape
        x, y = min(int(xa[0]), w - 1), min(int(xa[1]), h - 1)
        on_object.append(fa.object_id[y, x] > 0)
        best = np.inf
        for yy in range(max(y - 1, 0), min(y + 2, h)):
            for xx in range(max(x - 1, 0), min(x + 2, w)):
                z = float(fa.depth[yy, xx])
                if not np.isfinite(z):
                    continue
                point = np.linalg.solve(fa.camera.intrinsics, [xa[0], xa[1], 1.0]) * z
                world = fa.camera.camera_to_world @ np.r_[point, 1.0]
                q = fb.camera.intrinsics @ (fb.camera.world_to_camera @ world)[:3]
                best = min(best, float(np.linalg.norm(q[:2] / q[2] - xb)))
        errors.append(best)
    return np.array(errors), np.array(on_object)


def expected_ends(run: str, rig: str, matches) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Per end ``a``, ``b`` of every match, rendered by the trained model (no jitter, 2048 rays a call): the
    expected canonical point ``sum_i w_i c'_i`` (M, 3) and the expected flow ``sum_i w_i flow_i`` (M, 3)."""
    views, _ = split_by_camera(load_rig_video(rig), ["cam0", "cam1", "cam3"], ["cam2"])
    model = load_dynamic_model(run)
    near, far = float(model.scene.near), float(model.scene.far)
    ends = {}
    for end in ("a", "b"):
        origins, directions = keypoint_rays(views.cameras, matches[f"view_{end}"], matches[f"xy_{end}"])
        times = torch.as_tensor(np.asarray(views.times)[matches[f"view_{end}"]], dtype=torch.float32)
        canonical, flow = [], []
        with torch.no_grad():
            for s in range(0, len(times), 2048):
                n = len(times[s:s + 2048])
                r = model.render_rays(origins[s:s + 2048], directions[s:s + 2048], torch.full((n,), near),
                                      torch.full((n,), far), times[s:s + 2048], color=False)
                canonical.append((r.weights[..., None] * r.canonical).sum(dim=-2))
                flow.append((r.weights[..., None] * r.flow).sum(dim=-2))
        ends[end] = (torch.cat(canonical).numpy(), torch.cat(flow).numpy())
    return ends


def residuals(run: str, rig: str, matches) -> np.ndarray:
    """(M,) Eq. 5.7 distance of every match, rendered by the trained model (no jitter)."""
    ends = expected_ends(run, rig, matches)
    return np.linalg.norm(ends["a"][0] - ends["b"][0], axis=1)


def main(run: str, rig: str, out_json: str) -> None:
    torch.set_num_threads(1)
    matches = dict(np.load(f"{run}/priors/sparse_flow.npz"))
    names = json.load(open(f"{run}/priors/sparse_flow.json"))["key"]["views"]
    error, on_object = truth_errors(matches, names, rig)
    distance = residuals(run, rig, matches)
    across = matches["across_time"].astype(bool)
    total = float(np.sum(distance ** 2))
    result = {"run": run, "rig": rig, "matches": int(len(distance)),
              "distance_quantiles_50_90_99": np.quantile(distance, [0.5, 0.9, 0.99]).tolist(), "groups": []}
    for name, group in (("same-time static", ~across & ~on_object), ("across-time static", across & ~on_object),
                        ("same-time objects", ~across & on_object), ("across-time objects", across & on_object)):
        for lo, hi in BINS:
            k = group & (error >= lo) & (error < hi)
            if k.any():
                result["groups"].append({
                    "group": name, "truth_error_px": [lo, None if np.isinf(hi) else hi], "n": int(k.sum()),
                    "distance_median": float(np.median(distance[k])), "distance_mean": float(distance[k].mean()),
                    "share_of_squared_loss": float(np.sum(distance[k] ** 2) / total)})
                print(result["groups"][-1], flush=True)
    open(out_json, "w").write(json.dumps(result, indent=1) + "\n")


if __name__ == "__main__":
    main(*sys.argv[1:])
