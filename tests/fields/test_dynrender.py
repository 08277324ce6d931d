"""Renderers of exported dynamic fields (engine/fields/dynamic.py numpy / onnxruntime, engine/fields/gldynamic.py GL)
against the torch renderer of models/fields/dynamic/model.py, and the numpy reference against the GL shader; with
deferred shading too; and a baked DeRF field's numpy oracle (engine/fields/baked.py) against its exact render.

Fixtures: a tiny DeRF trained on the moving sphere of tests/fields/test_dynamic_field.py (40 steps), then given a
motion that matters (time planes and flow MLP perturbed: |flow| 0.19 contracted units on average, up to 0.43,
changing with time; 40 steps alone leave |flow| < 0.02) and an occupancy grid with empty cells (a ball),
exported; and an untrained forward-facing (NDC) K-Planes field with perturbed time planes and no grid, exported
(its tests are marked slow: another ONNX export, ~10 s).

Tolerances (measured in brackets): numpy query against torch's field 1e-5 [1.2e-7]; renders (numpy and
onnxruntime) against torch without the occupancy grid: colour and opacity within 1e-5 [2.4e-7]; with it:
colour within 1e-4 on > 97% of the pixels [99.7%] and 0.05 everywhere [1.3e-2 on 2 of 768 pixels: a sample
within float rounding of an occupancy-cell boundary is skipped by one renderer and not the other, as in
tests/fields/test_field_export.py], opacity within 0.05 [3.1e-2], the same pixels without a surface. GL against numpy
with early termination and the colour skip off and exact filtering: colour and opacity within 1e-4 [6.6e-7],
the same +inf depth pixels, median depth within 1e-4 [2.4e-7]; with the defaults colour within
transmittance_eps + num_samples * color_eps and PSNR > 40 dB [134-144 dB; these tiny fields are
semi-transparent, so early termination never triggers]; hardware filtering > 60 dB [139-144 dB].
"""
from __future__ import annotations

import dataclasses
import json
import math

import numpy as np
import pytest
import torch

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.eval.metrics import psnr
from engine.fields.camera_path import scale_intrinsics
from engine.fields.dynamic import deform_np, load_dynamic_field, normalize_time, query_dynamic, render_dynamic_field
from engine.fields.gl import COLOR_EPS, TRANSMITTANCE_EPS, available
from export.dynamic import export_dynamic
from models.fields.components.render import render_image
from models.fields.data.timed import split_by_camera
from models.fields.dynamic.model import AtTime, DynamicFieldModel
from models.fields.static.model import RenderConfig, SceneBox
from models.fields.train_dynamic import load_dynamic_model, train_dynamic
from tests.fields.test_dynamic_field import TIMES, TINY, sphere_video, tiny_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 24, 32
EXACT = {"transmittance_eps": 0.0, "color_eps": 0.0, "filtering": "exact"}
#: DeRF (the default: its canonical field has time planes), DeRF with tri-planes and DeRF with deferred shading by
#: default; the K-Planes fixtures cost another ONNX export each (~10 s), so they run with ``-m slow``.
BOTH = ["derf", "derf_triplanes", "derf_deferred", pytest.param("kplanes", marks=pytest.mark.slow),
        pytest.param("kplanes_deferred", marks=pytest.mark.slow)]
#: The fixtures with a motion field, with canonical time planes, with an occupancy grid.
MOVING, CANONICAL_TIME, GRID = {"derf", "derf_triplanes", "derf_deferred"}, {"derf", "derf_deferred"}, {"derf"}
gl_only = pytest.mark.skipif(not available(), reason="no EGL context with OpenGL 4.3 compute shaders and fp64")


