"""Issue 43: where the no-vector path loses to `mvec`: estimation or extrapolation (2026-11-29 page's script).

Experiments, not engine code: each variant is a predictor made here and evaluated with ``interleave eval``'s
protocol (``engine.eval.protocol.evaluate_sequence``), or an end-point error of u(n -> n-k) against the
generator's truth. Conventions: ``engine/predict/base.py``; flows (H, W, 2) pixels, centres at +0.5.

``python docs/results/2026-11-29-no-vector-estimation.py scores SEQ[,SEQ...] K[,K...] VARIANTS OUT.json``
    VARIANTS: ``;``-separated engine method names (``reproject;flow2d;mvec``) and variants of this script:
    ``2d:SOURCE`` (``flow2d``'s pipeline: trust rule, 2D linear extrapolation, forward warp, fed the SOURCE's flow)
    and ``3d:SOURCE`` (the SOURCE's flow turned into motion vectors n -> n-k and run through ``mvec``: 3D velocity,
    the change of velocity, the same warp). SOURCE: ``true`` (the generator's exact u(n -> n-k)), ``dis``
    (OpenCV DIS medium, what ``flow2d`` uses), ``corr`` (DIS from the committed correlation network,
    ``flow2d[estimator=corr]``), ``segment:S`` (S, with every group of pixels that arrived since frame n-k
    given the translation of its best masked RGB-D template match, where it explains the pixel's
    neighbourhood better).
``python docs/results/2026-11-29-no-vector-estimation.py epe SEQ[,SEQ...] K[,K...] SOURCES OUT.json``
    SOURCES: ``,``-separated: ``dis``, ``dis@S`` (DIS with finest scale S), ``corr``, ``net`` (the network alone),
    ``net@W`` / ``corr@W`` (the network at working width W), ``net=PATH.onnx`` / ``corr=PATH.onnx`` (another
    exported network), ``warm:SOURCE`` (also DIS from the previous interval's flow continued at constant
    velocity; per pixel the candidate with the lower 9x9 luma error), ``fuse`` (per pixel, ``corr`` or ``dis``,
    whichever has the lower 15x15 luma + 4 x depth-code error). Mean EPE over moving pixels of every frame
    pair (from the second interval on, so ``warm`` has a start) and the share under 3 px.
"""
from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np

from engine import geometry
from engine.eval.protocol import evaluate_sequence
from engine.io.rgbd import read_sequence
from engine.predict.base import Target, Timer, true_object_flow, warp_fill_depth
from engine.predict.classic import Flow2D
from engine.predict.corrflow import CorrFlowNetwork, depth_code, depth_reference, dis_start
from engine.predict.dis import dis_calc, dis_estimator, drop_untrusted, encode8, luma8
from engine.predict.mvec import Mvec
from engine.predict.registry import use_backend

sys.path.insert(0, str(Path(__file__).resolve().parents[2]))
from tools.heldout import set_rows  # noqa: E402


# ---------------------------------------------------------------- flow sources: (state, older, newest, warped, depth_w)
def source_of(spec: str, objects: dict, cache: dict):
    """A flow source by name (module docstring); ``cache`` keeps networks and DIS objects per name."""
    if spec == "true":
        return lambda st, older, newest, w, d: true_object_flow(newest, objects, older.index)[..., :2]
    if spec.startswith("dis"):
        scale = int(spec.split("@")[1]) if "@" in spec else None
        dis = cache.setdefault(spec, dis_estimator("medium", scale))
        return lambda st, older, newest, w, d: dis_calc(dis, luma8(newest.color), luma8(w))
    if spec.startswith(("corr", "net")):
        name, _, path = spec.partition("=")
        name, _, width = name.partition("@")
        net = cache.setdefault(f"net={path}@{width}", CorrFlowNetwork(path or None))
        if width:
            net.working_width = int(width)
        dis = cache.setdefault("dis", dis_estimator("medium"))

        def run(st, older, newest, w, d):
            start = net.estimate(newest.color, w, newest.depth, d)
            return start if name == "net" else dis_calc(dis, luma8(newest.color), luma8(w), dis_start(start))
        return run
    if spec.startswith("warm:"):
        return warm_source(source_of(spec[5:], objects, cache), cache.setdefault("dis", dis_estimator("medium")))
    if spec.startswith("segment:"):
        return segment_source(source_of(spec[8:], objects, cache))
    if spec == "fuse":
        return fuse_source([source_of("corr", objects, cache), source_of("dis@1", objects, cache)])
    raise SystemExit(f"unknown source {spec!r}")


def sampled(image: np.ndarray, flow: np.ndarray, border: float) -> np.ndarray:
    """``image`` (H, W) float32 at p + flow(p), bilinear; ``border`` outside."""
    h, w = image.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float32)
    return cv2.remap(image, xs + flow[..., 0], ys + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT,
                     borderValue=border)


