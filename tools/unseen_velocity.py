"""How far ``mvec``'s motion misses on points frame n-k did not see, against the true motion and holding. A diagnostic.

``python -m tools.unseen_velocity SEQ_DIR... [--k 2,4] [--json FILE]``
``python -m tools.unseen_velocity --score [--sets gentle,fast,spin,fast2] [--rules static,hold,...] [--k 2,3,4]``

``mvec`` turns each moving pixel's vector (frame n -> n-k, exact here: ``interleave eval``'s derivation) into a 3D
velocity with the point's depth in frame n-k, read at the vector's end (``engine.geometry.motion.scene_velocity``:
the 2x2 neighbour within ``DEFAULT_DEPTH_BAND`` of the depth a static point would have there). Where none is
(the end lies outside frame n-k's image, or frame n-k shows another surface there), the point was not seen in
frame n-k and its previous depth is that static guess. Per sequence and k, over the moving pixels of ``mvec``
(linear, two frames) and the evaluation's targets, the table gives:

- the share of the moving pixels not seen in frame n-k, and of those whose vector ends outside its image;
- the mean end-point error (px) at the target of the object flow of: ``mvec`` (its velocity extrapolated), the
  TRUE velocity of the last interval extrapolated the same way (what exact depths would give), and holding
  (no object motion: what ``reproject`` does), over all moving pixels and over the unseen ones;
- the median ratio of the true previous depth to the static guess on the unseen pixels.

With ``--score``, ``mvec`` (linear, and rigid + fall-back) runs on ``tools.bench_mvec``'s sets (its cached
sequences under ``--out``) with each of ``RULES`` for the unseen pixels' motion (``UnseenRule``) and prints the
PSNR over the whole frame / moving pixels, means over each set's sequences, beside ``reproject``.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from engine.core.frames import rigid_inverse
from engine.eval.protocol import evaluate_sequence, evaluation_pairs, rendered_history
from engine.geometry.motion import DEFAULT_DEPTH_BAND, extrapolated_flow
from engine.io.rgbd import read_sequence
from engine.predict import Mvec, MvecConfig
from engine.predict.base import true_object_flow
from tools.heldout import write_json

MOTIONS = ("mvec", "true velocity", "hold")
#: ``UnseenRule``'s rules for the moving pixels frame n-k did not see: ``static`` (as shipped: the static depth
#: guess), ``hold`` (no object motion), ``hold-outside`` (no object motion where the vector ends outside frame
#: n-k), ``unseen-regions`` (no object motion in connected moving regions with fewer than ``MIN_SEEN`` seen
#: pixels; the static guess elsewhere), ``region-median`` (the median velocity of the seen pixels of their
#: connected moving region, no object motion where it has fewer than ``MIN_SEEN``)
RULES = ("static", "hold", "hold-outside", "unseen-regions", "region-median")
MIN_SEEN = 16


def previous_depths(newest, older, moving: np.ndarray, band: float = DEFAULT_DEPTH_BAND,
                    vectors: Optional[np.ndarray] = None):
    """For the flat pixel indices ``moving`` of frame ``newest`` (its vectors, or ``vectors``, point to ``older``):
    the static guess of each point's depth in frame ``older`` (M,), whether that frame saw it (a 2x2 neighbour of
    the vector's end within ``band`` of the guess; ``scene_velocity``'s rule) and whether the end lies inside
    its image."""
    vectors = newest.motion_vectors if vectors is None else vectors
    h, w = newest.depth.shape
    y, x = np.divmod(moving, w)
    z = newest.depth[y, x].astype(np.float64)
    points = z[:, None] * (np.stack([x + 0.5, y + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(newest.camera.intrinsics).T)
    relative = older.camera.world_to_camera @ newest.camera.camera_to_world
    guess = points @ relative[2, :3] + relative[2, 3]
    end = np.stack([x + 0.5, y + 0.5], 1) + vectors[y, x].astype(np.float64)
    hp, wp = older.depth.shape
    inside = (end[:, 0] >= 0) & (end[:, 0] < wp) & (end[:, 1] >= 0) & (end[:, 1] < hp)
    seen = np.zeros(len(moving), bool)
    x0, y0 = np.floor(end[:, 0] - 0.5).astype(np.int64), np.floor(end[:, 1] - 0.5).astype(np.int64)
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            ok = (xi >= 0) & (xi < wp) & (yi >= 0) & (yi < hp)
            found = np.full(len(moving), np.inf)
            found[ok] = older.depth[yi[ok], xi[ok]]
            with np.errstate(divide="ignore", invalid="ignore"):
                seen |= ok & np.isfinite(found) & (np.maximum(found / guess, guess / found) <= band)
    return guess, seen, inside


def true_velocity(newest, older, objects: dict, moving: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(H, W, 3) the true 3D displacement n-k -> n of the ``moving`` pixels' points in frame n's camera axes (object
    motion alone, ``mvec``'s velocity convention), and (M,) the true previous depth in frame n-k's camera."""
    h, w = newest.depth.shape
    y, x = np.divmod(moving, w)
    ids = newest.object_id[y, x]
    to_world = newest.camera.camera_to_world
    z = newest.depth[y, x].astype(np.float64)
    points = z[:, None] * (np.stack([x + 0.5, y + 0.5, np.ones_like(z)], 1) @ np.linalg.inv(newest.camera.intrinsics).T)
    world = np.c_[points, np.ones(len(z))] @ to_world.T
    before = world.copy()
    for oid in np.unique(ids):
        obj = objects.get(int(oid))
        if obj is not None and obj.moving:
            sel = ids == oid
            motion = obj.world_from_object[older.index] @ rigid_inverse(obj.world_from_object[newest.index])
            before[sel] = world[sel] @ motion.T
    velocity = np.zeros(newest.depth.shape + (3,), np.float32)
    velocity[y, x] = ((world - before) @ rigid_inverse(to_world).T)[:, :3]
    return velocity, (before @ older.camera.world_to_camera.T)[:, 2]


