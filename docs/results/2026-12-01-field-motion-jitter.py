"""Probes of a trained dynamic field's motion in time (``2026-12-01-field-motion-jitter.md``), run from the checkout:

    PYTHONPATH=. python docs/results/2026-12-01-field-motion-jitter.py trajectory DEMO [--catmull-rom] [--train T]
    PYTHONPATH=. python docs/results/2026-12-01-field-motion-jitter.py demo ARGS...          # two-interval vectors
    TLR=F [TEPS=E] PYTHONPATH=. python docs/results/2026-12-01-field-motion-jitter.py cli train dynamic ARGS...

``trajectory`` follows the surface points of the middle frame of ``interleave demo --field`` output DEMO through the
demo's times (the motion field inverted, ``earlier_points``) and prints, per frame and on the mean, the speed, the
miss of constant velocity over the last k = 2 interval, the second difference of the path, the second difference
in time of the flow at a fixed point, and how much of the path's second difference lies along the ray of the
training camera nearest in time (``--train``: a D-NeRF ``transforms_train.json``; 1/3 for an isotropic jitter).
Units: contracted cube units x 1e3 per demo frame. ``--catmull-rom`` reads the motion's time planes with a
Catmull-Rom cubic in time (linear in space) instead of linearly, at render time only.
``demo`` runs ``interleave demo`` with the field's vectors of unsteady points (``coherent_motion``) set to the mean
motion of the last two intervals instead of the camera's alone. ``cli`` runs the CLI with the motion field's time
planes in their own Adam group at ``TLR`` times the learning rate (default 1) and, with ``TEPS``, Adam's eps at E
(the trainer's: 1e-15).
"""
from __future__ import annotations

import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

import engine.fields.dynamic as dyn
from engine.io.rgbd import read_sequence


