"""Baked static fields (``models.fields.bake``, ``engine.fields.baked``, ``engine.fields.glbaked``).

The bake stores at brick vertices the least-squares fit of the bricks' trilinear interpolation to the field at
their vertices and cell centres (to float16 / uint8 rounding), so its render differs from the exact render of the
same field by the grid's interpolation only: measured in brackets. The GL renderer against the numpy
reference: with early termination and the colour skip off within 1e-4 [3e-6] with exact filtering (1.1e-3
[1.1e-4 on llvmpipe] with hardware filtering), with the defaults within their documented bound
(``engine.fields.gl``).
"""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest
import torch

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from engine.fields import gl as glfield
from engine.fields.glbaked import channel_groups
from engine.fields.baked import BAKED_TRANSMITTANCE_EPS, load_baked, query_baked, render_baked, trilinear_np
from engine.fields.render import load_field, render_field
from export.field import export_field
from models.fields.bake import LOWEST_RAW_DENSITY, bake_static, fit_matrix, fit_points
from models.fields.static.field import MAX_LOG_DENSITY
from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel
from models.fields.train_static import config_from_file, load_model, train_field
from tests.fields.test_deferred_field import DEFERRED, deferred_run  # noqa: F401  (module fixture)
from tests.fields.test_field_export import _forward_facing, bounded_run  # noqa: F401  (module fixture)
from tests.fields.test_field_train import TINY_FIELD, sphere_views, tiny_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 24, 32


@pytest.fixture(scope="module")
def ndc_deferred_run(tmp_path_factory):
    """A forward-facing deferred field (no occupancy grid: the bricks come from the vertex densities), baked at 64."""
    root = tmp_path_factory.mktemp("ndc-deferred")
    config = dataclasses.replace(tiny_config(100, field=DEFERRED), render=RenderConfig(num_samples=32))
    run = train_field(_forward_facing(sphere_views([0, 15, 30])), config, root / "run", progress=False)
    manifest = export_field(run, root / "export", views=_forward_facing(sphere_views([10])), bake_resolution=64)
    return run, root / "export", manifest


def _camera(which: str):
    return sphere_views([20] if which == "deferred_run" else [10]).cameras[0]


def _psnr(a: dict, b: dict) -> float:
    return psnr(display_encode(a["color"]), display_encode(b["color"]))


@pytest.mark.parametrize("which", ["deferred_run", "ndc_deferred_run"])
def test_export_writes_the_baked_field_beside_the_exact_one(which, request):
    _, out, manifest = request.getfixturevalue(which)
    baked = load_baked(out)
    grid = manifest["baked"]["grid"]
    assert baked.grid == json.loads((out / "baked.json").read_text())["grid"]
    assert grid["resolution"] == grid["brick"] * grid["bricks"] and grid["count"] == baked.density.shape[0] > 0
    assert grid["bricks_from"] == ("occupancy grid" if which == "deferred_run" else
                                   "vertex density >= the occupancy threshold")
    assert manifest["baked"]["check"]["psnr_baked_vs_exact"] > 40.0  # [68.9 dB, 49.5 dB; 66 / 49 with vertex samples]


def test_the_fit_reproduces_a_trilinear_brick_and_beats_vertex_samples():
    brick = 4
    local = fit_points(brick)
    v = brick + 1
    solve = fit_matrix(brick).double()
    assert solve.shape == (v ** 3, v ** 3 + brick ** 3)
    assert torch.equal(local[:v ** 3].reshape(v, v, v, 3)[2, 3, 1], torch.tensor([2.0, 3.0, 1.0], dtype=torch.float64))
    g = torch.Generator().manual_seed(0)
    vertices = torch.randn(v, v, v, generator=g, dtype=torch.float64)
    values = _trilinear(vertices, local)  # a field trilinear within the brick: the fit gives its vertices back
    assert torch.allclose(solve.float().double() @ values, vertices.reshape(-1), atol=1e-5)
    def wavy(p):  # a smooth field, a period ~7 cells
        return torch.sin(0.9 * p[:, 0]) * torch.cos(0.63 * p[:, 1] + 0.5 * p[:, 2])

    fitted = (solve @ wavy(local)).reshape(v, v, v)
    sampled = wavy(local)[:v ** 3].reshape(v, v, v)  # vertex samples: exact at the vertices only
    dense = torch.rand(4000, 3, generator=g, dtype=torch.float64) * brick

    def error(vertex_values, points):
        return float((_trilinear(vertex_values, points) - wavy(points)).square().mean())

    assert error(fitted, local) <= error(sampled, local)  # least squares at the fit points
    assert error(fitted, dense) < 0.5 * error(sampled, dense)  # and between them [0.31x]


