"""Bake a static field trained with deferred shading into the sparse brick grid of ``engine.fields.baked``.

``bake_static(model, resolution)`` returns ``(arrays, manifest)`` of ``baked.npz`` / ``baked.json``
(``docs/field-assets.md``, "Baked fields"): the bricks are the cells of the model's occupancy grid that it marks
occupied (so the baked field skips exactly the samples the exact renderer skips), or, for a field without a grid,
the bricks in which some vertex's density reaches the grid's threshold (``StaticFieldModel.occupancy_threshold``).
Each occupied brick stores raw log-density (float16) and deferred features ``sigmoid(h)`` (uint8) at its vertices,
fitted by least squares so that the brick's trilinear interpolation matches the field at its vertices and cell
centres (:func:`fit_matrix`); the colour MLP is the field's own. ``interleave export field`` writes them beside
the exact assets and records the PSNR of the baked render against the exact one on a view.
"""
from __future__ import annotations

from typing import Iterator, Optional

import numpy as np
import torch

from engine.core.errors import InputError
from engine.fields.baked import BAKED_DYNAMIC_FORMAT, BAKED_DYNAMIC_VERSION, BAKED_FORMAT, BAKED_VERSION
from models.fields.assets import _add_mlps, _render_section, direction_degree
from models.fields.dynamic.model import DynamicFieldModel
from models.fields.static.field import MAX_LOG_DENSITY

__all__ = ["DEFAULT_RESOLUTION", "DEFAULT_MOTION_RESOLUTION", "LOWEST_RAW_DENSITY", "bake_static", "bake_dynamic",
           "bakes_dynamic", "motion_keys", "fit_points", "fit_matrix", "fit_bricks",
           "write_baked", "baked_check"]

#: Grid cells per side of the field's cube: 4 cells per occupancy cell of the default 64^3 grid.
DEFAULT_RESOLUTION = 256
#: Flow vertices per side of a baked dynamic field's motion grid. The flow's trilinear approximation is nearly all of
#: a bake's error (lego: 47-49 dB against the exact render with the exact flow): at 33 (the finest motion plane's
#: texels) the worst held-out view was 34.5 dB, at 49 38.9-39.5 (a 512x512 GL frame 2 ms slower on llvmpipe), at 65
#: 40.6-41.2 (4 ms slower; docs/results/2026-11-30-gl-march-speed.md).
DEFAULT_MOTION_RESOLUTION = 49
#: Raw log-densities are clamped below here before float16 (exp(-30) per scene unit is empty at any step).
LOWEST_RAW_DENSITY = -30.0


def fit_points(brick: int) -> torch.Tensor:
    """(P, 3) float64 points of a brick in vertex units ([0, brick] a side) at which its vertex values are fitted:
    its (brick + 1)^3 vertices, then its brick^3 cell centres (the vertices' interpolation is worst there)."""
    v = torch.arange(brick + 1, dtype=torch.float64)
    c = torch.arange(brick, dtype=torch.float64) + 0.5
    return torch.cat([torch.stack(torch.meshgrid(a, a, a, indexing="ij"), dim=-1).reshape(-1, 3) for a in (v, c)])