class UnseenRule(Mvec):
    """``mvec`` whose pixels frame n-k did not see move by ``rule`` (``RULES``) instead of the static depth guess."""

    def __init__(self, rule: str, config: Optional[MvecConfig] = None) -> None:
        super().__init__(config)
        if rule not in RULES:
            raise ValueError(f"rule must be one of {', '.join(RULES)}, got {rule!r}")
        self.rule = rule

    def _velocity(self, newest, older, vectors):
        velocity, moving = super()._velocity(newest, older, vectors)
        if self.rule == "static" or not moving.size:
            return velocity, moving
        _, seen, inside = previous_depths(newest, older, moving, self.config.depth_band, vectors)
        unsure = ~inside if self.rule == "hold-outside" else ~seen
        flat = velocity.reshape(-1, 3)
        drop = unsure.copy()
        if self.rule in ("unseen-regions", "region-median"):
            mask = np.zeros(newest.depth.shape, np.uint8)
            mask.flat[moving] = 1
            labels = cv2.connectedComponents(mask, connectivity=8)[1].reshape(-1)[moving]
            for label in np.unique(labels[unsure]):
                region = labels == label
                known = region & ~unsure
                if known.sum() >= MIN_SEEN:
                    drop[region] = False
                    if self.rule == "region-median":
                        flat[moving[region & unsure]] = np.median(flat[moving[known]], axis=0)
        flat[moving[drop]] = 0.0
        return velocity, moving[~drop]


def score(args) -> None:
    """``--score``: the PSNR table of ``RULES`` on ``tools.bench_mvec``'s sets (module docstring)."""
    from tools.bench_mvec import SETS, sequence_folder

    width, height = (int(v) for v in args.size.lower().split("x"))
    rules = args.rules.split(",")
    configs = {"mvec": None, "rigid+fb": MvecConfig(extrapolation="rigid", fallback=True)}
    rows = []
    print("| set | k | reproject | " + " | ".join(f"{c} {r}" for c in configs for r in rules) + " |\n|---|---|---|"
          + "---|" * (len(configs) * len(rules)))
    for set_name in args.sets.split(","):
        scores: dict = {}
        for seq_name, overrides in SETS[set_name]:
            seq = read_sequence(sequence_folder(args.out, seq_name, overrides, width, height, args.frames))
            for k in args.ks:
                given = {f"{c} {r}": UnseenRule(r, cfg) for c, cfg in configs.items() for r in rules}
                for res in evaluate_sequence(seq, ["reproject", *given], k, with_flip=False, predictors=given):
                    scores.setdefault((k, res.method), []).append((res.psnr, res.psnr_moving))
                    rows.append({"set": set_name, "sequence": seq_name, "k": k, "method": res.method,
                                 "psnr": res.psnr, "psnr_moving": res.psnr_moving})
        for k in args.ks:
            cells = [np.mean(scores[(k, m)], axis=0) for m in ["reproject", *given]]
            print(f"| {set_name} | {k} | " + " | ".join(f"{a:.2f} / {b:.2f}" for a, b in cells) + " |")
    write_json(args.json, {"size": [width, height], "frames": args.frames, "rules": rules, "rows": rows})


