"""A dynamic-field export whose motion is known in closed form: the test and benchmark field of the motion vectors.

``python -m tools.programmed_field OUT_DIR [--beta B] [--fog] [--zigzag]`` writes ``dynamic.json`` + ``dynamic.npz`` (the
format of ``interleave export dynamic``; no ONNX graph, which the GL and numpy renderers never open), so that
``interleave demo --field OUT_DIR`` renders it. The field is a tiny DeRF (bounded scene [-1, 1]^3, times
[0, 1]) whose parameters are set, not trained:

- **motion**: the motion planes are 1 except channel 0, which is ``1 + beta x`` on the xy plane and
  ``tau + 2`` on the xt plane (bilinear interpolation reproduces both exactly); the flow MLP passes that
  feature to ``flow_x = max_flow tanh(GAIN f + BIAS)``, ``flow_y = flow_z = 0``. With beta = 0 every point of
  the cube translates by the same amount between two times (about 0.6 units over the time range).
  ``--zigzag``: the xt plane alternates between 1 and 3 from one time row to the next instead, so the
  translation reverses at every row (a motion that extrapolating the last interval gets wrong);
- **canonical field** (default): a textured opaque box [-0.4, 0.4]^3 in empty space: channel 0 of the finest
  scale is the box's indicator on each plane (their product is the box), channel 1 a texture; density
  ``exp(40 f0 - 20)``, grey level ``sigmoid((6, 5, 4) f1 - 3)``. ``--fog``: the untrained model's canonical
  field instead (semi-transparent everywhere).
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import sys
from pathlib import Path
from typing import Optional

import numpy as np
import torch

from models.fields.assets import dynamic_assets
from models.fields.dynamic.model import DynamicFieldConfig, DynamicFieldModel, MotionConfig
from models.fields.static.field import FieldConfig
from models.fields.static.model import RenderConfig, SceneBox

__all__ = ["GAIN", "BIAS", "tiny_model", "programmed_arrays", "flow_x", "write_export", "main"]

GAIN, BIAS = 0.6, -1.8

TINY = DynamicFieldConfig(kind="derf",
                          canonical=FieldConfig(resolutions=(8, 16), feature_dim=4, density_hidden=16,
                                                geo_feature_dim=7, color_hidden=16),
                          motion=MotionConfig(resolutions=(8,), feature_dim=4, hidden=16),
                          canonical_time=False)  # the programmed content is static in canonical space


def tiny_model(kind: str = "derf") -> DynamicFieldModel:
    """An untrained tiny dynamic field (seed 0): scene [-1, 1]^3, near 1, far 5, white background, times [0, 1]."""
    torch.manual_seed(0)
    scene = SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3)
    return DynamicFieldModel(scene, [1.0, 1.0, 1.0], (0.0, 1.0), dataclasses.replace(TINY, kind=kind),
                             RenderConfig(num_samples=16), time_resolution=4)


def flow_x(max_flow: float, x, tau, beta: float = 0.0):
    """The programmed flow's x component (contracted units) at contracted x and normalised time tau."""
    return max_flow * np.tanh(GAIN * (1.0 + beta * np.asarray(x)) * (np.asarray(tau) + 2.0) + BIAS)


def programmed_arrays(beta: float = 0.0, *, opaque: bool = True, zigzag: bool = False) -> tuple[dict, dict]:
    """``(arrays, manifest)`` of the programmed field (see the module doc)."""
    arrays, manifest = dynamic_assets(tiny_model("derf"))
    for key in [k for k in arrays if k.startswith("motion_") and not k.endswith(("_u8", "_range"))]:
        plane = arrays[key]
        plane[...] = 1.0
        if key.startswith("motion_spatial_0"):
            plane[0, 0] = 1.0 + beta * np.linspace(-1.0, 1.0, plane.shape[3])[None, :]
        elif key.startswith("motion_temporal_0"):
            rows = (np.arange(plane.shape[2]) % 2 * 2.0 + 1.0 if zigzag
                    else np.linspace(-1.0, 1.0, plane.shape[2]) + 2.0)
            plane[0, 0] = rows[:, None]
    _set_mlp(arrays, "flow", len(manifest["field"]["mlps"]["flow"]), first=[(0, 0)], out=[(0, 0, GAIN)],
             bias={0: BIAS})
    if opaque:
        _opaque_box(arrays, manifest)
    return arrays, manifest


