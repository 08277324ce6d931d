"""Dynamic fields (thesis Ch. 5): hex-planes, DeRF / K-Planes models, time handling, data, sparse flow priors,
training, export, the command line and the hard cases (static scene, no matches, objects entering)."""
from __future__ import annotations

import dataclasses
import json
import math
import warnings
from dataclasses import replace
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from engine.core.colorspace import linear_to_srgb
from engine.core.errors import InputError
from engine.core.frames import Camera
from engine.io.rgbd import read_rig
from models.fields.components.encodings import plane_grid, read_planes, sample_planes
from models.fields.data.select import select_dynamic_views
from models.fields.data.timed import TimedViews, border_crossings, load_dnerf, load_rig_video, split_by_camera
from models.fields.dynamic.model import (DynamicFieldConfig, DynamicFieldModel, MotionConfig, MotionField,
                                         sample_hex_planes, time_grid, time_smoothness)
from models.fields.losses import LOSS_TERMS, LossInputs, LossTerm, RayBatch, check_loss_terms
from models.fields.priors.flow import (SparseFlowPrior, SparseFlowState, coherent_matches, flow_pairs,
                                       fundamental_matrix, sampson_distance, sparse_flow_loss)
from models.fields.static.field import FieldConfig
from models.fields.static.model import RenderConfig, SceneBox
from models.fields.train_dynamic import (MOTION_TERMS, DynamicTrainConfig, evaluate_dynamic, load_dynamic_model,
                                         train_dynamic)
from tests.fields.test_field_train import look_at_origin

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------------------------------
# A textured sphere moving along x, rendered in closed form (white background, true planar depth)


def sphere_video(azimuths, times, *, size: int = 20, speed: float = 0.5, radius: float = 0.55,
                 texture: bool = True, frequency: float = 1.0) -> TimedViews:
    """Fixed cameras at ``azimuths`` (degrees) see a sphere whose centre is (speed * t, 0, 0) at each time."""
    focal = size / (2 * np.tan(np.radians(25.0)))
    k = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    images, depths, cams, stamp, cam_ids, frame_ids, hits = [], [], [], [], [], [], []
    for c, az in enumerate(azimuths):
        a, e = np.radians(az), np.radians(25.0)
        eye = 3.0 * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        w2c = look_at_origin(eye)
        d = np.stack([(u - k[0, 2]) / focal, (v - k[1, 2]) / focal, np.ones_like(u)], -1) @ w2c[:3, :3]
        for f, t in enumerate(times):
            centre = np.array([speed * t, 0.0, 0.0])
            o = eye - centre
            qa, qb, qc = (d * d).sum(-1), 2 * (d @ o), o @ o - radius ** 2
            disc = qb * qb - 4 * qa * qc
            hit = disc > 0
            depth = np.where(hit, (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa), np.inf)
            p = (o + np.where(hit, depth, 0)[..., None] * d) * frequency  # object coordinates: moves with it
            tex = 0.5 + 0.4 * np.stack([np.sin(7 * p[..., 0] + 1), np.sin(6 * p[..., 1] - 4 * p[..., 2]),
                                        np.cos(8 * p[..., 2] + p[..., 0])], -1) if texture else np.full(p.shape, 0.4)
            images.append(np.where(hit[..., None], tex, 1.0).astype(np.float32))
            depths.append(depth.astype(np.float32))
            hits.append(hit)
            cams.append(Camera(k.copy(), w2c))
            stamp.append(float(t))
            cam_ids.append(c)
            frame_ids.append(f)
    n = len(images)
    return TimedViews(images=np.stack(images), cameras=cams, near_far=np.tile([1.0, 5.0], (n, 1)),
                      scene_type="bounded-360", depth=np.stack(depths), bounds=np.array([[-1.0] * 3, [1.0] * 3]),
                      background=np.ones(3, np.float32), names=[f"cam{c}@{f}" for c, f in zip(cam_ids, frame_ids)],
                      times=np.array(stamp), camera_ids=np.array(cam_ids), frame_ids=np.array(frame_ids),
                      camera_names=[f"cam{c}" for c in range(len(azimuths))], objects=np.stack(hits))


TINY = DynamicFieldConfig(kind="derf",
                          canonical=FieldConfig(resolutions=(8, 16), feature_dim=4, density_hidden=16,
                                                geo_feature_dim=7, color_hidden=16),
                          motion=MotionConfig(resolutions=(8,), feature_dim=4, hidden=16))


def tiny_config(steps: int = 40, **changes) -> DynamicTrainConfig:
    base = DynamicTrainConfig(steps=steps, rays_per_batch=256, warmup_steps=10, occupancy_warmup=1000,
                              log_every=10, field=TINY, render=RenderConfig(num_samples=24))
    return dataclasses.replace(base, **changes)


TIMES = [0.0, 0.25, 0.5, 0.75, 1.0]


@pytest.fixture(scope="module")
def moving():
    """3 train cameras and 1 held-out camera between them, 5 times, the sphere moving 0.5 units."""
    video = sphere_video([0, 30, 15, 60], TIMES)
    return split_by_camera(video, ["cam0", "cam1", "cam3"], ["cam2"])


@pytest.fixture(scope="module")
def derf_run(moving, tmp_path_factory):
    train, _ = moving
    return train_dynamic(train, tiny_config(40), tmp_path_factory.mktemp("derf"), progress=False)


def _model(kind: str = "derf", **config) -> DynamicFieldModel:
    torch.manual_seed(0)
    scene = SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3)
    cfg = dataclasses.replace(TINY, kind=kind, **config)
    return DynamicFieldModel(scene, [1.0, 1.0, 1.0], (0.0, 1.0), cfg, RenderConfig(num_samples=16), time_resolution=4)


# ----------------------------------------------------------------------------------------------------
# Components


