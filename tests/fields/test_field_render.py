"""Volume rendering, sampling, contraction and the occupancy grid of models.fields (hard cases first)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from engine.core.errors import InputError
from models.fields.components.encodings import MLP, channel_first, sample_planes, sh_encoding
from models.fields.components.render import OPACITY_EPS, composite, render_image, volume_weights
from models.fields.components.sampling import (OccupancyGrid, camera_rays, contract_ndc, ray_box_intersection,
                                               sample_intervals)
from models.fields.static.field import FieldConfig, TriPlaneField
from models.fields.static.model import RenderConfig, SceneBox, StaticFieldModel

TINY_FIELD = FieldConfig(resolutions=(4, 8), feature_dim=4, density_hidden=8, geo_feature_dim=3, color_hidden=8)


pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _reference_weights(sigma: np.ndarray, deltas: np.ndarray) -> np.ndarray:
    """Textbook product form in float64: T_i = prod_{j<i} (1 - alpha_j), w_i = T_i alpha_i."""
    alpha = 1.0 - np.exp(-sigma * deltas)
    trans = np.cumprod(np.concatenate([np.ones_like(alpha[..., :1]), 1.0 - alpha[..., :-1]], axis=-1), axis=-1)
    return trans * alpha


def _box_model(density_bias: float = 0.0, near: float = 0.1, far: float = 10.0) -> StaticFieldModel:
    torch.manual_seed(0)
    scene = SceneBox("bounded-360", near, far, box_min=[-1.0, -1.0, -1.0], box_max=[1.0, 1.0, 1.0])
    cfg = FieldConfig(**{**TINY_FIELD.__dict__, "density_bias": density_bias})
    return StaticFieldModel(scene, [1.0, 1.0, 1.0], cfg, RenderConfig(num_samples=32))


# ----------------------------------------------------------------------------------------------------
# volume_weights


def test_weights_match_product_form_reference():
    rng = np.random.default_rng(0)
    sigma = rng.exponential(2.0, size=(64, 40))
    deltas = rng.uniform(0.0, 0.2, size=(64, 40))
    w, t = volume_weights(torch.tensor(sigma, dtype=torch.float32), torch.tensor(deltas, dtype=torch.float32))
    np.testing.assert_allclose(w.numpy(), _reference_weights(sigma, deltas), atol=2e-6)
    np.testing.assert_allclose(t[:, 0].numpy(), 1.0)


def test_long_rays_with_huge_densities_do_not_underflow_to_nan():
    n = 10_000
    sigma = torch.full((4, n), 1e4)
    sigma[1] = torch.logspace(-3, 6, n)          # from empty to extreme
    sigma[2, : n // 2] = 0.0                      # empty first half, then a wall
    sigma[3] = torch.rand(n, generator=torch.Generator().manual_seed(1)) * 1e6
    deltas = torch.full((4, n), 0.01, requires_grad=True)
    sigma.requires_grad_(True)
    w, t = volume_weights(sigma, deltas)
    assert torch.isfinite(w).all() and torch.isfinite(t).all()
    assert (w >= 0).all() and (w.sum(-1) <= 1.0 + 1e-6).all()
    assert torch.allclose(w.sum(-1), torch.ones(4), atol=1e-5)  # all four rays end opaque
    assert w[2, n // 2].item() == pytest.approx(1.0)   # the wall takes everything
    (w * torch.linspace(0, 1, n)).sum().backward()
    assert torch.isfinite(sigma.grad).all() and torch.isfinite(deltas.grad).all()


def test_infinite_density_is_an_opaque_sample():
    sigma = torch.tensor([[0.0, float("inf"), 3.0, float("inf")]])
    deltas = torch.tensor([[1.0, 1.0, 0.0, 1.0]])
    w, t = volume_weights(sigma, deltas)
    assert w.tolist() == [[0.0, 1.0, 0.0, 0.0]]
    assert t.tolist() == [[1.0, 1.0, 0.0, 0.0]]


def test_zero_densities_give_zero_weights_and_defined_depth():
    sigma = torch.zeros(3, 50, requires_grad=True)
    deltas = torch.full((3, 50), 0.1)
    w, trans = volume_weights(sigma, deltas)
    assert (w == 0).all() and (trans == 1).all()
    t = torch.linspace(1, 5, 50).expand(3, 50)
    background = torch.tensor([0.2, 0.4, 0.6])
    color, depth, expected, opacity = composite(w, torch.rand(3, 50, 3), t, background)
    assert torch.isinf(depth).all() and (depth > 0).all()   # "no surface", the project's sky convention
    assert (expected == 0).all() and (opacity == 0).all()
    assert torch.allclose(color, background.expand(3, 3))
    (color.sum() + expected.sum() + torch.where(torch.isfinite(depth), depth, 0).sum()).backward()
    assert torch.isfinite(sigma.grad).all()


def test_depth_of_an_opaque_sample_and_background_blend():
    sigma = torch.tensor([[0.0, 0.0, 1e3, 0.0], [0.0, math.log(2.0), 0.0, 0.0]])
    deltas = torch.ones(2, 4)
    t = torch.tensor([[1.0, 2.0, 3.0, 4.0]] * 2)
    w, _ = volume_weights(sigma, deltas)
    color, depth, expected, opacity = composite(w, torch.ones(2, 4, 3) * 0.5, t, torch.zeros(3))
    assert depth[0] == pytest.approx(3.0) and expected[0] == pytest.approx(3.0)
    assert opacity[1] == pytest.approx(0.5) and depth[1] == pytest.approx(2.0)   # normalised by opacity
    assert expected[1] == pytest.approx(1.0) and color[1, 0] == pytest.approx(0.25)
    assert OPACITY_EPS < 0.5


@pytest.mark.parametrize("scale", [1e-3, 1.0, 1e3, 1e5])
def test_fp16_weights_are_finite(scale):
    sigma = (torch.rand(8, 1000, generator=torch.Generator().manual_seed(2)) * scale).half()
    deltas = torch.full((8, 1000), 0.01).half()
    w, t = volume_weights(sigma, deltas)
    assert w.dtype == torch.float16
    assert torch.isfinite(w).all() and torch.isfinite(t).all()
    assert (w.float().sum(-1) <= 1.0 + 1e-3).all()


def test_volume_weights_rejects_mismatched_shapes():
    with pytest.raises(InputError, match="deltas"):
        volume_weights(torch.ones(2, 5), torch.ones(2, 4))
    with pytest.raises(InputError, match="sigma"):
        volume_weights(torch.ones(2, 5, dtype=torch.long), torch.ones(2, 5))


# ----------------------------------------------------------------------------------------------------
# rays, samples, bounds


def test_camera_rays_are_planar_depth_rays_through_pixel_centres():
    rng = np.random.default_rng(3)
    k = np.array([[40.0, 0.0, 17.0], [0.0, 38.0, 11.0], [0.0, 0.0, 1.0]])
    q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
    q *= np.sign(np.linalg.det(q))
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = q, rng.normal(size=3)
    h, w = 6, 9
    origins, dirs = camera_rays(k, w2c, h, w, dtype=torch.float64)
    points = (origins + 2.5 * dirs).numpy()
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    np.testing.assert_allclose(cam[:, 2], 2.5, atol=1e-9)          # t is camera z
    uv = (cam @ k.T)[:, :2] / cam[:, 2:]
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    np.testing.assert_allclose(uv, np.stack([u, v], -1).reshape(-1, 2), atol=1e-9)


def test_ray_box_intersection_handles_axis_aligned_and_missing_rays():
    o = torch.tensor([[0.0, 0.0, -3.0], [0.0, 5.0, -3.0], [0.0, 0.0, 0.0], [1.0, 0.0, -3.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    t0, t1 = ray_box_intersection(o, d, -torch.ones(3), torch.ones(3))
    assert torch.isfinite(t0).all() and torch.isfinite(t1).all()
    assert (t0[0].item(), t1[0].item()) == (2.0, 4.0)
    assert t1[1] <= t0[1]                      # misses (outside the y slab)
    assert t0[2] == -1.0 and t1[2] == 1.0       # origin inside
    assert t0[3] == 2.0 and t1[3] == 4.0        # grazing the face x = 1


@pytest.mark.parametrize("spacing", ["linear", "disparity"])
def test_sample_intervals_tile_the_range(spacing):
    near, far = torch.tensor([1.0, 2.0, 3.0]), torch.tensor([5.0, 2.0, 1.0e30])
    for jitter in (False, True):
        t, deltas = sample_intervals(near, far, 16, spacing=spacing, jitter=jitter,
                                     generator=torch.Generator().manual_seed(0))
        assert (deltas >= 0).all() and (t[:, 1:] >= t[:, :-1]).all()
        assert deltas[0].sum().item() == pytest.approx(4.0, rel=1e-5)
        assert (deltas[1] == 0).all() and (t[1] == 2.0).all()   # empty range -> zero-length bins
        assert torch.isfinite(t).all() and torch.isfinite(deltas).all()
    if spacing == "disparity":
        t, _ = sample_intervals(torch.tensor([1.0]), torch.tensor([float("inf")]), 4, spacing="disparity")
        np.testing.assert_allclose(1.0 / t[0].numpy(), [0.875, 0.625, 0.375, 0.125], rtol=1e-5)


def test_rays_missing_the_box_get_background_and_skip_the_field():
    model = _box_model(density_bias=5.0)
    calls = []
    model.field.register_forward_hook(lambda *args: calls.append(1))
    o = torch.tensor([[0.0, 3.0, -5.0], [0.0, 0.0, -5.0]])
    d = torch.tensor([[0.0, 0.0, 1.0], [0.0, 0.0, 1.0]])
    out = model.render_rays(o[:1], d[:1], torch.tensor([0.1]), torch.tensor([10.0]))
    assert not calls                                       # nothing sampled inside the box
    assert out.weights.abs().sum() == 0 and out.opacity.item() == 0.0
    assert torch.isinf(out.depth).all() and torch.allclose(out.color, torch.ones(1, 3))
    out = model.render_rays(o, d, torch.full((2,), 0.1), torch.full((2,), 10.0))
    assert out.opacity[0] == 0 and out.opacity[1] > 0.99
    assert 4.0 - 1e-4 <= out.depth[1] <= 4.2            # the box's front face is at planar depth 4


def test_camera_inside_the_box_starts_at_near():
    model = _box_model(density_bias=2.0, near=0.3)
    o = torch.zeros(5, 3)
    d = torch.nn.functional.normalize(torch.randn(5, 3, generator=torch.Generator().manual_seed(4)), dim=-1)
    t_near, t_far = model.ray_bounds(o, d, torch.full((5,), 0.3), torch.full((5,), 10.0))
    assert (t_near == 0.3).all() and (t_far > 0.99).all() and (t_far < 1.8).all()
    out = model.render_rays(o, d, torch.full((5,), 0.3), torch.full((5,), 10.0))
    assert (out.t >= 0.3).all() and torch.isfinite(out.color).all() and (out.opacity > 0.5).all()


def test_contract_ndc_maps_the_reference_frustum_to_the_cube():
    k = torch.tensor([[50.0, 0.0, 32.0], [0.0, 50.0, 24.0], [0.0, 0.0, 1.0]])
    w2c = torch.eye(4)
    pts = torch.tensor([[0.0, 0.0, 2.0], [0.0, 0.0, 1e9], [-32 / 50 * 4, -24 / 50 * 4, 4.0], [0.0, 0.0, -1.0]])
    c = contract_ndc(pts, k, w2c, 64, 48, near=2.0)
    assert c[0].tolist() == pytest.approx([0.0, 0.0, -1.0])
    assert c[1, 2].item() == pytest.approx(1.0)
    assert c[2, :2].tolist() == pytest.approx([-1.0, -1.0])     # the top-left image corner
    assert (c[3].abs() > 1).any()                               # behind the camera: outside


def test_forward_facing_model_renders_finite_rays_to_infinity():
    views_scene = SceneBox("forward-facing", 1.8, float("inf"), ndc_intrinsics=[[20, 0, 8], [0, 20, 8], [0, 0, 1]],
                           ndc_world_to_camera=np.eye(4).tolist(), ndc_size=[16, 16])
    torch.manual_seed(0)
    model = StaticFieldModel(views_scene, [0, 0, 0], TINY_FIELD, RenderConfig(num_samples=16))
    out = render_image(model, np.array([[20.0, 0, 8], [0, 20, 8], [0, 0, 1]]), np.eye(4), 16, 16, 1.8, float("inf"))
    assert np.isfinite(out["color"]).all() and out["color"].shape == (16, 16, 3)
    assert (out["opacity"] <= 1 + 1e-6).all() and not np.isnan(out["depth"]).any()


def test_render_image_is_independent_of_chunking():
    model = _box_model()
    k = np.array([[10.0, 0, 4], [0, 10, 3], [0, 0, 1]])
    w2c = np.eye(4)
    w2c[2, 3] = 4.0
    a = render_image(model, k, w2c, 6, 8, 0.1, 10.0, chunk=7)
    b = render_image(model, k, w2c, 6, 8, 0.1, 10.0, chunk=1000)
    np.testing.assert_allclose(a["color"], b["color"], atol=1e-6)
    np.testing.assert_allclose(a["depth"], b["depth"], atol=1e-5)


# ----------------------------------------------------------------------------------------------------
# components


def test_sample_planes_is_a_product_of_bilinear_lookups():
    torch.manual_seed(0)
    planes = [torch.rand(3, 2, 5, 5)]
    coords = torch.tensor([[0.3, -0.7, 0.1]])
    feats = sample_planes(planes, coords)

    def bilinear(img, x, y):  # align_corners=True texel grid
        r = img.shape[-1] - 1
        fx, fy = (x + 1) / 2 * r, (y + 1) / 2 * r
        x0, y0 = int(math.floor(fx)), int(math.floor(fy))
        ax, ay = fx - x0, fy - y0
        return ((1 - ax) * (1 - ay) * img[:, y0, x0] + ax * (1 - ay) * img[:, y0, x0 + 1]
                + (1 - ax) * ay * img[:, y0 + 1, x0] + ax * ay * img[:, y0 + 1, x0 + 1])

    x, y, z = coords[0].tolist()
    want = bilinear(planes[0][0], x, y) * bilinear(planes[0][1], x, z) * bilinear(planes[0][2], y, z)
    assert torch.allclose(feats[0], want, atol=1e-6)


@pytest.mark.parametrize("in_dim,layers", [(8, 1), (24, 1), (8, 0)])
def test_an_mlp_of_channel_first_features_trains_as_its_sequential_form(in_dim, layers):
    """Plane features (a transposed (C, M) tensor) take the first layer's channel-first backward: the same
    outputs, input and bias gradients bit for bit, and the same weight gradient to float32 round-off (its sum
    is rounded in another order)."""
    torch.manual_seed(0)
    mlp = MLP(in_dim, 32, 3, layers=layers)
    stored = torch.randn(in_dim, 3000, requires_grad=True)
    assert channel_first(stored.t()) and not channel_first(stored) and not channel_first(stored.t()[:1])
    grad_out = torch.randn(3000, 3)
    results = []
    for forward in (mlp, mlp.net):  # the MLP's own forward, then nn.Sequential (the reference)
        stored.grad = None
        mlp.zero_grad()
        out = forward(stored.t())
        out.backward(grad_out)
        results.append((out.detach(), stored.grad.clone(), [p.grad.clone() for p in mlp.parameters()]))
    (out, grad_in, grads), (ref_out, ref_in, ref_grads) = results
    assert torch.equal(out, ref_out) and torch.equal(grad_in, ref_in)
    assert torch.equal(grads[1], ref_grads[1]) and all(torch.equal(a, b) for a, b in zip(grads[2:], ref_grads[2:]))
    torch.testing.assert_close(grads[0], ref_grads[0], rtol=1e-5, atol=1e-5)
    rows = stored.detach().t().contiguous()
    assert torch.equal(mlp(rows), mlp.net(rows))  # row-major inputs run nn.Sequential
    with torch.no_grad():
        assert torch.equal(mlp(stored.t()), ref_out)


def test_sh_encoding_band_zero_and_one():
    d = torch.nn.functional.normalize(torch.randn(10, 3), dim=-1)
    e = sh_encoding(d, 4)
    assert e.shape == (10, 16)
    assert torch.allclose(e[:, 0], torch.full((10,), 0.28209479177387814))
    # band-1 is linear in the direction, band-2/3 even/odd under d -> -d
    assert torch.allclose(sh_encoding(-d, 4)[:, 1:4], -e[:, 1:4], atol=1e-6)
    assert torch.allclose(sh_encoding(-d, 4)[:, 4:9], e[:, 4:9], atol=1e-6)


@pytest.mark.filterwarnings("ignore::FutureWarning")  # torch.export internals
def test_field_exports_to_onnx_and_matches(tmp_path):
    pytest.importorskip("onnxscript")
    ort = pytest.importorskip("onnxruntime")
    torch.manual_seed(0)
    field = TriPlaneField(TINY_FIELD).eval()
    coords = torch.rand(64, 3) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(64, 3), dim=-1)
    torch.onnx.export(field, (coords, dirs), str(tmp_path / "field.onnx"), dynamo=True, opset_version=20,
                      input_names=["coords", "directions"], output_names=["sigma", "rgb"])
    session = ort.InferenceSession(str(tmp_path / "field.onnx"))
    sigma, rgb = session.run(None, {"coords": coords.numpy(), "directions": dirs.numpy()})
    want_sigma, want_rgb = field(coords, dirs)
    np.testing.assert_allclose(sigma, want_sigma.detach().numpy(), rtol=1e-5, atol=1e-6)
    np.testing.assert_allclose(rgb, want_rgb.detach().numpy(), rtol=1e-5, atol=1e-6)


def test_field_outputs_are_finite_and_bounded():
    field = TriPlaneField(TINY_FIELD)
    coords = torch.rand(100, 3) * 2 - 1
    dirs = torch.nn.functional.normalize(torch.randn(100, 3), dim=-1)
    sigma, rgb = field(coords, dirs)
    assert sigma.shape == (100,) and rgb.shape == (100, 3)
    assert (sigma > 0).all() and torch.isfinite(sigma).all() and ((rgb >= 0) & (rgb <= 1)).all()
    with pytest.raises(InputError, match="direction_encoding"):
        TriPlaneField(FieldConfig(direction_encoding="fancy"))


def test_occupancy_grid_marks_a_ball():
    grid = OccupancyGrid(16)

    def ball(coords):
        return torch.where(coords.norm(dim=-1) < 0.5, 100.0, 0.0)

    frac = grid.update(ball, threshold=1.0, generator=torch.Generator().manual_seed(0))
    assert 0.01 < frac < 0.2
    q = grid.query(torch.tensor([[0.0, 0.0, 0.0], [0.9, 0.9, 0.9], [1.5, 0.0, 0.0]]))
    assert q.tolist() == [True, False, False]


def test_the_logistic_function_saturates_without_an_overflow_warning():
    """A colour logit far below zero (a trained field's dark sample) gives exactly 0 and no RuntimeWarning."""
    import warnings

    from engine.fields.render import sigmoid_np

    with warnings.catch_warnings():
        warnings.simplefilter("error")
        got = sigmoid_np(np.array([-1000.0, -5.0, 0.0, 5.0, 1000.0], np.float32))
    np.testing.assert_allclose(got, [0.0, 1 / (1 + np.exp(5.0)), 0.5, 1 / (1 + np.exp(-5.0)), 1.0], rtol=1e-6)
    assert got.dtype == np.float32
