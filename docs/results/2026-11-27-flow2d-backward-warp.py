"""Experiment (issue 23, speed): flow2d's preparation with frame n-k BACKWARD-warped into frame n's view
(frame n's depth reprojected into camera n-k, frame n-k's colour sampled bilinearly there; pixels that
land outside frame n-k take frame n's own colour) instead of the forward warp + hole fill. DIS, trust rules
and render unchanged. Scores via engine.eval.protocol with make_predictor patched."""
import json, sys
import cv2
import numpy as np
from engine import geometry
from engine.io.rgbd import read_sequence
from engine.predict import make_predictor as _make
from engine.predict.classic import Flow2D
from engine.predict.dis import dis_calc, luma8, trusted_motion
from engine.predict.registry import use_backend
import engine.eval.protocol as protocol


def backward_warp(older, newest):
    uv, _, valid = geometry.reproject(newest.depth, newest.camera.intrinsics, newest.camera.world_to_camera,
                                      older.camera.intrinsics, older.camera.world_to_camera)
    h, w = older.depth.shape
    mx = np.where(valid, uv[..., 0] - 0.5, -10.0).astype(np.float32)
    my = np.where(valid, uv[..., 1] - 0.5, -10.0).astype(np.float32)
    sampled = cv2.remap(older.color, mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
    covered = valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)
    return np.where(covered[..., None], sampled, newest.color), covered


class BackPrep(Flow2D):
    def _prepare(self, state, timer):
        older, newest = state.history[-2], state.history[-1]
        with timer("warp"):
            warped, seen = backward_warp(older, newest)
        luma_n, luma_w = luma8(newest.color), luma8(warped)
        with timer("flow"):
            flow = dis_calc(self._dis, luma_n, luma_w)
        with timer("trust"):
            flow[~trusted_motion(luma_n, luma_w, flow, seen)] = 0.0
        return self.state_of(newest, flow, timer)


def patched(name, objects=None, backend="auto", **kw):
    if name == "flow2d_back":
        return use_backend(BackPrep(), backend)
    return _make(name, objects, backend=backend, **kw)


protocol.make_predictor = patched
out = {}
for path in sys.argv[2:]:
    seq = read_sequence(path)
    for k in (2, 4):
        for r in protocol.evaluate_sequence(seq, ["reproject", "flow2d", "flow2d_back"], k, with_flip=False, backend="cpu"):
            d = {"psnr": r.psnr, "psnr_moving": r.psnr_moving, "ms": r.ms_per_frame, "epe": r.epe_moving}
            out.setdefault(path.rstrip("/").split("/")[-1], {}).setdefault(str(k), {})[r.method] = d
            print(path.rstrip("/").split("/")[-1], k, r.method, {a: round(b, 3) for a, b in d.items()}, flush=True)
json.dump(out, open(sys.argv[1], "w"), indent=1)