def _bilinear(plane: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """(C, H, W) plane at (a along the width, b along the height) in [-1, 1], align_corners=True, border."""
    c, h, w = plane.shape
    x = np.clip((a + 1) / 2 * (w - 1), 0, w - 1)
    y = np.clip((b + 1) / 2 * (h - 1), 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = x - x0, y - y0
    return (plane[:, y0, x0] * (1 - fx) * (1 - fy) + plane[:, y0, x0 + 1] * fx * (1 - fy)
            + plane[:, y0 + 1, x0] * (1 - fx) * fy + plane[:, y0 + 1, x0 + 1] * fx * fy).T


def test_hex_plane_lookup_matches_a_hand_written_bilinear_reference():
    g = torch.Generator().manual_seed(0)
    spatial = [torch.rand(3, 3, r, r, generator=g) + 0.5 for r in (5, 9)]
    temporal = [torch.rand(3, 3, 4, r, generator=g) + 0.5 for r in (5, 9)]
    coords = torch.rand(50, 3, generator=g) * 2.2 - 1.1  # a few outside: border texels
    times = torch.rand(50, generator=g) * 2 - 1
    got = sample_hex_planes(spatial, temporal, coords, times).numpy()
    x, t = coords.numpy().astype(np.float64), times.numpy().astype(np.float64)
    want = []
    for s, tp in zip(spatial, temporal):
        s, tp = s.numpy().astype(np.float64), tp.numpy().astype(np.float64)
        f = _bilinear(s[0], x[:, 0], x[:, 1]) * _bilinear(s[1], x[:, 0], x[:, 2]) * _bilinear(s[2], x[:, 1], x[:, 2])
        f *= _bilinear(tp[0], x[:, 0], t) * _bilinear(tp[1], x[:, 1], t) * _bilinear(tp[2], x[:, 2], t)
        want.append(f)
    assert got.shape == (50, 6)
    np.testing.assert_allclose(got, np.concatenate(want, axis=1), rtol=1e-5, atol=1e-6)
    assert sample_hex_planes(spatial, temporal, torch.zeros(0, 3), torch.zeros(0)).shape == (0, 6)


def _prod_lookup(plane: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    # the lookup before 2026-11-28 (the oracle of read_planes): torch.prod across the three planes
    return torch.nn.functional.grid_sample(plane, grid, mode="bilinear", padding_mode="border",
                                           align_corners=True)[:, :, 0, :].prod(dim=0)


def test_hex_plane_lookup_equals_the_prod_lookup_with_its_gradients():
    """The fused lookup (grids built once, the product as multiplications) gives the same features as the
    earlier per-plane ``prod`` code, bit for bit, and the same gradients to float round-off."""
    g = torch.Generator().manual_seed(1)
    spatial = [torch.rand(3, 4, r, r, generator=g).requires_grad_() for r in (6, 11)]
    temporal = [(torch.rand(3, 4, 5, r, generator=g) + 0.5).requires_grad_() for r in (6, 11)]
    coords = (torch.rand(300, 3, generator=g) * 2.2 - 1.1).requires_grad_()
    times = torch.rand(300, generator=g) * 2 - 1
    flat = coords[None]
    grid = torch.stack([flat[..., list(a)] for a in ((0, 1), (0, 2), (1, 2))], dim=0)
    tgrid = torch.stack([torch.cat([flat[..., k:k + 1], times[None, :, None]], dim=-1) for k in range(3)], dim=0)
    want = torch.cat([(_prod_lookup(s, grid) * _prod_lookup(t, tgrid)).T for s, t in zip(spatial, temporal)], dim=-1)
    got = sample_hex_planes(spatial, temporal, coords, times)
    assert torch.equal(got, want)
    assert torch.equal(sample_planes(spatial, coords), torch.cat([_prod_lookup(s, grid).T for s in spatial], dim=-1))
    w = torch.randn(got.shape, generator=g)
    params = [coords] + spatial + temporal
    for a, b in zip(torch.autograd.grad((got * w).sum(), params), torch.autograd.grad((want * w).sum(), params)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-6)


def test_contiguous_plane_grids_give_the_strided_grids_lookups_and_gradients_bit_for_bit():
    """plane_grid / time_grid stack the coordinate columns into contiguous grids (faster on the CPU); the
    previous builds (a gather by index, then a permute: strided grids) are the oracle. Same grids, and a hex
    lookup with the coordinates' gradient (the canonical field's case) gives the same features and gradients,
    bit for bit."""
    g = torch.Generator().manual_seed(4)
    spatial = [torch.rand(3, 4, r, r, generator=g).requires_grad_() for r in (6, 11)]
    temporal = [(torch.rand(3, 4, 5, r, generator=g) + 0.5).requires_grad_() for r in (6, 11)]
    coords = (torch.rand(500, 3, generator=g) * 2.2 - 1.1).requires_grad_()
    times = torch.rand(500, generator=g) * 2 - 1
    old_grid = coords[:, torch.tensor([[0, 1], [0, 2], [1, 2]])].permute(1, 0, 2).unsqueeze(1)
    old_tgrid = torch.stack([coords, times[:, None].expand(-1, 3)], dim=-1).permute(1, 0, 2).unsqueeze(1)
    grid, tgrid = plane_grid(coords), time_grid(coords, times)
    assert grid.is_contiguous() and tgrid.is_contiguous() and not old_grid.is_contiguous()
    assert torch.equal(grid, old_grid) and torch.equal(tgrid, old_tgrid)
    want = torch.cat([read_planes(s, old_grid) * read_planes(t, old_tgrid) for s, t in zip(spatial, temporal)]).T
    got = sample_hex_planes(spatial, temporal, coords, times)
    assert torch.equal(got, want)
    w = torch.randn(got.shape, generator=g)
    params = [coords] + spatial + temporal
    for a, b in zip(torch.autograd.grad((got * w).sum(), params), torch.autograd.grad((want * w).sum(), params)):
        assert torch.equal(a, b)


def test_time_smoothness_is_zero_for_planes_linear_in_time():
    rows = torch.linspace(0, 1, 6)[None, None, :, None]
    assert float(time_smoothness([rows.expand(3, 2, 6, 4).clone()])) < 1e-12
    bumpy = torch.zeros(3, 2, 6, 4)
    bumpy[:, :, 3] = 1.0
    assert float(time_smoothness([bumpy])) > 0.1


def test_motion_field_starts_with_zero_flow_and_groups_are_named():
    field = MotionField(MotionConfig(resolutions=(8,), feature_dim=4), time_resolution=4)
    coords = torch.rand(100, 3) * 2 - 1
    assert torch.equal(field(coords, torch.rand(100) * 2 - 1), torch.zeros(100, 3))
    free = MotionField(MotionConfig(resolutions=(8,), feature_dim=4, zero_init=False), time_resolution=4)
    flow = free(coords, torch.zeros(100))
    assert flow.abs().max() > 0 and flow.abs().max() <= free.config.max_flow
    model = _model()
    assert set(model.field.plane_groups()) == {"spatial", "motion_spatial", "temporal"}
    assert set(_model("kplanes").field.plane_groups()) == {"spatial", "temporal"}
    # the temporal group: the motion field's time planes, then the canonical field's ((xt, yt, zt), C, Rt, R)
    assert [p.shape for p in model.field.plane_groups()["temporal"]] == [(3, 4, 4, 8), (3, 4, 4, 8), (3, 4, 4, 16)]
    plain = _model(canonical_time=False).field.plane_groups()["temporal"]
    assert [p.shape for p in plain] == [(3, 4, 4, 8)]
    # a fresh 4D canonical field is time-independent (its time planes start at 1): the thesis's field at step 0
    coords, dirs = torch.rand(50, 3) * 2 - 1, torch.nn.functional.normalize(torch.randn(50, 3), dim=-1)
    with torch.no_grad():
        early, late = model.field(coords, torch.full((50,), -1.0), dirs), model.field(coords, torch.ones(50), dirs)
    assert torch.equal(early.sigma, late.sigma)


def test_static_options_the_dynamic_fields_do_not_build_are_refused():
    for change, name in (({"shading": "latent"}, "field.shading"),
                         ({"density_layers": 2}, "field.canonical.density_layers")):
        with pytest.raises(InputError) as err:
            dataclasses.replace(TINY, canonical=dataclasses.replace(TINY.canonical, **change)).validate()
        assert err.value.field == name


def _deferred(kind: str) -> DynamicFieldModel:
    """A tiny deferred field whose colour MLP's residual matters (an untrained one gives tanh of ~0)."""
    model = _model(kind, canonical=replace(TINY.canonical, shading="deferred"))
    head = model.field.canonical_field if kind == "derf" else model.field
    with torch.no_grad():
        head.color_mlp.net[-1].weight.normal_(0.0, 2.0, generator=torch.Generator().manual_seed(6))
    return model


@pytest.mark.parametrize("kind", ["derf", "kplanes"])
def test_deferred_shading_composites_the_features_and_runs_the_colour_mlp_once_per_ray(kind):
    """``--field.canonical.shading deferred`` (SNeRG / MERF, as the static field): each sample gives sigmoid(h),
    the weights composite them on zeros, and the colour MLP runs once per ray on [F, enc(d)] (DeRF: and the
    encoded time) for ``F[:3] + (1 - A) background + A tanh(.)``. The oracle is that formula written out from the
    samples' latents. ``residual_density_grad`` off changes the gradients, not the render."""
    from models.fields.components.encodings import fourier_encoding

    model = _deferred(kind)
    head = model.field.canonical_field if kind == "derf" else model.field
    g = torch.Generator().manual_seed(3)
    origins = torch.randn(12, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0])
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(12, 3) + torch.randn(12, 3, generator=g) * 0.1
    near, far, times = torch.ones(12), torch.full((12,), 5.0), torch.rand(12, generator=g)
    placed = model.place_timed(origins, directions, near, far, times)
    out = model.render_placed([placed])[0]
    idx, taus, unit = placed.placed.idx, placed.taus, placed.placed.unit
    with torch.no_grad():
        _, h, _, _ = model.field.geometry(placed.placed.coords[idx], taus[idx[0]])
        dense = h.new_zeros(*out.weights.shape, h.shape[-1]).index_put(idx, torch.sigmoid(h))
        features, opacity = (out.weights[..., None] * dense).sum(dim=1), out.weights.sum(dim=1)
        inputs = [features, head.direction_encoding(unit)]
        if kind == "derf":
            inputs.append(fourier_encoding(taus[:, None], TINY.time_frequencies))
        residual = torch.tanh(head.color_mlp(torch.cat(inputs, dim=-1)))
        diffuse = features[:, :3] + (1.0 - opacity)[:, None] * model.background
        want = diffuse + opacity[:, None] * residual
    torch.testing.assert_close(out.color, want, rtol=1e-5, atol=1e-6)
    assert float(opacity.min()) > 0.05 and float((want - diffuse).abs().max()) > 0.05  # the residual matters
    if kind == "derf":  # the colour MLP reads the time: the same features shade otherwise at another time
        other = model.field.shade_pixels(features, opacity, unit, model.background, times=-taus)
        assert float((other - out.color).abs().max()) > 1e-3
    full = model.render_rays(origins, directions, near, far, times)
    assert torch.equal(full.color, out.color)
    geometry = model.render_rays(origins, directions, near, far, times, color=False)
    torch.testing.assert_close(geometry.color, model.background.expand(12, 3) * (1 - geometry.opacity[:, None]))
    colors, grads = [], []
    for through in (True, False):
        model.field.config.residual_density_grad = through
        model.zero_grad()
        color = model.render_rays(origins, directions, near, far, times).color
        color.sum().backward()
        colors.append(color.detach())
        grads.append(head.density_mlp.net[0].weight.grad.clone())
    assert torch.equal(colors[0], colors[1]) and not torch.allclose(grads[0], grads[1])


@pytest.mark.parametrize("kind", ["derf", "kplanes"])
def test_deferred_dynamic_fields_train(moving, tmp_path, kind):
    """Measured at 120 steps on the moving sphere (held-out camera): DeRF 21.67 dB deferred / 22.69 per-sample,
    K-Planes 20.48 / 21.51 (40 steps: 16.24 and 17.64); bound 19 dB."""
    train, test = moving
    field = replace(TINY, kind=kind, canonical=replace(TINY.canonical, shading="deferred"))
    run = train_dynamic(train, tiny_config(120, field=field), tmp_path / "run", progress=False)
    assert load_dynamic_model(run).field.deferred
    assert evaluate_dynamic(run, test, with_flip=False)["psnr"] > 19.0


def test_render_is_finite_for_huge_densities_and_shapes():
    model = _model()
    with torch.no_grad():  # every density at the clamp, huge plane features everywhere
        model.field.canonical_field.density_mlp.net[-1].bias.fill_(1e6)
        for p in model.field.plane_groups()["spatial"]:
            p.fill_(1e4)
    o = torch.tensor([[0.0, 0.0, -3.0]]).repeat(4, 1)
    d = torch.tensor([[0.0, 0.0, 1.0], [0.3, 0.0, 1.0], [5.0, 0.0, 1.0], [0.0, 0.1, 1.0]])
    out = model.render_rays(o, d, torch.ones(4), torch.full((4,), 5.0), torch.tensor([0.0, 0.3, 0.6, 1.0]))
    assert torch.isfinite(out.color).all() and torch.isfinite(out.expected_depth).all()
    assert not torch.isnan(out.depth).any() and (out.weights.sum(-1) <= 1 + 1e-5).all()
    assert out.opacity[0] > 0.99 and out.opacity[2] == 0  # ray 2 misses the box
    empty = model.render_rays(torch.zeros(0, 3), torch.zeros(0, 3), torch.zeros(0), torch.zeros(0), torch.zeros(0))
    assert empty.color.shape == (0, 3)
    with pytest.raises(InputError, match="times"):
        model.render_rays(o, d, torch.ones(4), torch.full((4,), 5.0), torch.zeros(3))


def test_time_outside_the_trained_range_is_a_clear_error(derf_run, moving):
    model = load_dynamic_model(derf_run)
    o, d = torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]])
    with pytest.raises(InputError, match=r"time 1\.5 is outside the trained range \[0, 1\]"):
        model.render_rays(o, d, torch.ones(1), torch.full((1,), 5.0), torch.tensor([1.5]))
    with pytest.raises(InputError, match=r"time -0\.1 is outside"):
        model.query(torch.zeros(1, 3), torch.tensor([-0.1]), d)
    model.render_rays(o, d, torch.ones(1), torch.full((1,), 5.0), torch.tensor([1.0 + 1e-9]))  # round-off is fine
    late = sphere_video([15], [1.2])
    with pytest.raises(InputError, match="outside the trained range"):
        evaluate_dynamic(model, late, with_flip=False)