@pytest.fixture(scope="module")
def derf(tmp_path_factory):
    """(model, export folder, held-out camera scaled to W x H) of the trained, motion-perturbed DeRF."""
    root = tmp_path_factory.mktemp("dynrender")
    train, test = split_by_camera(sphere_video([0, 30, 15, 60], TIMES), ["cam0", "cam1", "cam3"], ["cam2"])
    run = train_dynamic(train, tiny_config(40), root / "run", progress=False)
    model = load_dynamic_model(run)
    g = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for plane in model.field.motion_field.temporal_planes() + model.field.canonical_field.temporal_planes():
            plane.mul_(1.0 + 0.5 * torch.randn(plane.shape, generator=g))
        last = model.field.motion_field.flow_mlp.net[-1]
        last.weight.copy_(torch.randn(last.weight.shape, generator=g) * 3.0)
        last.bias.copy_(torch.randn(last.bias.shape, generator=g) * 0.02)
        axis = (torch.arange(64) + 0.5) / 32.0 - 1.0
        cells = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), dim=-1)
        model.occupancy.occupied.copy_(cells.norm(dim=-1) < 0.8)
        model.occupancy.updates.fill_(1)  # the renderers use a grid once it has been updated
    export_dynamic(model, root / "export")
    cam = test.cameras[0]
    return model, root / "export", (scale_intrinsics(cam.intrinsics, 20, 20, W, H), cam.world_to_camera)


def _kplanes(root, shading: str):
    """(model, export folder, camera) of an untrained forward-facing K-Planes field with time-varying planes."""
    video = sphere_video([0, 20, 40], [0.0, 1.0])
    video = dataclasses.replace(video, scene_type="forward-facing", bounds=None, background=np.zeros(3, np.float32))
    torch.manual_seed(0)
    config = dataclasses.replace(TINY, kind="kplanes", canonical=dataclasses.replace(TINY.canonical, shading=shading))
    model = DynamicFieldModel(SceneBox.from_views(video), [0.0, 0.0, 0.0], (2.0, 4.0), config,
                              RenderConfig(num_samples=24), time_resolution=3).eval()
    g = torch.Generator().manual_seed(1)
    with torch.no_grad():
        for plane in model.field.encoding.temporal_planes():
            plane.mul_(1.0 + 0.5 * torch.randn(plane.shape, generator=g))
        if shading == "deferred":
            _perturb_colour(model.field.color_mlp, g)
    export_dynamic(model, root / "export")
    cam = sphere_video([10], [0.0]).cameras[0]
    return model, root / "export", (scale_intrinsics(cam.intrinsics, 20, 20, W, H), cam.world_to_camera)


def _perturb_colour(color_mlp, g: torch.Generator) -> None:
    """A colour MLP whose view-dependent residual matters (an untrained one gives tanh of ~0)."""
    last = color_mlp.net[-1]
    last.weight.copy_(torch.randn(last.weight.shape, generator=g) * 2.0)


@pytest.fixture(scope="module")
def kplanes(tmp_path_factory):
    return _kplanes(tmp_path_factory.mktemp("dynrender_kplanes"), "per-sample")


@pytest.fixture(scope="module")
def kplanes_deferred(tmp_path_factory):
    """As ``kplanes``, with deferred shading (``canonical.shading="deferred"``) and a residual that matters."""
    return _kplanes(tmp_path_factory.mktemp("dynrender_kplanes_deferred"), "deferred")


def _untrained_derf(root, config):
    """(model, export folder, camera) of an untrained bounded DeRF field with time-varying motion planes (and
    canonical time planes, if it has them), a large flow, and with deferred shading a colour residual that
    matters."""
    torch.manual_seed(0)
    model = DynamicFieldModel(SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3), [1.0, 1.0, 1.0], (0.0, 1.0),
                              config, RenderConfig(num_samples=24), time_resolution=3).eval()
    g = torch.Generator().manual_seed(3)
    with torch.no_grad():
        for plane in model.field.motion_field.temporal_planes():
            plane.mul_(1.0 + 0.5 * torch.randn(plane.shape, generator=g))
        last = model.field.motion_field.flow_mlp.net[-1]
        last.weight.copy_(torch.randn(last.weight.shape, generator=g) * 3.0)
        for plane in model.field.canonical_field.temporal_planes():
            plane.mul_(1.0 + 0.5 * torch.randn(plane.shape, generator=g))
        if model.field.deferred:
            _perturb_colour(model.field.canonical_field.color_mlp, g)
    export_dynamic(model, root / "export")
    cam = sphere_video([10], [0.0]).cameras[0]
    return model, root / "export", (scale_intrinsics(cam.intrinsics, 20, 20, W, H), cam.world_to_camera)


