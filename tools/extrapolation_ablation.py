"""What to do with an estimated object flow once it is estimated: extrapolate it in 2D (``flow2d``), lift it to
3D, hand it to ``mvec`` as motion vectors, or keep it only where it predicted the last frame. An experiment.

``python -m tools.extrapolation_ablation [--variants 2d,lift,vectors,backtest,backtest_frame]
[--estimators truth,dis,corr] [--sets gentle,fast,extreme] [--heldout | --wide] [--cycles SEQ...] [--k 2,4]
[--json FILE]``

Every variant starts from the camera-compensated u(n -> n-k) of frame n (frame n-k warped into frame n's
view, what ``flow2d`` estimates), from one of three ``--estimators``: ``truth`` (the exact one, from the object
transforms: the variant's own bound), ``dis`` (``flow2d``'s) or ``corr`` (``flow2d[estimator=corr]``'s),
both with ``flow2d``'s trust rule. Then:

- ``2d``: ``flow2d``: u(n -> n+k') = -(k'/k) u(n -> n-k), frame n splatted by that 2D flow and the camera;
- ``lift``: each pixel's 3D velocity P(n) - Q(n-k) in frame n's camera, Q unprojected at p + u with the
  camera-compensated frame n-k's depth (``geometry.motion.scene_velocity`` with frame n's camera for both),
  extrapolated linearly in 3D (``PointMotion``, what ``mvec`` renders);
- ``vectors``: the flow made motion vectors to frame n-k's image (p + u moved back by the camera motion of
  the surface at p + u) and given to ``mvec``, with the previous interval's estimate as frame n-k's vectors:
  3D, and the parabola through three positions where the change of velocity is smooth (``mvec``'s guard);
- ``backtest``: ``2d``, keeping each connected region of motion (1 px or more, grown by 8 px) only where the
  previous interval's flow, extrapolated from frame n-k, predicted frame n better (summed luma error) than
  the camera-only warp of frame n-k did;
- ``backtest_frame``: the same test over the whole frame: no motion at all for this interval where the
  previous interval's flow predicted frame n worse than the camera-only warp.

Sets: the validation sequences of ``tools.motion_ablation`` (``--wide``: its wider set; ``--heldout``: the
held-out sets of ``tools.bench_motion`` instead), and ``--cycles``: imported path-traced sequences as one more
set. Prints PSNR over the whole frame and over moving pixels per (set, k,
variant, estimator); scores are ``interleave eval``'s.
"""
from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path

import cv2
import numpy as np

from engine import geometry
from engine.eval.protocol import evaluate_sequence, summarize
from engine.geometry.motion import camera_motion_vectors, sample_nearest, scene_velocity
from engine.io.rgbd import read_sequence
from engine.predict import registry
from engine.predict.base import (PointMotion, Predictor, Target, Timer, extrapolation_factor, true_object_flow,
                                 warp_and_fill, warp_fill_depth)
from engine.predict.classic import Flow2D
from engine.predict.corrflow import CorrFlowNetwork, dis_start
from engine.predict.dis import dis_calc, dis_estimator, luma8, trusted_motion
from engine.predict.mvec import Mvec
from tools.bench_motion import set_sequences
from tools.heldout import write_json
from tools.motion_ablation import validation_sets

VARIANTS = ("2d", "lift", "vectors", "backtest", "backtest_frame")
ESTIMATORS = ("truth", "dis", "corr")


