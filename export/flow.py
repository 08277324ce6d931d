"""ONNX export of the 3D flow network (``models.flow.network.Flow3D``) and an onnxruntime parity check.

The exported graph takes the two MPIs as flat tensors and returns the 3D flow ``u(n -> n-k)``:

| input | shape | meaning |
| --- | --- | --- |
| ``color_n``, ``color_prev`` | (B, 3, Z, H, W) float32 | linear RGB, 0 where alpha = 0 |
| ``depth_n``, ``depth_prev`` | (B, 1, Z, H, W) float32 | planar depth where alpha = 1 (+inf sky), 0 elsewhere |
| ``alpha_n``, ``alpha_prev`` | (B, 1, Z, H, W) float32 | occupancy |
| ``plane_depths`` | (B, Z) float32 | frame n's plane depths (shared by both MPIs, ``mpi_pair``) |
| output ``flow`` | (B, 3, Z, H, W) float32 | (du, dv) pixels, dz scene units; 0 where alpha_n = 0 |

``export_flow(..., depth_flow=False)`` (``--no-depth-flow``; the engine's committed graph) leaves dz out:
the output keeps its shape with dz = 0 and the same (du, dv), without the plane softmax and the logits'
upsampling at full size. The metadata records which (``depth_flow``), and the engine refuses
``decomp[depth_flow=1]`` with a graph that has no dz. Every partial convolution is exported as one Conv3d
(``models.flow.network.set_direct_conv3d``): the same map as torch's plane-stacked Conv2d, faster in onnxruntime.

B, H and W are dynamic; Z is fixed by the network (``Flow3DConfig.num_planes``; ``with_planes`` rebuilds
the same weights for another Z before export). Any H, W >= 1 run:
the graph pads both with alpha = 0 to multiples of the pyramid stride (16 for 4 levels,
``models.flow.network.pyramid_stride``) and crops the flow back; sizes that are already multiples skip that
work and are the recommended ones. Exported with ``torch.onnx.export(..., dynamo=True, opset_version=20)``.

>>> path = export_flow("runs/flow3d/checkpoint.pt", "flow3d.onnx")          # doctest: +SKIP
>>> err = check_parity(path, load_model("runs/flow3d/checkpoint.pt"), inputs)  # doctest: +SKIP
>>> export_flow(with_planes(load_model("models/weights/flow3d.pt"), 8), "flow3d_z8.onnx")  # doctest: +SKIP
"""
from __future__ import annotations

import argparse
import copy
import dataclasses
import json
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.errors import InputError
from engine.predict.decomp.network import METADATA_KEY, FlowNetwork
from models.flow.network import Flow3D, pyramid_stride, set_direct_conv3d
from models.flow.train import load_model
from models.geometry import Mpi, build_mpi

__all__ = ["FlowGraph", "INPUT_NAMES", "INITIAL_FLOW", "input_names", "export_flow", "check_parity",
           "example_inputs", "with_planes"]

INPUT_NAMES = ("color_n", "depth_n", "alpha_n", "color_prev", "depth_prev", "alpha_prev", "plane_depths")
#: the extra input of networks built with ``Flow3DConfig.initial_flow``: (B, 2, H, W) pixels, u(n -> n-k)
INITIAL_FLOW = "initial_flow"


def input_names(model: Flow3D) -> tuple[str, ...]:
    """The graph's inputs in order: ``INPUT_NAMES`` (+ ``initial_flow`` when the network refines one)."""
    return INPUT_NAMES + ((INITIAL_FLOW,) if model.config.initial_flow else ())
OPSET = 20


class FlowGraph(nn.Module):
    """``Flow3D`` with flat tensor inputs (the ONNX signature above); runs ``Flow3D.flow_unchecked``
    (``depth_flow=False``: dz = 0, not computed)."""

    def __init__(self, model: Flow3D, depth_flow: bool = True) -> None:
        super().__init__()
        self.model = model
        self.depth_flow = bool(depth_flow)

    def forward(self, color_n: Tensor, depth_n: Tensor, alpha_n: Tensor, color_prev: Tensor, depth_prev: Tensor,
                alpha_prev: Tensor, plane_depths: Tensor, initial_flow: Optional[Tensor] = None) -> Tensor:
        return self.model.flow_unchecked(Mpi(color_n, depth_n, alpha_n, plane_depths),
                                         Mpi(color_prev, depth_prev, alpha_prev, plane_depths), initial_flow,
                                         self.depth_flow)