# ----------------------------------------------------------------------------------------------------
# Data


def _write_dnerf(root: Path, views: TimedViews, split: str, *, folder: str | None = None, missing=()) -> None:
    """A D-NeRF split: ``file_path`` names ``folder`` (default the split); images go to the split's folder."""
    frames = []
    (root / split).mkdir(parents=True, exist_ok=True)
    for i, (image, cam) in enumerate(zip(views.images, views.cameras)):
        c2w_gl = cam.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"./{folder or split}/r_{i}", "time": float(views.times[i]),
                       "transform_matrix": c2w_gl.tolist()})
        if i in missing:
            continue
        rgba = np.concatenate([np.round(linear_to_srgb(image) * 255), np.full(image.shape[:2] + (1,), 255)], -1)
        cv2.imwrite(str(root / split / f"r_{i}.png"), rgba.astype(np.uint8)[..., [2, 1, 0, 3]])
    k = views.cameras[0].intrinsics
    angle = 2 * np.arctan(views.width / (2 * k[0, 0]))
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def _monocular(azimuths, times, size=20) -> TimedViews:
    """One view per time, each from its own camera (D-NeRF's monocular capture)."""
    views = [sphere_video([az], [t], size=size) for az, t in zip(azimuths, times)]
    return TimedViews(images=np.concatenate([v.images for v in views]), cameras=[v.cameras[0] for v in views],
                      near_far=np.tile([2.0, 6.0], (len(views), 1)), scene_type="bounded-360",
                      background=np.ones(3, np.float32), times=np.array(times, float),
                      camera_ids=np.arange(len(views)), frame_ids=np.arange(len(views)),
                      camera_names=[str(i) for i in range(len(views))])


def test_dnerf_loader_skips_missing_frames_with_one_warning(tmp_path):
    views = _monocular([0, 20, 40, 60, 80], [0.5, 0.0, 0.25, 1.0, 0.75])  # listed out of time order
    _write_dnerf(tmp_path, views, "train", folder="train_low", missing=(1, 3))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        got = load_dnerf(tmp_path, "train", downscale=2)
    messages = [str(w.message) for w in caught if issubclass(w.category, UserWarning)]
    assert len(messages) == 1 and "skipping 2 listed frame(s)" in messages[0] and "train_low/r_1" in messages[0]
    assert got.names == ["r_2", "r_0", "r_4"] and got.times.tolist() == [0.25, 0.5, 0.75]  # sorted by time
    assert got.images.shape == (3, 10, 10, 3) and got.camera_ids.tolist() == [0, 1, 2]
    np.testing.assert_allclose(got.cameras[0].intrinsics[0, 0], views.cameras[0].intrinsics[0, 0] / 2, rtol=1e-6)
    np.testing.assert_allclose(got.cameras[1].world_to_camera, views.cameras[0].world_to_camera, atol=1e-9)
    assert got.subset([2, 0]).times.tolist() == [0.75, 0.25]
    bad = json.loads((tmp_path / "transforms_train.json").read_text())
    del bad["frames"][0]["time"]
    (tmp_path / "transforms_train.json").write_text(json.dumps(bad))
    with pytest.raises(InputError, match="time"):
        load_dnerf(tmp_path, "train")


def test_rig_video_loader_returns_every_frame_of_every_camera(tmp_path):
    from engine.scenegen import RigConfig, SceneConfig, generate_rig

    scene = SceneConfig(seed=2, width=32, height=24, num_frames=3, num_objects=(1, 2), supersample=1,
                        shadow_map_size=256, pause_probability=0.0)
    rig = generate_rig(RigConfig(scene=scene, num_cameras=4, test_cameras=1), tmp_path / "rig", progress=False)
    video = load_rig_video(rig)
    assert len(video) == 12 and video.camera_names == ["cam0", "cam1", "cam2", "cam3"]
    np.testing.assert_allclose(video.times[:3], [0.0, 1 / 30, 2 / 30])
    assert video.depth is not None and video.depth.shape == (12, 24, 32) and np.isfinite(video.depth).any()
    train_idx, test_idx = video.default_split
    assert sorted(set(video.camera_ids[test_idx].tolist())) == [2] and len(train_idx) == 9
    train, test = split_by_camera(video, ["cam0", "cam3"], ["cam2"])
    assert len(train) == 6 and test.names == ["cam2@0", "cam2@1", "cam2@2"]
    assert load_rig_video(rig, frames=[2], downscale=2).images.shape == (4, 12, 16, 3)
    # the objects' pixels: object_id > 0 of each frame, sampled as the depth when downscaled
    frame = read_rig(rig).cameras["cam1"][2]
    np.testing.assert_array_equal(video.objects[5], frame.object_id > 0)
    assert 0 < video.objects.mean() < 1
    np.testing.assert_array_equal(load_rig_video(rig, downscale=2).objects[5], (frame.object_id > 0)[1::2, 1::2])
    np.testing.assert_array_equal(video.downscaled(2).objects, load_rig_video(rig, downscale=2).objects)
    with pytest.raises(InputError, match="both train and test"):
        split_by_camera(video, ["cam2"], ["cam2"])
    with pytest.raises(InputError, match="holds out cameras, not a split") as err:
        select_dynamic_views("rig", rig, 1, test_split="val")
    assert err.value.field == "test_split"
    with pytest.raises(InputError, match="must be one of"):
        select_dynamic_views("dnerf", rig, 1, test_split="train")