@pytest.fixture(scope="module")
def derf_triplanes(tmp_path_factory):
    """The untrained DeRF whose canonical field is tri-planes (``canonical_time=False``, the thesis's)."""
    return _untrained_derf(tmp_path_factory.mktemp("dynrender_derf_triplanes"),
                           dataclasses.replace(TINY, canonical_time=False))


@pytest.fixture(scope="module")
def derf_deferred(tmp_path_factory):
    """The untrained DeRF with canonical time planes and deferred shading (features composited, the colour MLP
    once per pixel on them, the view direction and the encoded time)."""
    return _untrained_derf(tmp_path_factory.mktemp("dynrender_derf_deferred"),
                           dataclasses.replace(TINY, canonical=dataclasses.replace(TINY.canonical, shading="deferred")))


def _torch(model, camera, t: float) -> dict:
    k, w2c = camera
    return render_image(AtTime(model, t), k, w2c, H, W, model.scene.near, model.scene.far)


def _psnr(a: dict, b: dict) -> float:
    return psnr(display_encode(a["color"]), display_encode(b["color"]))


def assert_close_to_torch(ref: dict, got: dict, *, grid: bool) -> None:
    error = np.abs(got["color"] - ref["color"]).max(-1)
    if grid:  # a few samples within float rounding of an occupancy-cell boundary
        assert np.mean(error < 1e-4) > 0.97 and error.max() < 0.05
        assert np.abs(got["opacity"] - ref["opacity"]).max() < 0.05
    else:
        assert error.max() < 1e-5 and np.abs(got["opacity"] - ref["opacity"]).max() < 1e-5
    finite = np.isfinite(ref["depth"])
    assert np.array_equal(np.isfinite(got["depth"]), finite) and finite.any()
    assert np.median(np.abs(got["depth"][finite] - ref["depth"][finite])) < 1e-4


def assert_same_render(ref: dict, got: dict, tol: float) -> None:
    assert got["color"].shape == (H, W, 3) and got["depth"].shape == (H, W) and got["opacity"].shape == (H, W)
    assert all(got[k].dtype == np.float32 for k in ("color", "depth", "opacity"))
    assert np.abs(got["color"] - ref["color"]).max() <= tol
    assert np.abs(got["opacity"] - ref["opacity"]).max() <= tol
    finite = np.isfinite(ref["depth"])
    assert np.array_equal(np.isfinite(got["depth"]), finite)
    if finite.any():
        assert np.median(np.abs(got["depth"][finite] - ref["depth"][finite])) < 1e-4
    assert _psnr(ref, got) > 40.0


# ----------------------------------------------------------------------------------------------------
# numpy / onnxruntime against torch


