"""Which regions ``mvec``'s fall-back sends to the camera-only warp, and whether that was right at the targets.

``python -m tools.fallback_audit [--out out/bench_mvec] [--size 640x360] [--frames 16] [--k 2]
[--sequences fast3202,fast3203] [--method mvec[extrapolation=linear,fallback=true]] [--min-pixels 100] [--json FILE]``

The sequences are ``tools.bench_mvec``'s (rendered once and cached under ``--out``). For every evaluation pair
with frame n-2k (the fall-back needs it), the moving pixels of frame n are grouped as ``mvec``'s fall-back
groups them (``rigid.motion_components``) and ``--method`` is prepared: a group is "held" where the method
left its pixels out of the motion (camera-only warp). At each target the true object flow (the sequence's
object transforms) scores two choices per group, over its pixels in frame n: keeping the linear motion
(``mvec``'s extrapolated flow, with its change of velocity) and the camera-only warp (no object motion); the
mean screen error of each, in pixels. A decision is "right" where the held groups are those whose
camera-only error is the smaller. Printed: each group held or better held (at least ``--min-pixels``
pixels), and per sequence the flow error summed over moving pixels (kilo-pixels) of keeping every group, of
the method's decisions, and of the best choice per group.
"""
from __future__ import annotations

import math

import numpy as np

from engine.eval.protocol import evaluation_pairs, rendered_history
from engine.geometry.motion import extrapolated_flow
from engine.geometry.rigid import motion_components, moving_points
from engine.predict import make_predictor
from engine.predict.base import Target, extrapolation_factor, true_object_flow
from engine.predict.mvec import SAMPLES
from tools.heldout import write_json
from tools.profile_mvec import named_sequences, sequences_parser


def audit_pair(sequence, history, targets: list[int], method: str, min_pixels: int) -> tuple[list[dict], dict]:
    """The groups of one evaluation pair (``history``: frames n-2k, n-k, n) and the summed flow errors
    (``keep``, ``method``, ``best``) over its targets."""
    objects = {o.id: o for o in sequence.objects}
    linear = make_predictor("mvec", sequence.objects).prepare(history)
    state = make_predictor(method, sequence.objects).prepare(history)
    newest = history[-1]
    moving = linear.data.moving
    totals = {"keep": 0.0, "method": 0.0, "best": 0.0}
    if moving.size == 0:
        return [], totals
    held = ~np.isin(moving, state.data.motion.moving if state.data.motion is not None else [])
    k = newest.camera.intrinsics
    stride = max(1, math.ceil(math.sqrt(moving.size / SAMPLES)))  # as mvec samples; the groups do not depend on it
    now, speed, _, _ = moving_points(newest.depth, linear.data.velocity, moving, k, stride)
    labels, count = motion_components(newest.depth.shape, moving, now, speed)
    keep_err, still_err = np.zeros(count), np.zeros(count)
    for t in targets:
        step = extrapolation_factor(linear, Target(sequence.cameras[t], float(sequence.times[t]), t))
        flow = extrapolated_flow(newest.depth, linear.data.velocity, k, step, moving, linear.data.acceleration)
        truth = true_object_flow(newest, objects, t).reshape(-1, 3)[moving, :2]
        kept = np.linalg.norm(flow.reshape(-1, 3)[moving, :2] - truth, axis=1)
        still = np.linalg.norm(truth, axis=1)
        keep_err += np.bincount(labels, kept, minlength=count)
        still_err += np.bincount(labels, still, minlength=count)
        totals["keep"] += float(kept.sum())
        totals["method"] += float(np.where(held, still, kept).sum())
        totals["best"] += float(np.minimum(np.bincount(labels, kept, minlength=count),
                                           np.bincount(labels, still, minlength=count)).sum())
    sizes = np.bincount(labels, minlength=count)
    groups = []
    for g in range(count):
        member = labels == g
        was_held = bool(held[member].mean() > 0.5)
        better_held = bool(still_err[g] < keep_err[g])
        if sizes[g] >= min_pixels and (was_held or better_held):
            per = sizes[g] * len(targets)
            groups.append({"group": g, "pixels": int(sizes[g]), "held": was_held, "better_held": better_held,
                           "keep_px": float(keep_err[g] / per), "camera_only_px": float(still_err[g] / per)})
    return groups, totals


def main(argv=None) -> None:
    parser = sequences_parser(__doc__, "640x360", "2", "fast3202,fast3203")
    parser.add_argument("--method", default="mvec[extrapolation=linear,fallback=true]")
    parser.add_argument("--min-pixels", type=int, default=100)
    args = parser.parse_args(argv)
    rows = []
    for name, sequence, ks in named_sequences(args):
        for k in ks:
            totals = {"keep": 0.0, "method": 0.0, "best": 0.0}
            for older, newest, targets in evaluation_pairs(len(sequence), k):
                history = rendered_history(sequence, older, newest, with_vectors=True, three=True)
                if len(history) < 3:
                    continue
                groups, pair = audit_pair(sequence, history, targets, args.method, args.min_pixels)
                for key in totals:
                    totals[key] += pair[key]
                for g in groups:
                    verdict = "right" if g["held"] == g["better_held"] else "WRONG"
                    print(f"{name} k={k} n={newest} group {g['group']} ({g['pixels']} px): "
                          f"{'held' if g['held'] else 'kept'}, error keeping {g['keep_px']:.2f} px, camera-only "
                          f"{g['camera_only_px']:.2f} px: {verdict}")
                    rows.append({"sequence": name, "k": k, "n": newest, **g})
            print(f"{name} k={k}: flow error (kilo-px) keeping all {totals['keep'] / 1e3:.1f}, {args.method} "
                  f"{totals['method'] / 1e3:.1f}, best per group {totals['best'] / 1e3:.1f}")
            rows.append({"sequence": name, "k": k, "totals_kpx": {key: v / 1e3 for key, v in totals.items()}})
    write_json(args.json, {"method": args.method, "rows": rows})


if __name__ == "__main__":
    main()