def _trilinear(vertices: torch.Tensor, local: torch.Tensor) -> torch.Tensor:
    """(V, V, V) vertex values interpolated at (P, 3) vertex-unit points by the renderers' ``trilinear_np``."""
    bricks = np.broadcast_to(vertices.numpy()[None, ..., None], (local.shape[0], *vertices.shape, 1))
    return torch.from_numpy(trilinear_np(bricks, local.numpy().astype(np.float32))[:, 0]).double()


def fitted_bricks(get_density, cells: np.ndarray, grid: dict) -> tuple[np.ndarray, np.ndarray]:
    """What the bake stores for bricks ``cells`` (n, 3) of ``grid``: the fit (:func:`fit_matrix`) of the raw
    log-density (n, V, V, V) and features sigmoid(h) (n, V, V, V, G) of ``get_density`` (contracted coords ->
    density, h) at the bricks' fit points, clamped as the bake clamps."""
    brick, resolution = grid["brick"], grid["resolution"]
    points = (torch.from_numpy(cells).double()[:, None, :] * brick + fit_points(brick)) * (2.0 / resolution) - 1.0
    with torch.no_grad():
        sigma, h = get_density(points.float())
    raw = torch.log(sigma).clamp(LOWEST_RAW_DENSITY, MAX_LOG_DENSITY)
    solve, v = fit_matrix(brick), brick + 1
    raw = torch.einsum("vp,np->nv", solve, raw).clamp(LOWEST_RAW_DENSITY, MAX_LOG_DENSITY)
    feats = torch.einsum("vp,npg->nvg", solve, torch.sigmoid(h)).clamp(0.0, 1.0)
    return raw.reshape(-1, v, v, v).numpy(), feats.reshape(-1, v, v, v, feats.shape[-1]).numpy()


def test_the_bricks_are_the_occupancy_grid_and_the_vertices_the_fit(deferred_run):
    run, out, _ = deferred_run
    model = load_model(run)
    baked = load_baked(out)
    assert np.array_equal(baked.occupancy, model.occupancy.occupied.numpy())
    cells = np.argwhere(baked.occupancy)[:50]
    rows = baked.brick_index[cells[:, 0], cells[:, 1], cells[:, 2]]
    raw, feats = fitted_bricks(model.field.get_density, cells, baked.grid)
    # float16 raw density (relative 2^-11, |raw| <= 30), uint8 features within half a code
    np.testing.assert_allclose(baked.density[rows], raw, rtol=1e-3, atol=1e-3)
    assert np.abs(baked.features[rows] / 255.0 - feats).max() <= 0.5 / 255 + 1e-5


def test_without_an_occupancy_grid_a_brick_is_occupied_where_one_of_its_vertices_is(ndc_deferred_run):
    """The vertex pass evaluates each grid vertex once, plane by plane; the oracle evaluates every brick's 125
    vertices on its own (the same points: vertex i at -1 + 2 i / R) and takes their largest raw density. The
    model's own threshold fills this small field's grid, so thresholds at quantiles of the bricks' maxima too."""
    from models.fields.bake import _occupied_bricks, _raw_outputs, _vertex_occupancy

    run, out, _ = ndc_deferred_run
    model = load_model(run)
    threshold = float(np.log(model.occupancy_threshold()))
    for resolution in (16, 64):
        b = resolution // 4
        cells = np.stack(np.meshgrid(*[np.arange(b)] * 3, indexing="ij"), -1).reshape(-1, 1, 1, 1, 3)
        offsets = np.stack(np.meshgrid(*[np.arange(5)] * 3, indexing="ij"), -1)[None]
        points = torch.from_numpy(((cells * 4 + offsets) * (2.0 / resolution) - 1.0).astype(np.float32))
        raw, _ = _raw_outputs(model.field, points, 1 << 16)
        top = raw.reshape(raw.shape[0], -1).amax(dim=-1).reshape(b, b, b)
        for level in (threshold, *torch.quantile(top.flatten(), torch.tensor([0.1, 0.5, 0.9])).tolist()):
            want = top >= level
            assert torch.equal(_vertex_occupancy(model.field, resolution, level, 1 << 16), want)
            if level != threshold:
                assert 0 < int(want.sum()) < want.numel()
    occupied, bricks, from_grid = _occupied_bricks(model, model.field, 64, 1 << 16)
    assert (bricks, from_grid) == (16, False) and torch.equal(occupied, top >= threshold)
    assert np.array_equal(load_baked(out).brick_index >= 0, occupied.numpy())  # the export's bake at 64


