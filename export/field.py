"""Export a trained static field: an ONNX query network and the assets a real-time renderer needs.

``export_field(RUN_DIR, OUT_DIR)`` writes (format documented in ``docs/field-assets.md``):

- ``field.onnx``: the density / colour query, ``points (N, 3), directions (N, 3) -> density (N,),
  color (N, 3)``: world points and world view directions (any length; normalised inside), density per
  scene unit (0 outside the field's cube), linear RGB in [0, 1]. The same torch code the renderer trains
  (``StaticFieldModel.contract`` then ``TriPlaneField``), exported with ``torch.onnx.export(...,
  dynamo=True, opset_version=20)``; N is dynamic.
- ``field.npz`` + ``field.json``: the tri-plane textures (float32, and uint8 with a per-plane, per-channel
  [min, max] range), the MLP weights, the occupancy grid, the scene contraction, the background and the
  sampling settings, so a shader (or :mod:`engine.fields.render`, its numpy reference) can render the field
  without torch or onnxruntime.

Parity: :func:`check_parity` holds onnxruntime against the field evaluated by torch in float64 on random points
in and around the cube and on points along the rays of a real view; the command fails above ``--tolerance``
(default :func:`parity_tolerance`, derived from the renderer's 8-bit output) or, for a field whose float32
arithmetic alone is further off than that, above 3x torch's own float32 difference (:func:`parity_excess`). The
quantized planes are scored by rendering a view with float and with uint8 planes (PSNR between the two, in
``field.json``).
"""
from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path
from typing import Optional, Union

import numpy as np
import torch
from torch import Tensor, nn

from engine.core.colorspace import SRGB_LINEAR_SLOPE, display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from models.fields.components.render import render_image
from models.fields.components.sampling import camera_rays, sample_intervals
from models.fields.data.select import load_run_views
from models.fields.assets import OPSET, STATIC_FORMAT, STATIC_VERSION, mlp_layers, quantize_planes, static_assets
from models.fields.bake import DEFAULT_RESOLUTION, write_baked
from models.fields.static.model import StaticFieldModel
from models.fields.train_static import load_model

__all__ = ["FieldQueryGraph", "export_field", "check_parity", "parity_figures", "parity_excess", "parity_tolerance",
           "DISPLAY_LEVELS", "example_points", "query_outputs", "quantize_planes", "report_export", "main",
           "ASSET_FORMAT", "ASSET_VERSION", "OPSET", "FLOAT32_SPREAD", "mlp_layers", "strip_debug", "export_command",
           "run_as_script"]

#: Largest code of the renderer's output: 8-bit display-encoded (sRGB) colour.
DISPLAY_LEVELS = 255

ASSET_FORMAT, ASSET_VERSION = STATIC_FORMAT, STATIC_VERSION


class FieldQueryGraph(nn.Module):
    """world points (N, 3), view directions (N, 3) -> density (N,) per scene unit, linear RGB (N, 3).

    Density is 0 where the contracted point leaves [-1, 1]^3 (the renderer never queries there). The
    occupancy grid is not applied: it is an acceleration structure, exported beside the graph.
    """

    def __init__(self, model) -> None:
        super().__init__()
        self.model = model

    def forward(self, points: Tensor, directions: Tensor) -> tuple[Tensor, Tensor]:
        coords = self.model.contract(points)
        inside = (coords.abs() <= 1.0).all(dim=-1)
        unit = torch.nn.functional.normalize(directions, dim=-1)
        sigma, rgb = self.model.field(coords.clamp(-1.0, 1.0), unit)
        return torch.where(inside, sigma, torch.zeros_like(sigma)), rgb


def query_outputs(model) -> list[str]:
    """The ONNX graph's output names: density and colour, or density and the features of a deferred field."""
    return ["density", "features" if model.field.deferred else "color"]


