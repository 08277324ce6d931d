"""Time the engine's networks in torch on a device, at the working sizes the engine feeds them.

``python -m tools.bench_torch_networks [--devices cpu,cuda] [--repeats 20] [--json FILE]``

Where ``onnxruntime-gpu`` is not installed (the lent GPU machines carry only the CPU build), this is how a
network's GPU time is measured: the same weights as the committed ONNX graphs, in torch, fp32. Per network
(``corrflow``: the motion network of ``flow2d[estimator=corr]``, 2 update iterations as exported; ``flow3d``:
decomp's 3D flow over one full-frame gate box; ``infill``: decomp's infilling network), the inputs are the export's
example inputs at the network's working size for a 16:9 frame (the engine scales every frame to the network's
working width, so the size does not grow with the frame's). It prints the median ms per call over ``--repeats``
calls after 3 warm-up calls (CUDA: ``torch.cuda.Event`` around each call, so GPU time with launch overhead) and the
largest difference of each device's output from the CPU's (the parity of the device path).
"""
from __future__ import annotations

import argparse
import statistics
import time
from pathlib import Path

import torch

from export.corrflow import _LastFlow
from export.corrflow import load_checkpoint as load_corrflow
from export.flow import FlowGraph, _as_model, _working_width
from export.flow import example_inputs as flow_inputs
from export.infill import InfillGraph, _as_net
from export.infill import _working_width as infill_width
from export.infill import example_inputs as infill_inputs
from tools.heldout import write_json

WEIGHTS = Path(__file__).resolve().parents[1] / "models" / "weights"
ITERATIONS = 2  # engine/weights/corrflow.onnx is exported with --iterations 2


def _round(value: float, multiple: int) -> int:
    return max(multiple, int(round(value / multiple)) * multiple)


def networks() -> dict:
    """name -> (module in eval mode, CPU inputs, working (h, w)) for 16:9 frames."""
    out = {}
    model, config = load_corrflow(WEIGHTS / "corrflow.pt")
    model.config.iterations = ITERATIONS
    w = int(config["net_width"])
    h = _round(w * 9 / 16, 8)
    g = torch.Generator().manual_seed(0)
    c = model.config.in_channels
    images = (torch.rand(1, c, h, w, generator=g), torch.rand(1, c, h, w, generator=g))
    out["corrflow"] = (_LastFlow(model).eval(), images, (h, w))
    flow = _as_model(str(WEIGHTS / "flow3d.pt")).eval()
    w = _working_width(str(WEIGHTS / "flow3d.pt"))
    h = _round(w * 9 / 16, 16)
    out["flow3d"] = (FlowGraph(flow).eval(), flow_inputs(flow, h, w), (h, w))
    net = _as_net(str(WEIGHTS / "infill.pt")).eval()
    w = infill_width(str(WEIGHTS / "infill.pt"))
    h = _round(w * 9 / 16, 16)
    out["infill"] = (InfillGraph(net).eval(), infill_inputs(net, h, w, batch=1), (h, w))
    return out


def time_calls(module, inputs, device: str, repeats: int) -> tuple[float, torch.Tensor]:
    """(median ms per call, the last output on the CPU)."""
    module = module.to(device)
    args = tuple(x.to(device) for x in inputs)
    times = []
    with torch.no_grad():
        for i in range(3 + repeats):
            if device == "cuda":
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                result = module(*args)
                end.record()
                torch.cuda.synchronize()
                ms = start.elapsed_time(end)
            else:
                t0 = time.perf_counter()
                result = module(*args)
                ms = 1e3 * (time.perf_counter() - t0)
            if i >= 3:
                times.append(ms)
    module.to("cpu")
    return float(statistics.median(times)), result.float().cpu()


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--devices", default="cpu,cuda" if torch.cuda.is_available() else "cpu")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    devices = [d.strip() for d in args.devices.split(",") if d.strip()]
    if "cuda" in devices and not torch.cuda.is_available():
        raise SystemExit("bench_torch_networks: --devices names cuda but torch sees no CUDA device")
    name = torch.cuda.get_device_name(0) if "cuda" in devices else "cpu only"
    print(f"torch {torch.__version__}, {torch.get_num_threads()} CPU threads, GPU: {name}")
    print("\n| network | working size | device | ms per call | max diff from cpu |\n|---|---|---|---|---|")
    rows = []
    for net, (module, inputs, (h, w)) in networks().items():
        reference = None
        for device in ["cpu"] + [d for d in devices if d != "cpu"]:
            ms, result = time_calls(module, inputs, device, args.repeats)
            diff = 0.0 if reference is None else float((result - reference).abs().max())
            reference = result if reference is None else reference
            if device not in devices:
                continue
            rows.append({"network": net, "working_size": [h, w], "device": device, "ms": ms,
                         "max_diff_from_cpu": diff})
            print(f"| {net} | {w}x{h} | {device} | {ms:.2f} | {diff:.2e} |", flush=True)
    write_json(args.json, {"torch": torch.__version__, "gpu": name, "iterations_corrflow": ITERATIONS, "rows": rows})


if __name__ == "__main__":
    main()
