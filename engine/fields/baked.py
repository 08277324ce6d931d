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

A baked DeRF field (``baked_dynamic.json`` + ``baked_dynamic.npz``, ``models.fields.bake.bake_dynamic``;
``docs/field-assets.md``, "Baked dynamic fields") holds its canonical field as such bricks and its flow at the
vertices of a grid per time key: ``render_baked_dynamic`` moves each sample to its canonical point by the flow
(trilinear, linear in time between keys) and shades with the encoded time; ``engine.fields.glbaked`` renders both
in real time.

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
from engine.fields.dynamic import normalize_time, time_encoding_np
from engine.fields.encoding import direction_encoding_np
from engine.fields.manifest import DIRECTION_ENCODINGS, array_name, check_time_range, choice, number, section
from engine.fields.render import (ExportedAssets, array_getter, load_mlp, load_occupancy, march_field, pixel_shader,
                                  read_asset_files)

__all__ = ["BAKED_FORMAT", "BAKED_VERSION", "BAKED_DYNAMIC_FORMAT", "BAKED_DYNAMIC_VERSION", "BakedAssets",
           "BakedDynamicAssets", "load_baked", "load_baked_dynamic", "check_baked_layout", "query_baked",
           "lookup_bricks", "render_baked", "time_keys", "baked_flow", "query_baked_dynamic", "render_baked_dynamic",
           "trilinear_np", "BAKED_TRANSMITTANCE_EPS"]

BAKED_FORMAT, BAKED_VERSION = "interleave-baked-field", 1
BAKED_DYNAMIC_FORMAT, BAKED_DYNAMIC_VERSION = "interleave-baked-dynamic-field", 1
#: Largest grid side a manifest may ask for (a dense index of bricks^3 int32 is allocated).
MAX_RESOLUTION = 4096
#: The baked renderers' early ray termination (``engine.fields.glbaked``): a ray stops once its transmittance is
#: below one 8-bit step, so the samples it skips change a pixel's opacity and composited features by less than
#: 1/255, its colour by what the colour MLP makes of that (an exact renderer stops at
#: ``engine.fields.render.TRANSMITTANCE_EPS``, 1e-4). On the lego bakes: 7-14 % fewer evaluations,
#: 3-7 % less time a frame on llvmpipe, >= 65 dB against the 1e-4 render (docs/results/2026-11-30-baked-termination.md).
BAKED_TRANSMITTANCE_EPS = 1.0 / 255.0


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


def check_baked_layout(manifest: dict, file: Path, extra_inputs: int = 0) -> tuple[int, int, int, int]:
    """The ``grid`` and ``field`` sections of ``baked.json`` (``extra_inputs``: the colour MLP's inputs after the
    direction encoding, a baked dynamic field's encoded time); returns (resolution, brick, bricks, feature_dim)."""
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
    expected = features + direction_encoding_np(np.zeros((1, 3)), encoding, degree).shape[-1] + int(extra_inputs)
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
    return BakedAssets(manifest, *_load_bricks(root / "baked.json", root / "baked.npz", manifest, arrays))


def _load_bricks(meta_file: Path, npz_file: Path, manifest: dict, arrays: dict[str, np.ndarray],
                 extra_inputs: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray, list]:
    """A baked manifest's bricks, checked (:func:`check_baked_layout`): float32 raw densities, uint8 feature codes,
    the brick index, the colour MLP's layers."""
    _, brick, bricks, features = check_baked_layout(manifest, meta_file, extra_inputs)
    get = array_getter(arrays, npz_file, meta_file.name)
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
    return density.astype(np.float32), codes, index, layers


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
    sigma, feats, occupied = lookup_bricks(baked, coords)
    if not occupied.all():
        raise InputError(f"{int((~occupied).sum())} points lie in empty bricks", field="coords")
    return sigma, feats