# ----------------------------------------------------------------------------------------------------
# Sparse flow priors


def test_frame_pairs_take_the_nearest_available_time_on_each_side():
    times = np.array([0, 1, 2, 3, 6, 7, 20], float)  # frames 4, 5 and 8..19 are missing
    pairs = flow_pairs(times, SparseFlowPrior(time_offset=3, across_cameras=False))
    # t + 3 or the nearest available time on that side: 1 -> 4 -> 3, 2 -> 5 -> 6, 6 -> 9 -> 7, 7 -> 10 -> 20
    assert {(0, 3), (1, 3), (2, 4), (4, 5), (5, 6)} <= set(pairs)
    assert all(times[a] != times[b] for a, b in pairs)
    two_cams = np.array([0, 0, 1, 1], float)
    assert flow_pairs(two_cams, SparseFlowPrior(across_time=False)) == [(0, 1), (2, 3)]


def test_geometric_verification_rejects_wrong_matches():
    k = np.array([[50.0, 0, 32], [0, 50, 32], [0, 0, 1]])
    b = np.eye(4)
    b[0, 3] = -0.5  # camera b half a unit to the right of a
    cam_a, cam_b = Camera(k, np.eye(4)), Camera(k, b)
    rng = np.random.default_rng(0)
    world = np.concatenate([rng.uniform(-1, 1, (40, 2)), rng.uniform(3, 5, (40, 1))], 1)
    xa = world[:, :2] / world[:, 2:] * 50 + 32
    xb = (world[:, :2] + [-0.5, 0]) / world[:, 2:] * 50 + 32
    f = fundamental_matrix(cam_a, cam_b)
    assert sampson_distance(f, xa, xb).max() < 1e-9
    off_line = xb + [0, 6.0]
    assert (sampson_distance(f, xa, off_line) > 2).all()
    grid = np.stack(np.meshgrid(np.arange(8) * 5.0, np.arange(8) * 5.0), -1).reshape(-1, 2)
    moved = grid + [3.0, 1.0]
    moved[10] += [9.0, -7.0]  # one wrong match among coherent ones
    keep = coherent_matches(grid, moved, neighbours=6, min_coherent=3, tolerance=2.0)
    assert not keep[10] and keep.sum() == len(grid) - 1
    assert not coherent_matches(grid[:2], moved[:2], min_coherent=3).any()


def test_sparse_flow_loss_vanishes_when_canonical_points_coincide_and_reaches_the_weights():
    g = torch.Generator().manual_seed(0)
    weights_a = torch.rand(5, 8, generator=g).requires_grad_()
    canonical_a = torch.rand(5, 8, 3, generator=g)
    point = (weights_a[..., None] * canonical_a).sum(1).detach()
    weights_b = torch.full((5, 4), 0.25, requires_grad=True)
    canonical_b = (point / 1.0)[:, None, :].expand(5, 4, 3).clone()  # sum_i w_i c'_i = point as well
    assert float(sparse_flow_loss(weights_a, canonical_a, weights_b, canonical_b).detach()) < 1e-10
    loss = sparse_flow_loss(weights_a, canonical_a, weights_b, canonical_b + 0.1)
    assert float(loss.detach()) == pytest.approx(0.03, rel=1e-4)  # 3 coordinates off by 0.1
    grad_a, grad_b = torch.autograd.grad(loss, [weights_a, weights_b])
    assert grad_a.abs().sum() > 0 and grad_b.abs().sum() > 0  # no stop-gradient on the weights
    # through a real model: the loss reaches the canonical density (via the weights) and the motion field
    model = _model()
    with torch.no_grad():
        model.field.motion_field.flow_mlp.net[-1].bias.fill_(0.01)
    o, d = torch.tensor([[0.0, 0.0, -3.0]] * 2), torch.tensor([[0.0, 0.0, 1.0], [0.05, 0.0, 1.0]])
    out_a = model.render_rays(o[:1], d[:1], torch.ones(1), torch.full((1,), 5.0), torch.tensor([0.0]))
    out_b = model.render_rays(o[1:], d[1:], torch.ones(1), torch.full((1,), 5.0), torch.tensor([1.0]))
    loss = sparse_flow_loss(out_a.weights, out_a.canonical, out_b.weights, out_b.canonical)
    loss.backward()
    assert model.field.canonical_field.density_mlp.net[0].weight.grad.abs().sum() > 0
    assert model.field.motion_field.flow_mlp.net[-1].weight.grad.abs().sum() > 0


def test_flow_l1_sums_every_sample_as_the_mean_over_the_evaluated_ones_with_the_same_gradients():
    """flow_l1 sums |flow| over all samples (0 where none was evaluated) and divides by the evaluated count:
    the mean over the gathered evaluated samples (the earlier code, the oracle), to round-off, and the same
    gradients."""
    model = _model()
    with torch.no_grad():
        model.field.motion_field.flow_mlp.net[-1].bias.copy_(torch.tensor([0.05, -0.03, 0.02]))
    g = torch.Generator().manual_seed(6)
    origins = torch.randn(20, 3, generator=g) * 0.3 - torch.tensor([0.0, 0.0, 3.0])
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(20, 3) + torch.randn(20, 3, generator=g) * 0.4
    out = model.render_rays(origins, directions, torch.ones(20), torch.full((20,), 5.0), torch.rand(20, generator=g),
                            jitter=True, generator=g)
    assert 0 < int(out.evaluated.sum()) < out.evaluated.numel()  # some samples are outside the cube
    batch = RayBatch(origins, directions, torch.ones(20), torch.full((20,), 5.0), torch.zeros(20, 3))
    got = LOSS_TERMS["flow_l1"](LossInputs(model, batch, out, 0, LossTerm("flow_l1"), {}))
    want = out.flow[out.evaluated].abs().sum(dim=-1).mean()
    torch.testing.assert_close(got, want, rtol=1e-6, atol=0)
    params = [p for p in model.field.motion_field.parameters()]
    grads = torch.autograd.grad(got, params, retain_graph=True)
    for a, b in zip(grads, torch.autograd.grad(want, params)):
        torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-9)
    assert float(grads[-1].abs().sum()) > 0  # the flow MLP's last bias


def test_sparse_flow_prior_without_matches_warns_and_adds_nothing(tmp_path):
    blank = sphere_video([0, 40], [0.0, 0.5], texture=False)  # flat grey disc on white: no SIFT feature
    with pytest.warns(UserWarning, match="no verified match in any of"):
        state = SparseFlowState(blank, SparseFlowPrior(enabled=True), tmp_path / "priors")
    assert len(state.matches) == 0 and state.extras(_model(), torch.Generator()) == {}
    meta = json.loads((tmp_path / "priors" / "sparse_flow.json").read_text())
    assert meta["matches"] == 0 and meta["pairs_without_matches"] == len(meta["pairs"]) > 0 and "command" in meta
    model = _model()
    batch = RayBatch(torch.zeros(1, 3), torch.ones(1, 3), torch.ones(1), torch.ones(1), torch.zeros(1, 3))
    out = model.render_rays(torch.tensor([[0.0, 0.0, -3.0]]), torch.tensor([[0.0, 0.0, 1.0]]), torch.ones(1),
                            torch.full((1,), 5.0), torch.zeros(1))
    term = LOSS_TERMS["sparse_flow"](LossInputs(model, batch, out, 0, LossTerm("sparse_flow"), {}))
    assert float(term) == 0.0
    config = tiny_config(6, priors=replace(DynamicTrainConfig().priors, flow=SparseFlowPrior(enabled=True)))
    with pytest.warns(UserWarning, match="no verified match"):
        run = train_dynamic(blank, config, tmp_path / "run", progress=False)
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert last["sparse_flow"] == 0.0 and math.isfinite(last["loss"])


