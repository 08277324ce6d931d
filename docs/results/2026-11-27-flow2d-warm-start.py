"""Experiment (issue 23, EPE): flow2d with DIS warm-started from the previous interval's flow.

The previous preparation's trusted flow u(n-k -> n-2k) (frame n-k's pixels) is carried to frame n under
constant velocity: each point of frame n-k is reprojected into camera n and moved by -u (its object motion over
one interval), and carries u there (the engine's forward splat, ``geometry.forward_warp_frame``, with the flow as
its colour); DIS then starts from that field (0 where nothing landed). Trust rules, extrapolation and render are
flow2d's. Variants: ``flow2d_warm`` (DIS from the carried flow), ``flow2d_warm_min`` (only carried motion of at
least MIN px). Scores via engine.eval.protocol with make_predictor patched.
Usage: python warm.py OUT.json SEQ..."""
import json, sys
import numpy as np
from engine import geometry
from engine.io.rgbd import read_sequence
from engine.predict import make_predictor as _make
from engine.predict.base import Target
from engine.predict.classic import Flow2D
from engine.predict.corrflow import dis_start
from engine.predict.dis import dis_calc, drop_untrusted, luma8
from engine.predict.registry import use_backend
import engine.eval.protocol as protocol


class WarmFlow2D(Flow2D):
    def __init__(self, min_motion=0.0):
        super().__init__()
        self._last = None  # (frame index, frame, trusted flow u(n -> n-k))
        self.min_motion = min_motion

    def _initial(self, older, newest):
        if self._last is None or self._last[0] != older.index:
            return None
        _, frame, flow = self._last
        if not np.any(flow):
            return None
        src, dst = frame.camera, newest.camera
        carried = np.zeros(flow.shape[:2] + (3,), np.float32)
        carried[..., :2] = flow
        moved, _, holes = geometry.forward_warp_frame(carried, frame.depth, src.intrinsics, src.world_to_camera,
                                                      dst.intrinsics, dst.world_to_camera, -flow)
        init = np.ascontiguousarray(moved[..., :2])
        init[holes] = 0.0
        return dis_start(init, self.min_motion) if self.min_motion > 0 else init

    def _prepare(self, state, timer):
        older, newest = state.history[-2], state.history[-1]
        target = Target(newest.camera, newest.time, newest.index)
        warped, _ = self.frames.warp_and_fill(self.frames.resident(older, timer), target, timer)
        luma_n, luma_w = luma8(newest.color), luma8(warped)
        with timer("flow"):
            init = self._initial(older, newest)
            flow = dis_calc(self._dis, luma_n, luma_w, init)
        with timer("trust"):
            src, dst = older.camera, newest.camera
            seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics,
                                        src.world_to_camera, older.depth.shape)
            drop_untrusted(flow, luma_n, luma_w, seen)
        self._last = (newest.index, newest, flow.copy())
        return self.state_of(newest, flow, timer)


def patched(name, objects=None, backend="auto", **kw):
    if name == "flow2d_warm":
        return use_backend(WarmFlow2D(), backend)
    if name == "flow2d_warm_min":
        return use_backend(WarmFlow2D(2.0), backend)
    return _make(name, objects, backend=backend, **kw)


protocol.make_predictor = patched
out = {}
methods = ["reproject", "flow2d", "flow2d_warm", "flow2d_warm_min", "oracle"]
for path in sys.argv[2:]:
    seq = read_sequence(path)
    for k in (2, 4):
        for r in protocol.evaluate_sequence(seq, methods, k, with_flip=False, backend="cpu"):
            d = {"psnr": r.psnr, "psnr_moving": r.psnr_moving, "ms": r.ms_per_frame, "epe": r.epe_moving}
            out.setdefault(path.rstrip("/").split("/")[-1], {}).setdefault(str(k), {})[r.method] = d
            print(path.rstrip("/").split("/")[-1], k, r.method, {a: round(b, 3) for a, b in d.items()}, flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