def assert_query_matches_torch(model, assets, points: int = 3000):
    """numpy's density and colour of ``assets`` against ``model.field`` at random points, times and directions
    (seed 2); returns (coords, taus, torch's outputs, numpy's sigma, numpy's rgb) for the caller's checks."""
    g = torch.Generator().manual_seed(2)
    coords = torch.rand(points, 3, generator=g) * 2 - 1
    taus = torch.rand(points, generator=g) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(points, 3, generator=g), dim=-1)
    with torch.no_grad():
        want = model.field(coords, taus, dirs)
    sigma, rgb = query_dynamic(assets, coords.numpy(), taus.numpy(), dirs.numpy())
    np.testing.assert_allclose(sigma, want.sigma.numpy(), rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(rgb, want.rgb.numpy(), atol=1e-5)
    return coords, taus, want, sigma, rgb


@pytest.mark.parametrize("which", BOTH)
def test_numpy_query_matches_torch_at_random_points_and_times(which, request):
    model, out, _ = request.getfixturevalue(which)
    assets = load_dynamic_field(out)
    coords, taus, want, sigma, rgb = assert_query_matches_torch(model, assets)
    if which in MOVING:  # the motion field is exercised: large flows that depend on time
        canonical, flow = deform_np(assets, coords.numpy(), taus.numpy())
        np.testing.assert_allclose(canonical, want.canonical.numpy(), atol=1e-5)
        magnitude = np.linalg.norm(flow, axis=-1)
        assert magnitude.max() > 0.1 and magnitude.mean() > 0.02
        _, early = deform_np(assets, coords.numpy(), np.full(3000, -1.0, np.float32))
        _, late = deform_np(assets, coords.numpy(), np.full(3000, 1.0, np.float32))
        assert np.abs(early - late).max() > 0.05
    assert (assets.canonical_temporal is not None) == (which in CANONICAL_TIME)
    assert assets.deferred == which.endswith("deferred") and rgb.shape[1] == assets.feature_dim
    assert sigma.dtype == np.float32
    assert query_dynamic(assets, np.zeros((0, 3)), np.zeros(0), np.zeros((0, 3)))[0].shape == (0,)  # empty batch


@pytest.mark.parametrize("which", BOTH)
def test_numpy_and_onnx_renders_match_the_torch_renderer(which, request):
    model, out, camera = request.getfixturevalue(which)
    assets = load_dynamic_field(out)
    grid = assets.occupancy is not None
    assert grid == (which in GRID)
    t0, t1 = assets.time_range
    renders = []
    for t in (t0 + 0.3 * (t1 - t0), t1):
        ref = _torch(model, camera, t)
        got = render_dynamic_field(assets, *camera, H, W, t, chunk=300)
        assert_close_to_torch(ref, got, grid=grid)
        assert_close_to_torch(ref, render_dynamic_field(assets, *camera, H, W, t, query="onnx"), grid=grid)
        renders.append(got)
        if grid:  # without the grid, the renderers agree everywhere
            assets.occupancy, updates = None, int(model.occupancy.updates)
            model.occupancy.updates.fill_(0)
            try:
                assert_close_to_torch(_torch(model, camera, t), render_dynamic_field(assets, *camera, H, W, t),
                                      grid=False)
            finally:
                model.occupancy.updates.fill_(updates)
            assets = load_dynamic_field(out)
    assert np.abs(renders[0]["color"] - renders[1]["color"]).max() > 1e-4  # time matters


def test_manifest_describes_what_the_renderers_read(derf):
    _, out, camera = derf
    assets = load_dynamic_field(out)
    spec = assets.manifest["field"]
    assert assets.kind == "derf" and spec["max_flow"] == 1.0 and spec["time_frequencies"] == 2
    assert assets.occupancy is not None and 0.1 < assets.occupancy.mean() < 0.5
    assert [p.shape[2] for p in assets.planes["motion_temporal"]] == [assets.manifest["time"]["time_resolution"]]
    assert assets.mlps["color"][0][0].shape[1] == spec["geo_feature_dim"] + 9 + 5  # h, SH (3 bands), time
    quantized = load_dynamic_field(out, quantized=True)  # every plane group from its uint8 codes and ranges
    full = render_dynamic_field(assets, *camera, H, W, 0.5)
    assert np.abs(render_dynamic_field(quantized, *camera, H, W, 0.5)["color"] - full["color"]).max() < 0.02


def test_a_deferred_export_records_its_shading_and_its_residual_matters(derf_deferred, tmp_path):
    _, out, camera = derf_deferred
    assets = load_dynamic_field(out)
    manifest = assets.manifest
    assert manifest["field"]["shading"] == "deferred" and manifest["onnx"]["outputs"] == ["density", "features"]
    assert assets.feature_dim == TINY.canonical.geo_feature_dim
    parity = manifest["parity"]["random_points"]
    assert parity["density"] < 1e-4 and parity["color"] < 1e-4
    shaded = render_dynamic_field(assets, *camera, H, W, 0.3)
    (w, b) = assets.mlps["color"][-1]
    assets.mlps["color"][-1] = (np.zeros_like(w), np.zeros_like(b))  # residual tanh(0): the diffuse colour alone
    diffuse = render_dynamic_field(assets, *camera, H, W, 0.3)
    assert np.abs(shaded["color"] - diffuse["color"]).max() > 0.05
    assert np.array_equal(shaded["opacity"], diffuse["opacity"])
    for change, key in (({"shading": "forward"}, "field.shading"),
                        ({"geo_feature_dim": 2}, "field.geo_feature_dim")):
        bad = json.loads((out / "dynamic.json").read_text())
        bad["field"].update(change)
        (tmp_path / "dynamic.json").write_text(json.dumps(bad))
        (tmp_path / "dynamic.npz").write_bytes((out / "dynamic.npz").read_bytes())
        with pytest.raises(InputError, match=key):
            load_dynamic_field(tmp_path)


# ----------------------------------------------------------------------------------------------------
# GL against the numpy reference


@gl_only
@pytest.mark.parametrize("which", BOTH)
def test_gl_matches_the_numpy_reference_at_two_times(which, request):
    """On a GPU the tolerances grow by ``GPU_SLACK`` (tests/fields/test_glfield.py): on an H200 (2026-11-30) the
    DeRF field's exact GL render was 7.4e-3 from numpy in colour, as the static fields were in 2026-11-27."""
    from engine.fields.gldynamic import GlDynamicRenderer
    from tests.fields.test_glfield import GPU_SLACK

    _, out, camera = request.getfixturevalue(which)
    assets = load_dynamic_field(out)
    t0, t1 = assets.time_range
    bound = TRANSMITTANCE_EPS + assets.manifest["render"]["num_samples"] * COLOR_EPS
    with GlDynamicRenderer(assets, W, H) as fast, GlDynamicRenderer(assets, W, H, **EXACT) as exact:
        for t in (t0 + 0.3 * (t1 - t0), t1, t0 + 0.3 * (t1 - t0)):  # and back: the renderer is reusable
            ref = render_dynamic_field(assets, *camera, H, W, t)
            assert_same_render(ref, exact.render(*camera, t), 1e-4 + GPU_SLACK)
            assert_same_render(ref, fast.render(*camera, t), bound + GPU_SLACK)
    with GlDynamicRenderer(assets, W, H, transmittance_eps=0.0, color_eps=0.0) as hardware:  # sampler filtering
        assert _psnr(ref, hardware.render(*camera, t0 + 0.3 * (t1 - t0))) > 60.0


# ----------------------------------------------------------------------------------------------------
# Errors


def test_time_outside_the_trained_range_is_refused(derf):
    _, out, camera = derf
    assets = load_dynamic_field(out)
    with pytest.raises(InputError, match=r"time 1\.5 is outside the trained range \[0, 1\]"):
        render_dynamic_field(assets, *camera, H, W, 1.5)
    with pytest.raises(InputError, match=r"time -0\.1 is outside"):
        render_dynamic_field(assets, *camera, H, W, -0.1, query="onnx")
    with pytest.raises(InputError, match="time"):
        render_dynamic_field(assets, *camera, H, W, float("nan"))
    assert normalize_time(1.0 + 1e-9, assets.time_range) == 1.0  # round-off is accepted
    assert normalize_time(0.5, (0.5, 0.5)) == 0.0  # one trained time
    if available():
        from engine.fields.gldynamic import GlDynamicRenderer

        with GlDynamicRenderer(assets, 8, 8) as renderer:
            with pytest.raises(InputError, match=r"time 2 is outside the trained range \[0, 1\]"):
                renderer.render(*camera, 2.0)


def test_bad_cameras_sizes_and_assets_are_refused(derf, tmp_path):
    _, out, (k, w2c) = derf
    assets = load_dynamic_field(out)
    squashed = w2c.copy()
    squashed[:3, :3] *= 1.5
    flat = k.copy()
    flat[0, 0] = 0.0
    renderers = [lambda k_, p_: render_dynamic_field(assets, k_, p_, 8, 8, 0.5)]
    if available():
        from engine.fields.gldynamic import GlDynamicRenderer

        gl = GlDynamicRenderer(assets, 8, 8)
        renderers.append(lambda k_, p_: gl.render(k_, p_, 0.5))
        with pytest.raises(InputError, match="size"):
            GlDynamicRenderer(assets, 0, 8)
        with pytest.raises(InputError, match="filtering"):
            GlDynamicRenderer(assets, 8, 8, filtering="cubic")
    for render in renderers:
        with pytest.raises(InputError, match="world_to_camera"):
            render(k, squashed)
        with pytest.raises(InputError):
            render(flat, w2c)
        with pytest.raises(InputError):
            render(np.full((3, 3), np.nan), w2c)
    if available():
        gl.release()
    with pytest.raises(InputError, match="query"):
        render_dynamic_field(assets, k, w2c, 8, 8, 0.5, query="cuda")
    with pytest.raises(InputError, match="does not exist"):
        load_dynamic_field(tmp_path)
    with pytest.raises(InputError, match="interleave-dynamic-field"):  # a static export is not a dynamic one
        (tmp_path / "dynamic.json").write_text('{"format": "interleave-field", "version": 1}')
        np.savez(tmp_path / "dynamic.npz", a=np.zeros(1))
        load_dynamic_field(tmp_path)


# ----------------------------------------------------------------------------------------------------
# A baked DeRF field (models.fields.bake.bake_dynamic) and its numpy oracle (engine.fields.baked)


@pytest.fixture(scope="module")
def derf_baked(tmp_path_factory):
    """(model, exact assets, baked folder, camera): the untrained DeRF with a canonical field of tri-planes and
    deferred shading (what bakes), its density given a sharp surface (the raw density crosses the occupancy
    threshold where a random projection of the density MLP's hidden features reaches its 90th percentile, 100x as
    steep) so that part of the bricks are occupied and moved samples land in empty ones, baked at 64 cells a side
    and 33^3 flow vertices per time key."""
    from models.fields.assets import dynamic_assets
    from models.fields.bake import bake_dynamic

    root = tmp_path_factory.mktemp("dynrender_derf_baked")
    canonical = dataclasses.replace(TINY.canonical, shading="deferred")
    model, _, camera = _untrained_derf(root, dataclasses.replace(TINY, canonical_time=False, canonical=canonical))
    g = torch.Generator().manual_seed(7)
    with torch.no_grad():
        field = model.field.canonical_field
        last = field.density_mlp.net[-1]
        w = torch.randn(last.weight.shape[1], generator=g)
        hidden = field.density_mlp.net[:-1](field.encoding(torch.rand(20000, 3, generator=g) * 2 - 1))
        level = (hidden @ w).quantile(0.9)
        last.weight[0].copy_(w * 100.0)
        last.bias[0] = -100.0 * float(level) + math.log(model.occupancy_threshold())
    out = root / "exact"
    out.mkdir()
    arrays, manifest = dynamic_assets(model)
    np.savez(out / "dynamic.npz", **arrays)
    (out / "dynamic.json").write_text(json.dumps(manifest))
    arrays, manifest = bake_dynamic(model, 64, 33)
    assert 0.2 < manifest["grid"]["occupied_fraction"] < 0.6
    np.savez(root / "baked_dynamic.npz", **arrays)
    (root / "baked_dynamic.json").write_text(json.dumps(manifest))
    return model, out, root, camera


def test_the_bake_holds_the_fields_flow_at_its_vertices_and_the_canonical_fit(derf_baked):
    from engine.fields.baked import baked_flow, load_baked_dynamic
    from tests.fields.test_baked_field import fitted_bricks

    model, _, folder, _ = derf_baked
    baked = load_baked_dynamic(folder)
    keys, m = baked.motion.shape[0], baked.motion.shape[1]
    assert keys == model.time_resolution and m == 33
    g = np.random.default_rng(0)
    vertices = g.integers(0, m, size=(500, 3))
    coords = (vertices * (2.0 / (m - 1)) - 1.0).astype(np.float32)
    for k in range(keys):  # at a key's time and a vertex, the flow is the field's (float16)
        tau = -1.0 + 2.0 * k / (keys - 1)
        with torch.no_grad():
            want = model.field.motion_field(torch.from_numpy(coords), torch.full((500,), tau)).numpy()
        np.testing.assert_allclose(baked_flow(baked, coords, tau), want, atol=1e-3)
        assert np.abs(want).max() > 0.1  # the flow is large
    cells = np.argwhere(baked.brick_index >= 0)[:20]
    rows = baked.brick_index[cells[:, 0], cells[:, 1], cells[:, 2]]
    canonical = model.field.canonical_field
    raw, feats = fitted_bricks(lambda c: canonical.get_density(c, torch.zeros(c.shape[:-1])), cells, baked.grid)
    np.testing.assert_allclose(baked.density[rows], raw, rtol=1e-3, atol=1e-3)  # float16 log-density
    assert np.abs(baked.features[rows] / 255.0 - feats).max() <= 0.5 / 255 + 1e-5  # half a code


def test_the_baked_render_is_the_exact_render_up_to_the_grids(derf_baked):
    """Measured (64 cells, 33^3 flow vertices, 32x24, at t = 0.3 / 1): 57.8 / 36.8 dB against the exact numpy
    render, mean |opacity difference| 5.7e-3 / 4.7e-3 (up to 0.16 on a surface's edge: its brick, or its flow,
    differs); bounds 30 dB and 0.02. The fixture's flow is large and varies fast in space, so its 33^3 grid is a
    rough stand-in (a trained lego field: 37 dB, docs/results/2026-11-29-dynamic-deferred.md)."""
    from engine.fields.baked import load_baked_dynamic, render_baked_dynamic

    _, out, folder, camera = derf_baked
    baked, exact = load_baked_dynamic(folder), load_dynamic_field(out)
    frames = []
    for t in (0.3, 1.0):
        want = render_dynamic_field(exact, *camera, H, W, t)
        got = render_baked_dynamic(baked, *camera, H, W, t)
        assert got["color"].shape == (H, W, 3) and got["color"].dtype == np.float32
        assert _psnr(want, got) > 30.0 and np.abs(got["opacity"] - want["opacity"]).mean() < 0.02
        frames.append(got)
    assert np.abs(frames[0]["color"] - frames[1]["color"]).max() > 1e-2  # time matters
    with pytest.raises(InputError, match="outside the trained range"):
        render_baked_dynamic(baked, *camera, H, W, 1.5)


def test_only_a_deferred_derf_of_tri_planes_bakes_and_bad_baked_assets_name_their_key(derf_baked, derf_deferred,
                                                                                      tmp_path):
    from engine.fields.baked import load_baked_dynamic
    from models.fields.bake import bake_dynamic

    model, _, folder, _ = derf_baked
    for other in (derf_deferred[0], _model_with(model, "per-sample")):  # canonical time planes; per-sample colour
        with pytest.raises(InputError, match="no-field.canonical-time"):
            bake_dynamic(other, 32, 9)
    with pytest.raises(InputError, match="bake_resolution"):
        bake_dynamic(model, 30, 9)
    with pytest.raises(InputError, match="motion_resolution"):
        bake_dynamic(model, 32, 1)
    manifest = json.loads((folder / "baked_dynamic.json").read_text())
    for change, key in ((("time", "range", [1.0, 0.0]), "time.range"), (("motion", "resolution", 17), "motion"),
                        (("field", "time_frequencies", 3), r"field.mlps.color\[0\].in")):
        bad = json.loads(json.dumps(manifest))
        bad[change[0]][change[1]] = change[2]
        (tmp_path / "baked_dynamic.json").write_text(json.dumps(bad))
        (tmp_path / "baked_dynamic.npz").write_bytes((folder / "baked_dynamic.npz").read_bytes())
        with pytest.raises(InputError, match=key):
            load_baked_dynamic(tmp_path)


def _model_with(model, shading: str) -> DynamicFieldModel:
    """A fresh DynamicFieldModel like ``model`` with another canonical shading."""
    config = dataclasses.replace(model.config, canonical=dataclasses.replace(model.config.canonical, shading=shading))
    return DynamicFieldModel(SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3), [1.0, 1.0, 1.0], (0.0, 1.0),
                             config, RenderConfig(num_samples=24), time_resolution=3)