def sequence_rows(path: Path, ks) -> list[dict]:
    """One row per k of ``path``'s sequence (module docstring)."""
    seq = read_sequence(path)
    objects = {o.id: o for o in seq.objects}
    rows = []
    for k in ks:
        predictor = Mvec()
        sums = {f"{m}{part}": [0.0, 0] for m in MOTIONS for part in ("", " unseen")}
        shares, ratios = {"unseen": [], "outside": []}, []
        for older, newest, targets in evaluation_pairs(len(seq), k):
            history = rendered_history(seq, older, newest, with_vectors=True, three=False)
            state = predictor.prepare(history)
            o, n = history
            moving = state.data.moving
            if not moving.size:
                continue
            y, x = np.divmod(moving, n.depth.shape[1])
            guess, seen, inside = previous_depths(n, o, moving)
            truth_v, truth_z = true_velocity(n, o, objects, moving)
            shares["unseen"].append((~seen).mean())
            shares["outside"].append((~inside).mean())
            if (~seen).any():
                ratios.append(np.median(truth_z[~seen] / guess[~seen]))
            for t in targets:
                step = (seq[t].time - n.time) / (n.time - o.time)
                truth = true_object_flow(n, objects, t)[y, x, :2]
                for m, velocity in zip(MOTIONS, (state.data.velocity, truth_v, None)):
                    flow = 0.0 if velocity is None else extrapolated_flow(n.depth, velocity, n.camera.intrinsics, step,
                                                                         moving)[y, x, :2]
                    error = np.linalg.norm(flow - truth, axis=1)
                    for part, sel in (("", slice(None)), (" unseen", ~seen)):
                        sums[f"{m}{part}"][0] += float(error[sel].sum())
                        sums[f"{m}{part}"][1] += int(error[sel].size)
        rows.append({"sequence": path.name.split("_")[0], "k": k,
                     "unseen_share": float(np.mean(shares["unseen"])) if shares["unseen"] else 0.0,
                     "outside_share": float(np.mean(shares["outside"])) if shares["outside"] else 0.0,
                     "epe": {name: (s / c if c else None) for name, (s, c) in sums.items()},
                     "true_over_guess_depth": float(np.median(ratios)) if ratios else None})
    return rows


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="*", type=Path)
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--json", type=Path, default=None)
    parser.add_argument("--score", action="store_true", help="score RULES on tools.bench_mvec's sets")
    parser.add_argument("--sets", default="gentle,fast,spin,fast2")
    parser.add_argument("--rules", default=",".join(RULES))
    parser.add_argument("--out", default="out/bench_mvec")
    parser.add_argument("--size", default="640x360")
    parser.add_argument("--frames", type=int, default=16)
    args = parser.parse_args(argv)
    args.ks = [int(v) for v in args.k.split(",")]
    if args.score:
        score(args)
        return
    if not args.sequences:
        parser.error("give sequence folders, or --score")
    rows = [r for path in args.sequences for r in sequence_rows(path, args.ks)]
    names = [f"{m}{part}" for part in ("", " unseen") for m in MOTIONS]
    print("| sequence | k | unseen | outside | " + " | ".join(f"EPE {n}" for n in names)
          + " | true / guessed depth |\n|---|---|---|---|" + "---|" * (len(names) + 1))
    for r in rows:
        cells = ["-" if r["epe"][n] is None else f"{r['epe'][n]:.1f}" for n in names]
        ratio = "-" if r["true_over_guess_depth"] is None else f"{r['true_over_guess_depth']:.2f}"
        print(f"| {r['sequence']} | {r['k']} | {100 * r['unseen_share']:.0f}% | {100 * r['outside_share']:.0f}% | "
              + " | ".join(cells) + f" | {ratio} |")
    write_json(args.json, {"sequences": [p.name for p in args.sequences], "rows": rows})


if __name__ == "__main__":
    main()
