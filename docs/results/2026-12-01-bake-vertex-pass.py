"""The bake's vertex occupancy pass timed: brick by brick (the code it replaced, kept here) against once per vertex.

    PYTHONPATH=. python docs/results/2026-12-01-bake-vertex-pass.py RUN RESOLUTION [REPEATS]

RUN is a dynamic run trained to bake (``--config configs/dynamic-baked.json``). Prints one JSON line: process CPU
seconds of each pass per repeat (alternating), whether they find the same bricks, and the whole ``bake_dynamic``.
"""
import json
import sys
import time

import numpy as np
import torch

from models.fields.bake import _raw_outputs, _vertex_occupancy, bake_dynamic
from models.fields.train_dynamic import load_dynamic_model


def brick_by_brick(field, resolution: int, threshold: float, chunk: int = 1 << 16) -> torch.Tensor:
    """The replaced pass: every brick's 5^3 vertices evaluated on their own (shared vertices up to 8 times)."""
    bricks = resolution // 4
    axis = torch.arange(bricks)
    cells = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    occupied = torch.zeros(cells.shape[0], dtype=torch.bool)
    step = max(1, chunk // 125)
    local = torch.arange(5, dtype=torch.float64)
    offsets = torch.stack(torch.meshgrid(local, local, local, indexing="ij"), dim=-1)
    for i in range(0, cells.shape[0], step):
        vertex = cells[i:i + step].double()[:, None, None, None, :] * 4 + offsets
        raw, _ = _raw_outputs(field, (vertex * (2.0 / resolution) - 1.0).float(), chunk)
        occupied[i:i + step] = raw.reshape(raw.shape[0], -1).amax(dim=-1) >= threshold
    return occupied.reshape(bricks, bricks, bricks)


def main(run: str, resolution: str, repeats: str = "1") -> None:
    torch.set_num_threads(1)
    res = int(resolution)
    model = load_dynamic_model(run).eval()
    field = model.field.canonical_field
    threshold = float(np.log(model.occupancy_threshold()))
    out = {"run": run, "resolution": res, "vertex_pass_cpu_s": [], "brick_by_brick_cpu_s": []}
    for _ in range(int(repeats)):
        c = time.process_time()
        new = _vertex_occupancy(field, res, threshold, 1 << 16)
        out["vertex_pass_cpu_s"].append(time.process_time() - c)
        c = time.process_time()
        old = brick_by_brick(field, res, threshold)
        out["brick_by_brick_cpu_s"].append(time.process_time() - c)
    out["same_bricks"] = bool(torch.equal(new, old))
    out["occupied_fraction"] = float(new.float().mean())
    c = time.process_time()
    bake_dynamic(model, res)
    out["bake_dynamic_cpu_s"] = time.process_time() - c
    out["median_ratio"] = float(np.median(out["brick_by_brick_cpu_s"]) / np.median(out["vertex_pass_cpu_s"]))
    print(json.dumps(out))


if __name__ == "__main__":
    main(*sys.argv[1:])
