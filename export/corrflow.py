"""Export ``models.flow.corrflow.CorrFlow`` to ONNX for the engine's ``flow2d[estimator=corr]``.

``python -m export.corrflow CHECKPOINT OUT.onnx`` writes the graph (opset 20, dynamo exporter; dynamic
height and width, multiples of 8) with inputs ``image_a``, ``image_b`` (1, C, H, W) display-encoded sRGB in
[0, 1] (C = 3), plus the depth code for an RGB-D network (C = 4, ``CorrFlowConfig.depth``), and output
``flow`` (1, 2, H, W) pixels a -> b, the last iteration's estimate, and stores the network config and its
working width under the metadata key ``interleave.corrflow``; then checks onnxruntime against torch on a
random pair.
"""
from __future__ import annotations

import argparse
import pickle
import sys
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.config import config_from_dict
from engine.predict.corrflow import METADATA_KEY
from export.flow import OPSET, write_metadata
from models.flow.corrflow import CorrFlow, CorrFlowConfig

__all__ = ["load_checkpoint", "export_corrflow", "check_parity", "main"]


class _LastFlow(nn.Module):
    def __init__(self, model: CorrFlow) -> None:
        super().__init__()
        self.model = model

    def forward(self, image_a: Tensor, image_b: Tensor) -> Tensor:
        return self.model(image_a, image_b, every_iteration=False)[-1]


def load_checkpoint(path: Union[str, Path]) -> tuple[CorrFlow, dict]:
    """(the network in eval mode, the training config dict) of a ``models.flow.corrflow_train`` checkpoint."""
    state = torch.load(str(path), map_location="cpu", weights_only=False)
    model = CorrFlow(config_from_dict(CorrFlowConfig, state["config"]["model"]))
    model.load_state_dict(state["model"])
    return model.eval(), state["config"]


def export_corrflow(model: CorrFlow, path: Union[str, Path], working_width: int,
                    example_size: tuple[int, int] = (96, 160)) -> Path:
    """Write ``model`` to ``path`` (dynamic H, W as multiples of 8) with its metadata; returns ``path``."""
    out = Path(path)
    out.parent.mkdir(parents=True, exist_ok=True)
    h, w = example_size
    c = model.config.in_channels
    inputs = (torch.rand(1, c, h, w), torch.rand(1, c, h, w))
    rows = torch.export.Dim("rows", min=2, max=1024)
    cols = torch.export.Dim("cols", min=2, max=1024)
    image = {2: 8 * rows, 3: 8 * cols}
    with torch.no_grad():
        program = torch.onnx.export(_LastFlow(model).eval(), inputs, dynamo=True, opset_version=OPSET,
                                    input_names=["image_a", "image_b"], output_names=["flow"],
                                    dynamic_shapes={"image_a": image, "image_b": image}, verbose=False)
    program.save(str(out))
    write_metadata(out, model, working_width, key=METADATA_KEY)
    return out


def check_parity(path: Union[str, Path], model: CorrFlow, size: tuple[int, int] = (144, 256), seed: int = 0) -> float:
    """Max abs difference (pixels) between onnxruntime and torch on a random smooth pair of ``size``."""
    import onnxruntime as ort

    rng = np.random.default_rng(seed)
    h, w = size
    base = rng.random((1, model.config.in_channels, h // 8, w // 8)).astype(np.float32)
    a = torch.nn.functional.interpolate(torch.from_numpy(base), size=(h, w), mode="bilinear", align_corners=False)
    b = torch.roll(a, shifts=(3, 11), dims=(2, 3))
    with torch.no_grad():
        expected = model(a, b)[-1].numpy()
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"image_a": a.numpy(), "image_b": b.numpy()})[0]
    return float(np.max(np.abs(got - expected)))


def main(argv: Optional[list[str]] = None, prog: str = "python -m export.corrflow") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("checkpoint", type=Path)
    parser.add_argument("out", type=Path)
    parser.add_argument("--tolerance", type=float, default=1e-2,
                        help="largest onnxruntime - torch difference accepted, in pixels of flow")
    parser.add_argument("--iterations", type=int, default=None,
                        help="update iterations of the graph (default: the training config's; fewer is faster)")
    parser.add_argument("--working-width", type=int, default=None,
                        help="longer side the engine resizes frames to (default: the training pairs' width)")
    args = parser.parse_args(argv)
    try:
        model, config = load_checkpoint(args.checkpoint)
    except (OSError, KeyError, RuntimeError, pickle.UnpicklingError) as exc:
        print(f"{prog}: error: {args.checkpoint}: not a correlation flow checkpoint ({type(exc).__name__})",
              file=sys.stderr)
        return 2
    if args.iterations is not None:
        if args.iterations < 1:
            print(f"{prog}: error: --iterations must be >= 1, got {args.iterations}", file=sys.stderr)
            return 2
        model.config.iterations = args.iterations
    width = int(config["net_width"]) if args.working_width is None else args.working_width
    if width < 8:
        print(f"{prog}: error: --working-width must be >= 8, got {width}", file=sys.stderr)
        return 2
    export_corrflow(model, args.out, width)
    diff = check_parity(args.out, model)
    print(f"wrote {args.out}; onnxruntime differs from torch by at most {diff:.2e} px")
    if diff > args.tolerance:
        print(f"{prog}: error: {args.out}: onnxruntime differs from torch by {diff:.2e} > {args.tolerance:.0e} px",
              file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