def _model(run_or_model):
    if isinstance(run_or_model, StaticFieldModel):
        return run_or_model.eval()
    return load_model(run_or_model)


def example_points(model, count: int = 4096, seed: int = 0) -> tuple[Tensor, Tensor]:
    """Random world points over the field's cube and 10% beyond it, and random unit directions."""
    g = torch.Generator().manual_seed(seed)
    cube = torch.rand(count, 3, generator=g) * 2.2 - 1.1
    if model.bounded:
        points = model.center + cube * model.half_size
    else:  # invert the NDC of the reference camera: z_ndc = 1 - 2 near / Z
        s = model.scene
        k = torch.tensor(s.ndc_intrinsics, dtype=torch.float32)
        w2c = torch.tensor(s.ndc_world_to_camera, dtype=torch.float32)
        w, h = s.ndc_size
        m = 1.0 + model.render_config.ndc_margin
        z = 2.0 * s.near / (1.0 - cube[:, 2].clamp(-0.999, 0.999))
        u = (cube[:, 0] * m + 1.0) * w / 2.0
        v = (cube[:, 1] * m + 1.0) * h / 2.0
        y = (v - k[1, 2]) / k[1, 1] * z
        x = (u - k[0, 2] - k[0, 1] * y / z) / k[0, 0] * z
        cam = torch.stack([x, y, z], dim=-1)
        points = (cam - w2c[:3, 3]) @ w2c[:3, :3]
    directions = torch.nn.functional.normalize(torch.randn(count, 3, generator=g), dim=-1)
    return points.float(), directions.float()