class Estimates:
    """u(n -> n-k) of a pair of frames by one estimator, with the camera-compensated frame n-k (colour, depth
    with +inf in the warp's holes), cached per pair: a stream asks for each pair twice (as frame n's, then as
    frame n-k's previous interval)."""

    def __init__(self, estimator: str, objects) -> None:
        self.estimator = estimator
        self.objects = {o.id: o for o in objects}
        self.dis = dis_estimator("medium")
        self.network = CorrFlowNetwork() if estimator == "corr" else None
        self.cache: dict = {}

    def __call__(self, older, newest) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        key = (older.index, newest.index, older.time, newest.time)
        if key not in self.cache:
            self.cache = {k: v for k, v in self.cache.items() if k[1] >= older.index}  # the last pair stays
            self.cache[key] = self._estimate(older, newest)
        return self.cache[key]

    def _estimate(self, older, newest):
        warped, depth_w, holes = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index), Timer())
        depth_w = np.where(holes, np.inf, depth_w).astype(np.float32)
        if self.estimator == "truth":
            return true_object_flow(newest, self.objects, older.index)[..., :2].copy(), warped, depth_w
        luma_n, luma_w = luma8(newest.color), luma8(warped)
        start = None
        if self.network is not None:
            start = dis_start(self.network.estimate(newest.color, warped, newest.depth, depth_w))
        flow = dis_calc(self.dis, luma_n, luma_w, start)
        src, dst = older.camera, newest.camera
        seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics,
                                    src.world_to_camera, older.depth.shape)
        flow[~trusted_motion(luma_n, luma_w, flow, seen)] = 0.0
        return flow, warped, depth_w


def flow_vectors(flow: np.ndarray, newest, older, depth_w: np.ndarray) -> np.ndarray:
    """Motion vectors (H, W, 2) of frame n to frame n-k's image from the camera-compensated u(n -> n-k):
    p + u is where the point was, seen from frame n's camera; the camera's own motion vector of the
    compensated surface there (depth ``depth_w``) takes it to frame n-k's image. Where p + u leaves the frame
    or falls in a hole, and where u is 0, frame n's own camera vector at p stands in for that second part."""
    h, w = flow.shape[:2]
    own = camera_motion_vectors(newest.depth, newest.camera, older.camera)
    compensated = camera_motion_vectors(depth_w, newest.camera, older.camera)
    v, u = np.mgrid[0:h, 0:w].astype(np.float64)
    at = sample_nearest(compensated, u + 0.5 + flow[..., 0], v + 0.5 + flow[..., 1])
    depth_at = sample_nearest(depth_w[..., None], u + 0.5 + flow[..., 0], v + 0.5 + flow[..., 1])[..., 0]
    bad = ~np.isfinite(at).all(axis=-1) | ~np.isfinite(depth_at) | ~flow.any(axis=-1)
    at[bad] = own[bad]
    return (flow + at).astype(np.float32)