@gl_only
@pytest.mark.parametrize("filtering", ["exact", "hardware"])
def test_gl_renders_the_baked_oracles_frame(derf_baked, filtering):
    """Tolerances as the static baked renderer's (tests/fields/test_baked_field.py): early termination and the
    colour skip off 1e-4 (hardware filtering + 1e-3), the defaults their bound (+ 1e-3); a GPU's filtering gets
    ``GPU_SLACK``. Measured on llvmpipe at t = 0.3 and 1 (32x24): exact filtering colour 3.1e-6 (the defaults
    5.7e-5), opacity 2.3e-6; hardware filtering colour 2.0e-4, opacity 1.7e-4. Samples moved into empty bricks
    get no density (before that was handled the GL colour differed by 0.2 on the lego bake)."""
    from engine.fields.baked import BAKED_TRANSMITTANCE_EPS, load_baked_dynamic, render_baked_dynamic
    from engine.fields.glbaked import GlBakedDynamicRenderer
    from tests.fields.test_glfield import GPU_SLACK

    _, _, folder, camera = derf_baked
    baked = load_baked_dynamic(folder)
    bound = BAKED_TRANSMITTANCE_EPS + baked.manifest["render"]["num_samples"] * COLOR_EPS  # the default's stop
    slack = 0.0 if filtering == "exact" else 1e-3
    for options, tol in (({"transmittance_eps": 0.0, "color_eps": 0.0}, 1e-4 + slack), ({}, bound + slack)):
        with GlBakedDynamicRenderer(baked, W, H, filtering=filtering, **options) as renderer:
            for t in (0.3, 1.0, 0.3):  # and back: the renderer is reusable
                ref = render_baked_dynamic(baked, *camera, H, W, t)
                got = renderer.render(*camera, t)
                assert np.abs(got["color"] - ref["color"]).max() <= tol + GPU_SLACK
                assert np.abs(got["opacity"] - ref["opacity"]).max() <= tol + GPU_SLACK
                finite = np.isfinite(ref["depth"])
                assert np.array_equal(np.isfinite(got["depth"]), finite) and finite.any()