def lookup_bricks(baked: BakedAssets, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Density (M,), features (M, G) and whether the brick is occupied (M,) bool at contracted coordinates
    (M, 3); density and features 0 in empty bricks."""
    coords = np.asarray(coords, np.float32)
    grid = baked.grid
    b, s, r = int(grid["bricks"]), int(grid["brick"]), int(grid["resolution"])
    cell = np.clip(np.floor((coords + np.float32(1.0)) * np.float32(0.5 * b)).astype(np.int64), 0, b - 1)
    k = baked.brick_index[cell[:, 0], cell[:, 1], cell[:, 2]]
    occupied = k >= 0
    sigma = np.zeros(coords.shape[0], np.float32)
    feats = np.zeros((coords.shape[0], baked.feature_dim), np.float32)
    if occupied.any():
        local = np.clip((coords[occupied] + np.float32(1.0)) * np.float32(0.5 * r)
                        - (cell[occupied] * s).astype(np.float32), 0.0, s)
        raw = trilinear_np(baked.density[k[occupied]][..., None], local)[:, 0]
        sigma[occupied] = np.exp(np.minimum(raw, np.float32(baked.manifest["field"]["max_log_density"])))
        feats[occupied] = trilinear_np(baked.features[k[occupied]], local) * np.float32(1.0 / 255.0)
    return sigma, feats, occupied


def render_baked(baked: BakedAssets, intrinsics, world_to_camera, height: int, width: int, *, chunk: int = 16384,
                 near: Optional[float] = None, far: Optional[float] = None,
                 transmittance_eps: float = BAKED_TRANSMITTANCE_EPS) -> dict[str, np.ndarray]:
    """Render a baked field: ``color`` (H, W, 3) linear RGB, ``depth`` (H, W) planar (+inf: nothing hit),
    ``opacity``, ``evaluations`` (H, W) (samples in occupied bricks up to early termination at
    ``transmittance_eps``, what the GL renderer evaluates; the image is the full march's) and ``seconds``;
    arguments as :func:`engine.fields.render.render_field`."""
    return march_field(baked, intrinsics, world_to_camera, height, width,
                       lambda points, coords, directions: query_baked(baked, coords), chunk=chunk, near=near,
                       far=far, shade=pixel_shader(baked), channels=baked.feature_dim,
                       transmittance_eps=transmittance_eps)


# ----------------------------------------------------------------------------------------------------
# Baked dynamic fields (``docs/dynamic_fields.md``, "Baking a dynamic field"): the numpy oracle


@dataclass(eq=False)
class BakedDynamicAssets(BakedAssets):
    """A baked DeRF field (``baked_dynamic.json`` + ``baked_dynamic.npz``, ``models.fields.bake.bake_dynamic``): the
    canonical field's bricks (:class:`BakedAssets`' attributes, looked up at the canonical point), and

    Attributes:
        motion: (K, M, M, M, 3) float32 flow ``c' - c`` (contracted units) at the vertices of an M^3 grid over the
            cube (vertex i at ``-1 + 2 i / (M - 1)``, indexed [key, ix, iy, iz]) at the K time keys
            ``tau_k = -1 + 2 k / (K - 1)``.
        sample_occupancy: (R, R, R) bool time-agnostic occupancy grid at the samples' points (the exact export's),
            or None: what the marcher skips by (:attr:`occupancy`).
    """

    motion: np.ndarray = field(default=None, repr=False)
    sample_occupancy: Optional[np.ndarray] = field(default=None, repr=False)

    @property
    def occupancy(self) -> Optional[np.ndarray]:
        """The marcher's grid: at the samples' points, before the motion (the bricks are in canonical space)."""
        return self.sample_occupancy

    @property
    def time_range(self) -> tuple[float, float]:
        t0, t1 = self.manifest["time"]["range"]
        return float(t0), float(t1)


def load_baked_dynamic(path: str | Path) -> BakedDynamicAssets:
    """Load a baked dynamic field from a folder (or its ``baked_dynamic.json``).

    Raises:
        InputError (naming the file and the key or array): missing files, another format or version, a bad
        manifest, arrays whose shapes or values disagree with it.
    """
    root, manifest, arrays = read_asset_files(path, "baked_dynamic", BAKED_DYNAMIC_FORMAT, BAKED_DYNAMIC_VERSION,
                                              "models.fields.bake.bake_dynamic", onnx=False)
    meta_file, npz_file = root / "baked_dynamic.json", root / "baked_dynamic.npz"
    frequencies = int(number(section(manifest, "field", meta_file), "time_frequencies", meta_file, "field", low=0,
                             high=16, integer=True))
    check_time_range(manifest, meta_file)
    keys = int(number(section(manifest, "time", meta_file), "keys", meta_file, "time", low=2, high=4096, integer=True))
    motion = section(manifest, "motion", meta_file)
    m = int(number(motion, "resolution", meta_file, "motion", low=2, high=512, integer=True))
    array_name(motion, "array", meta_file, "motion")
    bricks = _load_bricks(meta_file, npz_file, manifest, arrays, 2 * frequencies + 1)
    get = array_getter(arrays, npz_file, meta_file.name)
    flows = get(motion["array"], "motion.array")
    if flows.shape != (keys, m, m, m, 3) or flows.dtype.kind != "f":
        raise InputError(f"array {motion['array']!r} has shape {flows.shape} / {flows.dtype}, expected float "
                         f"({keys}, {m}, {m}, {m}, 3)", file=npz_file)
    return BakedDynamicAssets(manifest, *bricks, motion=flows.astype(np.float32),
                              sample_occupancy=load_occupancy(manifest, get, npz_file))


def time_keys(tau: float, keys: int) -> tuple[int, np.float32]:
    """The first of the two time keys around normalised time ``tau`` (keys at ``-1 + 2 k / (keys - 1)``) and the
    second's weight in [0, 1] (float32 arithmetic, as the GL renderer's uniforms)."""
    position = (np.float32(tau) + np.float32(1.0)) * np.float32(0.5 * (keys - 1))
    k0 = min(int(np.floor(position)), keys - 2)
    return k0, np.float32(position - k0)


def baked_flow(baked: BakedDynamicAssets, coords: np.ndarray, tau: float) -> np.ndarray:
    """The baked flow (M, 3) at contracted coordinates (M, 3) and normalised time ``tau``: the flow grid at tau
    (the two time keys around tau blended linearly, in float32), looked up trilinearly (clamped to the grid). The
    same as blending the two keys' lookups; blending the grids first is what the GL renderer does once a frame."""
    coords = np.asarray(coords, np.float32)
    m = baked.motion.shape[1]
    k0, w = time_keys(tau, baked.motion.shape[0])
    local = np.clip((coords + np.float32(1.0)) * np.float32(0.5 * (m - 1)), 0.0, m - 1).astype(np.float32)
    n = coords.shape[0]
    grid = (baked.motion[k0] * (np.float32(1.0) - w) + baked.motion[k0 + 1] * w).astype(np.float32)
    return trilinear_np(np.broadcast_to(grid, (n,) + grid.shape), local).astype(np.float32)


