"""Where constant velocity breaks, and whether a second frame of vectors would help: an experiment.

``python -m tools.mvec_extrapolation SEQ_DIR... [--k 2,4] [--json FILE]``

``mvec`` extrapolates each surface point with constant 3D velocity from frames n-k and n (the vectors of
frame n). A renderer could also hand over frame n-k's vectors (to n-2k), giving each point a third
position and so an acceleration. This measures both models on the exact trajectories of the sequences'
rigid objects (``objects`` + ``object_id``: no vector, depth or splat error involved), per future step
j = 1 .. k-1 (frame n + j): the end-point error in pixels over the moving pixels of frame n of

- ``velocity``: ``P(n + j) = P(n) + (j / k) (P(n) - P(n - k))``;
- ``acceleration``: the parabola through P(n - 2k), P(n - k), P(n), evaluated at n + j;
- ``guarded``: acceleration where the change of velocity is at most half the velocity, else velocity;
- ``still``: no object motion (what camera-only reprojection assumes).

Printed per (sequence, k, j), with the share of moving pixels for which acceleration beats velocity.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from engine import geometry
from engine.core.frames import rigid_inverse
from engine.io.rgbd import read_sequence


def trajectories(seq, n: int, positions: list[int]) -> tuple[np.ndarray, dict[int, np.ndarray]]:
    """Frame n's moving pixels (flat indices) and their points at each frame of ``positions``, in frame n's
    camera axes (N, 3)."""
    frame = seq[n]
    objects = {o.id: o for o in seq.objects if o.moving}
    mask = frame.moving & np.isfinite(frame.depth) & np.isin(frame.object_id, list(objects))
    idx = np.flatnonzero(mask)
    points = geometry.unproject(frame.depth, frame.camera.intrinsics).reshape(-1, 4)[idx]
    ids = frame.object_id.reshape(-1)[idx]
    view = frame.camera.world_to_camera
    out = {}
    for p in positions:
        moved = np.empty((idx.size, 3))
        for oid, obj in objects.items():
            sel = ids == oid
            motion = view @ obj.world_from_object[p] @ rigid_inverse(obj.world_from_object[n]) @ rigid_inverse(view)
            moved[sel] = (points[sel] @ motion.T)[:, :3]
        out[p] = moved
    return idx, out


def project(points: np.ndarray, k: np.ndarray) -> np.ndarray:
    z = np.maximum(points[:, 2], 1e-6)
    return np.stack([k[0, 0] * points[:, 0] / z + k[0, 2], k[1, 1] * points[:, 1] / z + k[1, 2]], axis=-1)


def measure(seq, k: int) -> list[dict]:
    rows: dict[int, dict[str, list]] = {j: {"velocity": [], "acceleration": [], "guarded": [], "still": [],
                                            "wins": []}
                                        for j in range(1, k)}
    for n in range(2 * k, len(seq) - k + 1, k):
        idx, pts = trajectories(seq, n, [n - 2 * k, n - k, n] + list(range(n + 1, n + k)))
        if idx.size == 0:
            continue
        kk = seq[n].camera.intrinsics
        a, b, c = pts[n - 2 * k], pts[n - k], pts[n]
        for j in range(1, k):
            s = j / k
            velocity = c + s * (c - b)
            # parabola through s = -2, -1, 0 evaluated at s
            accel = (c - b) - (b - a)
            acceleration = c + s * (c - b) + 0.5 * s * (s + 1) * accel
            # trusted only while the change of velocity is small against the velocity (smooth motion)
            smooth = np.linalg.norm(accel, axis=-1) <= 0.5 * np.linalg.norm(c - b, axis=-1)
            guarded = np.where(smooth[:, None], acceleration, velocity)
            truth = project(pts[n + j], kk)
            errors = {name: np.linalg.norm(project(p, kk) - truth, axis=-1)
                      for name, p in (("velocity", velocity), ("acceleration", acceleration), ("guarded", guarded),
                                      ("still", c))}
            for name, e in errors.items():
                rows[j][name].append(e)
            rows[j]["wins"].append(errors["acceleration"] < errors["velocity"])
    out = []
    for j, r in rows.items():
        if not r["velocity"]:
            continue
        cat = {name: np.concatenate(v) for name, v in r.items()}
        out.append({"sequence": Path(str(seq.path)).name, "k": k, "step": j, "pixels": int(cat["velocity"].size),
                    **{f"epe_{name}": float(cat[name].mean()) for name in ("still", "velocity", "acceleration", "guarded")},
                    **{f"median_{name}": float(np.median(cat[name])) for name in ("still", "velocity", "acceleration",
                                                                                    "guarded")},
                    "acceleration_wins": float(cat["wins"].mean())})
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    rows = []
    for path in args.sequences:
        seq = read_sequence(path)
        for k in (int(v) for v in args.k.split(",")):
            rows += measure(seq, k)
    print("| sequence | k | j | pixels | EPE still | EPE velocity | EPE acceleration | EPE guarded | median velocity | "
          "median acceleration | acceleration better |\n|---|---|---|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['sequence']} | {r['k']} | {r['step']} | {r['pixels']} | {r['epe_still']:.2f} | "
              f"{r['epe_velocity']:.2f} | {r['epe_acceleration']:.2f} | {r['epe_guarded']:.2f} | "
              f"{r['median_velocity']:.2f} | {r['median_acceleration']:.2f} | {100 * r['acceleration_wins']:.0f}% |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
