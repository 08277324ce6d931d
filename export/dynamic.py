"""Export a trained dynamic field: an ONNX (points, times, directions) query and the renderer's assets.

``export_dynamic(RUN_DIR, OUT_DIR)`` writes:

- ``dynamic.onnx``: ``points (N, 3), times (N,), directions (N, 3) -> density (N,), color (N, 3)``: world
  points, times in the data's units, world view directions (any length; normalised inside); density per
  scene unit (0 outside the scene cube; a canonical point outside the canonical cube reads its border), linear RGB
  in [0, 1]. The same torch code the renderer trains (``DynamicFieldModel.contract``, the motion field, the
  canonical field), exported with ``torch.onnx.export(..., dynamo=True, opset_version=20)``; N is dynamic.
  Times are normalised inside the graph and **clamped** to the trained range (a graph cannot raise): callers
  check the range (``time_range`` in the manifest), as ``DynamicFieldModel.query`` does. A field trained with
  deferred shading (``--field.canonical.shading deferred``) outputs ``features`` (N, G), ``sigmoid(h)``, instead
  of ``color``: the renderer composites them and shades once per pixel (as ``export/field.py``).
- ``dynamic.npz`` + ``dynamic.json``: every plane (float32, and uint8 with a per-plane, per-channel
  [min, max] range, decoded as in ``export/field.py``), the MLP weights (``y = W x + b``, ReLU between
  layers), the occupancy grid, the scene contraction, the trained time range and its normalisation, the
  time and direction encodings, the flow bound, the sampling settings, and the run's canonical-volume check
  (``canonical_limit`` from ``RUN_DIR/scores.json`` when the run was evaluated) so a renderer can warn at the
  flagged times instead of showing garbage.

Parity: :func:`check_parity` holds onnxruntime against the field evaluated by torch in float64 on random points,
times and directions in and around the cube; the command fails as ``export field`` does
(:func:`export.field.parity_excess`).
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from export.field import example_points, export_command, parity_figures, query_outputs, run_as_script, strip_debug
from models.fields.assets import DYNAMIC_FORMAT, DYNAMIC_VERSION, OPSET, dynamic_assets
from models.fields.bake import DEFAULT_RESOLUTION, bakes_dynamic, write_baked
from models.fields.data.select import load_dynamic_run_views
from models.fields.dynamic.model import DynamicFieldModel
from models.fields.train_dynamic import load_dynamic_model

__all__ = ["DynamicQueryGraph", "export_dynamic", "check_parity", "example_queries", "main", "ASSET_FORMAT",
           "ASSET_VERSION"]

ASSET_FORMAT, ASSET_VERSION = DYNAMIC_FORMAT, DYNAMIC_VERSION


class DynamicQueryGraph(nn.Module):
    """world points (N, 3), times (N,), view directions (N, 3) -> density (N,), linear RGB (N, 3).

    Times are normalised to [-1, 1] over the trained range and clamped there (see the module doc).
    """

    def __init__(self, model) -> None:
        super().__init__()
        self.model = model
        self.t_min, self.t_max = (float(x) for x in model.time_range)

    def forward(self, points: Tensor, times: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        span = self.t_max - self.t_min
        if span > 0:
            taus = ((times - self.t_min) * (2.0 / span) - 1.0).clamp(-1.0, 1.0)
        else:
            taus = times * 0.0
        return self.model._query(points, taus, directions)


def _model(run_or_model):
    if isinstance(run_or_model, DynamicFieldModel):
        return run_or_model.eval()
    return load_dynamic_model(run_or_model)


def example_queries(model, count: int = 4096, seed: int = 0) -> tuple[Tensor, Tensor, Tensor]:
    """Random world points over the field's cube and 10% beyond it, random trained times, unit directions."""
    points, directions = example_points(model, count, seed)
    g = torch.Generator().manual_seed(seed + 7)
    t0, t1 = model.time_range
    times = t0 + (t1 - t0) * torch.rand(count, generator=g)
    return points, times.float(), directions


