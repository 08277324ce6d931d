"""Issue 42, 2026-11-29 fast-objects page, lead's addendum: two hole rules for spinning objects, scored as bounds.

``python docs/results/2026-11-29-fast-objects-fill-rules.py RULE CACHE SEQ[,SEQ...] K[,K...] METHODS OUT.json``

Every method's warp (``engine.predict.base.warp_fill_depth``) is patched; the holes it leaves are filled as
the engine fills them, then RULE overrides some of them:

- ``nearer``: holes where the TRUE target shows a moving object (``Frame.moving`` of the target: an oracle's
  knowledge) take the nearer (smaller depth) of their nearest known left / right pixels on the row, the object's
  side, instead of the farther one (a bound on telling object holes from uncovered background);
- ``underlay``: holes that frame n's moving pixels cover in the camera-only warp take that warp's colour (the
  object held where it was, under the moved one).

Scores: ``interleave eval``'s protocol (``evaluate_sequence``), FLIP off, without and with the rule.
"""
from __future__ import annotations

import json
import sys

import numpy as np

import engine.predict.base as base
from engine import geometry
from engine.eval.protocol import evaluate_sequence
from engine.geometry.holefill import fill_holes, nearest_known
from engine.io.rgbd import read_sequence

STATE = {"rule": None, "sequence": None}
_ORIGINAL = base.warp_fill_depth


def _nearer(color, depth, holes, out, truth):
    obj = holes & truth.moving
    if obj.any():
        left, right = nearest_known(~holes)
        r, c = np.nonzero(obj)
        lc, rc = left[r, c], right[r, c]
        dl = np.where(lc >= 0, depth[r, np.maximum(lc, 0)], np.inf)
        dr = np.where(rc >= 0, depth[r, np.maximum(rc, 0)], np.inf)
        pick = np.where(dl <= dr, lc, rc)
        ok = pick >= 0
        out[r[ok], c[ok]] = color[r[ok], pick[ok]]


def _underlay(frame, target, holes, out):
    src, dst = frame.camera, target.camera
    held, _, held_holes = geometry.forward_warp_frame(frame.color, frame.depth, src.intrinsics, src.world_to_camera,
                                                      dst.intrinsics, dst.world_to_camera)
    marks = np.repeat(frame.moving[..., None].astype(np.float32), 3, -1)
    covered, _, _ = geometry.forward_warp_frame(marks, frame.depth, src.intrinsics, src.world_to_camera,
                                                dst.intrinsics, dst.world_to_camera)
    take = holes & ~held_holes & (covered[..., 0] > 0.5)
    out[take] = held[take]


def patched(frame, target, timer, flow=None, flow_spans=None):
    if STATE["rule"] is None or flow is None:
        return _ORIGINAL(frame, target, timer, flow, flow_spans)
    src, dst = frame.camera, target.camera
    color, depth, holes = geometry.forward_warp_frame(frame.color, frame.depth, src.intrinsics, src.world_to_camera,
                                                      dst.intrinsics, dst.world_to_camera, flow, flow_spans=flow_spans)
    out, out_depth = fill_holes(color, depth, holes, frame.color)
    if STATE["rule"] == "nearer":
        _nearer(color, depth, holes, out, STATE["sequence"][target.index])
    elif frame.moving is not None:
        _underlay(frame, target, holes, out)
    return out, out_depth, holes


def main(argv) -> None:
    rule, cache, names, ks, methods, path = argv
    if rule not in ("nearer", "underlay"):
        raise SystemExit(f"unknown rule {rule!r}: nearer or underlay")
    base.warp_fill_depth = patched
    rows = {}
    for name in names.split(","):
        sequence = read_sequence(f"{cache}/{name}")
        STATE["sequence"] = sequence
        for k in (int(v) for v in ks.split(",")):
            for applied in (None, rule):
                STATE["rule"] = applied
                for result in evaluate_sequence(sequence, methods.split(";"), k, with_flip=False, backend="cpu"):
                    key = f"{name}|{k}|{result.method}|{applied or 'engine'}"
                    rows[key] = {"psnr": result.psnr, "psnr_moving": result.psnr_moving}
                    print(key, f"{result.psnr:.2f} / {result.psnr_moving:.2f}", flush=True)
    with open(path, "w") as f:
        json.dump({"rule": rule, "argv": argv, "rows": rows}, f, indent=1)


if __name__ == "__main__":
    main(sys.argv[1:])
