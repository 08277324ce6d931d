"""Render an exported static radiance field without torch: the numpy reference renderer of the assets.

Reads what ``interleave export field`` writes (``field.json`` + ``field.npz`` + ``field.onnx``; the
format is ``docs/field-assets.md``) and renders colour and planar depth for any camera, so a trained field
can feed the interleaved-reprojection loop like any renderer. The field is evaluated either by the numpy
code here (``query="numpy"``, the oracle of the asset format and of the real-time shader) or by the
exported ONNX graph through onnxruntime (``query="onnx"``, the same torch code that training ran).

Conventions (``engine/core/frames.py``): OpenCV cameras, rigid ``world_to_camera``, pixel (u, v) centred at
(u + 0.5, v + 0.5), planar depth with ``+inf`` where a ray hits nothing (opacity < ``OPACITY_EPS``), linear
RGB. Rays are parameterised by planar depth (directions have camera z = 1); samples are the bin centres
of ``render.num_samples`` equal bins (linear in depth inside the box for bounded scenes, uniform in
inverse depth for forward-facing ones); samples outside the field's cube or in empty occupancy cells are
not evaluated. This mirrors ``models/fields`` (sampling, rendering) and is tested against it.

>>> field = load_field("runs/lego/export")                       # doctest: +SKIP
>>> out = render_field(field, K, world_to_camera, 540, 960)      # doctest: +SKIP
"""
from __future__ import annotations

import json
import time
import zipfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.core.errors import InputError
from engine.core.frames import validate_intrinsics, validate_pose
from engine.fields.encoding import SH_C0, SH_C1, SH_C2, SH_C3, direction_encoding_np, sh_encoding_np
from engine.fields.manifest import check_scene, check_static_layout

__all__ = ["ASSET_FORMAT", "ASSET_VERSION", "OPACITY_EPS", "FAR_AT_INFINITY", "MIN_NEAR", "SH_C0", "SH_C1",
           "SH_C2", "SH_C3", "ExportedAssets", "FieldAssets", "load_field", "array_getter", "decode_plane", "load_mlp",
           "load_occupancy", "camera_rays_np", "sh_encoding_np", "direction_encoding_np", "contract_np",
           "uncontract_np", "sigmoid_np", "query_field", "shade_pixels_np", "pixel_shader", "composite_np", "optical_depth",
           "evaluated_samples", "evaluation_macs",
           "render_field", "TRANSMITTANCE_EPS"]

ASSET_FORMAT = "interleave-field"
ASSET_VERSION = 1
#: Opacity below which a ray has "no surface" (depth +inf); the same as models.fields.components.render.OPACITY_EPS.
OPACITY_EPS = 1e-3
#: Stand-in for an infinite far bound in inverse-depth sampling; models.fields.components.sampling uses the same.
FAR_AT_INFINITY = 1e10
#: Smallest near bound used in inverse-depth sampling.
MIN_NEAR = 1e-6
#: The real-time renderers' early ray termination: a ray stops once its transmittance is below this (the
#: reference composites every sample; ``evaluated_samples`` counts what such a renderer evaluates).
TRANSMITTANCE_EPS = 1e-4

PLANE_AXES = ((0, 1), (0, 2), (1, 2))


class ExportedAssets:
    """What static and dynamic exported assets share (subclasses hold ``manifest``, ``onnx_path`` and a
    ``_session`` slot): the scene, the background, and the onnxruntime session of the query graph."""

    manifest: dict
    onnx_path: Path
    _session: object

    @property
    def scene(self) -> dict:
        return self.manifest["scene"]

    @property
    def background(self) -> np.ndarray:
        return np.asarray(self.manifest["background"], np.float32)

    @property
    def bounded(self) -> bool:
        return self.scene["kind"] == "bounded-360"

    @property
    def deferred(self) -> bool:
        """Deferred shading (``field.shading``): samples give features, :func:`shade_pixels_np` the colour."""
        return self.manifest["field"].get("shading", "per-sample") == "deferred"

    @property
    def feature_dim(self) -> int:
        """Values a sample gives the compositing: 3 (RGB), or the latent size of a deferred field."""
        return int(self.manifest["field"]["geo_feature_dim"]) if self.deferred else 3

    def onnx_session(self, threads: int = 0):
        """The onnxruntime session of the exported query graph (created once)."""
        if self._session is None:
            self._session = open_onnx(self.onnx_path, threads)
        return self._session