def _synthetic_flow_state(prior: SparseFlowPrior, n: int) -> SparseFlowState:
    # n matched pairs of rays from near (0, 0, -3) looking along +z, at random times in [0, 1]
    state = SparseFlowState.__new__(SparseFlowState)
    g = torch.Generator().manual_seed(2)
    state.prior, state.term = prior, prior.loss_term()
    state.matches = type("M", (), {"__len__": lambda self: n})()
    state.origins_a, state.origins_b = torch.randn(n, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0]), \
        torch.randn(n, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0])
    forward = torch.tensor([0.0, 0.0, 1.0])
    state.directions_a = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.2 + forward, dim=-1)
    state.directions_b = torch.nn.functional.normalize(torch.randn(n, 3, generator=g) * 0.2 + forward, dim=-1)
    state.times_a, state.times_b = torch.rand(n, generator=g), torch.rand(n, generator=g)
    return state


def test_the_prior_renders_both_ends_in_one_geometry_call_with_the_samples_of_two_colour_calls(moving):
    """SparseFlowState.extras renders rays a and b in one ``color=False`` call: the same jitter, weights and
    canonical points as two full renders a then b from the same generator state (the earlier code)."""
    train, _ = moving
    n = 40
    state = _synthetic_flow_state(SparseFlowPrior(enabled=True, rays=16), n)
    model = _model()
    with torch.no_grad():
        model.field.motion_field.flow_mlp.net[-1].bias.fill_(0.05)  # a non-zero flow
    got = state.extras(model, torch.Generator().manual_seed(5))["sparse_flow"]
    gen = torch.Generator().manual_seed(5)
    idx = torch.randint(n, (16,), generator=gen)
    near, far = torch.full((16,), float(model.scene.near)), torch.full((16,), float(model.scene.far))
    for end in ("a", "b"):
        want = model.render_rays(getattr(state, f"origins_{end}")[idx], getattr(state, f"directions_{end}")[idx],
                                 near, far, getattr(state, f"times_{end}")[idx], jitter=True, generator=gen)
        out = got[end]
        assert torch.equal(out.t, want.t) and torch.equal(out.evaluated, want.evaluated)
        assert float(want.weights.detach().sum()) > 0.1 and float(want.flow.detach().abs().max()) > 0.01
        for name in ("weights", "canonical", "flow", "opacity", "depth"):
            torch.testing.assert_close(getattr(out, name), getattr(want, name), rtol=1e-5, atol=1e-6)
        torch.testing.assert_close(out.color, model.background.expand(16, 3) * (1 - out.opacity[:, None]))


def test_the_training_step_renders_the_batch_and_the_matched_rays_in_one_pass_as_two_calls_do(moving):
    """``DynamicKind.render_step`` evaluates the batch's samples and the prior's matched rays in one pass
    (``render_placed``); the reference is what the step did before: ``render_rays`` of the batch, then
    ``SparseFlowState.extras`` (its own call), from the same generator state. The same draws and sample
    values; the parameters' gradients equal to float32 round-off."""
    from models.fields.train_dynamic import DYNAMIC

    n = 40
    state = _synthetic_flow_state(SparseFlowPrior(enabled=True, rays=16), n)
    priors = type("P", (), {"flow": state})()
    model = _model()
    with torch.no_grad():  # a non-zero flow that depends on the motion features
        model.field.motion_field.flow_mlp.net[-1].bias.fill_(0.05)
        model.field.motion_field.flow_mlp.net[-1].weight.normal_(0.0, 0.1, generator=torch.Generator().manual_seed(1))
    g = torch.Generator().manual_seed(3)
    batch = RayBatch(torch.randn(24, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0]),
                     torch.tensor([[0.0, 0.0, 1.0]]).expand(24, 3) + torch.randn(24, 3, generator=g) * 0.1,
                     torch.ones(24), torch.full((24,), 5.0), torch.rand(24, 3, generator=g))
    times = torch.rand(24, generator=g)

    def step(reference: bool):
        model.zero_grad()
        gen = torch.Generator().manual_seed(5)
        if reference:
            out = model.render_rays(batch.origins, batch.directions, batch.near, batch.far, times, jitter=True,
                                    generator=gen)
            extras = state.extras(model, gen)
        else:
            out, extras = DYNAMIC.render_step(priors, model, batch, times, 0, gen)
        inputs = LossInputs(model, batch, out, 0, LossTerm("sparse_flow"), extras)
        loss = (LOSS_TERMS["photometric"](inputs) + LOSS_TERMS["sparse_flow"](inputs)
                + 0.01 * LOSS_TERMS["flow_l1"](inputs))
        loss.backward()
        return out, extras["sparse_flow"], {k: p.grad.clone() for k, p in model.named_parameters()}, gen

    (out, matched, grads, gen), (ref, ref_matched, ref_grads, ref_gen) = step(False), step(True)
    assert torch.equal(gen.get_state(), ref_gen.get_state())
    assert float(out.opacity.detach().min()) > 0.05 and float(out.flow.detach().abs().max()) > 0.01
    for got, want in [(out, ref), (matched["a"], ref_matched["a"]), (matched["b"], ref_matched["b"])]:
        assert torch.equal(got.t, want.t) and torch.equal(got.evaluated, want.evaluated)
        for name in ("color", "weights", "canonical", "flow", "opacity", "depth", "canonical_outside"):
            torch.testing.assert_close(getattr(got, name), getattr(want, name), rtol=1e-6, atol=1e-7)
    assert grads.keys() == ref_grads.keys()
    for name, grad in grads.items():
        torch.testing.assert_close(grad, ref_grads[name], rtol=1e-5, atol=1e-7, msg=name)
    assert float(ref_grads["field.motion_field.flow_mlp.net.0.weight"].abs().max()) > 0


@pytest.mark.parametrize("kind", ["derf", "kplanes"])
def test_one_set_of_placed_samples_renders_the_fields_own_canonical_points(kind):
    """``render_placed`` writes the canonical points as the samples plus the dense flow: at the evaluated
    samples, the field's own canonical points bit for bit; elsewhere the samples."""
    model = _model(kind)
    with torch.no_grad():
        if kind == "derf":
            model.field.motion_field.flow_mlp.net[-1].bias.fill_(0.3)
    g = torch.Generator().manual_seed(4)
    origins = torch.randn(12, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0])
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(12, 3) + torch.randn(12, 3, generator=g) * 0.1
    placed = model.place_timed(origins, directions, torch.ones(12), torch.full((12,), 5.0),
                               torch.rand(12, generator=g))
    out = model.render_placed([placed])[0]
    idx = placed.placed.idx
    field = model.field(placed.placed.coords[idx], placed.taus[idx[0]], None)
    assert torch.equal(out.canonical[idx], field.canonical) and torch.equal(out.flow[idx], field.flow)
    assert torch.equal(out.canonical[~out.evaluated], placed.placed.coords[~out.evaluated])
    assert bool(out.canonical_outside.any()) == (kind == "derf")


@pytest.mark.parametrize("kind", ["derf", "kplanes"])
def test_a_geometry_only_render_has_the_weights_of_a_full_render_and_the_background_colour(kind):
    model = _model(kind)
    g = torch.Generator().manual_seed(3)
    origins = torch.randn(12, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0])
    directions = torch.tensor([[0.0, 0.0, 1.0]]).expand(12, 3) + torch.randn(12, 3, generator=g) * 0.1
    near, far, times = torch.ones(12), torch.full((12,), 5.0), torch.rand(12, generator=g)
    full = model.render_rays(origins, directions, near, far, times)
    geometry = model.render_rays(origins, directions, near, far, times, color=False)
    assert float(full.opacity.detach().min()) > 0.05
    for name in ("weights", "opacity", "depth", "canonical", "flow"):
        assert torch.equal(getattr(geometry, name), getattr(full, name)), name
    torch.testing.assert_close(geometry.color, model.background.expand(12, 3) * (1 - geometry.opacity[:, None]))