def ray_points(model, intrinsics, world_to_camera, height: int, width: int, count: int = 4096,
               seed: int = 0) -> tuple[Tensor, Tensor]:
    """Points where the renderer samples along ``count`` random rays of a view (bin centres)."""
    origins, dirs = camera_rays(intrinsics, world_to_camera, height, width)
    g = torch.Generator().manual_seed(seed)
    pick = torch.randint(origins.shape[0], (max(1, count // model.render_config.num_samples),), generator=g)
    o, d = origins[pick], dirs[pick]
    near = torch.full((o.shape[0],), float(model.scene.near))
    far = torch.full((o.shape[0],), float(model.scene.far))
    t0, t1 = model.ray_bounds(o, d, near, far)
    t, _ = sample_intervals(t0, t1, model.render_config.num_samples,
                            spacing="linear" if model.bounded else "disparity")
    points = o[:, None] + t[..., None] * d[:, None]
    return points.reshape(-1, 3), d[:, None].expand_as(points).reshape(-1, 3)


def parity_figures(graph: nn.Module, inputs: tuple[Tensor, ...], got: tuple[np.ndarray, np.ndarray]
                   ) -> dict[str, float]:
    """How far onnxruntime's ``got`` (density, colour) and torch's float32 evaluation of ``graph`` lie from
    torch's float64 evaluation of a copy of it (the exact field, for this purpose) at ``inputs`` (float32):
    the largest density difference relative to ``max(1, |density|)`` and the largest colour difference, as
    ``density``, ``color`` (onnxruntime) and ``density_float32``, ``color_float32`` (torch in float32)."""
    with torch.no_grad():
        sigma32, rgb32 = graph(*inputs)
        sigma64, rgb64 = copy.deepcopy(graph).double()(*(x.double() for x in inputs))
    exact_sigma, exact_rgb = sigma64.numpy(), rgb64.numpy()
    if exact_sigma.size == 0:
        return {"density": 0.0, "color": 0.0, "density_float32": 0.0, "color_float32": 0.0}

    def gaps(sigma: np.ndarray, rgb: np.ndarray) -> tuple[float, float]:
        return (float(np.max(np.abs(sigma - exact_sigma) / np.maximum(1.0, np.abs(exact_sigma)))),
                float(np.max(np.abs(rgb - exact_rgb))))

    density, color = gaps(*got)
    density32, color32 = gaps(sigma32.numpy(), rgb32.numpy())
    return {"density": density, "color": color, "density_float32": density32, "color_float32": color32}


#: How far above torch's own float32 difference onnxruntime's may lie before an export is refused. Both are the
#: largest error over a few thousand random points, an extreme that moves from one set of points to the next:
#: over 20 sets of 8192 points on each of three trained dynamic fields, onnxruntime's colour error was 0.21 to 1.82
#: times torch's (median 0.84-1.00, docs/results/2026-11-30-dynamic-units.md). A wrong operator in the graph
#: shows as errors tens of times torch's float32 error or more.
FLOAT32_SPREAD = 3.0


def parity_excess(parity: dict[str, dict[str, float]], tolerance: float) -> Optional[tuple[str, float, float]]:
    """The worst parity figure over its limit, as ``(quantity, figure, limit)``, or None when all pass. A figure's
    limit is ``tolerance``, or :data:`FLOAT32_SPREAD` times torch's own float32 difference from the exact field
    where that is larger: an export is refused for falling short of torch, not for the float32 arithmetic that both
    share."""
    worst = None
    for figures in parity.values():
        for quantity in ("density", "color"):
            limit = max(tolerance, FLOAT32_SPREAD * figures.get(f"{quantity}_float32", 0.0))
            excess = figures[quantity] - limit
            if excess > 0 and (worst is None or excess > worst[1] - worst[2]):
                worst = (quantity, figures[quantity], limit)
    return worst


def check_parity(onnx_path: Union[str, Path], run_or_model, points: Tensor, directions: Tensor
                 ) -> dict[str, float]:
    """:func:`parity_figures` of the ONNX query at ``onnx_path`` against the model's query graph."""
    import onnxruntime as ort

    model = _model(run_or_model)
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    got = session.run(None, {"points": points.numpy(), "directions": directions.numpy()})
    return parity_figures(FieldQueryGraph(model).eval(), (points, directions), (got[0], got[1]))


def parity_tolerance(levels: int = DISPLAY_LEVELS) -> float:
    """The default ``--tolerance`` of ``interleave export field|dynamic``: ``1 / (2 * levels * 12.92)``, 1.52e-4
    for the renderer's 8-bit output, derived from what the renderer needs rather than chosen.

    The renderer composites samples, ``C = sum_i T_i alpha_i c_i + T_N background``, and shows
    ``round(levels * srgb(C))``. A colour error of at most ``e_c`` per sample moves C by at most ``e_c``
    (the weights sum to at most 1). A relative density error of at most ``e_s`` per sample moves C by at most
    ``e_s``: the derivative of C with respect to ``log sigma_i`` is ``sigma_i dt T_i (c_i - C_behind_i / T_i)``
    with both colours in [0, 1], so its magnitude is at most ``sigma_i dt T_i``, and these sum to at most 1.
    The sRGB encoding is steepest on its linear segment (slope ``SRGB_LINEAR_SLOPE`` = 12.92), so a linear
    error ``e`` moves the 8-bit code by at most ``levels * 12.92 * e``. Giving colour and density half each
    of one code step, ``e_c = e_s = 1 / (2 * levels * 12.92)`` moves no pixel's code by more than one step,
    anywhere on the curve: never more than the rounding to 8 bits itself may (uint8 planes, which cost
    ~61 dB, move codes too). The density check is relative to ``max(1, sigma)``, so below one per unit it
    is absolute, where samples are nearly transparent over the renderer's steps.

    >>> round(parity_tolerance(), 7)
    0.0001518
    """
    if isinstance(levels, bool) or not isinstance(levels, int) or levels < 1:
        raise InputError(f"must be a positive integer, got {levels!r}", field="levels")
    return 1.0 / (2.0 * levels * SRGB_LINEAR_SLOPE)


def export_field(run_dir: Union[str, Path], out_dir: Union[str, Path], *, views=None,
                 quantize_check: bool = True, bake_resolution: int = DEFAULT_RESOLUTION) -> dict:
    """Write ``field.onnx``, ``field.npz`` and ``field.json`` for the run into ``out_dir``; returns the manifest.

    Args:
        run_dir: a run directory from ``interleave train field``.
        out_dir: where to write (created).
        views: optional :class:`~models.fields.data.views.Views` whose first camera is used for the ray-point
            parity check and the quantization check (default: the run's first test view if the run
            records its data, else only random points are checked).
        bake_resolution: a field trained with deferred shading is also baked (``baked.npz`` + ``baked.json``,
            ``models.fields.bake``) at this many grid cells a side; its grid and check are the result's ``baked``.
    """
    model = _model(run_dir)
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    graph = FieldQueryGraph(model).eval()
    points, dirs = example_points(model, 64)
    n = torch.export.Dim("n", min=1, max=1 << 24)
    onnx_path = out / "field.onnx"
    with torch.no_grad():
        program = torch.onnx.export(graph, (points, dirs), dynamo=True, opset_version=OPSET,
                                    input_names=["points", "directions"], output_names=query_outputs(model),
                                    dynamic_shapes={"points": {0: n}, "directions": {0: n}}, verbose=False,
                                    optimize=False)
    program.save(str(onnx_path))
    strip_debug(onnx_path)

    arrays, manifest = static_assets(model)
    manifest["onnx"]["outputs"] = query_outputs(model)
    np.savez_compressed(out / "field.npz", **arrays)
    rand_pts, rand_dirs = example_points(model, 8192, seed=1)
    parity = {"random_points": check_parity(onnx_path, model, rand_pts, rand_dirs)}
    camera = _first_test_camera(run_dir, views)
    if camera is not None:
        k, w2c, h, w = camera
        ray_pts, ray_dirs = ray_points(model, k, w2c, h, w, 8192, seed=2)
        parity["ray_points"] = check_parity(onnx_path, model, ray_pts, ray_dirs)
        if quantize_check:
            manifest["quantization"] = _quantization_check(model, arrays, camera, render_image)
    manifest["parity"] = parity
    (out / "field.json").write_text(json.dumps(manifest, indent=2) + "\n")
    if model.field.deferred:
        baked = write_baked(model, out, bake_resolution, camera)
        manifest["baked"] = {"grid": baked["grid"], "check": baked.get("check")}
    return manifest


def _first_test_camera(run_dir, views):
    if views is not None:
        cam = views.cameras[0]
        return cam.intrinsics, cam.world_to_camera, views.height, views.width
    if isinstance(run_dir, (str, Path)) and (Path(run_dir) / "data.json").is_file():
        _, test = load_run_views(run_dir)
        cam = test.cameras[0]
        return cam.intrinsics, cam.world_to_camera, test.height, test.width
    return None


def _quantization_check(model, arrays: dict, camera, render_image) -> dict:
    """PSNR between renders with float planes and with uint8 planes (display-encoded), one view."""
    k, w2c, h, w = camera
    ref = render_image(model, k, w2c, h, w, model.scene.near, model.scene.far)
    saved = [p.detach().clone() for p in model.field.encoding.planes]
    try:
        with torch.no_grad():
            for i, p in enumerate(model.field.encoding.planes):
                r = arrays[f"planes_{i}_range"]
                codes = arrays[f"planes_{i}_u8"].astype(np.float32)
                p.copy_(torch.from_numpy(r[..., 0, None, None] + codes / 255.0 * (r[..., 1] - r[..., 0])[..., None, None]))
        quant = render_image(model, k, w2c, h, w, model.scene.near, model.scene.far)
    finally:
        with torch.no_grad():
            for p, s in zip(model.field.encoding.planes, saved):
                p.copy_(s)
    value = psnr(display_encode(ref["color"]), display_encode(quant["color"]))
    return {"psnr_uint8_vs_float": float(value) if np.isfinite(value) else None, "view_size": [int(h), int(w)]}


def strip_debug(path: Path) -> None:
    """Remove the debug metadata (names of source lines) that the torch exporter writes into an ONNX file."""
    import onnx

    proto = onnx.load(str(path))
    for node in proto.graph.node:
        node.doc_string = ""
        del node.metadata_props[:]
    onnx.save(proto, str(path))


def export_command(argv: Optional[list[str]], prog: str, description: str, made_by: str, export, onnx_name: str,
                   extra, bake: bool = False) -> None:
    """``interleave export field|dynamic RUN_DIR [--out DIR] [--tolerance T]``: ``export(run, out) -> manifest``,
    then :func:`report_export` with ``extra(manifest)`` (a dict) printed beside the parity."""
    parser = argparse.ArgumentParser(prog=prog, description=description)
    parser.add_argument("run", type=Path, help=f"run directory written by '{made_by}'")
    parser.add_argument("--out", type=Path, default=None, help="output folder (default: RUN_DIR/export)")
    parser.add_argument("--tolerance", type=float, default=parity_tolerance(),
                        help="largest accepted |onnxruntime - torch| colour difference and relative density "
                             f"difference (default {parity_tolerance():.3g} = 1 / (2 * 255 * 12.92): colour and "
                             "density each moving the renderer's 8-bit sRGB output by at most half a code step at "
                             "the curve's steepest; see export.field.parity_tolerance)")
    if bake:
        parser.add_argument("--bake-resolution", type=int, default=DEFAULT_RESOLUTION,
                            help="grid cells a side of the baked form of a field trained with deferred shading "
                                 f"(default {DEFAULT_RESOLUTION}; static: a multiple of the occupancy grid's; dynamic, "
                                 "a DeRF field with --no-field.canonical-time: a multiple of 4)")
    args = parser.parse_args(argv)
    out = args.out or args.run / "export"
    manifest = export(args.run, out, **({"bake_resolution": args.bake_resolution} if bake else {}))
    report_export(out, manifest, onnx_name, args.tolerance, **extra(manifest))


def main(argv: Optional[list[str]] = None, prog: str = "python -m export.field") -> None:
    """``interleave export field RUN_DIR [--out DIR]``: export, check parity, print a summary."""
    export_command(argv, prog, "Export a trained static field (ONNX query + renderer assets) and check onnxruntime "
                               "against torch.", "interleave train field", export_field, "field.onnx",
                   lambda manifest: {"quantization": manifest.get("quantization"), "baked": manifest.get("baked")},
                   bake=True)


def report_export(out: Path, manifest: dict, onnx_name: str, tolerance: float, **extra) -> None:
    """Print the written files' sizes and the parity scores (and ``extra``); InputError naming the worst figure
    over its limit (:func:`parity_excess`). Shared by ``export field`` and ``export dynamic``."""
    sizes = {p.name: p.stat().st_size for p in out.iterdir() if p.suffix in (".onnx", ".npz", ".json")}
    print(json.dumps({"out": str(out), "files_bytes": sizes, "parity": manifest["parity"], **extra}, indent=2))
    excess = parity_excess(manifest["parity"], tolerance)
    if excess is not None:
        quantity, figure, limit = excess
        why = ("--tolerance" if limit == tolerance
               else f"{FLOAT32_SPREAD:g}x torch's own float32 {quantity} error; --tolerance {tolerance:.3g}")
        raise InputError(f"onnxruntime's {quantity} differs from the exact field by {figure:.2e} > {limit:.3g} "
                         f"({why})", file=out / onnx_name)


def run_as_script(main) -> None:
    """``python -m export.field|dynamic``: run ``main`` (no arguments); on InputError print it and exit 2."""
    try:
        main()
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        sys.exit(2)


if __name__ == "__main__":  # pragma: no cover
    run_as_script(main)