def fit_matrix(brick: int, local: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(V^3, P) float32 least-squares solve: vertex values ``S @ f`` (vertices flattened [ix, iy, iz]) minimise the
    squared error of the brick's trilinear interpolation against values ``f`` (P,) at ``local`` (P, 3) vertex-unit
    points (default :func:`fit_points`; the vertices alone give the identity: sampling).

    Sampling the field at the vertices alone makes the interpolation exact there and worst between them; on a
    forward-facing field baked at 256 (planes up to 256 texels) the fit gains 1.3-1.5 dB against the exact render
    (docs/results/2026-12-01-baked-fit.md). A field trilinear within the brick is reproduced exactly."""
    local = fit_points(brick) if local is None else local.double()
    v = brick + 1
    i0 = torch.clamp(torch.floor(local), max=brick - 1).long()
    f = local - i0
    rows = torch.arange(local.shape[0])
    weights = torch.zeros(local.shape[0], v, v, v, dtype=torch.float64)
    for dx in (0, 1):
        for dy in (0, 1):
            for dz in (0, 1):
                w = (f[:, 0] if dx else 1 - f[:, 0]) * (f[:, 1] if dy else 1 - f[:, 1]) * \
                    (f[:, 2] if dz else 1 - f[:, 2])
                weights.index_put_((rows, i0[:, 0] + dx, i0[:, 1] + dy, i0[:, 2] + dz), w, accumulate=True)
    return torch.linalg.pinv(weights.reshape(local.shape[0], -1)).float()


@torch.no_grad()
def _raw_outputs(field, coords: torch.Tensor, chunk: int) -> tuple[torch.Tensor, torch.Tensor]:
    """The raw log-density (clamped, bias added) and features sigmoid(h) at (..., 3) coordinates of a field of
    tri-planes (``encoding``, ``density_mlp``, ``config``: a static field, a DeRF canonical field of tri-planes)."""
    flat = coords.reshape(-1, 3)
    raws, feats = [], []
    for i in range(0, flat.shape[0], chunk):
        out = field.density_mlp(field.encoding(flat[i:i + chunk]))
        raws.append(torch.clamp(out[:, 0] + field.config.density_bias, LOWEST_RAW_DENSITY, MAX_LOG_DENSITY))
        feats.append(torch.sigmoid(out[:, 1:]))
    return (torch.cat(raws).reshape(coords.shape[:-1]),
            torch.cat(feats).reshape(*coords.shape[:-1], -1))


def _check_resolution(resolution) -> None:
    """The grid's cells a side: a multiple of 4 (bricks of 4 cells where no occupancy grid sets them) in
    [4, 4096]; a field with an occupancy grid also needs a multiple of its resolution (:func:`_occupied_bricks`)."""
    if isinstance(resolution, bool) or not isinstance(resolution, int) or not 4 <= resolution <= 4096 \
            or resolution % 4:
        raise InputError(f"must be a multiple of 4 in [4, 4096], got {resolution!r}", field="bake_resolution")


def _occupied_bricks(model, field, resolution: int, chunk: int, use_grid: bool = True
                     ) -> tuple[torch.Tensor, int, bool]:
    """(B, B, B) bool of the occupied bricks, B, and whether they came from the model's occupancy grid
    (``use_grid``, once updated) rather than ``field``'s density at the brick vertices against the model's
    occupancy threshold (:func:`_vertex_occupancy`)."""
    grid = model.occupancy
    if use_grid and grid is not None and int(grid.updates) > 0:
        bricks = int(grid.resolution)
        if resolution % bricks:
            raise InputError(f"must be a multiple of the field's occupancy grid ({bricks}), got {resolution}",
                             field="bake_resolution")
        return grid.occupied.cpu().clone(), bricks, True
    threshold = float(np.log(model.occupancy_threshold()))
    return _vertex_occupancy(field, resolution, threshold, chunk), resolution // 4, False


def _vertex_plane(field, x: int, resolution: int, chunk: int) -> torch.Tensor:
    """(R + 1, R + 1) raw log-density of ``field`` at the grid vertices of x index ``x`` (R = ``resolution``;
    vertex (x, y, z) at ``-1 + 2 (x, y, z) / R``), indexed [y, z]."""
    axis = torch.arange(resolution + 1, dtype=torch.float64)
    y, z = torch.meshgrid(axis, axis, indexing="ij")
    points = torch.stack([torch.full_like(y, float(x)), y, z], dim=-1) * (2.0 / resolution) - 1.0
    return _raw_outputs(field, points.float(), chunk)[0]


def _vertex_occupancy(field, resolution: int, threshold: float, chunk: int) -> torch.Tensor:
    """(B, B, B) bool, B = R / 4: bricks of 4 cells a side whose largest raw log-density at their 5^3 vertices
    reaches ``threshold``. Each vertex of the grid is evaluated once, one x plane at a time (a vertex is shared by
    up to 8 bricks: (R + 1)^3 evaluations where brick by brick took 125 B^3, about 1.95 R^3); a brick's maximum
    is the largest over its 5 x planes, then a 5 x 5 window at stride 4 over y and z."""
    bricks = resolution // 4
    occupied = torch.zeros(bricks, bricks, bricks, dtype=torch.bool)
    plane = _vertex_plane(field, 0, resolution, chunk)
    for bx in range(bricks):
        slab = [plane] + [_vertex_plane(field, 4 * bx + j, resolution, chunk) for j in range(1, 5)]
        plane = slab[-1]
        top = torch.stack(slab).amax(dim=0)
        occupied[bx] = torch.nn.functional.max_pool2d(top[None, None], kernel_size=5, stride=4)[0, 0] >= threshold
    return occupied


def bake_static(model, resolution: int = DEFAULT_RESOLUTION, *, chunk: int = 1 << 16
                ) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, manifest)`` of the baked form of a :class:`models.fields.static.model.StaticFieldModel` trained
    with deferred shading, at ``resolution`` grid cells a side.

    Raises:
        InputError: a per-sample field (nothing to bake exactly), a resolution that is not a multiple of 4
            and of the occupancy grid's.
    """
    if not model.field.deferred:
        raise InputError("bakes only fields trained with deferred shading (--field.shading deferred)",
                         field="field.shading")
    _check_resolution(resolution)
    model = model.eval()
    arrays, grid = _bake_bricks(model, model.field, resolution, chunk)
    manifest = {
        "format": BAKED_FORMAT, "version": BAKED_VERSION,
        "scene": model.scene.to_dict(), "background": [float(x) for x in model.background],
        "render": _render_section(model), "grid": grid, "field": _baked_field_section(arrays, model.field),
    }
    return arrays, manifest


def fit_bricks(field, cells: torch.Tensor, brick: int, resolution: int, chunk: int = 1 << 16,
               local: Optional[torch.Tensor] = None) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """The fitted vertex values of bricks ``cells`` (n, 3) of ``field`` (see :func:`_raw_outputs`), in chunks of
    bricks: raw log-density (m, V, V, V) clamped to [LOWEST_RAW_DENSITY, MAX_LOG_DENSITY] and features (m, V, V, V,
    G) clamped to [0, 1], before rounding; fitted at ``local`` (default :func:`fit_points`, see
    :func:`fit_matrix`)."""
    local = fit_points(brick) if local is None else local.double()
    solve, v = fit_matrix(brick, local), brick + 1
    step = max(1, chunk // local.shape[0])
    for i in range(0, cells.shape[0], step):
        points = (cells[i:i + step].double()[:, None, :] * brick + local) * (2.0 / resolution) - 1.0
        raw, feat = _raw_outputs(field, points.float(), chunk)  # (m, P), (m, P, G)
        raw = torch.einsum("vp,np->nv", solve, raw).clamp(LOWEST_RAW_DENSITY, MAX_LOG_DENSITY)
        feat = torch.einsum("vp,npg->nvg", solve, feat).clamp(0.0, 1.0)
        yield raw.reshape(-1, v, v, v), feat.reshape(-1, v, v, v, feat.shape[-1])


def _bake_bricks(model, field, resolution: int, chunk: int, use_grid: bool = True
                 ) -> tuple[dict[str, np.ndarray], dict]:
    """The brick arrays (``density``, ``features``, ``brick_index``) of ``field`` (see :func:`_raw_outputs`) and
    the manifest's ``grid`` section; bricks as :func:`_occupied_bricks`."""
    occupied, bricks, from_grid = _occupied_bricks(model, field, resolution, chunk, use_grid)
    brick = resolution // bricks
    cells = occupied.nonzero()
    index = torch.full((bricks,) * 3, -1, dtype=torch.int32)
    index[cells[:, 0], cells[:, 1], cells[:, 2]] = torch.arange(cells.shape[0], dtype=torch.int32)
    raws, feats = [], []
    for raw, feat in fit_bricks(field, cells, brick, resolution, chunk):
        raws.append(raw.numpy().astype(np.float16))
        feats.append(np.rint(feat.numpy() * 255.0).astype(np.uint8))
    v = brick + 1
    arrays = {"density": np.concatenate(raws) if raws else np.zeros((0, v, v, v), np.float16),
              "features": (np.concatenate(feats) if feats
                           else np.zeros((0, v, v, v, field.config.geo_feature_dim), np.uint8)),
              "brick_index": index.numpy()}
    grid = {"resolution": int(resolution), "brick": int(brick), "bricks": int(bricks),
            "count": int(cells.shape[0]), "occupied_fraction": float(occupied.float().mean()),
            "density": "density", "features": "features", "index": "brick_index",
            "bricks_from": "occupancy grid" if from_grid else "vertex density >= the occupancy threshold"}
    return arrays, grid


def _baked_field_section(arrays: dict[str, np.ndarray], field) -> dict:
    """The manifest's ``field`` section of a baked field shaded by ``field``'s colour MLP (written to ``arrays``)."""
    cfg = field.config
    return {"feature_dim": int(cfg.geo_feature_dim), "max_log_density": MAX_LOG_DENSITY,
            "direction_encoding": cfg.direction_encoding, "direction_degree": direction_degree(cfg),
            "shading": "deferred", "mlps": _add_mlps(arrays, {"color": field.color_mlp})}


@torch.no_grad()
def motion_keys(model, resolution: int, *, chunk: int = 1 << 16) -> np.ndarray:
    """A DeRF field's flow ``c' - c`` (contracted units) at the vertices of a ``resolution``^3 grid over the cube
    (vertex i at ``-1 + 2 i / (resolution - 1)``, indexed [key, ix, iy, iz]) at each of the time planes' rows
    ``tau_k = -1 + 2 k / (Rt - 1)``: (Rt, M, M, M, 3) float16."""
    axis = torch.linspace(-1.0, 1.0, resolution)
    points = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1).reshape(-1, 3)
    keys = []
    for tau in torch.linspace(-1.0, 1.0, int(model.time_resolution)):
        flows = []
        for i in range(0, points.shape[0], chunk):
            part = points[i:i + chunk]
            flows.append(model.field.motion_field(part, part.new_full(part.shape[:1], float(tau))))
        keys.append(torch.cat(flows).reshape(resolution, resolution, resolution, 3).numpy().astype(np.float16))
    return np.stack(keys)


def bake_dynamic(model, resolution: int = DEFAULT_RESOLUTION, motion_resolution: int = DEFAULT_MOTION_RESOLUTION, *,
                 chunk: int = 1 << 16) -> tuple[dict[str, np.ndarray], dict]:
    """``(arrays, manifest)`` of the baked form of a DeRF field trained with deferred shading whose canonical field
    is tri-planes (``--field.canonical.shading deferred --no-field.canonical-time``; ``docs/dynamic_fields.md``,
    "Baking a dynamic field"), read by ``engine.fields.baked.load_baked_dynamic``: the canonical field's bricks
    (as :func:`bake_static`'s, occupied where a vertex's density reaches the occupancy threshold: the occupancy
    grid is over the samples' points, not the canonical ones), the flow at ``motion_resolution``^3 vertices per
    time key (:func:`motion_keys`), the (time-agnostic) occupancy grid at the samples' points and the colour MLP.

    Raises:
        InputError: a K-Planes or per-sample field, a canonical field with time planes, a bad resolution.
    """
    if not bakes_dynamic(model):
        raise InputError("bakes only DeRF fields trained with deferred shading and a canonical field of tri-planes "
                         "(--field.canonical.shading deferred --no-field.canonical-time)", field="field")
    _check_resolution(resolution)
    if isinstance(motion_resolution, bool) or not isinstance(motion_resolution, int) or not 2 <= motion_resolution \
            <= 512:
        raise InputError(f"must be an integer in [2, 512], got {motion_resolution!r}", field="motion_resolution")
    model = model.eval()
    canonical = model.field.canonical_field
    arrays, grid = _bake_bricks(model, canonical, resolution, chunk, use_grid=False)
    arrays["motion"] = motion_keys(model, motion_resolution, chunk=chunk)
    occupancy = None
    if model.occupancy is not None and int(model.occupancy.updates) > 0:
        arrays["occupancy"] = model.occupancy.occupied.cpu().numpy().astype(np.uint8)
        occupancy = {"array": "occupancy", "resolution": int(model.occupancy.resolution),
                     "time_agnostic": "max over trained times"}
    t0, t1 = model.time_range
    manifest = {
        "format": BAKED_DYNAMIC_FORMAT, "version": BAKED_DYNAMIC_VERSION,
        "scene": model.scene.to_dict(), "background": [float(x) for x in model.background],
        "render": _render_section(model), "grid": grid,
        "time": {"range": [t0, t1], "keys": int(model.time_resolution)},
        "motion": {"array": "motion", "resolution": int(motion_resolution),
                   "flow": "c' = clamp(c + lerp over the two time keys of trilinear flows, -1, 1)"},
        "occupancy": occupancy,
        "field": {**_baked_field_section(arrays, canonical), "time_frequencies": int(model.config.time_frequencies)},
    }
    return arrays, manifest


def baked_check(exact_dir, baked_dir, camera, time: Optional[float] = None) -> Optional[dict]:
    """PSNR (display-encoded) of the baked render against the exact render of the same field on one view, both
    with the numpy renderers; ``camera``: (K, world_to_camera, H, W); ``time``: a dynamic field's (its exact and
    baked assets), None for a static one."""
    from engine.core.colorspace import display_encode
    from engine.eval.metrics import psnr
    from engine.fields.baked import load_baked, load_baked_dynamic, render_baked, render_baked_dynamic
    from engine.fields.dynamic import load_dynamic_field, render_dynamic_field
    from engine.fields.render import load_field, render_field

    k, w2c, h, w = camera
    if time is None:
        exact = render_field(load_field(exact_dir), k, w2c, h, w)
        baked = render_baked(load_baked(baked_dir), k, w2c, h, w)
    else:
        exact = render_dynamic_field(load_dynamic_field(exact_dir), k, w2c, h, w, time)
        baked = render_baked_dynamic(load_baked_dynamic(baked_dir), k, w2c, h, w, time)
    value = psnr(display_encode(exact["color"]), display_encode(baked["color"]))
    return {"psnr_baked_vs_exact": float(value) if np.isfinite(value) else None, "view_size": [int(h), int(w)],
            "mean_evaluations": {"exact": float(exact["evaluations"].mean()),
                                 "baked": float(baked["evaluations"].mean())}}


def write_baked(model, out_dir, resolution: int = DEFAULT_RESOLUTION, camera=None, time: Optional[float] = None
                ) -> dict:
    """Bake ``model`` into ``out_dir/baked.npz`` + ``baked.json`` (a static field, beside its exact export, whose
    ``field.json`` the check reads) or ``baked_dynamic.npz`` + ``baked_dynamic.json`` (a DeRF field,
    :func:`bake_dynamic`, beside ``dynamic.json``); with ``camera`` (K, world_to_camera, H, W) the manifest records
    :func:`baked_check` (at ``time`` for a dynamic field)."""
    import json
    from pathlib import Path

    out = Path(out_dir)
    dynamic = isinstance(model, DynamicFieldModel)
    stem = "baked_dynamic" if dynamic else "baked"
    arrays, manifest = (bake_dynamic if dynamic else bake_static)(model, resolution)
    np.savez_compressed(out / f"{stem}.npz", **arrays)
    (out / f"{stem}.json").write_text(json.dumps(manifest, indent=2) + "\n")
    if camera is not None:
        manifest["check"] = baked_check(out, out, camera, time if dynamic else None)
        (out / f"{stem}.json").write_text(json.dumps(manifest, indent=2) + "\n")
    return manifest


def bakes_dynamic(model) -> bool:
    """Whether :func:`bake_dynamic` bakes ``model``: a DeRF field trained with deferred shading whose canonical
    field is tri-planes."""
    return bool(model.has_motion and model.field.deferred and not model.field.canonical_field.temporal_planes())
