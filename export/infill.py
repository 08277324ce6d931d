"""ONNX export of the disocclusion infilling network (``models.infill.network.InfillNet``) and its parity check.

| input | shape | meaning |
| --- | --- | --- |
| ``color`` | (B, 3, Z, H, W) float32 | the predicted frame's MPI (``engine.predict.decomp.infill.hole_mpi``), linear RGB |
| ``depth`` | (B, 1, Z, H, W) float32 | planar depth where alpha = 1 (+inf sky), 0 elsewhere |
| ``alpha`` | (B, 1, Z, H, W) float32 | occupancy, 0 on every plane of a hole pixel |
| ``plane_depths`` | (B, Z) float32 | frame n's plane depths |
| ``holes`` | (B, H, W) float32 | 1 where the pixel is a disocclusion |
| ``prior`` | (B, 2, H, W) float32 | prior vectors (``engine.predict.decomp.infill.prior_vectors``), pixels; choice head: (B, 2 K, H, W) candidate vectors (``engine.predict.decomp.infill.candidate_vectors``) |
| output ``residual`` | (B, 2, Z, H, W) float32 | residual head: the correction; vectors = prior + residual |
| output ``logits`` | (B, K, H, W) float32 | choice head: candidate scores; the engine copies the highest |

B, H and W are dynamic; H and W must be multiples of ``InfillConfig.stride`` (the engine pads). Exported
with ``torch.onnx.export(..., dynamo=True, opset_version=20)``; the ONNX metadata key
``engine.predict.decomp.infill.METADATA_KEY`` holds the network config and its working width.
"""
from __future__ import annotations

import argparse
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.errors import InputError
from engine.predict.decomp.infill import METADATA_KEY
from export.flow import write_metadata
from models.geometry import Mpi, build_mpi
from models.infill.network import InfillNet, infill_inputs
from models.infill.train import load_model

__all__ = ["InfillGraph", "INPUT_NAMES", "export_infill", "check_parity", "example_inputs", "main"]

INPUT_NAMES = ("color", "depth", "alpha", "plane_depths", "holes", "prior")
OPSET = 20


class InfillGraph(nn.Module):
    """``InfillNet`` with flat tensor inputs (the ONNX signature above)."""

    def __init__(self, net: InfillNet) -> None:
        super().__init__()
        self.net = net

    def forward(self, color: Tensor, depth: Tensor, alpha: Tensor, plane_depths: Tensor, holes: Tensor,
                prior: Tensor) -> Tensor:
        return self.net(infill_inputs(Mpi(color, depth, alpha, plane_depths), holes, prior))


