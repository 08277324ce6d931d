"""How far OpenCV DIS reaches: the end-point error of the object motion it estimates between two rendered
frames, for DIS presets and parameters, on fast held-out sequences.

``python -m tools.flow_reach SEQ_DIR... [--k 2] [--network ONNX] [--json FILE]``

For every pair (n-k, n) with moving pixels, frame n-k is warped into frame n's view (camera motion
cancelled, holes filled as ``reproject`` fills them, what ``flow2d`` matches against) and each variant
estimates u(n -> n-k) on 8-bit luma; the correlation network (``engine.predict.corrflow``, the committed one
unless ``--network`` names another) reads both colour images (and both depths, an RGB-D network): alone,
and as DIS medium's initial flow (``flow2d[estimator=corr]``). Scored against the true u(n -> n-k) of frame n (from the object
transforms) over the pixels that move more than 0.5 px: the median end-point error of each pair (means
over pairs) and the share of moving pixels within 3 px, with the median ms per pair. No extrapolation:
this is the estimate alone.
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import cv2
import numpy as np

from engine.io.rgbd import read_sequence
from engine.predict.base import Target, Timer, true_object_flow, warp_fill_depth
from engine.predict.corrflow import CorrFlowNetwork, dis_start
from engine.predict.dis import dis_calc, dis_estimator, luma8
from tools.heldout import write_json

MEDIUM, FAST = cv2.DISOPTICAL_FLOW_PRESET_MEDIUM, cv2.DISOPTICAL_FLOW_PRESET_FAST


def dis(preset: int, **settings):
    def make():
        estimator = cv2.DISOpticalFlow_create(preset)
        for name, value in settings.items():
            getattr(estimator, "set" + name)(value)
        return estimator
    return make


def at_half(make):
    """The variant on 2 x 2 block means, its flow upsampled and doubled (twice the reach in pixels)."""
    def make_half():
        estimator = make()

        class Half:
            def calc(self, a, b, _):
                small = [cv2.resize(x, None, fx=0.5, fy=0.5, interpolation=cv2.INTER_AREA) for x in (a, b)]
                return 2.0 * cv2.resize(estimator.calc(*small, None), (a.shape[1], a.shape[0]))
        return Half()
    return make_half


VARIANTS = {
    "medium": dis(MEDIUM),
    "fast": dis(FAST),
    "medium, patch 16": dis(MEDIUM, PatchSize=16, PatchStride=6),
    "medium, 50 descent iterations": dis(MEDIUM, GradientDescentIterations=50),
    "medium, no variational refinement": dis(MEDIUM, VariationalRefinementIterations=0),
    "medium at half resolution": at_half(dis(MEDIUM)),
}


def network_variants(network: CorrFlowNetwork) -> dict:
    """name -> f(newest, warped, depth_w, luma_n, luma_w) -> u(n -> n-k): the network alone and DIS started
    from it (``newest``: frame n; ``warped``, ``depth_w``: the camera-compensated frame n-k's colour and
    depth, the depth read by an RGB-D network only)."""
    medium = dis_estimator("medium")

    def alone(f, w, dw, ln, lw):
        return network.estimate(f.color, w, f.depth, dw)
    return {"correlation network alone": alone,
            "medium from the network (flow2d[estimator=corr])":
                lambda f, w, dw, ln, lw: dis_calc(medium, ln, lw, dis_start(alone(f, w, dw, ln, lw)))}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+", type=Path)
    parser.add_argument("--k", type=int, default=2)
    parser.add_argument("--network", type=Path, default=None, help="a correlation flow ONNX (default: committed)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    networks = network_variants(CorrFlowNetwork(args.network))
    scores = {name: {"median_epe": [], "within_3px": [], "ms": []}
              for name in ["zero motion", *VARIANTS, *networks]}
    for path in args.sequences:
        seq = read_sequence(path)
        objects = {o.id: o for o in seq.objects}
        for n in range(args.k, len(seq), args.k):
            older, newest = seq[n - args.k], seq[n]
            truth = true_object_flow(newest, objects, n - args.k)[..., :2]
            moving = np.linalg.norm(truth, axis=-1) > 0.5
            if moving.sum() < 50:
                continue
            warped, depth_w, _ = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index), Timer())
            luma_n, luma_w = luma8(newest.color), luma8(warped)
            estimates = {"zero motion": (np.zeros_like(truth), 0.0)}
            for name, make in VARIANTS.items():
                estimator = make()
                start = time.perf_counter()
                flow = estimator.calc(luma_n, luma_w, None)
                estimates[name] = (flow, 1e3 * (time.perf_counter() - start))
            for name, estimate in networks.items():
                start = time.perf_counter()
                flow = estimate(newest, warped, depth_w, luma_n, luma_w)
                estimates[name] = (flow, 1e3 * (time.perf_counter() - start))
            for name, (flow, ms) in estimates.items():
                error = np.linalg.norm(flow - truth, axis=-1)[moving]
                scores[name]["median_epe"].append(float(np.median(error)))
                scores[name]["within_3px"].append(float((error < 3.0).mean()))
                scores[name]["ms"].append(ms)
    rows = []
    print("| estimate | median EPE (px, mean over pairs) | moving pixels within 3 px | ms |\n|---|---|---|---|")
    for name, s in scores.items():
        row = {"estimate": name, "pairs": len(s["median_epe"]), "median_epe": float(np.mean(s["median_epe"])),
               "within_3px": float(np.mean(s["within_3px"])), "ms": float(statistics.median(s["ms"]))}
        rows.append(row)
        print(f"| {name} | {row['median_epe']:.2f} | {100 * row['within_3px']:.0f} % | {row['ms']:.1f} |")
    write_json(args.json, {"sequences": [p.name for p in args.sequences], "k": args.k,
                           "network": str(args.network or "committed"), "rows": rows})


if __name__ == "__main__":
    main()
