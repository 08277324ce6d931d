"""A baked static field (``baked.json`` + ``baked.npz``, written by ``interleave export field`` for a field
trained with deferred shading; format in ``docs/field-assets.md``, "Baked fields"): its loader and numpy
renderer, the oracle of the GL renderer ``engine.fields.glbaked``.

The baked field replaces the tri-plane features and the density MLP by a sparse grid: the field's cube
[-1, 1]^3 is split into ``bricks``^3 bricks of ``brick``^3 cells (``resolution = bricks * brick`` cells a
side); an occupied brick stores its (brick + 1)^3 vertices (shared faces are stored twice, so a lookup never
leaves its brick), each with the raw log-density (float16; ``sigma = exp(min(raw, max_log_density))``) and the
deferred features ``sigmoid(h)`` as uint8 codes (``code / 255``). A point's values are the trilinear
interpolation of its brick's vertices (raw density before ``exp``, features after the sigmoid); outside an
occupied brick the density is 0. Rays are sampled as the exact field's (``render`` section: the same bin
centres), samples outside occupied bricks are skipped, the features are composited with the volume-rendering
weights and the colour MLP runs once per pixel (``engine.fields.render.shade_pixels_np``), so nothing but the
grid's interpolation and quantisation differs from the exact render of the same field.

Conventions: those of ``engine.fields.render`` (OpenCV cameras, planar depth, +inf where nothing is hit).

>>> baked = load_baked("runs/lego/export")                              # doctest: +SKIP
>>> out = render_baked(baked, K, world_to_camera, 540, 960)             # doctest: +SKIP
"""
from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Optional

import numpy as np

from engine.core.errors import InputError
from engine.fields.encoding import direction_encoding_np
from engine.fields.manifest import DIRECTION_ENCODINGS, array_name, choice, number, section
from engine.fields.render import ExportedAssets, array_getter, load_mlp, march_field, pixel_shader, read_asset_files

__all__ = ["BAKED_FORMAT", "BAKED_VERSION", "BakedAssets", "load_baked", "check_baked_layout", "query_baked",
           "render_baked", "trilinear_np"]

BAKED_FORMAT, BAKED_VERSION = "interleave-baked-field", 1
#: Largest grid side a manifest may ask for (a dense index of bricks^3 int32 is allocated).
MAX_RESOLUTION = 4096


@dataclass(eq=False)
class BakedAssets(ExportedAssets):
    """A baked field in memory.

    Attributes:
        manifest: ``baked.json``.
        density: (n, V, V, V) float32 raw log-density of each occupied brick's vertices, indexed [brick, ix, iy,
            iz] (V = brick + 1).
        features: (n, V, V, V, G) uint8 codes of the features ``sigmoid(h)`` (value = code / 255).
        brick_index: (B, B, B) int32 [bx, by, bz] -> the brick's row of ``density`` / ``features``, -1 empty.
        color_layers: the colour MLP's ``(weight (out, in), bias (out,))`` layers, ReLU between.
    """

    manifest: dict
    density: np.ndarray = field(repr=False)
    features: np.ndarray = field(repr=False)
    brick_index: np.ndarray = field(repr=False)
    color_layers: list[tuple[np.ndarray, np.ndarray]] = field(repr=False)
    onnx_path: Optional[Path] = None
    _session: object = field(default=None, repr=False)

    @property
    def occupancy(self) -> np.ndarray:
        """(B, B, B) bool: the occupied bricks (what the marcher skips by, as an exact field's occupancy grid)."""
        return self.brick_index >= 0

    @property
    def deferred(self) -> bool:
        """Always: a baked field is shaded once per pixel (``engine.fields.render.pixel_shader``)."""
        return True

    @property
    def grid(self) -> dict:
        return self.manifest["grid"]

    @property
    def feature_dim(self) -> int:
        return int(self.features.shape[-1])


def check_baked_layout(manifest: dict, file: Path) -> tuple[int, int, int, int]:
    """The ``grid`` and ``field`` sections of ``baked.json``; returns (resolution, brick, bricks, feature_dim)."""
    grid = section(manifest, "grid", file)
    resolution = int(number(grid, "resolution", file, "grid", low=1, high=MAX_RESOLUTION, integer=True))
    brick = int(number(grid, "brick", file, "grid", low=1, high=64, integer=True))
    bricks = int(number(grid, "bricks", file, "grid", low=1, high=MAX_RESOLUTION, integer=True))
    if bricks * brick != resolution:
        raise InputError(f"must be resolution / brick = {resolution} / {brick}, got {bricks}", file=file,
                         field="grid.bricks")
    for key in ("density", "features", "index"):
        array_name(grid, key, file, "grid")
    spec = section(manifest, "field", file)
    encoding = choice(spec, "direction_encoding", tuple(DIRECTION_ENCODINGS), file, "field")
    low, high = DIRECTION_ENCODINGS[encoding]
    degree = int(number(spec, "direction_degree", file, "field", low=low, high=high, integer=True))
    number(spec, "max_log_density", file, "field", high=80.0)
    features = int(number(spec, "feature_dim", file, "field", low=3, high=1024, integer=True))
    layers = section(spec, "mlps", file, "field").get("color")
    if not isinstance(layers, list) or not layers:
        raise InputError("must be a non-empty list of layers", file=file, field="field.mlps.color")
    expected = features + direction_encoding_np(np.zeros((1, 3)), encoding, degree).shape[-1]
    for i, layer in enumerate(layers):
        where = f"field.mlps.color[{i}]"
        if not isinstance(layer, dict):
            raise InputError("must be an object", file=file, field=where)
        if number(layer, "in", file, where, low=1, integer=True) != expected:
            raise InputError(f"must be {expected} (what feeds this layer), got {layer['in']}", file=file,
                             field=f"{where}.in")
        expected = int(number(layer, "out", file, where, low=1, high=4096, integer=True))
        array_name(layer, "weight", file, where)
        array_name(layer, "bias", file, where)
    if expected != 3:
        raise InputError(f"must be 3, got {expected}", file=file, field=f"field.mlps.color[{len(layers) - 1}].out")
    return resolution, brick, bricks, features


