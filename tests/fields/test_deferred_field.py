"""Deferred shading (``FieldConfig.shading="deferred"``, SNeRG/MERF): the colour MLP once per pixel on the
composited features. The torch renderer (what training optimises), the exported ONNX query, the numpy reference
(``engine.fields.render``) and the GL renderer (``engine.fields.gl``) render the same frame.

Tolerances as tests/fields/test_glfield.py's for per-sample fields (measured in brackets): numpy and ONNX
against torch: 97 % of the pixels within 1e-4 (occupancy-cell boundaries), GL against numpy with early
termination and the colour skip off within 1e-4 [~1e-6], with the defaults within their documented bound.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest
import torch

from engine.core.errors import InputError
from engine.fields import gl as glfield
from engine.fields.render import load_field, render_field
from export.field import export_field
from models.fields.components.render import render_image
from models.fields.static.field import FieldConfig, TriPlaneField, bounded_tanh
from models.fields.train_static import load_model, train_field
from tests.fields.test_field_train import TINY_FIELD, sphere_views, tiny_config

pytestmark = pytest.mark.usefixtures("one_torch_thread")

H, W = 24, 32
DEFERRED = dataclasses.replace(TINY_FIELD, shading="deferred", density_layers=2)


@pytest.fixture(scope="module")
def deferred_run(tmp_path_factory):
    """A sphere field trained with deferred shading and an occupancy grid (200 steps), exported."""
    root = tmp_path_factory.mktemp("deferred")
    run = train_field(sphere_views([0, 40, 80]), tiny_config(200, field=DEFERRED), root / "run", progress=False)
    manifest = export_field(run, root / "export", views=sphere_views([20]))
    return run, root / "export", manifest


def _torch_render(run, cam):
    model = load_model(run)
    return render_image(model, cam.intrinsics, cam.world_to_camera, H, W, model.scene.near, model.scene.far)


def test_deferred_shading_composites_features_and_shades_once_per_pixel():
    torch.manual_seed(0)
    field = TriPlaneField(dataclasses.replace(DEFERRED))
    sigma, features = field(torch.rand(7, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(7, 3), dim=-1))
    assert features.shape == (7, DEFERRED.geo_feature_dim) and bool(((features > 0) & (features < 1)).all())
    background = torch.tensor([0.2, 0.4, 0.6])
    dirs = torch.nn.functional.normalize(torch.randn(5, 3), dim=-1)
    empty = field.shade_pixels(torch.zeros(5, DEFERRED.geo_feature_dim), torch.zeros(5), dirs, background)
    assert torch.equal(empty, background.expand(5, 3))  # nothing hit: the background, whatever the view
    full = torch.rand(5, DEFERRED.geo_feature_dim)
    shaded = field.shade_pixels(full, torch.ones(5), dirs, background)
    assert bool(((shaded - full[:, :3]).abs() < 1).all())  # the diffuse colour plus a residual in (-1, 1)
    with pytest.raises(InputError, match="field.shading"):
        FieldConfig(shading="latent").validate()
    with pytest.raises(InputError, match="geo_feature_dim"):
        FieldConfig(shading="deferred", geo_feature_dim=2).validate()


def test_bounded_tanh_is_tanh_with_the_gradient_of_the_bound_penalty_added():
    torch.manual_seed(0)
    x = (torch.randn(64, 3) * 4).requires_grad_()
    upstream = torch.randn(64, 3)
    y = bounded_tanh(x, 2.0)
    assert torch.equal(y, torch.tanh(x.detach()))
    (got,) = torch.autograd.grad(y, x, upstream)
    reference = x.detach().clone().requires_grad_()
    penalty = torch.relu(reference.abs() - 2.0).square().mean()
    (want,) = torch.autograd.grad((torch.tanh(reference) * upstream).sum() + penalty, reference)
    assert bool((x.detach().abs() > 2.0).any()) and torch.allclose(got, want, rtol=1e-6, atol=1e-7)
    (plain,) = torch.autograd.grad(bounded_tanh(x, 0.0), x, upstream)
    assert torch.allclose(plain, upstream * (1 - torch.tanh(x.detach()) ** 2), rtol=1e-6, atol=1e-7)
    with pytest.raises(InputError, match="field.residual_bound"):
        FieldConfig(residual_bound=-1.0).validate()


@pytest.mark.parametrize("bound", [0.0, 2.0])
def test_a_residual_saturated_out_of_range_comes_back_only_with_the_bound(bound):
    """The failure of lego's seed 2 (docs/results/2026-11-28-baked-features.md): the blue residual's logit far
    negative, so tanh is flat and the colour below 0, where the photometric loss's clip has no gradient either."""
    from models.fields.losses import srgb_encode

    torch.manual_seed(0)
    field = TriPlaneField(dataclasses.replace(DEFERRED, residual_bound=bound))
    with torch.no_grad():
        field.color_mlp.net[-1].bias.copy_(torch.tensor([0.0, 0.0, -12.0]))
    features = torch.full((256, DEFERRED.geo_feature_dim), 0.2)
    dirs = torch.nn.functional.normalize(torch.randn(256, 3), dim=-1)
    target = torch.full((256, 3), 0.5)
    optimizer = torch.optim.Adam(field.color_mlp.parameters(), lr=0.02)
    for _ in range(150):
        color = field.shade_pixels(features, torch.ones(256), dirs, torch.ones(3))
        loss = (srgb_encode(color) - srgb_encode(target)).square().mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
    blue = field.shade_pixels(features, torch.ones(256), dirs, torch.ones(3)).detach()[:, 2]
    if bound > 0:
        assert bool(((blue - 0.5).abs() < 0.05).all())  # back in range and fitted
    else:
        assert bool((blue < -0.7).all())  # stuck: no gradient reaches the logit