def test_export_bakes_a_bakeable_run_and_checks_it_on_a_held_out_view(derf_triplanes, tmp_path):
    """``interleave export dynamic`` on a DeRF run trained with deferred shading and canonical tri-planes (40 steps on
    the moving sphere) also writes ``baked_dynamic.*`` and records the baked render's PSNR against the exact one on
    the given held-out view (measured 81.9 dB at 32 cells a side: a field this young is nearly uniform); a
    per-sample one writes no bake."""
    from engine.fields.baked import load_baked_dynamic

    train, test = split_by_camera(sphere_video([0, 30, 15, 60], TIMES), ["cam0", "cam1", "cam3"], ["cam2"])
    canonical = dataclasses.replace(TINY.canonical, shading="deferred")
    field = dataclasses.replace(TINY, canonical_time=False, canonical=canonical)
    run = train_dynamic(train, tiny_config(40, field=field), tmp_path / "run", progress=False)
    manifest = export_dynamic(run, tmp_path / "export", views=test.subset([2]), bake_resolution=32)
    assert manifest["baked"]["grid"]["resolution"] == 32 and manifest["baked"]["check"]["psnr_baked_vs_exact"] > 40
    assert not (derf_triplanes[1] / "baked_dynamic.json").exists() and "baked" not in json.loads(
        (derf_triplanes[1] / "dynamic.json").read_text())
    assert load_baked_dynamic(tmp_path / "export").motion.shape[0] == manifest["time"]["time_resolution"]


