"""The GL flow's configurations on this machine (Mesa llvmpipe): per configuration, the compute dispatches of one
estimate (``dispatch_counts``), the wall ms per estimate, llvmpipe's ms per pass (a ``glFinish`` after every
dispatch, timed on the CPU: a proxy, not a GPU's time; llvmpipe's timer queries read 0), and the flow's
difference from the first configuration's.

``PYTHONPATH=. python docs/results/2026-11-28-gpu-flow-search.py OUT.json SEQUENCE... [--repeats 2]``
(sequences: folders of ``tools.bench_gl_flow``'s renders; pairs (n, n-2) for n = 4, 9, 14)
"""
from __future__ import annotations

import argparse
import json
import statistics
import time

import numpy as np

from engine.geometry.backends.gl.context import GlContext
from engine.geometry.backends.gl.flow import GlFlowConfig, GlOpticalFlow, dispatch_counts
from engine.io.rgbd import read_sequence

CONFIGS = {  # label -> GlFlowConfig
    "before (every level by its passes)": GlFlowConfig(search="thread", sor="passes", coarse_pixels=0),
    "flow_coarse (levels <= 8192 px)": GlFlowConfig(search="thread", sor="passes", coarse_pixels=8192),
    "flow_refine_tile": GlFlowConfig(search="thread", sor="tile", coarse_pixels=0),
    "both (the GPU's defaults, thread search)": GlFlowConfig(search="thread", sor="tile", coarse_pixels=8192),
}


def per_pass_ms(estimator: GlOpticalFlow, pairs: list) -> dict:
    """{pass: ms per estimate}, each dispatch followed by glFinish and timed on the CPU."""
    original, totals = GlContext.dispatch_groups, {}

    def timed(self, program, groups, uniforms=None):
        start = time.perf_counter()
        original(self, program, groups, uniforms)
        self.ctx.finish()
        name = self._pass_names.get(id(program), "?")
        totals[name] = totals.get(name, 0.0) + 1e3 * (time.perf_counter() - start)

    GlContext.dispatch_groups = timed
    try:
        for a, b in pairs:
            estimator.estimate(a, b)
    finally:
        GlContext.dispatch_groups = original
    return {name: ms / len(pairs) for name, ms in sorted(totals.items(), key=lambda kv: -kv[1])}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("out")
    parser.add_argument("sequences", nargs="+")
    parser.add_argument("--repeats", type=int, default=2)
    args = parser.parse_args()
    pairs = []
    for folder in args.sequences:
        frames = list(read_sequence(folder))
        pairs += [(frames[n].color, frames[n - 2].color) for n in (4, 9, 14) if n < len(frames)]
    shape = pairs[0][0].shape[:2]
    doc = {"renderer": GlOpticalFlow().gl.renderer, "shape": list(shape), "pairs": len(pairs), "rows": {}}
    first = None
    for label, config in CONFIGS.items():
        estimator = GlOpticalFlow(config=config)
        estimator.estimate(*pairs[0])  # programs compiled
        walls, flows = [], []
        for _ in range(args.repeats):
            flows = []
            for a, b in pairs:
                start = time.perf_counter()
                flows.append(estimator.estimate(a, b))
                walls.append(1e3 * (time.perf_counter() - start))
        passes = per_pass_ms(estimator, pairs)
        estimator.release()
        first = flows if first is None else first
        diff = np.concatenate([np.abs(f - g).max(axis=-1).ravel() for f, g in zip(flows, first)])
        row = doc["rows"][label] = {
            "dispatches": sum(dispatch_counts(shape, config, True).values()),
            "wall_ms": statistics.median(walls), "llvmpipe_pass_ms": passes,
            "diff_px": {"p99": float(np.percentile(diff, 99)), "max": float(diff.max())}}
        print(label, row["dispatches"], f"{row['wall_ms']:.1f}", {k: round(v, 1) for k, v in passes.items()},
              row["diff_px"], flush=True)
    with open(args.out, "w") as f:
        json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
