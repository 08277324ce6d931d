"""Ablation of what ``flow2d`` does with DIS's flow before extrapolating it: which estimated object motion to
keep, and whether matching changed regions whole reaches motion DIS misses.

``python -m tools.motion_ablation [--out out/validation] [--variants ...] [--k 2,4]
[--estimator dis|gl|corr|corr_alone] [--wide] [--json FILE]``

Runs on VALIDATION sequences, apart from the benchmark's held-out ones (``tools/bench_motion.py``), so the
choice it informs is not tuned on the sets it is reported on: ``gentle`` seeds 1005, 1006 (generator
defaults); ``fast``: the first 2 seeds from 7201 of the ``fast`` preset moving a median 10-35 px a frame;
``extreme``: the first seed from 7301 of the ``extreme`` preset moving a median 20-80 px a frame.

Variants (each is ``flow2d`` with another rule between DIS and the extrapolation):

- ``dis``: DIS's flow as it comes;
- ``confidence``: motion kept only where it explains frame n better than none (``dis.confident_motion``,
  margin ``--margin``) at every pixel;
- ``seen``: none where frame n-k did not see the surface (``geometry.seen_before``);
- ``trusted``: ``seen`` and motion under ``--small`` px (1) only where confident: ``dis.trusted_motion``;
- ``gated``: ``trusted``, and none outside the boxes of ``decomp``'s motion gate (tiles where the
  camera-compensated frame n-k differs from frame n in colour or depth, grown by its margin);
- ``regions``: each changed region of frame n matched whole against the camera-compensated frame n-k
  (masked template matching within 15 % of the width on 2 x 2 block means), DIS around the region's shift
  where that explains the region better than plain DIS by more than 1 level a pixel, then ``trusted``;
- ``regions_failed``: the same, only in regions where plain DIS's mean error exceeds 8 levels;
- ``revealed``: ``trusted``, and none where frame n sees at least 1.43x farther than the camera-compensated
  frame n-k did (surface an object uncovered; a smaller jump can be an object moving away);
- ``regions_arrived``: ``regions``, matching only regions of which at least 30 % is nearer in frame n than in
  the camera-compensated frame n-k (an object arrived there), not surface an object uncovered;
- ``not_worse``: ``trusted``, and none where the motion explains frame n worse than none by more than
  ``--margin`` levels (9 x 9 means): the converse of ``confidence``, which keeps ties;
- ``region_check``: ``trusted``, then each connected region of motion of at least 1 px kept whole only where
  its summed photometric error drops by more than ``--margin`` levels a pixel against no motion;
- ``depth_evidence``: ``trusted``, then each connected region of motion of at least 1 px dropped unless at
  least ``--margin`` of its pixels lie within 2 px of a pixel whose inverse depth differs from the
  camera-compensated frame n-k's by more than ``DEPTH_CHANGE`` (a moving object changes depth at its
  silhouette);
- ``blurred``: ``trusted`` with DIS run on lumas blurred by a Gaussian of sigma ``--margin`` px (noise);
- ``depth_static``: ``trusted``, and where frame n's depth equals the camera-compensated frame n-k's
  (``STATIC_DEPTH``; both sky) motion only where it is confident (margin ``--margin``): a static surface
  at its place;
- ``behind_edge``: ``trusted``, and on pixels with a surface nearer by ``BEHIND_STEP`` within
  ``BEHIND_RADIUS`` px (the background side of a silhouette, where DIS spreads an object's motion) motion
  only where it is confident (margin ``--margin``);
- ``depth_consistent``: ``trusted``, and no motion where no motion is depth-consistent (frame n's log depth
  within ``--margin`` of the camera-compensated frame n-k's at the same pixel) and the motion is not (frame
  n-k's depth where the motion points differs by ``--margin`` more): a static surface beside a moving
  object, onto which DIS spread the object's motion;
- ``network_veto`` (``--estimator corr`` only): ``trusted``, and no motion where the correlation network's
  own estimate moves under ``--margin`` px;
- ``rigid_ids``: ``trusted``, then the flow of each object of frame n's ``object_id`` channel (as a renderer's
  Object Index pass would give it, the static scene included) replaced by the rigid motion that best
  explains it (RANSAC over 3-point fits of DIS's 3D correspondences, inliers within 1.5 px; no motion when
  that explains at least 90 % as many), where that motion explains at least half of the object's samples.

``--estimator`` picks the optical flow the rules apply to: OpenCV DIS, the GPU's, DIS started from the
correlation network's estimate (``flow2d[estimator=corr]``) or the network's estimate alone (``corr_alone``).

Prints per (set, k, variant) PSNR over the whole frame and over moving pixels and the end-point error over
moving pixels, beside ``reproject``'s; scores are ``interleave eval``'s.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Callable

import cv2
import numpy as np

from engine import geometry
from engine.eval.protocol import evaluate_sequence, summarize
from engine.io.rgbd import read_sequence
from engine.predict import registry
from engine.predict.base import Target, Timer, warp_fill_depth
from engine.predict.classic import Flow2D
from engine.predict.corrflow import CorrFlowNetwork, dis_start
from engine.predict.decomp.gate import GateConfig, gate_boxes
from engine.predict.decomp.predictor import full_box
from engine.predict.dis import SMALL_MOTION, confident_motion, dis_calc, luma8, trusted_motion, warp_error
from tools.heldout import render_set, speed_set, write_json
from tools.mvec_extrapolation import rigid_fit

#: a rule: (estimator, luma_n, target, seen, context) -> flow u(n -> n-k) (H, W, 2); context: dict with
#: "gate" (H, W) bool, inside the boxes of decomp's motion gate (engine.predict.decomp.gate) at full
#: resolution, and "revealed" (H, W) bool, where frame n sees at least 1 / (1 - REVEAL_DROP) times farther
#: than the camera-compensated frame n-k (outside the warp's holes)
Rule = Callable[[object, np.ndarray, np.ndarray, np.ndarray, dict], np.ndarray]
REVEAL_DROP = 0.3
#: ``depth_evidence``: frame n's inverse depth differs from the camera-compensated frame n-k's by this share
DEPTH_CHANGE = 0.05
#: ``depth_static``: frame n's depth within this log ratio of the camera-compensated frame n-k's (or both sky)
STATIC_DEPTH = 0.01
#: ``behind_edge``: a pixel with a surface nearer by this share within this many px (640 px frames)
BEHIND_STEP, BEHIND_RADIUS = 0.1, 32


def region_shifts(luma_n: np.ndarray, target: np.ndarray, radius: int, min_area: int,
                  threshold: float = 10.0, scale: int = 2, arrived: np.ndarray | None = None,
                  arrived_share: float = 0.3) -> tuple[np.ndarray, np.ndarray]:
    """(piecewise-constant flow (H, W, 2), region labels (H, W)): each connected region where frame n's luma
    differs from the target's (5 x 5 mean > ``threshold``) takes the shift within +-``radius`` px at which it
    best matches the target as one masked template (squared differences, on ``scale`` x ``scale`` means)."""
    h, w = luma_n.shape
    flow = np.zeros((h, w, 2), np.float32)
    if min(h, w) < 2 * scale:
        return flow, np.zeros((h, w), np.int32)
    changed = cv2.blur(cv2.absdiff(luma_n, target).astype(np.float32), (5, 5)) > threshold
    changed = cv2.morphologyEx(changed.astype(np.uint8), cv2.MORPH_OPEN, np.ones((3, 3), np.uint8))
    count, labels, stats, _ = cv2.connectedComponentsWithStats(changed, connectivity=8)
    small_n = cv2.resize(luma_n, (w // scale, h // scale), interpolation=cv2.INTER_AREA).astype(np.float32)
    small_t = cv2.resize(target, (w // scale, h // scale), interpolation=cv2.INTER_AREA).astype(np.float32)
    small_labels = labels[scale // 2::scale, scale // 2::scale][:h // scale, :w // scale]
    sh, sw = small_n.shape
    r = max(1, radius // scale)
    share = None
    if arrived is not None:  # the share of each region's pixels where frame n sees nearer than frame n-k did
        share = np.bincount(labels.ravel(), arrived.ravel(), minlength=count) / np.maximum(
            np.bincount(labels.ravel(), minlength=count), 1)
    for i in range(1, count):
        if stats[i, cv2.CC_STAT_AREA] < min_area or (share is not None and share[i] < arrived_share):
            labels[labels == i] = 0
            continue
        x, y, bw, bh = (int(v) // scale for v in stats[i, :4])
        bw, bh = min(max(bw, 1), sw - x), min(max(bh, 1), sh - y)
        region = (small_labels[y:y + bh, x:x + bw] == i).astype(np.float32)
        if region.sum() < 4:
            continue
        x0, y0, x1, y1 = max(0, x - r), max(0, y - r), min(sw, x + bw + r), min(sh, y + bh + r)
        scores = cv2.matchTemplate(small_t[y0:y1, x0:x1], small_n[y:y + bh, x:x + bw], cv2.TM_SQDIFF, mask=region)
        best = cv2.minMaxLoc(scores)[2]
        flow[labels == i] = (scale * (x0 + best[0] - x), scale * (y0 + best[1] - y))
    return flow, labels


def regions_rule(estimator, luma_n, target, seen, context, failed: float = 0.0, arrived: bool = False) -> np.ndarray:
    """Region matching where it explains a region better than plain DIS; with ``failed`` > 0 only in regions
    where plain DIS's mean photometric error exceeds ``failed`` levels (DIS lost the motion there)."""
    flow = dis_calc(estimator, luma_n, target)
    h, w = luma_n.shape
    shifts, labels = region_shifts(luma_n, target, max(2, round(0.15 * w)), max(4, round(64 * (w / 640) ** 2)),
                                   arrived=context["arrived"] if arrived else None)
    if shifts.any():
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        moved = cv2.remap(target, gx + shifts[..., 0], gy + shifts[..., 1], cv2.INTER_LINEAR,
                          borderMode=cv2.BORDER_REPLICATE)
        shifted = shifts + dis_calc(estimator, luma_n, moved)
        index, count = labels.ravel(), int(labels.max()) + 1
        pixels = np.bincount(index, minlength=count)
        plain = np.bincount(index, warp_error(luma_n, target, (0, 0), flow).ravel(), minlength=count)
        other = np.bincount(index, warp_error(luma_n, target, (0, 0), shifted).ravel(), minlength=count)
        better = (other < plain - pixels) & (plain > failed * pixels)
        better[0] = False
        take = better[labels]
        flow[take] = shifted[take]
    flow[~trusted_motion(luma_n, target, flow, seen)] = 0.0
    return flow