def test_the_dynamic_baking_config_builds_a_field_that_bakes():
    """``configs/dynamic-baked.json`` (docs/dynamic_fields.md, "Baking a dynamic field"): deferred shading, a
    canonical field of tri-planes, the static recipe's wider density MLP and residual stop, but no density bias
    (with it the motion field moved nothing on lego: docs/results/2026-11-30-dynamic-baked-recipe.md), and a latent
    whose features and density fill two RGBA texel groups, as the static baking config's."""
    from pathlib import Path

    from engine.core.config import config_from_file
    from engine.fields.glbaked import channel_groups
    from models.fields.bake import bakes_dynamic
    from models.fields.train_dynamic import DynamicTrainConfig

    path = Path(__file__).resolve().parents[2] / "configs" / "dynamic-baked.json"
    config = config_from_file(DynamicTrainConfig, path)
    config.field.validate()
    canonical = config.field.canonical
    assert config.field.kind == "derf" and canonical.shading == "deferred" and not canonical.residual_density_grad
    assert canonical.density_bias == 0.0 and canonical.density_hidden == 64
    assert 4 * channel_groups(canonical.geo_feature_dim) == canonical.geo_feature_dim + 1 == 8
    scene = SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3)
    for field, bakes in ((config.field, True), (DynamicTrainConfig().field, False)):
        model = DynamicFieldModel(scene, [1.0] * 3, (0.0, 1.0), field, RenderConfig(num_samples=8), time_resolution=3)
        assert bakes_dynamic(model) == bakes