@dataclass(eq=False)
class FieldAssets(ExportedAssets):
    """An exported field in memory (see ``docs/field-assets.md``).

    Attributes:
        manifest: ``field.json``.
        planes: per scale, (3, C, R, R) float32 (xy, xz, yz), dequantized when loaded with ``quantized``.
        density_layers, color_layers: ``(weight (out, in), bias (out,))`` per linear layer, ReLU between.
        occupancy: (R, R, R) bool over the contracted cube indexed [ix, iy, iz], or None.
        onnx_path: the exported query graph.
    """

    manifest: dict
    planes: list[np.ndarray] = field(repr=False)
    density_layers: list[tuple[np.ndarray, np.ndarray]] = field(repr=False)
    color_layers: list[tuple[np.ndarray, np.ndarray]] = field(repr=False)
    occupancy: Optional[np.ndarray] = field(repr=False)
    onnx_path: Path
    _session: object = field(default=None, repr=False)


def open_onnx(path: Path, threads: int = 0):
    """A CPU onnxruntime session of an exported query graph (``threads`` 0: onnxruntime's default)."""
    import onnxruntime as ort

    options = ort.SessionOptions()
    if threads:
        options.intra_op_num_threads = threads
    return ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])


def read_asset_files(path: str | Path, stem: str, fmt: str, version: int, command: str, onnx: bool = True
                     ) -> tuple[Path, dict, dict[str, np.ndarray]]:
    """(folder, manifest, arrays) of exported assets ``<stem>.json`` + ``<stem>.npz`` in ``path`` (the folder or
    its json); InputError for missing files or another format / version (``onnx``: the manifest names a query
    graph, see ``check_scene``)."""
    root = Path(path)
    if root.name == f"{stem}.json":
        root = root.parent
    meta_file, npz_file = root / f"{stem}.json", root / f"{stem}.npz"
    for f in (meta_file, npz_file):
        if not f.is_file():
            raise InputError(f"file does not exist (write it with '{command}')", file=f)
    try:
        manifest = json.loads(meta_file.read_text())
    except (UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise InputError(f"is not valid JSON ({exc})", file=meta_file) from None
    if not isinstance(manifest, dict):
        raise InputError(f"must hold a JSON object, got {type(manifest).__name__}", file=meta_file)
    if manifest.get("format") != fmt or manifest.get("version") != version:
        raise InputError(f"is not {fmt} version {version} (format {manifest.get('format')!r}, "
                         f"version {manifest.get('version')!r})", file=meta_file)
    check_scene(manifest, meta_file, onnx)
    try:
        with np.load(npz_file) as data:  # no pickled objects (numpy's default)
            arrays = {k: data[k] for k in data.files}
    except (OSError, ValueError, zipfile.BadZipFile, EOFError) as exc:
        raise InputError(f"is not a readable .npz ({exc})", file=npz_file) from None
    return root, manifest, arrays


def array_getter(arrays: dict[str, np.ndarray], npz_file: Path, meta_name: str) -> Callable[[str, str], np.ndarray]:
    """``get(name, where)``: the array ``name`` of an asset file, or InputError naming the file and where
    ``meta_name`` (the manifest) refers to it."""
    def get(name: str, where: str) -> np.ndarray:
        if name not in arrays:
            raise InputError(f"lacks array {name!r} named by {meta_name} ({where})", file=npz_file)
        array = arrays[name]
        if array.dtype.kind not in "biuf":
            raise InputError(f"array {name!r} has dtype {array.dtype}, not a number", file=npz_file)
        if array.dtype.kind == "f" and not np.isfinite(array).all():
            raise InputError(f"array {name!r} has {int(np.count_nonzero(~np.isfinite(array)))} non-finite values",
                             file=npz_file)
        return array

    return get


def decode_plane(p: dict, get: Callable[[str, str], np.ndarray], where: str, quantized: bool) -> np.ndarray:
    """A manifest plane entry as float32: its ``float`` array, or (``quantized``) its ``uint8`` codes mapped
    back through the per-plane, per-channel [min, max] of ``range`` (``export.field.quantize_planes``)."""
    if not quantized:
        return get(p["float"], where).astype(np.float32)
    codes, ranges = get(p["uint8"], where), get(p["range"], where).astype(np.float32)
    return ranges[..., 0, None, None] + codes.astype(np.float32) / 255.0 * (
        ranges[..., 1] - ranges[..., 0])[..., None, None]


def load_mlp(specs: list[dict], get: Callable[[str, str], np.ndarray], name: str,
             npz_file: Path) -> list[tuple[np.ndarray, np.ndarray]]:
    """The (weight (out, in), bias (out,)) float32 layers of a manifest MLP; InputError on a shape mismatch."""
    layers = []
    for spec in specs:
        w, b = get(spec["weight"], name).astype(np.float32), get(spec["bias"], name).astype(np.float32)
        if w.shape != (spec["out"], spec["in"]) or b.shape != (spec["out"],):
            raise InputError(f"layer {spec['weight']} has shape {w.shape}, expected ({spec['out']}, {spec['in']})",
                             file=npz_file)
        layers.append((w, b))
    return layers


def load_field(path: str | Path, *, quantized: bool = False) -> FieldAssets:
    """Load exported assets from a folder (or its ``field.json``); ``quantized`` uses the uint8 planes.

    Raises:
        InputError: missing files, another format or version, arrays whose shapes disagree with the manifest.
    """
    root, manifest, arrays = read_asset_files(path, "field", ASSET_FORMAT, ASSET_VERSION,
                                              "interleave export field RUN_DIR")
    check_static_layout(manifest, root / "field.json")
    npz_file = root / "field.npz"
    get = array_getter(arrays, npz_file, "field.json")
    planes = []
    for p in manifest["field"]["planes"]:
        plane = decode_plane(p, get, "planes", quantized)
        if plane.shape != (3, p["channels"], p["resolution"], p["resolution"]):
            raise InputError(f"plane {p['float']} has shape {plane.shape}, field.json says "
                             f"(3, {p['channels']}, {p['resolution']}, {p['resolution']})", file=npz_file)
        planes.append(plane)
    layers = {name: load_mlp(specs, get, name, npz_file) for name, specs in manifest["field"]["mlps"].items()}
    occupancy = load_occupancy(manifest, get, npz_file)
    return FieldAssets(manifest, planes, layers["density"], layers["color"], occupancy,
                       root / manifest["onnx"]["file"])


def load_occupancy(manifest: dict, get: Callable[[str, str], np.ndarray], npz_file: Path) -> Optional[np.ndarray]:
    """The (R, R, R) bool occupancy grid the manifest names, or None."""
    occ = manifest.get("occupancy")
    if not occ:
        return None
    grid = get(occ["array"], "occupancy").astype(bool)
    if grid.ndim != 3 or len(set(grid.shape)) != 1:
        raise InputError(f"occupancy {occ['array']!r} has shape {grid.shape}, expected a cube (R, R, R)",
                         file=npz_file)
    return grid


# ----------------------------------------------------------------------------------------------------
# Pure functions (numpy mirrors of models/fields; tested against them)


def camera_rays_np(intrinsics: np.ndarray, world_to_camera: np.ndarray, height: int, width: int
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Rays through every pixel centre, row-major: origin (3,) and directions (H * W, 3) float64 whose
    camera-space z is 1 (so the ray parameter is planar depth). ``models.fields.components.sampling.camera_rays``
    wraps this function."""
    k = np.asarray(intrinsics, np.float64)
    t = np.asarray(world_to_camera, np.float64)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    x = (u - k[0, 2] - k[0, 1] * (v - k[1, 2]) / k[1, 1]) / k[0, 0]
    y = (v - k[1, 2]) / k[1, 1]
    cam = np.stack([x, y, np.ones_like(x)], axis=-1).reshape(-1, 3)
    rot = t[:3, :3]
    return -rot.T @ t[:3, 3], cam @ rot  # R^T d for row vectors


def contract_np(scene: dict, points: np.ndarray, ndc_margin: float) -> np.ndarray:
    """World points (..., 3) -> the field's cube coordinates (inside = all in [-1, 1]); behind the NDC
    reference camera -> -2 (outside)."""
    if scene["kind"] == "bounded-360":
        lo, hi = np.asarray(scene["box_min"], np.float32), np.asarray(scene["box_max"], np.float32)
        return (points - (lo + hi) / 2) / ((hi - lo) / 2)
    k = np.asarray(scene["ndc_intrinsics"], np.float32)
    t = np.asarray(scene["ndc_world_to_camera"], np.float32)
    w, h = scene["ndc_size"]
    cam = points @ t[:3, :3].T + t[:3, 3]
    z = cam[..., 2]
    ahead = z > 0
    zs = np.where(ahead, z, np.finfo(np.float32).tiny)
    u = (k[0, 0] * cam[..., 0] + k[0, 1] * cam[..., 1]) / zs + k[0, 2]
    v = k[1, 1] * cam[..., 1] / zs + k[1, 2]
    out = np.stack([(2.0 * u / w - 1.0) / (1.0 + ndc_margin), (2.0 * v / h - 1.0) / (1.0 + ndc_margin),
                    1.0 - 2.0 * scene["near"] / zs], axis=-1)
    return np.where(ahead[..., None], out, np.float32(-2.0))


def uncontract_np(scene: dict, coords: np.ndarray, ndc_margin: float) -> np.ndarray:
    """The inverse of :func:`contract_np`: cube coordinates (..., 3) -> world points, float32. For a
    forward-facing scene a coordinate with ``c_z >= 1`` lies at or beyond infinity: NaN."""
    coords = np.asarray(coords, np.float32)
    if scene["kind"] == "bounded-360":
        lo, hi = np.asarray(scene["box_min"], np.float32), np.asarray(scene["box_max"], np.float32)
        return coords * ((hi - lo) / 2) + (lo + hi) / 2
    k = np.asarray(scene["ndc_intrinsics"], np.float32)
    t = np.asarray(scene["ndc_world_to_camera"], np.float32)
    w, h = scene["ndc_size"]
    with np.errstate(divide="ignore", invalid="ignore"):
        z = np.where(coords[..., 2] < 1.0, np.float32(2.0 * scene["near"]) / (1.0 - coords[..., 2]), np.nan)
        u = (coords[..., 0] * (1.0 + ndc_margin) + 1.0) * (w / 2.0)
        v = (coords[..., 1] * (1.0 + ndc_margin) + 1.0) * (h / 2.0)
        y = (v - k[1, 2]) * z / k[1, 1]
        x = ((u - k[0, 2]) * z - k[0, 1] * y) / k[0, 0]
    cam = np.stack([x, y, z], axis=-1).astype(np.float32)
    return ((cam - t[:3, 3]) @ t[:3, :3]).astype(np.float32)  # R^T (cam - t) for row vectors


def bilinear_np(plane: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(C, H, W) plane at coordinates a (along the width), b (along the height) in [-1, 1] -> (C, N);
    ``grid_sample(align_corners=True, padding_mode='border')``. H, W >= 2 (tri-planes are square; the time
    planes of dynamic fields are (C, Rt, R)). The weights are float32 for float32 (or smaller) planes, float64
    for float64 ones."""
    h, w = plane.shape[-2:]
    x = np.clip((a + 1.0) * 0.5 * (w - 1), 0.0, w - 1)
    y = np.clip((b + 1.0) * 0.5 * (h - 1), 0.0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(np.int64), w - 2), np.minimum(np.floor(y).astype(np.int64), h - 2)
    fx, fy = (x - x0).astype(np.result_type(plane, np.float32)), (y - y0).astype(np.result_type(plane, np.float32))
    p00, p01 = plane[:, y0, x0], plane[:, y0, x0 + 1]
    p10, p11 = plane[:, y0 + 1, x0], plane[:, y0 + 1, x0 + 1]
    return (p00 * (1 - fx) + p01 * fx) * (1 - fy) + (p10 * (1 - fx) + p11 * fx) * fy


def mlp_np(x: np.ndarray, layers: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    for i, (w, b) in enumerate(layers):
        x = x @ w.T + b
        if i < len(layers) - 1:
            x = np.maximum(x, 0.0)
    return x


def query_field(assets: FieldAssets, coords: np.ndarray, directions: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Density (N,) per scene unit and linear RGB (N, 3) at contracted coordinates (N, 3) in [-1, 1]^3 for
    unit world view directions (N, 3): tri-plane features (product over planes, concatenated over scales),
    density MLP, colour MLP (numpy, float32)."""
    coords = np.asarray(coords, np.float32)
    feats = []
    for plane in assets.planes:
        prod = None
        for k, (a, b) in enumerate(PLANE_AXES):
            f = bilinear_np(plane[k], coords[:, a], coords[:, b])
            prod = f if prod is None else prod * f
        feats.append(prod)
    x = np.concatenate(feats, axis=0).T
    out = mlp_np(x, assets.density_layers)
    spec = assets.manifest["field"]
    sigma = np.exp(np.minimum(out[:, 0] + spec["density_bias"], spec["max_log_density"]))
    if assets.deferred:
        return sigma.astype(np.float32), sigmoid_np(out[:, 1:]).astype(np.float32)
    enc = direction_encoding_np(np.asarray(directions, np.float32), spec["direction_encoding"],
                                spec["direction_degree"])
    rgb = sigmoid_np(mlp_np(np.concatenate([out[:, 1:], enc], axis=-1), assets.color_layers))
    return sigma.astype(np.float32), rgb.astype(np.float32)


def sigmoid_np(x: np.ndarray) -> np.ndarray:
    """The logistic function; exp(-x) overflows to inf for x below about -88 (float32), where the result is
    the exact 0 it should be, so the overflow is not reported."""
    with np.errstate(over="ignore"):
        return 1.0 / (1.0 + np.exp(-x))


def shade_pixels_np(spec: dict, color_layers, background: np.ndarray, features: np.ndarray, opacity: np.ndarray,
                    directions: np.ndarray, extra: Optional[np.ndarray] = None) -> np.ndarray:
    """Deferred shading (``models.fields.static.field.shade_pixels``): composited features F (R, G), opacity A
    (R,), unit view directions (R, 3) -> linear RGB (R, 3)
    ``F[:3] + (1 - A) background + A tanh(colour MLP([F, enc(d), extra]))``. ``spec``: the manifest's ``field``;
    ``extra``: (E,) further inputs of the colour MLP, the same for every pixel (a DeRF field's encoded time), or
    None."""
    enc = direction_encoding_np(np.asarray(directions, np.float32), spec["direction_encoding"],
                                spec["direction_degree"])
    inputs = [features, enc]
    if extra is not None:
        inputs.append(np.broadcast_to(np.asarray(extra, np.float32), (features.shape[0], len(extra))))
    residual = np.tanh(mlp_np(np.concatenate(inputs, axis=-1), color_layers))
    return (features[:, :3] + (1.0 - opacity)[:, None] * background + opacity[:, None] * residual).astype(np.float32)


def pixel_shader(assets, extra: Optional[np.ndarray] = None) -> Optional[Callable]:
    """``march_field``'s ``shade`` of a deferred field (``(features, opacity, directions) -> RGB``), else None;
    ``extra``: (E,) the colour MLP's further inputs (``shade_pixels_np``)."""
    if not assets.deferred:
        return None
    return lambda f, a, d: shade_pixels_np(assets.manifest["field"], assets.color_layers, assets.background, f, a, d,
                                           extra)


def _ray_box(origin: np.ndarray, d: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    parallel = d == 0
    inv = 1.0 / np.where(parallel, 1.0, d)
    t0, t1 = (lo - origin) * inv, (hi - origin) * inv
    inside = (origin >= lo) & (origin <= hi)
    big = np.float32(1e30)
    t_lo = np.where(parallel, np.where(inside, -big, big), np.minimum(t0, t1))
    t_hi = np.where(parallel, np.where(inside, big, -big), np.maximum(t0, t1))
    return t_lo.max(axis=-1), t_hi.min(axis=-1)


def _lerp(a: np.ndarray, b: np.ndarray, w: np.ndarray) -> np.ndarray:
    """``torch.lerp``'s formula (exact at both ends), so sample positions round as in training."""
    return np.where(w < 0.5, a + w * (b - a), b - (b - a) * (1 - w)).astype(np.float32)


def _samples(t_near: np.ndarray, t_far: np.ndarray, n: int, spacing: str) -> tuple[np.ndarray, np.ndarray]:
    """Bin-centre samples (R, n) and bin lengths (R, n), as models.fields.components.sampling.sample_intervals."""
    t_far = np.maximum(t_far, t_near)
    steps = np.linspace(0.0, 1.0, n + 1, dtype=np.float32)
    centres = (np.arange(n, dtype=np.float32) + np.float32(0.5)) / np.float32(n)
    if spacing == "linear":
        a, b = t_near[:, None], t_far[:, None]
        edges, t = _lerp(a, b, steps), _lerp(a, b, centres)
    else:
        near = np.maximum(t_near, np.float32(MIN_NEAR))[:, None]
        far = np.maximum(np.minimum(t_far[:, None], np.float32(FAR_AT_INFINITY)), near)
        s_near, s_far = np.float32(1.0) / near, np.float32(1.0) / far
        edges, t = np.float32(1.0) / _lerp(s_near, s_far, steps), np.float32(1.0) / _lerp(s_near, s_far, centres)
    return t.astype(np.float32), np.maximum(edges[:, 1:] - edges[:, :-1], 0.0).astype(np.float32)


def composite_np(sigma: np.ndarray, rgb: np.ndarray, t: np.ndarray, lengths: np.ndarray, background: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Composite R rays of N samples front to back (``models.fields.components.render``'s weights and compositing).

    Args:
        sigma: (R, N) density per scene unit; rgb: (R, N, 3) linear RGB; t: (R, N) planar depths;
        lengths: (R, N) interval lengths in scene units (``0 * inf`` counts as an empty interval);
        background: (3,) linear RGB.

    Returns:
        colour (R, 3), planar depth (R,) (``sum w t / sum w``; +inf where the opacity is below
        :data:`OPACITY_EPS`), opacity (R,).
    """
    tau = optical_depth(sigma, lengths)
    excl = np.concatenate([np.zeros_like(tau[:, :1]), np.cumsum(tau, axis=-1)[:, :-1]], axis=-1)
    trans = np.exp(-excl)
    weights = trans * -np.expm1(-tau)
    acc = weights.sum(-1)
    expected = (weights * t).sum(-1)
    color = (weights[..., None] * rgb).sum(1) + (1.0 - acc)[:, None] * background
    depth = np.where(acc >= OPACITY_EPS, expected / np.maximum(acc, OPACITY_EPS), np.inf)
    return color, depth, acc


def optical_depth(sigma: np.ndarray, lengths: np.ndarray) -> np.ndarray:
    """(R, N) optical depth of each interval: density (per scene unit) times length, 0 where either is 0
    (``0 * inf`` counts as an empty interval)."""
    return np.where((sigma == 0) | (lengths == 0), np.float32(0.0), sigma * lengths)


def evaluated_samples(keep: np.ndarray, tau: np.ndarray, transmittance_eps: float = TRANSMITTANCE_EPS) -> np.ndarray:
    """(R,) int32: how many samples of each ray a renderer with early ray termination evaluates: the kept
    ones (``keep`` (R, N): inside the cube, occupied, non-empty) up to and including the first after which
    the transmittance ``exp(-sum tau)`` is below ``transmittance_eps`` (0: never stops). ``tau`` (R, N):
    ``optical_depth`` of every sample, 0 where not kept."""
    stopped = np.exp(-np.cumsum(tau, axis=-1, dtype=np.float32)) < np.float32(transmittance_eps)
    before = np.zeros_like(stopped)
    before[:, 1:] = np.logical_or.accumulate(stopped, axis=-1)[:, :-1]
    return (keep & ~before).sum(axis=-1).astype(np.int32)


def evaluation_macs(assets) -> int:
    """Multiply-adds of one field evaluation in the MLPs of ``assets`` (density and colour layers): the columns
    of the first colour layer that read the view direction (or other per-pixel inputs) are left out, since a
    renderer applies them once per pixel. Texture fetches are not counted."""
    density, color = list(assets.density_layers), list(assets.color_layers)
    latent = int(density[-1][0].shape[0]) - 1  # the last density layer: raw density and the latent
    per_pixel = int(color[0][0].shape[1]) - latent
    return sum(int(w.size) for w, _ in density + color) - per_pixel * int(color[0][0].shape[0])


def render_field(assets: FieldAssets, intrinsics, world_to_camera, height: int, width: int, *,
                 query: str = "numpy", chunk: int = 16384, near: Optional[float] = None,
                 far: Optional[float] = None) -> dict[str, np.ndarray]:
    """Render colour (H, W, 3) linear RGB, planar depth (H, W) (+inf: no surface) and opacity (H, W).

    Args:
        assets: from :func:`load_field`.
        intrinsics, world_to_camera: the camera (validated: K finite and positive focal, pose rigid).
        query: ``numpy`` (this module's field evaluation) or ``onnx`` (``field.onnx`` in onnxruntime).
        near, far: planar-depth bounds of every ray (default: the scene's).

    Returns:
        ``color``, ``depth``, ``opacity``, ``evaluations`` (H, W) int32 (``evaluated_samples`` at
        ``TRANSMITTANCE_EPS``: what the GL renderer evaluates per pixel) and ``seconds`` (wall time, ray
        generation included).
    """
    if query not in ("numpy", "onnx"):
        raise InputError(f"must be numpy or onnx, got {query!r}", field="query")

    def evaluate(points: np.ndarray, coords: np.ndarray, directions: np.ndarray):
        if query == "numpy":
            return query_field(assets, coords, directions)
        return assets.onnx_session().run(None, {"points": points, "directions": directions})

    return march_field(assets, intrinsics, world_to_camera, height, width, evaluate, chunk=chunk, near=near, far=far,
                       shade=pixel_shader(assets), channels=assets.feature_dim)


def march_field(assets, intrinsics, world_to_camera, height: int, width: int, evaluate, *, chunk: int = 16384,
                near: Optional[float] = None, far: Optional[float] = None, shade: Optional[Callable] = None,
                channels: int = 3, transmittance_eps: float = TRANSMITTANCE_EPS) -> dict[str, np.ndarray]:
    """The ray marcher shared by the static and dynamic renderers.

    Args:
        assets: anything with ``scene``, ``manifest["render"]``, ``bounded``, ``occupancy`` and ``background``
            (:class:`FieldAssets`, ``engine.fields.dynamic.DynamicAssets``).
        evaluate: ``(points (M, 3) world, coords (M, 3) contracted, directions (M, 3) unit) -> (density (M,),
            colour (M, 3))`` at the kept samples (inside the cube, in occupied cells).
        shade: deferred shading: ``evaluate`` gives ``channels`` features a sample, composited on zeros, and
            ``shade(features (R, channels), opacity (R,), unit directions (R, 3)) -> RGB (R, 3)`` makes the colour.
        transmittance_eps: the early ray termination that ``evaluations`` counts with (the image is always the
            full march's).

    Returns:
        ``color``, ``depth``, ``opacity``, ``evaluations``, ``seconds``, as :func:`render_field`.
    """
    if int(height) < 1 or int(width) < 1:
        raise InputError(f"must be >= 1, got {height}x{width}", field="size")
    k = validate_intrinsics(intrinsics)
    pose = validate_pose(world_to_camera)
    start = time.perf_counter()
    scene, render = assets.scene, assets.manifest["render"]
    near = float(scene["near"] if near is None else near)
    far = float(scene["far"] if far is None else far)
    n = int(render["num_samples"])
    origin, dirs = camera_rays_np(k, pose, int(height), int(width))
    origin, dirs = origin.astype(np.float32), dirs.astype(np.float32)
    unit = dirs / np.linalg.norm(dirs, axis=-1, keepdims=True)
    count = dirs.shape[0]
    color = np.empty((count, 3), np.float32)
    depth = np.empty(count, np.float32)
    opacity = np.empty(count, np.float32)
    evaluations = np.empty(count, np.int32)
    for s in range(0, count, chunk):
        d = dirs[s:s + chunk]
        r = d.shape[0]
        t0, t1 = np.full(r, near, np.float32), np.full(r, far, np.float32)
        if assets.bounded:
            enter, leave = _ray_box(origin, d, np.asarray(scene["box_min"], np.float32),
                                    np.asarray(scene["box_max"], np.float32))
            t0, t1 = np.maximum(t0, enter), np.minimum(t1, leave)
        t, deltas = _samples(t0, t1, n, render["spacing"])
        points = origin + t[..., None] * d[:, None, :]
        coords = contract_np(scene, points, render["ndc_margin"])
        keep = (np.abs(coords) <= 1.0).all(axis=-1) & (deltas > 0)
        if assets.occupancy is not None:
            res = assets.occupancy.shape[0]
            idx = np.clip(np.floor((coords + 1.0) * (0.5 * res)).astype(np.int64), 0, res - 1)
            keep &= assets.occupancy[idx[..., 0], idx[..., 1], idx[..., 2]]
        sigma = np.zeros((r, n), np.float32)
        rgb = np.zeros((r, n, channels), np.float32)
        rows, cols = np.nonzero(keep)
        if rows.size:
            sigma[rows, cols], rgb[rows, cols] = evaluate(points[rows, cols], coords[rows, cols], unit[s + rows])
        lengths = deltas * np.linalg.norm(d, axis=-1, keepdims=True)  # t is camera z; density is per unit length
        if shade is None:
            color[s:s + r], depth[s:s + r], opacity[s:s + r] = composite_np(sigma, rgb, t, lengths, assets.background)
        else:
            zero = np.zeros(channels, np.float32)
            feats, depth[s:s + r], opacity[s:s + r] = composite_np(sigma, rgb, t, lengths, zero)
            color[s:s + r] = shade(feats, opacity[s:s + r], unit[s:s + r])
        evaluations[s:s + r] = evaluated_samples(keep, optical_depth(sigma, lengths), transmittance_eps)
    seconds = time.perf_counter() - start
    return {"color": color.reshape(height, width, 3), "depth": depth.reshape(height, width),
            "opacity": opacity.reshape(height, width), "evaluations": evaluations.reshape(height, width),
            "seconds": seconds}