def load_baked(path: str | Path) -> BakedAssets:
    """Load a baked field from a folder (or its ``baked.json``).

    Raises:
        InputError (naming the file and the key or array): missing files, another format or version, a bad
        manifest, arrays whose shapes or values disagree with it.
    """
    root, manifest, arrays = read_asset_files(path, "baked", BAKED_FORMAT, BAKED_VERSION,
                                              "interleave export field RUN_DIR (a field trained with "
                                              "--field.shading deferred)", onnx=False)
    meta_file, npz_file = root / "baked.json", root / "baked.npz"
    _, brick, bricks, features = check_baked_layout(manifest, meta_file)
    get = array_getter(arrays, npz_file, "baked.json")
    grid = manifest["grid"]
    density = get(grid["density"], "grid.density")
    codes = get(grid["features"], "grid.features")
    index = get(grid["index"], "grid.index")
    v = brick + 1
    n = density.shape[0] if density.ndim == 4 else -1
    if density.ndim != 4 or density.shape[1:] != (v, v, v) or density.dtype.kind != "f":
        raise InputError(f"array {grid['density']!r} has shape {density.shape} / {density.dtype}, expected float "
                         f"(bricks, {v}, {v}, {v})", file=npz_file)
    if codes.shape != (n, v, v, v, features) or codes.dtype != np.uint8:
        raise InputError(f"array {grid['features']!r} has shape {codes.shape} / {codes.dtype}, expected uint8 "
                         f"({n}, {v}, {v}, {v}, {features})", file=npz_file)
    if index.shape != (bricks,) * 3 or index.dtype.kind not in "iu":
        raise InputError(f"array {grid['index']!r} has shape {index.shape} / {index.dtype}, expected integer "
                         f"({bricks}, {bricks}, {bricks})", file=npz_file)
    index = index.astype(np.int32)
    used = np.sort(index[index >= 0])
    if index.min(initial=-1) < -1 or not np.array_equal(used, np.arange(n)):
        raise InputError(f"array {grid['index']!r} must name each of the {n} bricks once (-1: empty)",
                         file=npz_file)
    layers = load_mlp(manifest["field"]["mlps"]["color"], get, "color", npz_file)
    return BakedAssets(manifest, density.astype(np.float32), codes, index, layers)


def trilinear_np(values: np.ndarray, local: np.ndarray) -> np.ndarray:
    """Per point, the trilinear interpolation of its brick's vertices ``values`` (M, V, V, V, C) at ``local``
    (M, 3) in [0, V - 1] (vertex units): bilinear in x, y on the two z layers, then linear in z (the GL
    renderer's order), float32 -> (M, C)."""
    last = values.shape[1] - 2
    i0 = np.minimum(np.floor(local), last).astype(np.int64)
    f = (local - i0).astype(np.float32)
    m = np.arange(values.shape[0])
    fx, fy, fz = (f[:, a, None] for a in range(3))
    layers = []
    for dz in (0, 1):
        z = i0[:, 2] + dz

        def at(dx, dy):
            return values[m, i0[:, 0] + dx, i0[:, 1] + dy, z].astype(np.float32)
        layers.append((at(0, 0) * (1 - fx) + at(1, 0) * fx) * (1 - fy) + (at(0, 1) * (1 - fx) + at(1, 1) * fx) * fy)
    return layers[0] * (1 - fz) + layers[1] * fz


def query_baked(baked: BakedAssets, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Density (M,) per scene unit and features (M, G) at contracted coordinates (M, 3) in occupied bricks."""
    coords = np.asarray(coords, np.float32)
    grid = baked.grid
    b, s, r = int(grid["bricks"]), int(grid["brick"]), int(grid["resolution"])
    cell = np.clip(np.floor((coords + np.float32(1.0)) * np.float32(0.5 * b)).astype(np.int64), 0, b - 1)
    k = baked.brick_index[cell[:, 0], cell[:, 1], cell[:, 2]]
    if (k < 0).any():
        raise InputError(f"{int((k < 0).sum())} points lie in empty bricks", field="coords")
    local = np.clip((coords + np.float32(1.0)) * np.float32(0.5 * r) - (cell * s).astype(np.float32), 0.0, s)
    raw = trilinear_np(baked.density[k][..., None], local)[:, 0]
    feats = trilinear_np(baked.features[k], local) * np.float32(1.0 / 255.0)
    sigma = np.exp(np.minimum(raw, np.float32(baked.manifest["field"]["max_log_density"])))
    return sigma.astype(np.float32), feats.astype(np.float32)


def render_baked(baked: BakedAssets, intrinsics, world_to_camera, height: int, width: int, *, chunk: int = 16384,
                 near: Optional[float] = None, far: Optional[float] = None) -> dict[str, np.ndarray]:
    """Render a baked field: ``color`` (H, W, 3) linear RGB, ``depth`` (H, W) planar (+inf: nothing hit),
    ``opacity``, ``evaluations`` (H, W) (samples in occupied bricks up to early termination) and ``seconds``;
    arguments as :func:`engine.fields.render.render_field`."""
    return march_field(baked, intrinsics, world_to_camera, height, width,
                       lambda points, coords, directions: query_baked(baked, coords), chunk=chunk, near=near,
                       far=far, shade=pixel_shader(baked), channels=baked.feature_dim)