def test_the_baked_render_is_the_exact_render_of_the_same_field(deferred_run):
    _, out, _ = deferred_run
    cam = _camera("deferred_run")
    exact = render_field(load_field(out), cam.intrinsics, cam.world_to_camera, H, W)
    baked = render_baked(load_baked(out), cam.intrinsics, cam.world_to_camera, H, W, chunk=100)
    assert np.array_equal(baked["evaluations"], exact["evaluations"]) or \
        np.mean(baked["evaluations"] == exact["evaluations"]) > 0.97  # the same samples skipped
    assert _psnr(exact, baked) > 40.0 and np.abs(baked["opacity"] - exact["opacity"]).max() < 0.05
    assert np.array_equal(np.isfinite(baked["depth"]), np.isfinite(exact["depth"]))


def test_the_baking_config_is_a_deferred_field_filling_two_texel_groups_exactly():
    """``configs/field-baked.json`` (docs/fields.md): deferred shading, a latent whose features plus the density
    lane fill two RGBA groups with no empty lane (each group costs the baked shader its own fetches per sample),
    and the distortion loss."""
    config = config_from_file(Path(__file__).resolve().parents[2] / "configs" / "field-baked.json")
    config.validate()
    assert config.field.shading == "deferred" and not config.field.residual_density_grad
    assert channel_groups(config.field.geo_feature_dim) == 2
    assert 4 * channel_groups(config.field.geo_feature_dim) == config.field.geo_feature_dim + 1
    assert [channel_groups(d) for d in (3, 4, 7, 8, 15)] == [1, 2, 2, 3, 4]
    # the distortion loss at 3e-3: fewer samples a pixel to bake (docs/results/2026-11-30-baked-distortion.md)
    assert config.priors.enabled() == ["distortion"] and config.priors.distortion.weight == 3e-3


def test_only_deferred_fields_bake():
    model = StaticFieldModel(SceneBox("bounded-360", 0.1, 10.0, box_min=[-1, -1, -1], box_max=[1, 1, 1]),
                             [1, 1, 1], TINY_FIELD)
    with pytest.raises(InputError, match="field.shading"):
        bake_static(model)
    deferred = StaticFieldModel(model.scene, [1, 1, 1], DEFERRED, RenderConfig(occupancy_resolution=32))
    deferred.update_occupancy()
    with pytest.raises(InputError, match="bake_resolution"):
        bake_static(deferred, 48)  # not a multiple of the 32^3 grid


def _corrupt(out, tmp_path, change_manifest=None, change_arrays=None):
    manifest = json.loads((out / "baked.json").read_text())
    with np.load(out / "baked.npz") as data:
        arrays = {k: data[k] for k in data.files}
    if change_manifest:
        change_manifest(manifest)
    if change_arrays:
        change_arrays(arrays)
    (tmp_path / "baked.json").write_text(json.dumps(manifest))
    np.savez(tmp_path / "baked.npz", **arrays)
    return tmp_path


def test_bad_baked_assets_raise_one_line_errors_naming_file_and_key(deferred_run, tmp_path):
    _, out, _ = deferred_run
    with pytest.raises(InputError, match="baked.json.*does not exist"):
        load_baked(tmp_path)
    cases = [
        (lambda m: m["grid"].update(bricks=7), None, "grid.bricks"),
        (lambda m: m["grid"].update(resolution="big"), None, "grid.resolution"),
        (lambda m: m["field"]["mlps"]["color"][0].update({"in": 5}), None, r"field.mlps.color\[0\].in"),
        (lambda m: m.update(version=2), None, "interleave-baked-field version 1"),
        (None, lambda a: a.update(features=a["features"].astype(np.float32)), "'features'.*uint8"),
        (None, lambda a: a.update(density=a["density"][:, :2]), "'density'"),
        (None, lambda a: a["brick_index"].__setitem__((0, 0, 0), 0), "'brick_index'.*once"),
        (None, lambda a: a.pop("color_w0"), "lacks array 'color_w0'"),
    ]
    for i, (manifest_change, arrays_change, match) in enumerate(cases):
        folder = tmp_path / str(i)
        folder.mkdir()
        with pytest.raises(InputError, match=match) as err:
            load_baked(_corrupt(out, folder, manifest_change, arrays_change))
        assert "\n" not in str(err.value) and "baked." in str(err.value)


gl_only = pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")