def rules(margin: float, small: float = SMALL_MOTION) -> dict[str, Rule]:
    def dis(e, ln, t, seen, context):
        return dis_calc(e, ln, t)

    def confidence(e, ln, t, seen, context):
        flow = dis_calc(e, ln, t)
        flow[~confident_motion(ln, t, flow, margin)] = 0.0
        return flow

    def not_worse(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        still = cv2.blur(cv2.absdiff(ln, t).astype(np.float32), (9, 9), borderType=cv2.BORDER_REFLECT)
        flow[warp_error(ln, t, (0, 0), flow, 9) > still + np.float32(margin)] = 0.0
        return flow

    def region_check(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        gain = cv2.absdiff(ln, t).astype(np.float64) - warp_error(ln, t, (0, 0), flow, 1)
        return drop_regions(flow, lambda labels, count: np.bincount(labels.ravel(), gain.ravel(), count)
                            <= margin * np.bincount(labels.ravel(), minlength=count))

    def blurred(e, ln, t, seen, context):
        flow = dis_calc(e, *(cv2.GaussianBlur(x, (0, 0), float(margin)) for x in (ln, t)))
        flow[~trusted_motion(ln, t, flow, seen, small)] = 0.0
        return flow

    def depth_evidence(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        changed = cv2.dilate(context["depth_change"].astype(np.uint8), np.ones((5, 5), np.uint8)) > 0
        return drop_regions(flow, lambda labels, count: np.bincount(labels.ravel(), changed.ravel(), count)
                            < max(1.0, margin))

    def rigid_ids(e, ln, t, seen, context):
        return rigid_object_flow(trusted(e, ln, t, seen, context), context)

    def seen_only(e, ln, t, seen, context):
        flow = dis_calc(e, ln, t)
        flow[~seen] = 0.0
        return flow

    def trusted(e, ln, t, seen, context):
        flow = dis_calc(e, ln, t)
        flow[~trusted_motion(ln, t, flow, seen, small)] = 0.0
        return flow

    def gated(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        flow[~context["gate"]] = 0.0
        return flow

    def revealed(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        flow[context["revealed"]] = 0.0
        return flow

    def regions_where_dis_failed(e, ln, t, seen, context):
        return regions_rule(e, ln, t, seen, context, failed=8.0)

    def regions_arrived(e, ln, t, seen, context):
        return regions_rule(e, ln, t, seen, context, arrived=True)

    def depth_static(e, ln, t, seen, context):
        flow = dis_calc(e, ln, t)
        keep = trusted_motion(ln, t, flow, seen, small)
        depth_n, depth_w = context["newest"].depth, context["depth_w"]
        with np.errstate(divide="ignore", invalid="ignore"):
            agree = (np.isinf(depth_n) & np.isinf(depth_w)) | (np.abs(np.log(depth_n / depth_w)) < STATIC_DEPTH)
        flow[~(keep & (~agree | confident_motion(ln, t, flow, margin)))] = 0.0
        return flow

    def behind_edge(e, ln, t, seen, context):
        flow = dis_calc(e, ln, t)
        keep = trusted_motion(ln, t, flow, seen, small)
        depth = np.where(np.isfinite(context["newest"].depth), context["newest"].depth, np.float32(3e38))
        side = 2 * BEHIND_RADIUS + 1
        behind = cv2.erode(depth.astype(np.float32), np.ones((side, side), np.uint8)) < (1 - BEHIND_STEP) * depth
        flow[~(keep & (~behind | confident_motion(ln, t, flow, margin)))] = 0.0
        return flow

    def depth_consistent(e, ln, t, seen, context):
        flow = trusted(e, ln, t, seen, context)
        log_n, log_w = (np.log(np.clip(np.nan_to_num(d, posinf=1e30), 1e-30, 1e30)).astype(np.float32)
                        for d in (context["newest"].depth, context["depth_filled"]))
        h, w = log_n.shape
        gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
        moved = cv2.remap(log_w, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_NEAREST,
                          borderMode=cv2.BORDER_REPLICATE)
        still, along = np.abs(log_n - log_w), np.abs(log_n - moved)
        flow[(still < margin) & (along > still + np.float32(margin))] = 0.0
        return flow

    def network_veto(e, ln, t, seen, context):
        if "network" not in context:
            raise ValueError("network_veto needs --estimator corr")
        flow = trusted(e, ln, t, seen, context)
        network = context["network"]
        flow[np.hypot(network[..., 0], network[..., 1]) < margin] = 0.0
        return flow

    return {"dis": dis, "confidence": confidence, "seen": seen_only, "trusted": trusted, "gated": gated,
            "not_worse": not_worse, "region_check": region_check, "depth_evidence": depth_evidence,
            "blurred": blurred, "rigid_ids": rigid_ids,
            "regions": regions_rule, "regions_failed": regions_where_dis_failed, "revealed": revealed,
            "regions_arrived": regions_arrived, "depth_static": depth_static, "behind_edge": behind_edge,
            "network_veto": network_veto, "depth_consistent": depth_consistent}


def drop_regions(flow: np.ndarray, drop: Callable[[np.ndarray, int], np.ndarray]) -> np.ndarray:
    """``flow`` with the connected regions of motion of at least 1 px that ``drop(labels, count)`` ((count,)
    bool per label, label 0 the still pixels, which stay) selects set to no motion; modifies ``flow``."""
    count, labels = cv2.connectedComponents((np.hypot(flow[..., 0], flow[..., 1]) >= 1.0).astype(np.uint8))
    if count > 1:
        dropped = drop(labels, count)
        dropped[0] = False
        flow[dropped[labels]] = 0.0
    return flow


def _rigid(before: np.ndarray, now: np.ndarray) -> np.ndarray:
    """``tools.mvec_extrapolation.rigid_fit`` as one 4x4 matrix M with now ~ M before."""
    rotation, c_before, c_now = rigid_fit(before, now)
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation, c_now - rotation @ c_before
    return m


def rigid_object_flow(flow: np.ndarray, context: dict, tolerance: float = 1.5, samples: int = 1500,
                      tries: int = 200) -> np.ndarray:
    """``rigid_ids``' rule (module docstring): ``context`` holds frame n (``newest``) and the depth of the
    camera-compensated frame n-k (``depth_w``, +inf in its holes)."""
    newest, depth_w = context["newest"], context["depth_w"]
    rng = np.random.default_rng(0)
    h, w = newest.depth.shape
    k = newest.camera.intrinsics
    points = geometry.unproject(newest.depth, k).astype(np.float64)[..., :3]
    pixels = geometry.pixel_centers(h, w).astype(np.float64)
    out = flow.copy()

    def moved_pixels(m: np.ndarray, p: np.ndarray) -> np.ndarray:
        inverse = np.linalg.inv(m)
        back = p @ inverse[:3, :3].T + inverse[:3, 3]
        uvw = back @ k.T
        return uvw[:, :2] / np.maximum(uvw[:, 2:3], 1e-9)

    for oid in np.unique(newest.object_id):
        ys, xs = np.nonzero((newest.object_id == oid) & np.isfinite(newest.depth))
        if len(ys) < 20:
            continue
        pick = rng.choice(len(ys), min(len(ys), samples), replace=False)
        sy, sx = ys[pick], xs[pick]
        u = flow[sy, sx].astype(np.float64)
        target = pixels[sy, sx] + u
        qx = np.clip(np.round(sx + u[:, 0]).astype(int), 0, w - 1)
        qy = np.clip(np.round(sy + u[:, 1]).astype(int), 0, h - 1)
        z = depth_w[qy, qx]
        ok = np.isfinite(z)
        if ok.sum() < 6:
            continue
        q = target[ok]
        before = np.concatenate([q, np.ones((len(q), 1))], 1) @ np.linalg.inv(k).T * z[ok, None]
        now = points[sy[ok], sx[ok]]

        def inliers(m):
            return np.linalg.norm(moved_pixels(m, now) - q, axis=1) < tolerance

        still = inliers(np.eye(4))
        best, best_in = np.eye(4), still
        for _ in range(tries):
            pick3 = rng.choice(len(q), 3, replace=False)
            m = _rigid(before[pick3], now[pick3])
            found = inliers(m)
            if found.sum() > best_in.sum():
                best, best_in = m, found
        if best_in.sum() >= 3:
            best = _rigid(before[best_in], now[best_in])
            best_in = inliers(best)
        if still.sum() >= 0.9 * best_in.sum():
            best, best_in = np.eye(4), still
        if best_in.mean() >= 0.5:
            out[ys, xs] = (moved_pixels(best, points[ys, xs]) - pixels[ys, xs]).astype(np.float32)
    return out


class Precomputed:
    """A stand-in for the DIS object whose ``calc`` returns a flow already estimated (by the GPU's estimator):
    the rules then apply to that flow (not to ``regions``, which runs DIS on parts of the frame)."""

    def __init__(self, flow: np.ndarray) -> None:
        self.flow = flow

    def calc(self, luma_a, luma_b, _):
        if luma_a.shape != self.flow.shape[:2]:
            raise ValueError("the precomputed flow serves the whole frame only")
        return self.flow.copy()


class RuleFlow2D(Flow2D):
    """``flow2d`` with another rule between its optical flow (``estimator``: DIS, or the GPU's) and the
    extrapolation."""

    def __init__(self, rule: Rule, estimator: str = "dis") -> None:
        super().__init__(estimator="dis" if estimator.startswith("corr") else estimator)
        self.estimator = estimator
        self.rule = rule
        self._network = CorrFlowNetwork() if estimator.startswith("corr") else None

    def _prepare(self, state, timer):
        older, newest = state.history[-2], state.history[-1]
        src, dst = older.camera, newest.camera
        # frame n-k in frame n's view, holes filled (outside the holes the depth is the warp's)
        warped, depth_filled, holes = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index),
                                                      Timer())
        seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics,
                                    src.world_to_camera, older.depth.shape)
        factor = geometry.downsample_factor(newest.depth.shape[1], 480)
        low_n = geometry.downsample_frame(newest.color, newest.depth, dst.intrinsics, factor)
        low_p = geometry.downsample_frame(older.color, older.depth, src.intrinsics, factor)
        gate = np.zeros(newest.depth.shape, bool)
        for box in gate_boxes(GateConfig(), low_n, low_p, dst.world_to_camera, src.world_to_camera, 1):
            y0, y1, x0, x1 = full_box(box, factor, low_n[1].shape, gate.shape)
            gate[y0:y1, x0:x1] = True
        inv_n = np.where(np.isfinite(newest.depth), 1.0 / newest.depth, 0.0)
        inv_w = np.where(np.isfinite(depth_filled), 1.0 / np.maximum(depth_filled, 1e-30), 0.0)
        context = {"gate": gate, "revealed": ~holes & (inv_n < (1.0 - REVEAL_DROP) * inv_w),
                   "arrived": (~holes & (inv_n > 1.05 * inv_w)).astype(np.float64),
                   "newest": newest, "depth_w": np.where(holes, np.inf, depth_filled), "depth_filled": depth_filled,
                   "depth_change": ~holes & (np.abs(inv_n - inv_w) > DEPTH_CHANGE * np.maximum(inv_n, inv_w))}
        with timer("flow"):
            estimator = self._dis
            if self.estimator == "gl":
                estimator = Precomputed(self._gl_estimators()[0].estimate(newest.color, warped))
            elif self.estimator == "corr_alone":
                estimator = Precomputed(self._network.estimate(newest.color, warped, newest.depth, depth_filled))
            elif self.estimator == "corr":
                context["network"] = self._network.estimate(newest.color, warped, newest.depth, depth_filled)
                estimator = Precomputed(dis_calc(self._dis, luma8(newest.color), luma8(warped),
                                                 dis_start(context["network"])))
            flow = self.rule(estimator, luma8(newest.color), luma8(warped), seen, context)
        return self.state_of(newest, flow, timer)


def validation_sets(out: Path, wide: bool = False) -> dict[str, list[Path]]:
    """The validation sequences (module docstring), rendered on first use; ``wide``: twice as many (gentle
    seeds 1005-1008, the first 4 ``fast`` and 2 ``extreme`` seeds of the same rules), for choices the small
    set cannot tell apart."""
    size, more = (640, 360, 16), 2 if wide else 1
    return {"gentle": [render_set(out, f"seed{s}", {"seed": s}, *size) for s in range(1005, 1005 + 2 * more)],
            "fast": [p for _, p in speed_set(out, "valfast", "fast", 7201, 2 * more, (10.0, 35.0), *size)],
            "extreme": [p for _, p in speed_set(out, "valextreme", "extreme", 7301, more, (20.0, 80.0), *size)]}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/validation"))
    parser.add_argument("--variants", default="dis,confidence,seen,trusted,regions")
    parser.add_argument("--margin", type=float, default=1.0,
                        help="margin of 'confidence', 'not_worse' and 'region_check' (levels); sigma of 'blurred'; "
                             "pixels of support of 'depth_evidence'; log-depth margin of 'depth_consistent'")
    parser.add_argument("--small", type=float, default=SMALL_MOTION,
                        help="motion under this many px must be confident in 'trusted' and 'gated'")
    parser.add_argument("--k", default="2,4")
    parser.add_argument("--estimator", choices=("dis", "gl", "corr", "corr_alone"), default="dis",
                        help="the optical flow the rules apply to: OpenCV DIS, the GPU's, DIS from the correlation "
                             "network, the network alone (not with regions*)")
    parser.add_argument("--wide", action="store_true", help="the wider validation set (twice the sequences)")
    parser.add_argument("--json", type=Path, default=None)
    args = parser.parse_args(argv)
    variants = args.variants.split(",")
    available = rules(args.margin, args.small)
    for v in variants:
        if v not in available:
            parser.error(f"unknown variant '{v}', expected some of {', '.join(available)}")
        if args.estimator != "dis" and v.startswith("regions"):
            parser.error(f"variant '{v}' runs DIS on parts of the frame: not with --estimator {args.estimator}")
        if v == "network_veto" and args.estimator != "corr":
            parser.error("variant 'network_veto' reads the correlation network's estimate: --estimator corr")
        registry.METHODS[f"flow2d:{v}"] = lambda objects, rule=available[v]: RuleFlow2D(rule, args.estimator)
    rows, sets = [], validation_sets(args.out, args.wide)
    for set_name, paths in sets.items():
        sequences = [read_sequence(p) for p in paths]
        for k in (int(v) for v in args.k.split(",")):
            results = []
            for seq in sequences:
                results += evaluate_sequence(seq, ["reproject"] + [f"flow2d:{v}" for v in variants], k,
                                             with_flip=False)
            summary = summarize(results)
            base = summary[f"reproject/k={k}"]
            for v in variants:
                row = summary[f"flow2d:{v}/k={k}"]
                rows.append({"set": set_name, "k": k, "variant": v, "psnr": row["psnr"],
                             "psnr_moving": row["psnr_moving"], "epe_moving": row["epe_moving"],
                             "reproject_psnr": base["psnr"], "reproject_psnr_moving": base["psnr_moving"]})
                print(f"{set_name:8s} k={k} {v:11s} PSNR {row['psnr']:.2f}  moving {row['psnr_moving']:.2f}  "
                      f"EPE {row['epe_moving']:.2f}   (reproject {base['psnr']:.2f} / {base['psnr_moving']:.2f})",
                      flush=True)
    write_json(args.json, {"sets": {s: [p.name for p in ps] for s, ps in sets.items()}, "margin": args.margin,
                           "estimator": args.estimator,
                           "small": args.small, "rows": rows})


if __name__ == "__main__":
    main()
