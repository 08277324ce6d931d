"""Time the engine's shipped networks as the engine runs them: onnxruntime on the CPU against the torch runner
(``engine.predict.torch_onnx``) on each device asked for, at each network's working size for a 16:9 frame.

``python -m tools.bench_net_runner [--devices cpu,cuda] [--repeats 20] [--json FILE]``

Per network (``corrflow``: ``flow2d[estimator=corr]``'s and ``decomp``'s motion network; ``flow3d``: ``decomp``'s 3D
flow over one full-frame box; ``infill``: ``decomp``'s infilling network): the median wall ms of a call (numpy in,
numpy out, so uploads and readbacks included, as the engine sees it) over ``--repeats`` calls after 3 warm-up
calls, its ratio to onnxruntime's on the CPU in the same run, and the largest difference of the runner's output
from onnxruntime's (the parity of the path). Inputs are random in the ranges the engine feeds (``graph_feeds``).
A device torch cannot use is reported as skipped, not as an error.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from engine.weights import CORRFLOW
from tools.heldout import write_json

WEIGHTS = CORRFLOW.parent
#: the networks timed (``flow2d.onnx`` is the 2D ablation, not run by default)
NETWORKS = ("corrflow", "flow3d", "infill")


def graph_feeds(path: Path, rows: int, cols: int, seed: int = 0) -> dict:
    """Inputs of the graph's declared shapes (``batch`` 1, ``N*rows`` / ``N*cols`` scaled by ``rows`` / ``cols``),
    in the ranges the engine feeds: colour in [0, 1], depths 1-5, alpha and holes 0/1, sorted plane depths, flows
    of a few pixels."""
    import onnx
    from onnx import helper

    rng = np.random.default_rng(seed)
    feeds = {}
    for value in onnx.load(str(path)).graph.input:
        dims = []
        for d in value.type.tensor_type.shape.dim:
            if d.dim_value:
                dims.append(d.dim_value)
            elif d.dim_param == "batch":
                dims.append(1)
            else:
                factor, name = d.dim_param.split("*")
                dims.append(int(factor) * {"rows": rows, "cols": cols}[name])
        dtype = helper.tensor_dtype_to_np_dtype(value.type.tensor_type.elem_type)
        name = value.name
        if name.startswith(("alpha", "holes")):
            array = rng.random(dims) < 0.7
        elif name.startswith("depth"):
            array = 1 + 4 * rng.random(dims)
        elif name == "plane_depths":
            array = np.sort(1 + 4 * rng.random(dims), axis=-1)
        elif name in ("initial_flow", "prior"):
            array = 3 * rng.standard_normal(dims)
        else:
            array = rng.random(dims)
        feeds[name] = array.astype(dtype)
    return feeds


def working_grid(path: Path) -> tuple[int, int]:
    """(rows, cols) that give the network's working width (its metadata) and the nearest 16:9 height."""
    import onnx

    model = onnx.load(str(path))
    meta = {p.key: json.loads(p.value) for p in model.metadata_props}
    width = int(next(iter(meta.values()))["working_width"])
    multiple = int(model.graph.input[0].type.tensor_type.shape.dim[-1].dim_param.split("*")[0])
    return max(1, round(width * 9 / 16 / multiple)), width // multiple


def _median_ms(call, repeats: int) -> float:
    for _ in range(3):
        call()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        call()
        times.append(1e3 * (time.perf_counter() - start))
    return float(statistics.median(times))


def main(argv=None) -> None:
    import onnxruntime as ort
    import torch

    from engine.predict.torch_onnx import TorchOnnxSession

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--devices", default="cpu,cuda", help="torch devices to run the graphs on")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--threads", type=int, default=0, help="CPU threads of onnxruntime and of torch on the CPU "
                        "(0: their defaults; 1 on a loaded machine, where pools of spinning threads collide)")
    parser.add_argument("--json", type=Path)
    args = parser.parse_args(argv)
    rows_out = []
    for name in NETWORKS:
        path = WEIGHTS / f"{name}.onnx"
        rows, cols = working_grid(path)
        feeds = graph_feeds(path, rows, cols)
        options = ort.SessionOptions()
        options.intra_op_num_threads = args.threads
        options.log_severity_level = 3
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")  # as the engine's sessions
        oracle = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
        want = oracle.run(None, feeds)
        base = _median_ms(lambda: oracle.run(None, feeds), args.repeats)
        shape = {k: list(v.shape) for k, v in feeds.items()}
        rows_out.append({"network": name, "runner": "onnxruntime", "device": "cpu", "ms": base, "ratio": 1.0,
                         "max_diff": 0.0, "inputs": shape})
        print(f"{name}: onnxruntime cpu {base:.1f} ms  (inputs {shape})", flush=True)
        for device in args.devices.split(","):
            if device == "cuda" and not torch.cuda.is_available():
                print(f"{name}: torch {device} skipped (torch sees no CUDA device)")
                rows_out.append({"network": name, "runner": "torch", "device": device, "skipped": True})
                continue
            session = TorchOnnxSession(path, device, args.threads)
            diff = max(float(np.abs(a - b).max()) for a, b in zip(want, session.run(None, feeds)))
            ms = _median_ms(lambda: session.run(None, feeds), args.repeats)
            rows_out.append({"network": name, "runner": "torch", "device": device, "ms": ms, "ratio": ms / base,
                             "max_diff": diff})
            print(f"{name}: torch {device} {ms:.1f} ms ({ms / base:.2f}x onnxruntime cpu), max |diff| {diff:.2e}",
                  flush=True)
    write_json(args.json, {"rows": rows_out, "torch": torch.__version__, "onnxruntime": ort.__version__})


if __name__ == "__main__":
    main()