def test_the_faded_prior_weighs_linearly_less_and_renders_no_matched_ray_once_gone(moving):
    """``fade_start`` / ``fade_steps`` / ``fade_to``: full weight until ``fade_start``, then linearly to
    ``fade_to``; the loss term follows, and from the end of a fade to 0 the training step draws no matched
    pair (the generator advances as a batch-only render's)."""
    from models.fields.train_dynamic import DYNAMIC

    prior = SparseFlowPrior(enabled=True, rays=8, start_step=2, fade_start=10, fade_steps=20, fade_to=0.0)
    term = prior.loss_term()
    factors = [term.factor(s) for s in (0, 1, 2, 10, 15, 20, 29, 30, 99)]
    assert factors == pytest.approx([0, 0, 1, 1, 0.75, 0.5, 0.05, 0, 0])
    assert LossTerm("x", fade_start=10).factor(10**6) == 1.0  # fade_steps 0: never fades
    floor = replace(prior, fade_to=0.1).loss_term()
    assert [floor.factor(s) for s in (10, 20, 30, 99)] == pytest.approx([1.0, 0.55, 0.1, 0.1])
    assert LossTerm("x", enabled=False).factor(5) == 0.0
    assert DynamicTrainConfig(priors=replace(DynamicTrainConfig().priors, flow=prior)).loss_terms()[-1] == term
    with pytest.raises(InputError, match="priors.flow.fade_steps"):
        replace(prior, fade_steps=-1).validate()
    with pytest.raises(InputError, match=r"losses\[photometric\].fade_start"):
        check_loss_terms([LossTerm("photometric", fade_start=-3)], has_depth=False)
    with pytest.raises(InputError, match="priors.flow.fade_to"):
        replace(prior, fade_to=float("nan")).validate()
    with pytest.raises(InputError, match=r"losses\[photometric\].fade_to"):
        check_loss_terms([LossTerm("photometric", fade_to=1.5)], has_depth=False)

    state = _synthetic_flow_state(prior, 40)
    priors = type("P", (), {"flow": state})()
    model = _model()
    g = torch.Generator().manual_seed(3)
    batch = RayBatch(torch.randn(24, 3, generator=g) * 0.1 - torch.tensor([0.0, 0.0, 3.0]),
                     torch.tensor([[0.0, 0.0, 1.0]]).expand(24, 3), torch.ones(24), torch.full((24,), 5.0),
                     torch.rand(24, 3, generator=g))
    times = torch.rand(24, generator=g)
    floored = type("P", (), {"flow": _synthetic_flow_state(replace(prior, fade_to=0.1), 40)})()
    for state_of, step, drawn in ((priors, 29, True), (priors, 30, False), (floored, 30, True)):
        gen, ref = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
        _, extras = DYNAMIC.render_step(state_of, model, batch, times, step, gen)
        model.render_rays(batch.origins, batch.directions, batch.near, batch.far, times, jitter=True, generator=ref)
        assert ("sparse_flow" in extras) == drawn
        assert torch.equal(gen.get_state(), ref.get_state()) == (not drawn)


def test_sparse_flow_prior_trains_on_textured_motion(tmp_path):
    video = sphere_video([0, 30, 15, 60], TIMES, size=48, frequency=3.0)  # fine texture: SIFT features
    train, _ = split_by_camera(video, ["cam0", "cam1", "cam3"], ["cam2"])
    config = tiny_config(6, priors=replace(DynamicTrainConfig().priors, flow=SparseFlowPrior(enabled=True, rays=32)))
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # some of the tiny frame pairs have no match
        run = train_dynamic(train, config, tmp_path / "run", progress=False)
    meta = json.loads((run / "priors" / "sparse_flow.json").read_text())
    assert meta["matches"] > 0 and meta["matches_across_time"] > 0
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert last["sparse_flow"] > 0 and math.isfinite(last["loss"])
    with pytest.raises(InputError, match="needs a motion field"):
        train_dynamic(train, dataclasses.replace(config, field=replace(TINY, kind="kplanes")), tmp_path / "k",
                      progress=False)


# ----------------------------------------------------------------------------------------------------
# Training, hard cases


def test_static_scene_keeps_the_motion_field_near_zero(tmp_path):
    """Measured (seeds 0, 1, 2): max |flow| over the cube 5.3e-4, 8.5e-4, 5.9e-4 contracted units after 60 steps
    (the mean over the batch peaks near 0.01 early in training and decays); bound 2e-3."""
    static = sphere_video([0, 30, 60], [0.0, 0.5, 1.0], speed=0.0)
    run = train_dynamic(static, tiny_config(60), tmp_path / "run", progress=False)
    scores = evaluate_dynamic(run, sphere_video([15], [0.0, 1.0], speed=0.0), with_flip=False)
    model = load_dynamic_model(run)
    pts = torch.rand(4000, 3) * 2 - 1
    with torch.no_grad():
        flow = model.field.motion_field(pts, torch.rand(4000) * 2 - 1)
    assert float(flow.norm(dim=-1).max()) < 2e-3
    hist = scores["flow_histogram"]
    assert sum(hist["samples"][:3]) == sum(hist["samples"])  # every sample below 0.01
    assert scores["flow_moving_fraction"] == 0.0 and not scores["canonical_limit"]["detected"]


def test_kplanes_baseline_trains_without_motion_terms(moving, tmp_path):
    train, test = moving
    config = tiny_config(20, field=replace(TINY, kind="kplanes"))
    assert not {t.name for t in config.loss_terms()} & MOTION_TERMS
    run = train_dynamic(train, config, tmp_path / "run", progress=False)
    scores = evaluate_dynamic(run, test, with_flip=False)
    assert scores["kind"] == "kplanes" and scores["motion_bytes"] == 0 and np.isfinite(scores["psnr"])
    assert set(json.loads((run / "log.jsonl").read_text().splitlines()[-1])) >= {"time_smoothness", "temporal_l1"}


def test_evaluation_reports_the_static_fields_keys_and_motion_diagnostics(derf_run, moving):
    from models.fields.train_static import evaluate_field
    from tests.fields.test_field_train import sphere_views

    _, test = moving
    scores = evaluate_dynamic(derf_run, test, with_flip=True)
    static = evaluate_field(load_dynamic_model(derf_run).__class__.__mro__[1](
        SceneBox("bounded-360", 1.0, 5.0, [-1.0] * 3, [1.0] * 3), [1.0, 1.0, 1.0]), sphere_views([20], size=8),
        with_flip=False)
    assert set(static) <= set(scores) and {"model_bytes", "motion_bytes", "per_time", "flow_histogram"} <= set(scores)
    assert [p["time"] for p in scores["per_time"]] == TIMES and scores["num_views"] == 5
    assert np.isfinite(scores["depth_mae"]) and 0 < scores["flip"] < 1 and scores["train_seconds"] > 0
    assert 0 < scores["motion_bytes"] < scores["model_bytes"]
    assert len(scores["flow_histogram"]["samples"]) == len(scores["flow_histogram"]["edges"]) - 1
    assert not scores["canonical_limit"]["detected"]  # the sphere stays inside every view
    # the error split between the objects' pixels and the background: the two MSEs make up the frame's
    one = evaluate_dynamic(derf_run, test.subset([2]), with_flip=False)
    share = test.objects[2].mean()
    mse = {name: 10 ** (-one[f"psnr_{name}"] / 10) for name in ("objects", "background")}
    assert 0 < share < 1 and one["psnr_objects"] != one["psnr_background"]
    np.testing.assert_allclose(10 ** (-one["psnr"] / 10), share * mse["objects"] + (1 - share) * mse["background"],
                               rtol=1e-6)


def test_interrupted_run_resumes_exactly(moving, tmp_path):
    train, _ = moving
    config = tiny_config(12, checkpoint_every=5, log_every=1)
    straight = train_dynamic(train, config, tmp_path / "straight", progress=False)

    def crash(model, batch, outputs, step):
        if step == 7:
            raise KeyboardInterrupt
        return {}

    with pytest.raises(KeyboardInterrupt):
        train_dynamic(train, config, tmp_path / "resumed", progress=False, extras_fn=crash)
    assert torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)["step"] == 5
    resumed = train_dynamic(train, config, tmp_path / "resumed", progress=False)
    a, b = load_dynamic_model(straight).state_dict(), load_dynamic_model(resumed).state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    steps = [json.loads(line)["step"] for line in (resumed / "log.jsonl").read_text().splitlines()]
    assert steps == list(range(1, 13))
    with pytest.raises(InputError, match="different config"):
        train_dynamic(train, dataclasses.replace(config, seed=1), resumed, progress=False)
    saved = DynamicTrainConfig.from_dict(json.loads((resumed / "config.json").read_text()))
    assert saved.field.time_resolution == 2 and saved.to_dict() == dataclasses.replace(  # auto values resolved
        config, downscale=1, field=replace(TINY, time_resolution=2)).to_dict()