class Extrapolated(Predictor):
    """A variant over one estimator (module docstring)."""

    history_needed = 2
    history_wanted = 3

    def __init__(self, variant: str, estimator: str, objects) -> None:
        self.variant = variant
        self.estimates = Estimates(estimator, objects)
        self.name = f"{variant}:{estimator}"
        self._flow2d, self._mvec = Flow2D(), Mvec()

    def _prepare(self, state, timer):
        history = list(state.history)
        older, newest = history[-2], history[-1]
        flow, warped, depth_w = self.estimates(older, newest)
        self.flow = flow
        if self.variant == "lift":
            velocity, moving = scene_velocity(newest.depth, flow, depth_w, newest.camera, newest.camera)
            return newest, (PointMotion(velocity, moving) if moving.size else None)
        if self.variant == "vectors":
            history[-1] = dataclasses.replace(newest, motion_vectors=flow_vectors(flow, newest, older, depth_w))
            if len(history) >= 3:
                previous, _, depth_p = self.estimates(history[-3], older)
                history[-2] = dataclasses.replace(older, motion_vectors=flow_vectors(previous, older, history[-3],
                                                                                       depth_p))
            return self._mvec.prepare(history)
        flow = flow.copy()
        if self.variant.startswith("backtest") and len(history) >= 3 and flow.any():
            first = history[-3]
            previous, _, _ = self.estimates(first, older)
            step = (newest.time - older.time) / (older.time - first.time)
            target = Target(newest.camera, newest.time, newest.index)
            predicted, _ = warp_and_fill(older, target, Timer(), -step * previous)
            luma_n = luma8(newest.color).astype(np.float32)
            error_motion = np.abs(luma8(predicted).astype(np.float32) - luma_n).ravel()
            error_camera = np.abs(luma8(warped).astype(np.float32) - luma_n).ravel()
            if self.variant == "backtest_frame":
                return newest, (flow if error_motion.sum() < error_camera.sum() else None)
            moving = np.hypot(flow[..., 0], flow[..., 1]) >= 1.0
            grown = cv2.dilate(moving.astype(np.uint8), np.ones((17, 17), np.uint8))
            count, labels = cv2.connectedComponents(grown, connectivity=8)
            keep = np.bincount(labels.ravel(), error_motion, count) < np.bincount(labels.ravel(), error_camera, count)
            keep[0] = True
            flow[~keep[labels] & moving] = 0.0
        return newest, flow

    def object_flow(self, state):
        return self.flow

    def _render(self, state, target, timer):
        if self.variant == "vectors":
            prediction = self._mvec.render(state.data, target)
            return prediction.color, prediction.holes
        newest, motion = state.data
        if motion is None:
            return warp_and_fill(newest, target, timer)
        if isinstance(motion, PointMotion):
            return self.frames.warp_and_fill(self.frames.resident(newest, timer), target, timer, motion,
                                             extrapolation_factor(state, target))
        return warp_and_fill(newest, target, timer, -extrapolation_factor(state, target) * motion)


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variants", default=",".join(VARIANTS))
    parser.add_argument("--estimators", default=",".join(ESTIMATORS))
    parser.add_argument("--sets", default="gentle,fast,extreme")
    parser.add_argument("--heldout", action="store_true", help="the held-out sets of tools.bench_motion")
    parser.add_argument("--wide", action="store_true", help="the wider validation set of tools.motion_ablation")
    parser.add_argument("--cycles", nargs="*", type=Path, default=[], help="imported path-traced sequences")
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    variants, estimators = args.variants.split(","), args.estimators.split(",")
    for v in variants:
        if v not in VARIANTS:
            parser.error(f"unknown variant '{v}', expected some of {', '.join(VARIANTS)}")
    for e in estimators:
        if e not in ESTIMATORS:
            parser.error(f"unknown estimator '{e}', expected some of {', '.join(ESTIMATORS)}")
    methods = ["reproject", "oracle"]
    for v in variants:
        for e in estimators:
            registry.METHODS[f"{v}:{e}"] = lambda objects, v=v, e=e: Extrapolated(v, e, objects)
            methods.append(f"{v}:{e}")
    if args.heldout:
        sets = {s: [p for _, p in set_sequences(Path("out/bench_motion"), s, 3, 640, 360, 16)]
                for s in args.sets.split(",")}
    else:
        sets = {s: p for s, p in validation_sets(Path("out/validation"), args.wide).items()
                if s in args.sets.split(",")}
    if args.cycles:
        sets["cycles"] = list(args.cycles)
    rows = []
    for set_name, paths in sets.items():
        sequences = [read_sequence(p) for p in paths]
        for k in (int(v) for v in args.k.split(",")):
            results = []
            for seq in sequences:
                results += evaluate_sequence(seq, methods, k, with_flip=False)
            summary = summarize(results)
            for m in methods:
                row = summary[f"{m}/k={k}"]
                rows.append({"set": set_name, "k": k, "method": m, "psnr": row["psnr"],
                             "psnr_moving": row["psnr_moving"], "epe_moving": row["epe_moving"]})
                print(f"{set_name:8s} k={k} {m:16s} PSNR {row['psnr']:.2f}  moving {row['psnr_moving']:.2f}",
                      flush=True)
    write_json(args.json, {"sets": {s: [p.name for p in ps] for s, ps in sets.items()}, "rows": rows})


if __name__ == "__main__":
    main()