def example_inputs(net: InfillNet, height: int = 32, width: int = 48, batch: int = 2,
                   seed: int = 0) -> tuple[Tensor, ...]:
    """Flat inputs of ``InfillGraph``: a random frame with sky rows and a hole band, ``INPUT_NAMES`` order."""
    g = torch.Generator().manual_seed(seed)
    depth = 1.0 + 9.0 * torch.rand(batch, height, width, generator=g)
    depth[:, : max(1, height // 8)] = float("inf")
    color = torch.rand(batch, height, width, 3, generator=g)
    mpi = build_mpi(color, depth, net.config.num_planes)
    holes = torch.zeros(batch, height, width)
    holes[:, height // 3: height // 2, width // 3: width // 2] = 1.0
    keep = (1.0 - holes)[:, None, None]
    channels = net.config.in_channels - 6  # 2 (the prior) or 2 K (the candidates)
    prior = torch.zeros(batch, channels, height, width)
    prior[:, 0::2] = -(holes[:, None] * 4.0)
    return (mpi.color * keep, mpi.depth * keep, mpi.alpha * keep, mpi.plane_depths, holes,
            prior + holes[:, None] * torch.randn(batch, channels, height, width, generator=g))


def _as_net(checkpoint_or_module: Union[str, Path, nn.Module]) -> InfillNet:
    if isinstance(checkpoint_or_module, InfillGraph):
        return checkpoint_or_module.net
    if isinstance(checkpoint_or_module, InfillNet):
        return checkpoint_or_module
    if isinstance(checkpoint_or_module, (str, Path)):
        return load_model(checkpoint_or_module)
    raise InputError(f"must be an InfillNet or a checkpoint path, got {type(checkpoint_or_module).__name__}",
                     field="checkpoint_or_module")


def _working_width(checkpoint: Union[str, Path]) -> int:
    config = torch.load(Path(checkpoint), map_location="cpu", weights_only=False).get("config", {})
    return int(config.get("scene_width", 960)) // int(config.get("downsample", 4))


def export_infill(checkpoint_or_module: Union[str, Path, nn.Module], path: Union[str, Path], *,
                  working_width: Optional[int] = None) -> Path:
    """Export to ONNX with dynamic B, H, W; returns ``path``. ``working_width``: the width of the training
    frames (default: from the checkpoint's config; required for a module)."""
    if working_width is None:
        if not isinstance(checkpoint_or_module, (str, Path)):
            raise InputError("give the working width for a module (the width of its training frames)",
                             field="working_width")
        working_width = _working_width(checkpoint_or_module)
    net = _as_net(checkpoint_or_module).eval()
    graph = InfillGraph(net).eval()
    stride = net.config.stride
    inputs = example_inputs(net, 4 * stride, 6 * stride, batch=2)
    batch = torch.export.Dim("batch", min=1, max=64)
    rows = torch.export.Dim("rows", min=2, max=8192 // stride)
    cols = torch.export.Dim("cols", min=2, max=8192 // stride)
    mpi_dims = {0: batch, 3: stride * rows, 4: stride * cols}
    dynamic = {"color": mpi_dims, "depth": mpi_dims, "alpha": mpi_dims, "plane_depths": {0: batch},
               "holes": {0: batch, 1: stride * rows, 2: stride * cols},
               "prior": {0: batch, 2: stride * rows, 3: stride * cols}}
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        program = torch.onnx.export(graph, inputs, dynamo=True, opset_version=OPSET, input_names=list(INPUT_NAMES),
                                    output_names=["residual" if net.config.head == "residual" else "logits"],
                                    dynamic_shapes=dynamic, verbose=False,
                                    optimize=False)
    program.save(str(out))

    write_metadata(out, net, working_width, METADATA_KEY)
    return out


def check_parity(onnx_path: Union[str, Path], module: nn.Module, inputs: tuple[Tensor, ...]) -> float:
    """Max |onnxruntime - torch| of the output (residual vectors, pixels, or choice logits) on ``inputs``
    (``INPUT_NAMES`` order)."""
    import onnxruntime as ort

    net = _as_net(module).eval()
    with torch.no_grad():
        expected = InfillGraph(net)(*inputs).numpy()
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {name: t.numpy() for name, t in zip(INPUT_NAMES, inputs)})[0]
    if got.shape != expected.shape:
        raise InputError(f"onnxruntime returned shape {got.shape}, torch {expected.shape}", field="onnx_path")
    return float(np.max(np.abs(got - expected))) if expected.size else 0.0


def main(argv: Optional[list[str]] = None, prog: str = "python -m export.infill") -> None:
    """``interleave export infill CHECKPOINT OUT.onnx``: export, then check onnxruntime against torch."""

    parser = argparse.ArgumentParser(prog=prog, description="Export the infilling network to ONNX and check parity.")
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt written by 'interleave train infill'")
    parser.add_argument("out", type=Path, help="the .onnx file to write")
    parser.add_argument("--tolerance", type=float, default=1e-3,
                        help="largest |onnxruntime - torch| vector difference accepted, pixels (default 1e-3)")
    args = parser.parse_args(argv)
    if not args.checkpoint.is_file():
        raise InputError("checkpoint not found", file=args.checkpoint)

    net = load_model(args.checkpoint)
    path = export_infill(net, args.out, working_width=_working_width(args.checkpoint))
    err = check_parity(path, net, example_inputs(net, 48, 80, batch=1, seed=1))
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB); max |onnxruntime - torch| = {err:.2e}")
    if err > args.tolerance:
        raise InputError(f"onnxruntime differs from torch by {err:.2e} > {args.tolerance:.0e}", file=path)


if __name__ == "__main__":
    main()