# ----------------------------------------------------------------------------------------------------
# Objects entering the views


def _entering_rig(out: Path, mode: str) -> Path:
    """A generated 64 x 36 rig, 12 frames: one object enters from the left and stops (``enter``), or moves a
    little inside the views (``inside``)."""
    from engine.io.rgbd import write_rig
    from engine.scenegen import RigConfig, SceneConfig
    from engine.scenegen.rig import make_rig, render_rig

    config = RigConfig(scene=SceneConfig(seed=3, width=64, height=36, num_frames=12, num_objects=(1, 1),
                                         supersample=1, shadow_map_size=512, pause_probability=0.0),
                       num_cameras=4, test_cameras=1)
    rig = make_rig(config)
    obj = rig.scene.objects[0]
    forward = (rig.target - rig.centre) / np.linalg.norm(rig.target - rig.centre)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    radius = obj.bounding_radius()
    distance = 2.5 * radius + 1.0
    end = rig.centre + forward * distance
    end[2] = max(radius, end[2] - 0.5 * radius)
    half_width = distance * math.tan(math.radians(rig.cameras[0].fov_deg) / 2) * 64 / 36
    start = end - right * ((2.0 * half_width + 2 * radius) if mode == "enter" else 0.4 * half_width)
    t_stop = 6 / 30.0
    motion = replace(obj.motion, kind="linear", anchor=start, t_ref=0.0, velocity=(end - start) / t_stop,
                     amplitude=np.zeros(3), circle=(0.0, 0.0, 0.0), hop=(0.0, 0.0, 0.0), spin_rate=0.0,
                     pause=(t_stop, math.inf))
    rig = replace(rig, scene=replace(rig.scene, objects=(replace(obj, motion=motion),)))
    stream = render_rig(rig)

    def frames_of(name):
        for _ in range(rig.num_frames):
            yield next(stream)[1]

    return write_rig(out, {n: frames_of(n) for n in rig.names}, list(rig.train_cameras), list(rig.test_cameras),
                     fps=30.0, objects=rig.scene.scene_objects())


def test_objects_entering_the_views_are_detected_and_reported(tmp_path):
    from engine.io.rgbd import read_rig

    enter = _entering_rig(tmp_path / "enter", "enter")
    video = load_rig_video(enter)
    truth = sorted({round(30 * f.time) for seq in read_rig(enter).cameras.values() for f in seq
                    if (f.object_id[[0, 1, -2, -1]] > 0).any() or (f.object_id[:, [0, 1, -2, -1]] > 0).any()})
    found = border_crossings(video)
    assert truth == [4] and [round(30 * t) for t in found["times"]] == truth  # the frame where it crosses the edge
    assert found["tested_cameras"] == ["cam0", "cam1", "cam2", "cam3"] and not found["skipped_cameras"]
    assert border_crossings(load_rig_video(_entering_rig(tmp_path / "inside", "inside")))["events"] == []
    assert border_crossings(_monocular([0, 20, 40], [0.0, 0.5, 1.0]))["skipped_cameras"] == ["0", "1", "2"]
    train, test = split_by_camera(video, ["cam0", "cam1", "cam3"], ["cam2"])
    config = tiny_config(5, render=RenderConfig(num_samples=8), field=replace(TINY, kind="kplanes"))
    run = train_dynamic(train, config, tmp_path / "run", progress=False)
    limit = evaluate_dynamic(run, test.subset([3, 4, 5]), with_flip=False, context_views=train)["canonical_limit"]
    assert limit["detected"] and [round(30 * t) for t in limit["flagged_times"]] == [4]
    assert any("border crossing in cam" in r for r in limit["reasons"]["0.133333"])
    assert math.isfinite(limit["psnr_flagged"]) and math.isfinite(limit["psnr_unflagged"])


# ----------------------------------------------------------------------------------------------------
# Command line and export