def _as_model(checkpoint_or_module: Union[str, Path, nn.Module]) -> Flow3D:
    if isinstance(checkpoint_or_module, FlowGraph):
        return checkpoint_or_module.model
    if isinstance(checkpoint_or_module, Flow3D):
        return checkpoint_or_module
    if isinstance(checkpoint_or_module, (str, Path)):
        return load_model(checkpoint_or_module)
    raise InputError(f"must be a Flow3D, a FlowGraph or a checkpoint path, got {type(checkpoint_or_module).__name__}",
                     field="checkpoint_or_module")


def with_planes(model: Flow3D, num_planes: int) -> Flow3D:
    """The same trained weights, built for ``num_planes`` MPI planes (eval mode; ``model`` is not changed).

    No weight depends on Z: every layer slides a (3, 3, 3) or 1x1x1 kernel along the planes and the plane
    softmax covers the offsets z' in [-s_z, s_z]; so the graph can be exported for any Z. The network was
    trained at its own Z: other values are an extrapolation whose quality is measured, not assumed
    (``interleave sweep --planes``).
    """

    if model.config.mode != "3d":
        raise InputError(f"only '3d' networks have MPI planes to change (this one is '{model.config.mode}')",
                         field="num_planes")
    if num_planes < 1:
        raise InputError(f"must be >= 1, got {num_planes}", field="num_planes")
    out = Flow3D(dataclasses.replace(model.config, num_planes=int(num_planes)))
    out.load_state_dict(model.state_dict(), strict=True)
    return out.eval()


def _working_width(checkpoint_or_module) -> int:
    if isinstance(checkpoint_or_module, (str, Path)):
        state = torch.load(Path(checkpoint_or_module), map_location="cpu", weights_only=False)
        config = state.get("config", {})
        if "scene_width" in config:
            return int(config["scene_width"]) // int(config.get("downsample", 1))
    return 480


