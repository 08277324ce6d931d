"""The GL flow's two inverse searches compared (page 2026-11-27-gl-flow-cooperative-search.md).

python docs/results/2026-11-27-gl-flow-cooperative-search.py passes SEQ OUT.json
    one dispatch of each pass (``flow_patch``, ``flow_patch_group``) on the 8-bit lumas of frames 4 and 2 of
    SEQ, from random start flows (sd 3 px), with and without propagation: how many patches agree
    (run from the repository root)
python docs/results/2026-11-27-gl-flow-cooperative-search.py estimates SEQ... OUT.json
    ``GlOpticalFlow.estimate`` of frame 4 -> frame 2 with each search: the flows' difference and the wall ms
python docs/results/2026-11-27-gl-flow-cooperative-search.py eval SEARCH EVAL_ARGS...
    ``interleave eval`` with every ``flow2d[estimator=gl]`` running the given search
"""
import json
import sys
import time

import numpy as np

from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.flow import PATCH_LANES, GlFlowConfig, GlOpticalFlow
from engine.geometry.backends.gl.reference import patch_origins
from engine.io.rgbd import read_sequence
from engine.predict.dis import luma8


def passes(seq: str, out: str) -> None:
    frames = list(read_sequence(seq))
    first, second = luma8(frames[4].color).astype(np.float32), luma8(frames[2].color).astype(np.float32)
    size, patch, stride, iterations = first.shape, 8, 3, 16
    rows, cols = (patch_origins(n, patch, stride).size for n in size)
    rng = np.random.default_rng(0)
    gl = glb.shared_context()
    doc = {"sequence": seq, "patches": rows * cols, "iterations": iterations, "runs": []}
    for propagate in (False, True):
        shape = (rows, cols, 2) if propagate else size + (2,)
        start = rng.normal(0, 3, shape).astype(np.float32)
        result = {}
        for name, lanes in (("flow_patch", 1), ("flow_patch_group", PATCH_LANES)):
            def run():
                zero = np.zeros(2, np.float32)
                data = {1: first, 3: second, 4: zero if propagate else start, 8: start if propagate else zero}
                bound = {b: gl.ctx.buffer(np.ascontiguousarray(a)) for b, a in data.items()}
                bound[5] = gl.ctx.buffer(reserve=8 * rows * cols)
                for binding, buf in bound.items():
                    buf.bind_to_storage_buffer(binding)
                defines = {"PATCH": patch, "LANES": PATCH_LANES, **({"PROPAGATE": 1} if propagate else {})}
                gl.dispatch(gl.program(name, defines), rows * cols * lanes,
                            {"size": size, "offset": 0, "stride": stride, "iterations": iterations})
                flows = np.frombuffer(bound[5].read(), np.float32).reshape(rows, cols, 2)
                for buf in bound.values():
                    buf.release()
                return flows
            result[name] = gl.call(run)
        d = np.abs(result["flow_patch"] - result["flow_patch_group"]).max(axis=-1)
        doc["runs"].append({"propagate": propagate, "max_px": float(d.max()),
                            **{f"share_over_{t}": float((d > float(t)).mean()) for t in ("0.001", "0.01", "0.5")}})
        print(doc["runs"][-1])
    json.dump(doc, open(out, "w"), indent=1)


def estimates(seqs: list, out: str) -> None:
    doc = []
    for seq in seqs:
        frames = list(read_sequence(seq))
        a, b = frames[4].color, frames[2].color
        flows, ms = {}, {}
        for search in ("thread", "group"):
            est = GlOpticalFlow(config=GlFlowConfig(search=search))
            est.estimate(a, b)
            start = time.perf_counter()
            flows[search] = est.estimate(a, b)
            ms[search] = 1e3 * (time.perf_counter() - start)
        d = np.abs(flows["thread"] - flows["group"]).max(axis=-1)
        doc.append({"sequence": seq, "wall_ms": ms, "max_px": float(d.max()), "share_over_0.01": float((d > 0.01).mean()),
                    "share_over_0.1": float((d > 0.1).mean()), "mean_abs_flow": float(np.abs(flows["thread"]).mean())})
        print(doc[-1])
    json.dump({"renderer": glb.shared_context().renderer, "pairs": doc}, open(out, "w"), indent=1)


def eval_with(search: str, args: list) -> int:
    from engine.geometry.backends.gl.trust import GlTrust
    from engine.predict import classic
    from engine.predict.dis import CONFIDENCE_MARGIN, CONFIDENCE_WINDOW, SMALL_MOTION

    classic.gl_flow_estimators = lambda: (GlOpticalFlow(config=GlFlowConfig(search=search)),
                                          GlTrust(SMALL_MOTION, CONFIDENCE_MARGIN, CONFIDENCE_WINDOW))
    from engine.cli import main
    return main(args)


if __name__ == "__main__":
    mode = sys.argv[1]
    if mode == "passes":
        passes(sys.argv[2], sys.argv[3])
    elif mode == "estimates":
        estimates(sys.argv[2:-1], sys.argv[-1])
    else:
        sys.exit(eval_with(sys.argv[2], sys.argv[3:]))