def luma_error(flow, luma_n, luma_w, window=9):
    """Box-filtered |luma(n) - luma(warped n-k at p + u)|."""
    s = sampled(luma_w.astype(np.float32), flow, -1e4)
    err = np.where(s < -1, 64.0, np.abs(s - luma_n.astype(np.float32))).astype(np.float32)
    return cv2.blur(err, (window, window))


def camera_positions(depth_o, cam_o, cam_n):
    """(H, W, 2) where each pixel of frame n-k lands in frame n by camera motion alone, and its depth there."""
    h, w = depth_o.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    z = np.where(np.isfinite(depth_o), depth_o, 1e9).astype(np.float64)
    ko, kn = cam_o.intrinsics, cam_n.intrinsics
    pts = np.stack([(xs + 0.5 - ko[0, 2]) / ko[0, 0] * z, (ys + 0.5 - ko[1, 2]) / ko[1, 1] * z, z, np.ones_like(z)], -1)
    pts = pts @ (cam_n.world_to_camera @ cam_o.camera_to_world).T
    return np.stack([kn[0, 0] * pts[..., 0] / pts[..., 2] + kn[0, 2], kn[1, 1] * pts[..., 1] / pts[..., 2] + kn[1, 2]],
                    -1), pts[..., 2]


def warm_start(prev_flow, depth_o, cam_o, cam_n, radius=2):
    """Frame n-k's u(n-k -> n-2k) continued at constant velocity into frame n's view: each moving pixel lands at
    its camera position minus its flow, carrying its flow (the nearest wins), splatted (2 radius + 1)^2."""
    h, w = depth_o.shape
    out, zbuf = np.zeros((h, w, 2), np.float32), np.full((h, w), np.inf)
    mov = np.flatnonzero(np.any(prev_flow.reshape(-1, 2) != 0, axis=1))
    if not mov.size:
        return out
    pos, zn = camera_positions(depth_o, cam_o, cam_n)
    val = prev_flow.reshape(-1, 2)[mov]
    pos, zn = pos.reshape(-1, 2)[mov] - val, zn.reshape(-1)[mov]
    order = np.argsort(-zn)
    pos, zn, val = pos[order], zn[order], val[order]
    for dy in range(-radius, radius + 1):
        for dx in range(-radius, radius + 1):
            j, i = np.floor(pos[:, 0]).astype(int) + dx, np.floor(pos[:, 1]).astype(int) + dy
            ok = (i >= 0) & (i < h) & (j >= 0) & (j < w)
            ii, jj, zz = i[ok], j[ok], zn[ok]
            take = zz <= zbuf[ii, jj] * (1 + 1e-6) if (dx or dy) else np.ones(ii.size, bool)
            out[ii[take], jj[take]] = val[ok][take]
            zbuf[ii[take], jj[take]] = np.minimum(zbuf[ii[take], jj[take]], zz[take])
    return out


def warm_source(cold, dis):
    def run(st, older, newest, w, d):
        ln, lw = luma8(newest.color), luma8(w)
        flow = cold(st, older, newest, w, d)
        prev = st.get("previous")
        if prev is not None and prev[0] == older.index and prev[1].shape == flow.shape:
            start = warm_start(prev[1], older.depth, older.camera, newest.camera)
            if np.any(start != 0):
                warm = dis_calc(dis, ln, lw, dis_start(start))
                flow = np.where((luma_error(warm, ln, lw) < luma_error(flow, ln, lw))[..., None], warm, flow)
        st["previous"] = (newest.index, np.asarray(flow, np.float32).copy())
        return flow
    return run


def rgbd8(color, depth, ref):
    return np.dstack([encode8(color).astype(np.float32), depth_code(depth, ref) * 255.0]).astype(np.float32)