@gl_only
@pytest.mark.parametrize("which", ["deferred_run", "ndc_deferred_run"])
@pytest.mark.parametrize("filtering", ["exact", "hardware"])
def test_gl_renders_the_numpy_frame_of_the_baked_field(which, filtering, request):
    from engine.fields.glbaked import GlBakedRenderer
    from tests.fields.test_glfield import GPU_SLACK

    _, out, manifest = request.getfixturevalue(which)
    cam = _camera(which)
    baked = load_baked(out)
    ref = render_baked(baked, cam.intrinsics, cam.world_to_camera, H, W)
    # the baked renderer's default stops at one 8-bit step of transmittance (the oracle counts its evaluations so):
    # opacity and the composited features change by less than that, the colour by what the colour MLP makes of
    # the features' change [6.5e-3 on the NDC field, whose colours reach 1.46]
    bound = BAKED_TRANSMITTANCE_EPS + manifest["render"]["num_samples"] * glfield.COLOR_EPS
    color_bound = 3.0 * BAKED_TRANSMITTANCE_EPS + manifest["render"]["num_samples"] * glfield.COLOR_EPS
    # hardware filtering: texture coordinates of a few thousand texels carry float32 rounding (~2e-4 texel) into
    # the interpolation weights [1.1e-4 on llvmpipe]
    slack = 0.0 if filtering == "exact" else 1e-3
    for options, tol, color_tol in (({"transmittance_eps": 0.0, "color_eps": 0.0}, 1e-4 + slack, 1e-4 + slack),
                                    ({}, bound + slack, color_bound + slack)):
        with GlBakedRenderer(baked, W, H, filtering=filtering, count_evaluations=True, **options) as renderer:
            got = renderer.render(cam.intrinsics, cam.world_to_camera)
        assert np.abs(got["color"] - ref["color"]).max() <= color_tol + GPU_SLACK
        assert np.abs(got["opacity"] - ref["opacity"]).max() <= tol + GPU_SLACK
        finite = np.isfinite(ref["depth"])
        assert np.array_equal(np.isfinite(got["depth"]), finite) and finite.any()
        if not options:
            assert renderer.transmittance_eps == BAKED_TRANSMITTANCE_EPS
            assert np.mean(got["evaluations"] == ref["evaluations"]) > 0.97
            longer = render_baked(baked, cam.intrinsics, cam.world_to_camera, H, W,
                                  transmittance_eps=glfield.TRANSMITTANCE_EPS)["evaluations"]
            assert (ref["evaluations"] <= longer).all()  # [equal sums here: these small fields stay translucent]


@gl_only
def test_gl_baked_renderer_refuses_bad_options(deferred_run):
    from engine.fields.glbaked import GlBakedRenderer

    _, out, _ = deferred_run
    for options, key in (({"filtering": "cubic"}, "filtering"), ({"transmittance_eps": 2.0}, "transmittance_eps")):
        with pytest.raises(InputError, match=key):
            GlBakedRenderer(out, W, H, **options)
    with pytest.raises(InputError, match="size"):
        GlBakedRenderer(out, 0, H)


@gl_only
def test_the_field_benchmark_times_the_baked_renderer(deferred_run, tmp_path):
    from tools.bench_fields import main as bench_main, run_static_bench

    run, out, _ = deferred_run
    records = run_static_bench(out, [(32, 24)], run=run, repeat=1, skip=("onnx",))
    by_name = {r["renderer"]: r for r in records}
    assert {"gl baked", "gl baked, exact filtering", "gl baked, early stop at 1e-4", "baked numpy", "torch",
            "gl float"} <= set(by_name)
    assert not any("once per pixel (approx.)" in name for name in by_name)  # not for a deferred field
    assert by_name["gl baked"]["psnr"] > 35.0 and by_name["gl baked"]["evaluations_per_pixel"] > 0
    assert bench_main(["static", str(out), "--sizes", "16x16", "--repeat", "1", "--skip", "torch,onnx,numpy,baked",
                       "--json", str(tmp_path / "b.json")]) == 0
    assert not any("baked" in r["renderer"] for r in json.loads((tmp_path / "b.json").read_text()))


def test_export_command_bakes_only_deferred_fields_and_checks_the_resolution(deferred_run, bounded_run, tmp_path,
                                                                             capsys):
    from engine.cli import main as cli_main

    _, per_sample_out, per_sample_manifest = bounded_run
    assert not (per_sample_out / "baked.json").exists() and "baked" not in per_sample_manifest
    run, _, _ = deferred_run
    assert cli_main(["export", "field", str(run), "--out", str(tmp_path / "bad"), "--bake-resolution", "48"]) == 2
    assert "bake_resolution" in capsys.readouterr().err