def query_baked_dynamic(baked: BakedDynamicAssets, coords: np.ndarray, tau: float) -> tuple[np.ndarray, np.ndarray]:
    """Density (M,) and features (M, G) at contracted coordinates (M, 3) at normalised time ``tau``: the canonical
    point ``clamp(c + baked_flow, -1, 1)`` looked up in the canonical bricks (0 in an empty brick)."""
    coords = np.asarray(coords, np.float32)
    canonical = np.clip(coords + baked_flow(baked, coords, tau), -1.0, 1.0)
    sigma, feats, _ = lookup_bricks(baked, canonical)
    return sigma, feats


def render_baked_dynamic(baked: BakedDynamicAssets, intrinsics, world_to_camera, height: int, width: int,
                         time: float, *, chunk: int = 16384, near: Optional[float] = None, far: Optional[float] = None,
                         transmittance_eps: float = BAKED_TRANSMITTANCE_EPS) -> dict[str, np.ndarray]:
    """Render a baked dynamic field at ``time`` (the data's units, inside the trained range): as
    :func:`render_baked`, the samples skipped by the time-agnostic occupancy grid at their own points, the colour
    MLP once per pixel on the composited features, the view direction and the encoded time."""
    tau = normalize_time(time, baked.time_range)
    extra = time_encoding_np(np.array([tau], np.float32), int(baked.manifest["field"]["time_frequencies"]))[0]
    return march_field(baked, intrinsics, world_to_camera, height, width,
                       lambda points, coords, directions: query_baked_dynamic(baked, coords, tau), chunk=chunk,
                       near=near, far=far, shade=pixel_shader(baked, extra), channels=baked.feature_dim,
                       transmittance_eps=transmittance_eps)