def match_component(img_n, img_w, mask, stat, radius, scale=2):
    """Best translation of frame n's masked RGB-D template (bounding box ``stat``) in the warped n-k: masked SQDIFF
    at 1/scale over +-radius, then at full resolution +-(scale + 1)."""
    x, y, w, h = (int(v) for v in stat[:4])
    H, W = mask.shape

    def search(a, b, m, cx, cy, r, s):
        x0, y0, x1, y1 = x // s, y // s, -(-(x + w) // s), -(-(y + h) // s)
        tpl, msk = a[y0:y1, x0:x1], m[y0:y1, x0:x1]
        if msk.sum() < 4:
            return None
        sx0, sy0 = max(0, x0 + cx - r), max(0, y0 + cy - r)
        sx1, sy1 = min(b.shape[1], x1 + cx + r), min(b.shape[0], y1 + cy + r)
        if sx1 - sx0 < tpl.shape[1] or sy1 - sy0 < tpl.shape[0]:
            return None
        res = cv2.matchTemplate(b[sy0:sy1, sx0:sx1], tpl, cv2.TM_SQDIFF, mask=np.repeat(msk[..., None], 4, -1))
        _, _, loc, _ = cv2.minMaxLoc(res)
        return sx0 + loc[0] - x0, sy0 + loc[1] - y0

    small = [cv2.resize(v, (W // scale, H // scale), interpolation=cv2.INTER_AREA) for v in (img_n, img_w)]
    msmall = (cv2.resize(mask.astype(np.float32), (W // scale, H // scale), interpolation=cv2.INTER_AREA) > 0.5)
    coarse = search(*small, msmall.astype(np.float32), 0, 0, radius // scale, scale)
    if coarse is None:
        return None
    return search(img_n, img_w, mask.astype(np.float32), coarse[0] * scale, coarse[1] * scale, scale + 1, 1)


def segment_source(inner, band=1.1, min_pixels=16, radius_share=0.35):
    def run(st, older, newest, w, d):
        flow = inner(st, older, newest, w, d)
        ref = depth_reference(newest.depth)
        a, b = rgbd8(newest.color, newest.depth, ref), rgbd8(w, d, ref)
        arrived = np.isfinite(newest.depth) & (~np.isfinite(d) | (newest.depth * band < d))
        count, labels, stats, _ = cv2.connectedComponentsWithStats(arrived.astype(np.uint8), connectivity=8)
        cand, has = np.zeros_like(flow), np.zeros(flow.shape[:2], bool)
        for i in range(1, count):
            if stats[i, cv2.CC_STAT_AREA] < min_pixels:
                continue
            mask = labels == i
            found = match_component(a, b, mask, stats[i], int(radius_share * max(newest.depth.shape)))
            if found is not None:
                cand[mask], has = found, has | mask
        ln, lw = luma8(newest.color), luma8(w)
        better = has & (luma_error(cand, ln, lw) < luma_error(flow, ln, lw))
        return np.where(better[..., None], cand, flow)
    return run


def fuse_source(sources, window=15, weight=4.0):
    def run(st, older, newest, w, d):
        flows = [np.asarray(s(st, older, newest, w, d), np.float32) for s in sources]
        ln, lw = luma8(newest.color).astype(np.float32), luma8(w).astype(np.float32)
        ref = depth_reference(newest.depth)
        cn, cw = depth_code(newest.depth, ref) * 255, depth_code(d, ref) * 255
        costs = []
        for f in flows:
            s = sampled(lw, f, -1e4)
            h, wd = cw.shape
            ys, xs = np.mgrid[0:h, 0:wd].astype(np.float32)
            c = cv2.remap(cw, xs + f[..., 0], ys + f[..., 1], cv2.INTER_NEAREST, borderMode=cv2.BORDER_REPLICATE)
            err = np.where(s < -1, 64.0, np.abs(s - ln) + weight * np.abs(c - cn)).astype(np.float32)
            costs.append(cv2.blur(err, (window, window)))
        pick = np.argmin(np.stack(costs), axis=0)
        return np.take_along_axis(np.stack(flows), pick[None, ..., None], 0)[0]
    return run


# ---------------------------------------------------------------- the two pipelines
def flow_vectors(flow, depth_n, depth_w, cam_n, cam_o):
    """Motion vectors n -> n-k (camera motion included, NaN for sky) from u(n -> warped n-k): a pixel with a
    flow goes where the warped n-k's surface at p + u (nearest pixel; its depth in frame n's view) was in
    frame n-k's image; a pixel without one where its own point was (the camera's motion alone)."""
    h, w = depth_n.shape
    ys, xs = np.mgrid[0:h, 0:w].astype(np.float64)
    px, py = xs + 0.5, ys + 0.5
    qx, qy = px + flow[..., 0], py + flow[..., 1]
    zq = depth_w[np.clip(np.floor(qy).astype(int), 0, h - 1), np.clip(np.floor(qx).astype(int), 0, w - 1)]
    ok = np.any(flow != 0, axis=-1) & np.isfinite(zq) & (zq > 0)
    z = np.where(ok, zq, np.where(np.isfinite(depth_n), depth_n, 1.0)).astype(np.float64)
    ux, uy = np.where(ok, qx, px), np.where(ok, qy, py)
    kn, ko = cam_n.intrinsics, cam_o.intrinsics
    pts = np.stack([(ux - kn[0, 2]) / kn[0, 0] * z, (uy - kn[1, 2]) / kn[1, 1] * z, z, np.ones_like(z)], -1)
    po = pts @ (cam_o.world_to_camera @ cam_n.camera_to_world).T
    vec = np.stack([ko[0, 0] * po[..., 0] / po[..., 2] + ko[0, 2] - px, ko[1, 1] * po[..., 1] / po[..., 2] + ko[1, 2] - py],
                   -1).astype(np.float32)
    vec[~np.isfinite(depth_n)] = np.nan
    return vec


def _warped_and_flow(predictor, source, state, timer):
    older, newest = state.history[-2], state.history[-1]
    warped, depth_w, _ = predictor.frames.warp_fill_depth(predictor.frames.resident(older, timer),
                                                          Target(newest.camera, newest.time, newest.index), timer)
    flow = np.ascontiguousarray(source(predictor.source_state, older, newest, warped, depth_w), np.float32)
    src, dst = older.camera, newest.camera
    seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics,
                                src.world_to_camera, older.depth.shape)
    drop_untrusted(flow, luma8(newest.color), luma8(warped), seen)  # flow2d's trust rule
    return older, newest, depth_w, flow


class Given2D(Flow2D):
    """``flow2d``'s pipeline on a given source's flow."""

    def __init__(self, source):
        super().__init__()
        self.source, self.source_state = source, {}

    def _prepare(self, state, timer):
        _, newest, _, flow = _warped_and_flow(self, self.source, state, timer)
        return self.state_of(newest, flow, timer)


class Given3D(Mvec):
    """``mvec``'s passes on motion vectors made from a given source's flow (``flow_vectors``); frame n-k's vectors
    are those made at its own preparation."""

    def __init__(self, source):
        super().__init__()
        self.source, self.source_state, self.made = source, {}, {}

    def _prepare(self, state, timer):
        older, newest, depth_w, flow = _warped_and_flow(self, self.source, state, timer)
        vectors = flow_vectors(flow, newest.depth, depth_w, newest.camera, older.camera)
        self.made = {key: v for key, v in self.made.items() if key == (older.index, older.time)}
        self.made[(newest.index, newest.time)] = vectors
        history = [dataclasses.replace(f, motion_vectors=self.made.get((f.index, f.time))) for f in state.history]
        return super()._prepare(dataclasses.replace(state, history=history), timer)


def scores(folders, ks, variants, out):
    rows = []
    for folder in folders:
        seq = read_sequence(folder)
        objects, cache = {o.id: o for o in seq.objects}, {}
        given = {}
        for v in variants:
            if v.startswith(("2d:", "3d:")):
                kind = Given2D if v.startswith("2d:") else Given3D
                given[v] = use_backend(kind(source_of(v[3:], objects, cache)), "cpu")
        for k in ks:
            given = {v: use_backend(type(p)(p.source), "cpu") for v, p in given.items()}  # fresh state per k
            res = evaluate_sequence(seq, variants, k, with_flip=False, max_groups=4, predictors=given)
            part = set_rows(Path(folder).name, res, variants, [k], ("psnr", "psnr_moving", "epe_moving", "ms_per_frame"))
            for r in part:
                print(f"{r['set']:24s} k={k} {r['method']:28s} {r['psnr']:6.2f} {r['psnr_moving']:6.2f}", flush=True)
            rows += [{key: v for key, v in r.items() if key != "records"} for r in part]
    Path(out).write_text(json.dumps(rows, indent=1))


def epe(folders, ks, specs, out):
    rows = []
    for k in ks:
        for folder in folders:
            seq = read_sequence(folder)
            objects, cache = {o.id: o for o in seq.objects}, {}
            sources = {s: source_of(s, objects, cache) for s in specs}
            states = {s: {} for s in specs}
            errors = {s: [] for s in specs}
            for b in range(k, len(seq), k):
                older, newest = seq[b - k], seq[b]
                warped, depth_w, _ = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index), Timer())
                truth = true_object_flow(newest, objects, older.index)[..., :2]
                moving = np.any(truth != 0, axis=-1)
                for s in specs:
                    flow = sources[s](states[s], older, newest, warped, depth_w)
                    if b >= 2 * k and moving.sum() >= 50:
                        e = np.linalg.norm(flow - truth, axis=-1)[moving]
                        errors[s].append((float(e.mean()), float((e < 3).mean())))
            for s in specs:
                v = np.array(errors[s])
                rows.append({"sequence": Path(folder).name, "k": k, "source": s, "pairs": len(v),
                             "epe_moving": float(v[:, 0].mean()), "under_3px": float(v[:, 1].mean())})
                print(f"k={k} {Path(folder).name:24s} {s:32s} EPE {v[:, 0].mean():6.2f} <3px {100 * v[:, 1].mean():5.1f}%",
                      flush=True)
    Path(out).write_text(json.dumps(rows, indent=1))


if __name__ == "__main__":
    mode, seqs, ks, what, out = sys.argv[1:6]
    folders, ks = seqs.split(","), [int(x) for x in ks.split(",")]
    if mode == "scores":
        scores(folders, ks, what.split(";"), out)
    else:
        epe(folders, ks, what.split(","), out)