def test_train_eval_export_dynamic_commands(tmp_path, capsys):
    from engine.cli import main

    _write_dnerf(tmp_path / "scene", _monocular([0, 25, 50, 75, 100, 125], [0.0, 0.2, 0.4, 0.6, 0.8, 1.0]), "train")
    _write_dnerf(tmp_path / "scene", _monocular([12, 60, 110], [0.1, 0.5, 1.2]), "test")  # 1.2: outside
    _write_dnerf(tmp_path / "scene", _monocular([40, 70, 90], [0.3, 0.45, 0.7]), "val")
    run = tmp_path / "run"
    with pytest.warns(UserWarning, match="outside the trained time range"):
        code = main(["train", "dynamic", "--scene", str(tmp_path / "scene"), "--out", str(run), "--steps", "8",
                     "--rays-per-batch", "128", "--field.canonical.resolutions", "8,16",
                     "--field.motion.resolutions", "8", "--render.num-samples", "16", "--no-flip",
                     "--render.occupancy", "false"])
    assert code == 0
    scores = json.loads((run / "scores.json").read_text())
    assert scores["dataset"] == "dnerf" and scores["test_views"] == 2 and scores["image_size"] == [20, 20]
    assert json.loads((run / "data.json").read_text())["dropped_test_views"] == ["r_2"]
    saved = json.loads((run / "config.json").read_text())  # the default: SF-DeRF, and why
    assert saved["field"]["kind"] == "derf" and saved["priors"]["flow"]["enabled"]
    assert saved["priors_choice"].startswith("auto:")
    # a monocular capture: the thesis's tri-plane canonical field, and why
    assert not saved["field"]["canonical_time"] and saved["canonical_time_choice"].startswith("auto: off")
    assert "canonical time planes: auto: off, a monocular capture (1 train view a time)" in capsys.readouterr().err
    assert scores["canonical_limit"]["border_crossings"]["skipped_cameras"]  # monocular: not testable
    capsys.readouterr()
    assert main(["eval", "dynamic", str(run), "--json", str(tmp_path / "s.json"), "--no-flip"]) == 0
    again = json.loads((tmp_path / "s.json").read_text())
    assert again["psnr"] == pytest.approx(scores["psnr"], abs=1e-6) and again["model_bytes"] == scores["model_bytes"]
    # the val split scored instead of the run's test split: other views, the same model
    assert main(["eval", "dynamic", str(run), "--split", "val", "--json", str(tmp_path / "v.json"), "--no-flip"]) == 0
    val = json.loads((tmp_path / "v.json").read_text())
    assert val["test_views"] == 3 and val["psnr"] != pytest.approx(scores["psnr"], abs=1e-6)
    assert val["model_bytes"] == scores["model_bytes"]
    assert main(["export", "dynamic", str(run), "--out", str(tmp_path / "export")]) == 0
    manifest = json.loads((tmp_path / "export" / "dynamic.json").read_text())
    assert manifest["kind"] == "derf" and manifest["time"]["range"] == [0.0, 1.0]
    assert max(manifest["parity"]["random_points"].values()) < 1e-4
    assert {"canonical_spatial", "motion_spatial", "motion_temporal"} == set(manifest["field"]["planes"])
    assert manifest["canonical_limit"] is not None
    arrays = np.load(tmp_path / "export" / "dynamic.npz")
    assert arrays["motion_temporal_0"].shape == (3, 4, 3, 8) and arrays["motion_temporal_0_u8"].dtype == np.uint8
    # the ONNX graph on ray points of a real view at a trained time, against torch
    from export.dynamic import check_parity

    model = load_dynamic_model(run)
    lo, hi = torch.tensor(model.scene.box_min), torch.tensor(model.scene.box_max)
    pts = lo + (hi - lo) * (torch.rand(500, 3) * 1.2 - 0.1)
    parity = check_parity(tmp_path / "export" / "dynamic.onnx", model, pts, torch.full((500,), 0.6),
                          torch.nn.functional.normalize(torch.randn(500, 3), dim=-1))
    assert max(parity.values()) < 1e-4
    assert main(["eval", "dynamic", str(tmp_path / "missing")]) == 2
    assert main(["train", "dynamic", "--scene", str(tmp_path / "missing"), "--out", str(tmp_path / "r2")]) == 2
    assert "error" in capsys.readouterr().err
    # a kplanes field has no motion field for the flow prior: one line saying what to change
    assert main(["train", "dynamic", "--scene", str(tmp_path / "scene"), "--out", str(tmp_path / "r3"),
                 "--field.kind", "kplanes", "--priors", "flow", "--steps", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "--field.kind derf" in err[-1] and "priors.flow.enabled" in err[-1] and err[-1].startswith("error")


def test_the_flow_prior_is_chosen_by_the_fields_kind_unless_asked():
    from models.fields.train_dynamic import choose_dynamic_priors

    base = DynamicTrainConfig()
    derf = choose_dynamic_priors(base)
    assert derf.priors.flow.enabled and derf.priors_choice.startswith("auto:")
    kplanes = choose_dynamic_priors(dataclasses.replace(base, field=replace(base.field, kind="kplanes")))
    assert not kplanes.priors.flow.enabled and "no motion field" in kplanes.priors_choice
    kplanes.validate()  # the automatic choice never contradicts the kind
    off = choose_dynamic_priors(base, "")
    assert not off.priors.flow.enabled and off.priors_choice == "explicit: --priors ''"
    on = dataclasses.replace(base, priors=replace(base.priors, flow=replace(base.priors.flow, enabled=True)))
    assert choose_dynamic_priors(on).priors_choice == "explicit: the config enables flow"
    with pytest.raises(InputError, match="unknown prior") as err:
        choose_dynamic_priors(base, "flow,depth")
    assert err.value.field == "priors"


def test_the_canonical_time_planes_are_chosen_by_the_cameras_per_time_unless_asked(tmp_path, capsys):
    from engine.cli import main
    from models.fields.train_dynamic import choose_canonical_time, views_per_time

    mono = _monocular([0, 20, 40, 60], [0.0, 0.25, 0.5, 0.75])
    rig = sphere_video([0, 30], [0.0, 0.5, 1.0], size=20)  # two synchronized cameras
    assert views_per_time(mono) == 1 and views_per_time(rig) == 2
    base = DynamicTrainConfig()
    assert base.field.canonical_time  # the config's default; the command line chooses
    off = choose_canonical_time(base, mono)
    assert not off.field.canonical_time and off.canonical_time_choice.startswith("auto: off, a monocular capture")
    on = choose_canonical_time(dataclasses.replace(base, field=replace(base.field, canonical_time=False)), rig)
    assert on.field.canonical_time
    assert on.canonical_time_choice == "auto: on, a synchronized capture (2 train views a time)"
    kept = choose_canonical_time(base, mono, explicit=True)
    assert kept.field.canonical_time and kept.canonical_time_choice == "explicit: on"
    kplanes = choose_canonical_time(dataclasses.replace(base, field=replace(base.field, kind="kplanes")), mono)
    assert kplanes.field == replace(base.field, kind="kplanes")
    assert "no canonical field" in kplanes.canonical_time_choice
    # the command line: --field.canonical-time or a config file's field.canonical_time is explicit
    _write_dnerf(tmp_path / "scene", mono, "train")
    _write_dnerf(tmp_path / "scene", _monocular([10, 50], [0.1, 0.6]), "test")
    small = ["--steps", "2", "--rays-per-batch", "64", "--field.canonical.resolutions", "8",
             "--field.motion.resolutions", "8", "--render.num-samples", "8", "--no-flip", "--render.occupancy", "false"]
    (tmp_path / "on.json").write_text(json.dumps({"field": {"canonical_time": True}}))
    for i, extra in enumerate((["--field.canonical-time"], ["--config", str(tmp_path / "on.json")])):
        assert main(["train", "dynamic", "--scene", str(tmp_path / "scene"), "--out", str(tmp_path / f"r{i}"),
                     *small, *extra]) == 0
        saved = json.loads((tmp_path / f"r{i}" / "config.json").read_text())
        assert saved["field"]["canonical_time"] and saved["canonical_time_choice"] == "explicit: on"
    capsys.readouterr()


def test_a_monocular_captures_motion_pays_more_for_bending_in_time_unless_asked(tmp_path, capsys):
    from engine.cli import main
    from models.fields.train_dynamic import MONOCULAR_TIME_SMOOTHNESS, choose_canonical_time, choose_time_smoothness

    def weight(config):
        return next(t.weight for t in config.losses if t.name == "time_smoothness")

    mono = _monocular([0, 20, 40, 60], [0.0, 0.25, 0.5, 0.75])
    rig = sphere_video([0, 30], [0.0, 0.5, 1.0], size=20)
    base = DynamicTrainConfig()
    default = weight(base)
    assert MONOCULAR_TIME_SMOOTHNESS > default
    chosen = choose_time_smoothness(choose_canonical_time(base, mono), mono)
    assert weight(chosen) == MONOCULAR_TIME_SMOOTHNESS
    assert chosen.time_smoothness_choice.startswith("auto: 0.03, a monocular capture")
    assert [t.name for t in chosen.losses] == [t.name for t in base.losses]  # the term's weight, nothing else
    synced = choose_time_smoothness(choose_canonical_time(base, rig), rig)
    assert weight(synced) == default
    assert synced.time_smoothness_choice == f"auto: {default:g}, a synchronized capture (2 train views a time)"
    # canonical time planes asked for on a monocular capture: the term would bend them too, so the weight stays
    asked = choose_time_smoothness(choose_canonical_time(base, mono, explicit=True), mono)
    assert weight(asked) == default and "the canonical field has time planes" in asked.time_smoothness_choice
    kplanes = choose_time_smoothness(dataclasses.replace(base, field=replace(base.field, kind="kplanes")), mono)
    assert weight(kplanes) == default and "a kplanes field" in kplanes.time_smoothness_choice
    kept = choose_time_smoothness(choose_canonical_time(base, mono), mono, explicit=True)
    assert weight(kept) == default and kept.time_smoothness_choice == f"explicit: {default:g}"
    # the command line: --loss time_smoothness=W or a config file's losses entry is explicit
    _write_dnerf(tmp_path / "scene", mono, "train")
    _write_dnerf(tmp_path / "scene", _monocular([10, 50], [0.1, 0.6]), "test")
    small = ["--steps", "2", "--rays-per-batch", "64", "--field.canonical.resolutions", "8",
             "--field.motion.resolutions", "8", "--render.num-samples", "8", "--no-flip", "--render.occupancy", "false"]
    (tmp_path / "w.json").write_text(json.dumps({"losses": [{"name": "time_smoothness", "weight": 0.002}]}))
    for name, extra, want in (("auto", [], MONOCULAR_TIME_SMOOTHNESS), ("flag", ["--loss", "time_smoothness=0.005"],
                              0.005), ("file", ["--config", str(tmp_path / "w.json")], 0.002)):
        assert main(["train", "dynamic", "--scene", str(tmp_path / "scene"), "--out", str(tmp_path / name),
                     *small, *extra]) == 0
        saved = json.loads((tmp_path / name / "config.json").read_text())
        assert [t["weight"] for t in saved["losses"] if t["name"] == "time_smoothness"] == [want]
        assert saved["time_smoothness_choice"].startswith("auto: 0.03" if name == "auto" else "explicit: ")
    capsys.readouterr()


def test_dense_dis_matches_recover_a_known_shift_and_reject_occlusions():
    """The dense-prior comparison's matches: DIS flow on a grid, forward-backward checked."""
    from models.fields.priors.flow import SparseFlowPrior, dense_flow_matches

    rng = np.random.default_rng(0)
    base = cv2.GaussianBlur(rng.uniform(0, 1, (64, 96)).astype(np.float32), (0, 0), 1.5)
    image_a = np.repeat(base[..., None], 3, -1)
    image_b = np.roll(image_a, 3, axis=1)  # everything moves 3 px to the right
    xy_a, xy_b = dense_flow_matches(image_a, image_b, stride=4)
    assert len(xy_a) > 100
    interior = (xy_a[:, 0] > 8) & (xy_a[:, 0] < 80)
    np.testing.assert_allclose(np.median((xy_b - xy_a)[interior], axis=0), [3.0, 0.0], atol=0.1)
    assert (xy_b[:, 0] <= 96).all() and (xy_b[:, 0] >= 0).all()  # matches stay inside image b
    with pytest.raises(InputError, match="sift or dis"):
        SparseFlowPrior(source="raft").validate()