def example_inputs(model: Flow3D, height: int = 64, width: int = 96, batch: int = 1,
                   seed: int = 0) -> tuple[Tensor, ...]:
    """Flat inputs of ``FlowGraph`` for a random two-layer-ish scene (sky included), ``INPUT_NAMES`` order."""
    g = torch.Generator().manual_seed(seed)
    z = model.config.num_planes
    depth = 2.0 + 8.0 * torch.rand(batch, height, width, generator=g)
    depth[:, : max(1, height // 8)] = float("inf")
    color = torch.rand(batch, height, width, 3, generator=g)
    first = build_mpi(color, depth, z)
    shift = torch.roll(torch.arange(width), 2)
    second = build_mpi(color[:, :, shift], depth[:, :, shift], z)._replace(plane_depths=first.plane_depths)
    out = (first.color, first.depth, first.alpha, second.color, second.depth, second.alpha, first.plane_depths)
    if model.config.initial_flow:  # about the true shift (2 px to the left), with noise
        init = torch.zeros(batch, 2, height, width)
        init[:, 0] = -2.0
        out = out + (init + 0.3 * torch.randn(batch, 2, height, width, generator=g),)
    return out


def export_flow(checkpoint_or_module: Union[str, Path, nn.Module], path: Union[str, Path], *,
                example_size: tuple[int, int] = (64, 96), working_width: Optional[int] = None,
                depth_flow: bool = True) -> Path:
    """Export the network to ONNX (opset 20, dynamo exporter) with dynamic B, H, W; returns ``path``.

    Args:
        checkpoint_or_module: a ``Flow3D``, a ``FlowGraph`` or a ``checkpoint.pt`` from ``train_flow``.
        path: the .onnx file to write.
        example_size: (H, W) of the tracing example (any size; shapes stay symbolic).
        working_width: width of the frames the network was trained on (recorded in the ONNX metadata for
            the engine); default: from the checkpoint's training config, else 480.
        depth_flow: False: the graph returns dz = 0 without computing it (recorded in the metadata).
    """

    if working_width is None:
        working_width = _working_width(checkpoint_or_module)
    model = set_direct_conv3d(copy.deepcopy(_as_model(checkpoint_or_module)).eval())
    graph = FlowGraph(model, depth_flow).eval()
    stride = pyramid_stride(model.config)
    height, width = example_size
    if height % stride or width % stride or height < 2 * stride or width < 2 * stride:
        raise InputError(f"must be multiples of {stride}, at least {2 * stride}, got {example_size}",
                         field="example_size")
    inputs = example_inputs(model, height, width, batch=2)  # batch 2: a size-1 example would be specialised
    batch = torch.export.Dim("batch", min=1, max=64)
    rows = torch.export.Dim("rows", min=2, max=8192 // stride)
    cols = torch.export.Dim("cols", min=2, max=8192 // stride)
    image = {0: batch, 3: stride * rows, 4: stride * cols}
    names = input_names(model)
    dynamic = {name: image for name in INPUT_NAMES[:-1]}
    dynamic["plane_depths"] = {0: batch}
    if model.config.initial_flow:
        dynamic[INITIAL_FLOW] = {0: batch, 2: stride * rows, 3: stride * cols}
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    with torch.no_grad():
        program = torch.onnx.export(graph, inputs, dynamo=True, opset_version=OPSET, input_names=list(names),
                                    output_names=["flow"], dynamic_shapes=dynamic, verbose=False,
                                    optimize=False)
    program.save(str(out))
    write_metadata(out, model, working_width, extra={"depth_flow": bool(depth_flow)})
    return out


def write_metadata(path: Path, model: nn.Module, working_width: int, key: Optional[str] = None,
                    extra: Optional[dict] = None) -> None:
    """Store the network config (``model.config``), its working width and ``extra`` entries in the ONNX
    metadata under ``key`` (default ``engine.predict.decomp.predictor.METADATA_KEY``; ``export.infill`` passes its own); drop
    the per-node debug records (source stack traces) the exporter writes."""

    import onnx

    proto = onnx.load(str(path))
    for node in proto.graph.node:  # the exporter's per-node stack traces: 6.5 MB of the 7.4 MB file
        node.doc_string = ""
        del node.metadata_props[:]
    del proto.metadata_props[:]
    entry = proto.metadata_props.add()
    entry.key = key or METADATA_KEY
    entry.value = json.dumps({"model": dataclasses.asdict(model.config), "working_width": int(working_width),
                              **(extra or {})})
    onnx.save(proto, str(path))


def check_parity(onnx_path: Union[str, Path], module: nn.Module, inputs: tuple[Tensor, ...]) -> float:
    """Max abs difference between onnxruntime (CPU) and torch on ``inputs`` (``INPUT_NAMES`` order); torch
    runs with the graph's own ``depth_flow`` (from its metadata, as the engine reads it) and its plane-stacked
    convolutions."""

    model = _as_model(module).eval()
    network = FlowNetwork(onnx_path, threads=1)
    with torch.no_grad():
        expected = FlowGraph(model, network.depth_flow)(*inputs).numpy()
    got = network.session.run(None, {name: t.numpy() for name, t in zip(input_names(model), inputs)})[0]
    if got.shape != expected.shape:
        raise InputError(f"onnxruntime returned shape {got.shape}, torch {expected.shape}", field="onnx_path")
    return float(np.max(np.abs(got - expected))) if expected.size else 0.0


def main(argv: Optional[list[str]] = None, prog: str = "python -m export.flow") -> None:
    """``interleave export flow CHECKPOINT OUT.onnx``: export, then check onnxruntime against torch on a
    random two-layer input and print the largest difference (fails above ``--tolerance``)."""

    parser = argparse.ArgumentParser(prog=prog, description="Export the flow network to ONNX and check parity.")
    parser.add_argument("checkpoint", type=Path, help="checkpoint.pt written by 'interleave train flow'")
    parser.add_argument("out", type=Path, help="the .onnx file to write")
    parser.add_argument("--tolerance", type=float, default=1e-3,
                        help="largest |onnxruntime - torch| flow difference accepted, pixels (default 1e-3)")
    parser.add_argument("--num-planes", type=int, default=None,
                        help="export the same weights for this many MPI planes Z (3d networks only; default: the "
                             "Z it was trained with); 'interleave sweep --planes' uses such exports")
    parser.add_argument("--no-depth-flow", action="store_true",
                        help="leave dz out (returned as 0, not computed): the engine's default decomp[depth_flow=0] "
                             "uses only (du, dv); saves the plane softmax at full size")
    args = parser.parse_args(argv)
    if not args.checkpoint.is_file():
        raise InputError("checkpoint not found", file=args.checkpoint)

    model = load_model(args.checkpoint)
    if args.num_planes is not None:
        model = with_planes(model, args.num_planes)
    path = export_flow(model, args.out, working_width=_working_width(args.checkpoint),
                       depth_flow=not args.no_depth_flow)
    err = check_parity(path, model, example_inputs(model, 96, 160, seed=1))
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB); max |onnxruntime - torch| = {err:.2e}")
    if err > args.tolerance:
        raise InputError(f"onnxruntime differs from torch by {err:.2e} > {args.tolerance:.0e}", file=path)


if __name__ == "__main__":
    main()