def catmull_rom_time(plane: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(C, Rt, R) time plane at a (space, width) and b (time, height) in [-1, 1] -> (C, N): linear in space,
    Catmull-Rom through the rows in time (align_corners, border rows repeated)."""
    _, h, w = plane.shape
    x = np.clip((a + 1.0) * 0.5 * (w - 1), 0.0, w - 1)
    y = np.clip((b + 1.0) * 0.5 * (h - 1), 0.0, h - 1)
    x0 = np.minimum(np.floor(x).astype(np.int64), w - 2)
    fx = (x - x0).astype(np.float32)
    y1 = np.minimum(np.floor(y).astype(np.int64), h - 2)
    t = (y - y1).astype(np.float32)
    rows = [plane[:, np.clip(y1 + d, 0, h - 1), x0] * (1 - fx) + plane[:, np.clip(y1 + d, 0, h - 1), x0 + 1] * fx
            for d in (-1, 0, 1, 2)]
    t2, t3 = t * t, t * t * t
    weights = [(-t3 + 2 * t2 - t) / 2, (3 * t3 - 5 * t2 + 2) / 2, (-3 * t3 + 4 * t2 + t) / 2, (t3 - t2) / 2]
    return sum(wt * r for wt, r in zip(weights, rows))


def deform_catmull_rom(assets, coords: np.ndarray, taus: np.ndarray):
    """``deform_np`` with the motion's time planes read by :func:`catmull_rom_time` (no motion slots)."""
    feats = []
    for s_plane, t_plane in zip(assets.planes["motion_spatial"], assets.planes["motion_temporal"]):
        space = dyn.triplane_features_np([s_plane], coords)
        prod = np.prod([catmull_rom_time(t_plane[k], coords[:, k], taus) for k in range(3)], axis=0)
        feats.append(space * prod.T)
    motion = dyn.mlp_np(np.concatenate(feats, axis=1), assets.flow_layers)
    flow = (np.float32(assets.max_flow) * np.tanh(motion)).astype(np.float32)
    return coords + flow, flow


def trajectory(demo: Path, train: Path | None, every: int = 7) -> None:
    assets = dyn.load_dynamic_field(json.loads((demo / "results.json").read_text())["field"]["export"])
    seq = read_sequence(demo / "field")
    n = len(seq)
    t0, t1 = assets.time_range
    times = t0 + (t1 - t0) * np.arange(n) / (n - 1)  # the demo's times (run_field_demo)
    taus = np.array([dyn.normalize_time(t, assets.time_range) for t in times], np.float32)
    ref = seq[n // 2]
    h, w = ref.depth.shape
    origin, dirs = dyn.camera_rays_np(ref.camera.intrinsics, ref.camera.world_to_camera, h, w)
    depth = ref.depth.reshape(-1)
    finite = np.isfinite(depth)
    margin = assets.manifest["render"]["ndc_margin"]
    coords = dyn.contract_np(assets.scene, (origin + np.where(finite, depth, 0)[:, None] * dirs)[finite]
                             .astype(np.float32), margin)
    coords = coords[(np.abs(coords) <= 1).all(axis=1)][::every]
    paths, found = [], np.ones(len(coords), bool)
    for tau in taus:
        moved, ok = dyn.earlier_points(assets, coords, taus[n // 2], tau)
        paths.append(moved)
        found &= ok
    path = np.array(paths)[:, found]
    path = path[:, (np.linalg.norm(path[2:] - path[:-2], axis=2) / 2).max(axis=0) > 1e-3]  # points that move
    print(f"{demo}: {path.shape[1]} moving points, {assets.manifest['time']['time_resolution']} time rows")
    rows = []
    for i in range(2, n - 1):
        step = path[i + 1] - path[i]
        miss = np.linalg.norm(step - (path[i] - path[i - 2]) / 2, axis=1).mean()
        second = np.linalg.norm(path[i + 1] - 2 * path[i] + path[i - 1], axis=1).mean()
        flows = [dyn.deform_np(assets, path[i], np.full(path.shape[1], taus[j], np.float32))[1]
                 for j in (i - 1, i, i + 1)]
        fixed = np.linalg.norm(flows[2] - 2 * flows[1] + flows[0], axis=1).mean()
        rows.append((np.linalg.norm(step, axis=1).mean(), miss, second, fixed))
        print(f"frame {i:2d} tau {taus[i]:+.3f}: speed {rows[-1][0] * 1e3:5.2f}  constant-velocity miss "
              f"{miss * 1e3:5.2f}  second difference {second * 1e3:5.2f}  flow at a fixed point {fixed * 1e3:5.2f}")
    m = np.mean(rows, axis=0) * 1e3
    print(f"mean: speed {m[0]:.3f} miss {m[1]:.3f} (ratio {m[1] / m[0]:.2f}) second difference {m[2]:.3f} "
          f"flow at a fixed point {m[3]:.3f}")
    if train is not None:
        frames = json.loads(train.read_text())["frames"]
        frames = [f for f in frames if (train.parent / "train" / (Path(f["file_path"]).name + ".png")).exists()]
        ttimes = np.array([f["time"] for f in frames])
        centres = np.array([np.asarray(f["transform_matrix"])[:3, 3] for f in frames])
        world = np.array([dyn.uncontract_np(assets.scene, p, margin) for p in path]).astype(np.float64)
        num = den = 0.0
        for i in range(1, n - 1):
            acc = world[i + 1] - 2 * world[i] + world[i - 1]
            ray = world[i] - centres[np.argmin(np.abs(ttimes - times[i]))]
            ray /= np.linalg.norm(ray, axis=1, keepdims=True)
            num += ((acc * ray).sum(axis=1) ** 2).sum()
            den += (acc ** 2).sum()
        print(f"share of the squared second difference along the nearest training camera's ray: {num / den:.2f} "
              f"({len(frames)} training frames)")


def points_two_interval(assets, k, pose, depth, time, other_time, iterations, coherence=None):
    """``_points_at`` where an unsteady point (``coherent_motion``'s test) that has a point two intervals back
    gets the mean of the two intervals' motion, ``(p + b) / 2``, instead of staying where it is."""
    if coherence is None:
        return ORIGINAL_POINTS_AT(assets, k, pose, depth, time, other_time, iterations)
    tau, tau_other = dyn.normalize_time(time, assets.time_range), dyn.normalize_time(other_time, assets.time_range)
    origin, dirs = (a.astype(np.float32) for a in dyn.camera_rays_np(k, pose, *depth.shape))
    d = depth.reshape(-1).astype(np.float32)
    finite = np.isfinite(d)
    points = np.where(finite[:, None], origin + np.where(finite, d, 0)[:, None] * dirs, dirs)
    margin = assets.manifest["render"]["ndc_margin"]
    coords = dyn.contract_np(assets.scene, points, margin)
    inside = finite & (np.abs(coords) <= 1.0).all(axis=-1)
    moved, found = dyn.earlier_points(assets, coords[inside], tau, tau_other, iterations=iterations)
    moved = np.where(found[:, None], dyn.uncontract_np(assets.scene, moved, margin), np.nan)
    p = points[inside].astype(np.float64)
    tau_before = dyn.time_before(tau, tau_other)
    if tau_before is not None and assets.has_motion:
        before, bfound = dyn.earlier_points(assets, coords[inside], tau, tau_before, iterations=iterations)
        outside = (np.abs(before) > 1.0).any(axis=1)
        b = dyn.uncontract_np(assets.scene, before, margin).astype(np.float64)
        last = p - moved
        with np.errstate(invalid="ignore"):
            turned = np.linalg.norm(last - (moved - b), axis=1) > float(coherence) * np.linalg.norm(last, axis=1)
        unsteady = found & ~(outside | (bfound & ~turned))
        usable = bfound & ~outside
        moved[unsteady & usable] = ((p + b) / 2)[unsteady & usable]
        moved[unsteady & ~usable] = p[unsteady & ~usable]
    points[inside] = moved
    return points, finite


ORIGINAL_POINTS_AT = dyn._points_at
ORIGINAL_ADAM = torch.optim.Adam


def scaled_adam(params, lr: float, **options):
    """``torch.optim.Adam`` with the "motion_time" group's rate at TLR x ``lr`` (the run's ``--lr``), set before
    the trainer's schedule reads the groups' rates."""
    optimizer = ORIGINAL_ADAM(params, lr=lr, **options)
    for group in optimizer.param_groups:
        if group.get("name") == "motion_time":
            group["lr"] = lr * float(os.environ.get("TLR", "1"))
    return optimizer


def motion_time_groups(self, model) -> list[dict]:
    """``DynamicKind.param_groups`` with the motion field's time planes in a third group, "motion_time" (with
    Adam's eps at TEPS; :func:`scaled_adam` sets its rate)."""
    chosen, planes, mlps = [], [], []
    for name, p in model.field.named_parameters():
        if "motion_field.encoding.temporal" in name:
            chosen.append(p)
        elif name.startswith("encoding.") or ".encoding." in name:
            planes.append(p)
        else:
            mlps.append(p)
    group = {"params": chosen, "name": "motion_time"}
    if "TEPS" in os.environ:
        group["eps"] = float(os.environ["TEPS"])
    return [{"params": planes, "name": "planes"}, {"params": mlps, "name": "mlps"}, group]


def main(argv: list[str]) -> int:
    from engine.cli import main as cli
    if argv[0] == "trajectory":
        if "--catmull-rom" in argv:
            dyn.deform_np = deform_catmull_rom
        train = Path(argv[argv.index("--train") + 1]) if "--train" in argv else None
        trajectory(Path(argv[1]), train)
        return 0
    if argv[0] == "demo":
        dyn._points_at = points_two_interval
        return cli(argv)
    if argv[0] == "cli":
        import models.fields.train_dynamic as train_dynamic
        train_dynamic.DynamicKind.param_groups = motion_time_groups
        torch.optim.Adam = scaled_adam
        return cli(argv[1:])
    raise SystemExit(__doc__)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