def _set_mlp(arrays: dict, name: str, layers: int, *, first: list, out: list, bias: dict) -> None:
    """Zero an MLP, then: ``first`` (row, column) ones in its first layer, hidden layers passing unit 0 and 1
    through (their inputs are >= 0: the ReLUs keep them), ``out`` (row, column, weight) and ``bias`` (row:
    value) in its last layer (when it has one layer, ``first`` and ``out`` both apply to it)."""
    for j in range(layers):
        arrays[f"{name}_w{j}"][...] = 0.0
        arrays[f"{name}_b{j}"][...] = 0.0
    for row, col in first:
        arrays[f"{name}_w0"][row, col] = 1.0
    for j in range(1, layers - 1):
        arrays[f"{name}_w{j}"][0, 0] = arrays[f"{name}_w{j}"][1, 1] = 1.0
    last = layers - 1
    for row, col, weight in out:
        arrays[f"{name}_w{last}"][row, col] = weight
    for row, value in bias.items():
        arrays[f"{name}_b{last}"][row] = value


def _opaque_box(arrays: dict, manifest: dict) -> None:
    scale = len(manifest["field"]["planes"]["canonical_spatial"]) - 1
    plane = arrays[f"canonical_spatial_{scale}"]
    grid = np.linspace(-1.0, 1.0, plane.shape[3])
    inside = (np.abs(grid) < 0.4).astype(np.float32)
    plane[...] = 0.0
    plane[:, 0] = inside[:, None] * inside[None, :]
    plane[:, 1] = 1.0
    plane[0, 1] = 0.5 + 0.5 * np.sin(7.0 * grid)[None, :] * np.cos(5.0 * grid)[:, None]
    first = scale * plane.shape[1]  # the scale's first column among the concatenated features
    mlps = manifest["field"]["mlps"]
    # hidden 0: the box, hidden 1: the texture; raw density 40 f0 - 20, latent 0: the texture
    _set_mlp(arrays, "density", len(mlps["density"]), first=[(0, first), (1, first + 1)],
             out=[(0, 0, 40.0), (1, 1, 1.0)], bias={0: -20.0})
    _set_mlp(arrays, "color", len(mlps["color"]), first=[(0, 0)], out=[(0, 0, 6.0), (1, 0, 5.0), (2, 0, 4.0)],
             bias={0: -3.0, 1: -3.0, 2: -3.0})


def write_export(out_dir: Path, beta: float = 0.0, *, opaque: bool = True, zigzag: bool = False) -> Path:
    """Write the programmed field as an export folder (``dynamic.json`` + ``dynamic.npz``); returns it."""
    arrays, manifest = programmed_arrays(beta, opaque=opaque, zigzag=zigzag)
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    np.savez(out_dir / "dynamic.npz", **arrays)
    (out_dir / "dynamic.json").write_text(json.dumps(manifest, indent=1) + "\n")
    return out_dir


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.programmed_field", description=__doc__.splitlines()[0])
    parser.add_argument("out", type=Path, help="export folder to write")
    parser.add_argument("--beta", type=float, default=0.0, help="how much the flow varies along x (0: a translation)")
    parser.add_argument("--fog", action="store_true", help="keep the untrained canonical field (no opaque box)")
    parser.add_argument("--zigzag", action="store_true", help="a translation that reverses at every time row")
    args = parser.parse_args(argv)
    print(write_export(args.out, args.beta, opaque=not args.fog, zigzag=args.zigzag))
    return 0


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