def test_the_residual_reads_the_same_features_with_or_without_the_density_gradient():
    from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel

    torch.manual_seed(0)
    model = StaticFieldModel(SceneBox("bounded-360", 0.1, 10.0, box_min=[-1, -1, -1], box_max=[1, 1, 1]),
                             [1.0, 1.0, 1.0], DEFERRED, RenderConfig(num_samples=16))
    origins = torch.tensor([[0.0, 0.0, -3.0]]).expand(6, 3)
    directions = torch.cat([torch.randn(6, 2) * 0.1, torch.ones(6, 1)], dim=-1)
    near, far = torch.full((6,), 0.1), torch.full((6,), 10.0)
    colors, grads = [], []
    for through in (True, False):
        model.field.config.residual_density_grad = through
        model.zero_grad()
        color = model.render_rays(origins, directions, near, far).color
        color.sum().backward()
        colors.append(color.detach())
        grads.append(model.field.density_mlp.net[0].weight.grad.clone())
    assert torch.equal(colors[0], colors[1])  # the same render: only the gradient's path differs
    assert not torch.allclose(grads[0], grads[1])


def test_a_field_without_view_dependence_exports_assets_that_load():
    from models.fields.assets import load_assets, static_assets
    from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel

    for shading in ("per-sample", "deferred"):
        config = dataclasses.replace(DEFERRED, shading=shading, direction_encoding="none")  # degree left at 3
        model = StaticFieldModel(SceneBox("bounded-360", 0.1, 10.0, box_min=[-1, -1, -1], box_max=[1, 1, 1]),
                                 [1.0, 1.0, 1.0], config, RenderConfig(num_samples=8))
        arrays, manifest = static_assets(model)
        assert manifest["field"]["direction_degree"] == 0
        assert load_assets(arrays, manifest, "field").deferred == (shading == "deferred")


def test_deferred_field_trains(deferred_run):
    run, _, _ = deferred_run
    cam = sphere_views([20]).cameras[0]
    views = sphere_views([20], size=32)
    got = render_image(load_model(run), cam.intrinsics, cam.world_to_camera, 32, 32, 0.1, 10.0)["color"]
    mse = float(np.mean((got - views.images[0]) ** 2))
    assert -10 * np.log10(mse) > 20.0


def test_export_records_deferred_shading_and_the_onnx_features(deferred_run):
    _, out, manifest = deferred_run
    assert manifest["field"]["shading"] == "deferred" and manifest["onnx"]["outputs"] == ["density", "features"]
    for name in ("random_points", "ray_points"):
        assert manifest["parity"][name]["density"] < 1e-4 and manifest["parity"][name]["color"] < 1e-4
    assert load_field(out).deferred


def test_numpy_and_onnx_render_the_torch_frame(deferred_run):
    run, out, _ = deferred_run
    cam = sphere_views([20]).cameras[0]
    ref = _torch_render(run, cam)
    assets = load_field(out)
    for query in ("numpy", "onnx"):
        got = render_field(assets, cam.intrinsics, cam.world_to_camera, H, W, query=query, chunk=100)
        error = np.abs(got["color"] - ref["color"]).max(-1)
        assert np.mean(error < 1e-4) > 0.97 and error.max() < 0.01
        assert np.abs(got["opacity"] - ref["opacity"]).max() < 0.01


def test_a_bad_shading_in_the_manifest_names_the_key(deferred_run, tmp_path):
    _, out, _ = deferred_run
    for bad, key in (("forward", "field.shading"),):
        manifest = json.loads((out / "field.json").read_text())
        manifest["field"]["shading"] = bad
        (tmp_path / "field.json").write_text(json.dumps(manifest))
        (tmp_path / "field.npz").write_bytes((out / "field.npz").read_bytes())
        with pytest.raises(InputError, match=key):
            load_field(tmp_path)


gl_only = pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")


@gl_only
@pytest.mark.parametrize("filtering", ["exact", "hardware"])
def test_gl_renders_the_numpy_frame(deferred_run, filtering):
    from tests.fields.test_glfield import GPU_SLACK

    _, out, manifest = deferred_run
    cam = sphere_views([20]).cameras[0]
    ref = render_field(load_field(out), cam.intrinsics, cam.world_to_camera, H, W)
    bound = glfield.TRANSMITTANCE_EPS + manifest["render"]["num_samples"] * glfield.COLOR_EPS
    for options, tol in (({"transmittance_eps": 0.0, "color_eps": 0.0}, 1e-4), ({}, bound)):
        with glfield.GlFieldRenderer(out, W, H, filtering=filtering, **options) as renderer:
            got = renderer.render(cam.intrinsics, cam.world_to_camera)
        assert np.abs(got["color"] - ref["color"]).max() <= tol + GPU_SLACK
        assert np.abs(got["opacity"] - ref["opacity"]).max() <= tol + GPU_SLACK
        assert np.array_equal(np.isfinite(got["depth"]), np.isfinite(ref["depth"]))


@gl_only
def test_gl_refuses_the_latent_approximation_on_a_deferred_field(deferred_run):
    _, out, _ = deferred_run
    with pytest.raises(InputError, match="color_mode"):
        glfield.GlFieldRenderer(out, W, H, color_mode="latent")