def check_parity(onnx_path: Union[str, Path], run_or_model, points: Tensor, times: Tensor, directions: Tensor
                 ) -> dict[str, float]:
    """:func:`export.field.parity_figures` of the ONNX query at ``onnx_path`` against the model's query graph."""
    import onnxruntime as ort

    model = _model(run_or_model)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"points": points.numpy(), "times": times.numpy(), "directions": directions.numpy()})
    return parity_figures(DynamicQueryGraph(model).eval(), (points, times, directions), (got[0], got[1]))


def export_dynamic(run_dir: Union[str, Path], out_dir: Union[str, Path], *, views=None,
                   bake_resolution: int = DEFAULT_RESOLUTION) -> dict:
    """Write ``dynamic.onnx``, ``dynamic.npz`` and ``dynamic.json`` for the run into ``out_dir``; returns the
    manifest (with the parity of onnxruntime against torch under ``parity``). A DeRF field trained with deferred
    shading and a canonical field of tri-planes is also baked (``baked_dynamic.npz`` + ``baked_dynamic.json``,
    ``models.fields.bake.bake_dynamic``) at ``bake_resolution`` cells a side; its grid and check (on the first
    camera and time of ``views``, a ``TimedViews``, by default the run's first held-out view when the run records
    its data) are the result's ``baked``."""
    model = _model(run_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    graph = DynamicQueryGraph(model).eval()
    points, times, dirs = example_queries(model, 64)
    n = torch.export.Dim("n", min=1, max=1 << 24)
    onnx_path = out / "dynamic.onnx"
    with torch.no_grad():
        program = torch.onnx.export(graph, (points, times, dirs), dynamo=True, opset_version=OPSET,
                                    input_names=["points", "times", "directions"], output_names=query_outputs(model),
                                    dynamic_shapes={"points": {0: n}, "times": {0: n}, "directions": {0: n}},
                                    verbose=False, optimize=False)
    program.save(str(onnx_path))
    strip_debug(onnx_path)

    limit = None
    if isinstance(run_dir, (str, Path)) and (Path(run_dir) / "scores.json").is_file():
        limit = json.loads((Path(run_dir) / "scores.json").read_text()).get("canonical_limit")
    arrays, manifest = dynamic_assets(model, canonical_limit=limit)
    manifest["onnx"]["outputs"] = query_outputs(model)
    np.savez_compressed(out / "dynamic.npz", **arrays)
    rp, rt, rd = example_queries(model, 8192, seed=1)
    manifest["parity"] = {"random_points": check_parity(onnx_path, model, rp, rt, rd)}
    (out / "dynamic.json").write_text(json.dumps(manifest, indent=2) + "\n")
    if bakes_dynamic(model):
        camera, time = None, None
        if views is None and isinstance(run_dir, (str, Path)) and (Path(run_dir) / "data.json").is_file():
            _, views = load_dynamic_run_views(run_dir)
        if views is not None:
            cam = views.cameras[0]
            camera, time = (cam.intrinsics, cam.world_to_camera, views.height, views.width), float(views.times[0])
        baked = write_baked(model, out, bake_resolution, camera, time)
        manifest["baked"] = {"grid": baked["grid"], "check": baked.get("check")}
    return manifest


def main(argv: Optional[list[str]] = None, prog: str = "python -m export.dynamic") -> None:
    """``interleave export dynamic RUN_DIR [--out DIR]``: export, check parity, print a summary."""
    export_command(argv, prog, "Export a trained dynamic field (ONNX (p, t, d) query + renderer assets) and check "
                               "onnxruntime against torch.", "interleave train dynamic", export_dynamic, "dynamic.onnx",
                   lambda manifest: {"time_range": manifest["time"]["range"], "baked": manifest.get("baked")},
                   bake=True)


if __name__ == "__main__":  # pragma: no cover
    run_as_script(main)
