"""Where constant velocity breaks, and whether a second frame of vectors would help: an experiment.

``python -m tools.mvec_extrapolation SEQ_DIR... [--k 2,4] [--json FILE]``

``mvec`` extrapolates each surface point with constant 3D velocity from frames n-k and n (the vectors of
frame n). A renderer could also hand over frame n-k's vectors (to n-2k), giving each point a third
position and so an acceleration. This measures both models on the exact trajectories of the sequences'
rigid objects (``objects`` + ``object_id``: no vector, depth or splat error involved), per future step
j = 1 .. k-1 (frame n + j): the end-point error in pixels over the moving pixels of frame n of

- ``velocity``: ``P(n + j) = P(n) + (j / k) (P(n) - P(n - k))``;
- ``acceleration``: the parabola through P(n - 2k), P(n - k), P(n), evaluated at n + j;
- ``guarded``: acceleration where the change of velocity is at most half the velocity, else velocity
  (what ``mvec`` does);
- ``damped``: guarded, and where the motion is not smooth the velocity shrunk by 0.5 |V| / |change|;
- ``rigid``: each object's points (exact masks) turning about their centroid at the rate of the last
  interval while the centroid moves linearly (a spin-aware model a renderer's object ids would allow);
- ``still``: no object motion (what camera-only reprojection assumes).

Printed per (sequence, k, j): mean end-point errors, and the share of moving pixels for which acceleration
beats velocity.
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


MODELS = ("still", "velocity", "acceleration", "guarded", "damped", "rigid")


def rotation_power(rotation: np.ndarray, s: float) -> np.ndarray:
    """``rotation`` (3, 3) raised to the real power ``s`` (the same axis, ``s`` times the angle)."""
    angle = float(np.arccos(np.clip((np.trace(rotation) - 1.0) / 2.0, -1.0, 1.0)))
    if angle < 1e-9:
        return np.eye(3)
    axis = np.array([rotation[2, 1] - rotation[1, 2], rotation[0, 2] - rotation[2, 0],
                     rotation[1, 0] - rotation[0, 1]]) / (2.0 * np.sin(angle))
    cross = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    return np.eye(3) + np.sin(s * angle) * cross + (1.0 - np.cos(s * angle)) * cross @ cross


def rigid_fit(before: np.ndarray, now: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Least-squares rotation R and centroids (c_before, c_now) with now ~ R (before - c_before) + c_now."""
    cb, cn = before.mean(axis=0), now.mean(axis=0)
    u, _, vt = np.linalg.svd((before - cb).T @ (now - cn))
    d = np.sign(np.linalg.det(vt.T @ u.T))
    return vt.T @ np.diag([1.0, 1.0, d]) @ u.T, cb, cn


def predictions(a, b, c, ids, s: float) -> dict[str, np.ndarray]:
    """Each model's position at s (frame intervals after n) of points at a (n-2k), b (n-k), c (n), (N, 3)."""
    velocity = c + s * (c - b)
    change = (c - b) - (b - a)
    acceleration = velocity + 0.5 * s * (s + 1) * change  # the parabola through s = -2, -1, 0
    ratio = np.linalg.norm(change, axis=-1) / np.maximum(np.linalg.norm(c - b, axis=-1), 1e-12)
    smooth = ratio <= 0.5
    guarded = np.where(smooth[:, None], acceleration, velocity)
    # damped: where the motion is not smooth, the velocity shrunk by 0.5 |V| / |change| (tried, dropped)
    damped = np.where(smooth[:, None], acceleration, c + s * (c - b) * np.minimum(1.0, 0.5 / ratio)[:, None])
    # rigid: each object's points turn about their centroid at a constant rate while it moves linearly
    rigid = velocity.copy()
    for oid in np.unique(ids):
        m = ids == oid
        if m.sum() >= 10:
            rotation, cb, cn = rigid_fit(b[m], c[m])
            rigid[m] = cn + s * (cn - cb) + (c[m] - cn) @ rotation_power(rotation, s).T
    return {"still": c, "velocity": velocity, "acceleration": acceleration, "guarded": guarded,
            "damped": damped, "rigid": rigid}


def measure(seq, k: int) -> list[dict]:
    rows: dict[int, dict[str, list]] = {j: {m: [] for m in MODELS + ("wins",)} for j in range(1, k)}
    for n in range(2 * k, len(seq) - k + 1, k):
        idx, pts = trajectories(seq, n, [n - 2 * k, n - k, n] + list(range(n + 1, n + k)))
        if idx.size == 0:
            continue
        frame = seq[n]
        kk, ids = frame.camera.intrinsics, frame.object_id.reshape(-1)[idx]
        for j in range(1, k):
            truth = project(pts[n + j], kk)
            guesses = predictions(pts[n - 2 * k], pts[n - k], pts[n], ids, j / k)
            errors = {name: np.linalg.norm(project(p, kk) - truth, axis=-1) for name, p in guesses.items()}
            for name, e in errors.items():
                rows[j][name].append(e)
            rows[j]["wins"].append(errors["acceleration"] < errors["velocity"])
    out = []
    for j, r in rows.items():
        if not r["velocity"]:
            continue
        cat = {name: np.concatenate(v) for name, v in r.items()}
        out.append({"sequence": Path(str(seq.path)).name, "k": k, "step": j, "pixels": int(cat["velocity"].size),
                    **{f"epe_{name}": float(cat[name].mean()) for name in MODELS},
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
    print("| sequence | k | j | pixels | " + " | ".join(f"EPE {m}" for m in MODELS) + " | acceleration better |\n"
          + "|---" * (5 + len(MODELS)) + "|")
    for r in rows:
        print(f"| {r['sequence']} | {r['k']} | {r['step']} | {r['pixels']} | "
              + " | ".join(f"{r['epe_' + m]:.2f}" for m in MODELS) + f" | {100 * r['acceleration_wins']:.0f}% |")
    if args.json:
        args.json.write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    main()
