"""The sparse-input priors of models.fields: SIFT sparse depth (DS-NeRF), Simple-RF augmentation, ViP-NeRF
visibility; each on hand-built scenes with a known answer, then switched on in short training runs."""
from __future__ import annotations

import dataclasses
import json
import warnings

import numpy as np
import pytest
import torch

from engine.core.errors import InputError
from engine.core.frames import Camera
from models.fields.data.views import Views
from models.fields.losses import LOSS_TERMS, LossInputs, LossTerm
from models.fields.priors.config import PRIOR_NAMES, PriorsConfig, build_priors, prior_loss_terms, with_priors
from models.fields.priors.depth import (SparseDepthPrior, SparseDepthState, projection_matrix, sparse_depth_points,
                                        triangulate_checked, triangulate_dlt)
from models.fields.priors.simple import mass_concentration, patch_reprojection_error, reliable_depth_masks
from models.fields.priors.vip import plane_depths_inverse, plane_sweep_visibility
from models.fields.train_static import FieldTrainConfig, build_model, load_model, main, train_field
from tests.fields.test_field_train import sphere_views, tiny_config, write_blender
from tools.field_ablation import main as ablation_main

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def _camera(position, look_at=(0.0, 0.0, 0.0), focal=80.0, size=64) -> Camera:
    eye = np.asarray(position, np.float64)
    f = np.asarray(look_at, np.float64) - eye
    f /= np.linalg.norm(f)
    r = np.cross(f, [0.0, 0.0, 1.0])
    r /= np.linalg.norm(r)
    rot = np.stack([r, np.cross(f, r), f])
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot, -rot @ eye
    return Camera(np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]]), w2c)


def _project(cam: Camera, world: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    cam_pts = world @ cam.world_to_camera[:3, :3].T + cam.world_to_camera[:3, 3]
    pix = cam_pts @ cam.intrinsics.T
    return pix[:, :2] / pix[:, 2:], cam_pts[:, 2]


# ----------------------------------------------------------------------------------------------------
# Sparse depth: triangulation with known poses


def test_dlt_triangulation_is_exact_on_synthetic_correspondences():
    rng = np.random.default_rng(0)
    cams = [_camera([4.0, 0.5, 1.0]), _camera([0.3, 4.2, 0.8]), _camera([-3.0, 2.5, 2.0])]
    world = rng.uniform(-1.0, 1.0, (200, 3))
    obs = np.stack([_project(c, world)[0] for c in cams], axis=1)
    true_depth = np.stack([_project(c, world)[1] for c in cams], axis=1)
    proj = np.stack([projection_matrix(c.intrinsics, c.world_to_camera) for c in cams])
    for views in ([0, 1], [0, 2], [0, 1, 2]):
        keep, depth, errors = triangulate_checked([cams[v] for v in views], obs[:, views])
        assert keep.all() and errors.max() < 1e-3
        assert np.abs(depth / true_depth[:, views] - 1).max() < 1e-6
    assert np.abs(triangulate_dlt(proj, obs) - world).max() < 1e-8
    observed = np.ones((200, 3), bool)
    observed[:, 2] = False
    assert np.abs(triangulate_dlt(proj, obs, observed) - world).max() < 1e-8
    observed[0, 1] = False  # one observation: undetermined
    assert np.isnan(triangulate_dlt(proj, obs, observed)[0]).all()


def test_triangulation_rejects_outliers_and_points_behind_a_camera():
    rng = np.random.default_rng(1)
    cams = [_camera([4.0, 0.0, 1.0]), _camera([2.8, 2.8, 1.0])]
    world = rng.uniform(-1.0, 1.0, (50, 3))
    obs = np.stack([_project(c, world)[0] for c in cams], axis=1)
    # wrong matches: moved 10 px across the epipolar line (the image in b of a's ray through the point)
    centre_a = cams[0].position
    near_pt = _project(cams[1], centre_a + 0.5 * (world[:10] - centre_a))[0]
    along = obs[:10, 1] - near_pt
    across = np.stack([-along[:, 1], along[:, 0]], axis=1) / np.linalg.norm(along, axis=1, keepdims=True)
    obs[:10, 1] += 10.0 * across
    # a point behind both cameras projects to pixels too; its DLT solution lies behind them and is rejected
    behind = np.array([[12.0, 4.0, 3.0]])
    obs_b = np.stack([_project(c, behind)[0] for c in cams], axis=1)
    keep, depth, errors = triangulate_checked(cams, np.concatenate([obs, obs_b]), max_error=2.0)
    assert not keep[:10].any() and keep[10:50].all() and not keep[50]
    assert (depth[10:50] > 0).all()


def _flat_views(n: int = 3, size: int = 24) -> Views:
    cams = [_camera([3.0 * np.cos(a), 3.0 * np.sin(a), 1.0], size=size, focal=30.0) for a in np.linspace(0, 1.2, n)]
    return Views(images=np.full((n, size, size, 3), 0.5, np.float32), cameras=cams,
                 near_far=np.tile([1.0, 5.0], (n, 1)), scene_type="bounded-360",
                 bounds=np.array([[-1.0] * 3, [1.0] * 3]), background=np.ones(3, np.float32))


def test_depth_prior_without_matches_warns_and_adds_zero_loss(tmp_path):
    views = _flat_views()
    points = sparse_depth_points(views, SparseDepthPrior(enabled=True))
    assert len(points) == 0 and all(n == 0 for n in points.matches.values())
    with pytest.warns(UserWarning, match="no SIFT match"):
        state = SparseDepthState(views, SparseDepthPrior(enabled=True), tmp_path / "cache")
    config = tiny_config(steps=3)
    model = build_model(views, config)
    assert state.extras(model, torch.Generator().manual_seed(0)) == {}
    out = model.render_rays(torch.zeros(2, 3), torch.tensor([[0.0, 0, 1]] * 2), torch.ones(2), torch.full((2,), 5.0))
    value = LOSS_TERMS["sift_depth"](LossInputs(model, None, out, 0, LossTerm("sift_depth"), {}))
    assert float(value) == 0.0
    # and a run with the prior on trains (finitely) rather than crashing
    config = dataclasses.replace(tiny_config(steps=3, rays_per_batch=64), priors=with_priors(PriorsConfig(), ["depth"]))
    with pytest.warns(UserWarning, match="no SIFT match"):
        run = train_field(views, config, tmp_path / "run", progress=False)
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert last["sift_depth"] == 0.0 and np.isfinite(last["loss"])
    assert json.loads((run / "priors" / "sparse_depth.json").read_text())["points"] == 0


# ----------------------------------------------------------------------------------------------------
# Simple-RF


def test_mass_concentration_is_finite_with_zero_weights():
    weights = torch.zeros(4, 20, requires_grad=True)
    value = mass_concentration(weights, 5)
    value.sum().backward()
    assert torch.equal(value.detach(), torch.zeros(4)) and torch.isfinite(weights.grad).all()
    w = torch.zeros(3, 20)
    w[0, 7] = 1.0  # all mass in one interval: entropy 0
    w[1] = 1.0 / 20  # spread evenly over the 5 intervals: log 5
    w[2, :4] = 0.25  # partial zeros
    w.requires_grad_(True)
    value = mass_concentration(w, 5)
    value.sum().backward()
    assert value[0].item() == pytest.approx(0.0, abs=1e-7)
    assert value[1].item() == pytest.approx(np.log(5), rel=1e-5)
    assert torch.isfinite(w.grad).all()


def _plane_views(size: int = 48, depth: float = 4.0):
    """A textured fronto-parallel plane Z = depth seen by two cameras 0.6 apart (one slightly rotated)."""
    k = np.array([[50.0, 0, size / 2], [0, 50.0, size / 2], [0, 0, 1.0]])
    w2c_a = np.eye(4)
    angle = np.radians(4.0)
    rot = np.array([[np.cos(angle), 0, -np.sin(angle)], [0, 1, 0], [np.sin(angle), 0, np.cos(angle)]])
    centre_b = np.array([0.6, 0.1, 0.0])
    w2c_b = np.eye(4)
    w2c_b[:3, :3], w2c_b[:3, 3] = rot, -rot @ centre_b
    cams = [Camera(k, w2c_a), Camera(k, w2c_b)]
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    images = []
    for cam in cams:
        d = np.stack([(u - size / 2) / 50.0, (v - size / 2) / 50.0, np.ones_like(u)], -1) @ cam.world_to_camera[:3, :3]
        o = cam.position
        t = (depth - o[2]) / d[..., 2]
        p = o + t[..., None] * d
        images.append(0.5 + 0.4 * np.stack([np.sin(7 * p[..., 0]), np.cos(5 * p[..., 1] + 2 * p[..., 0]),
                                             np.sin(6 * (p[..., 0] - p[..., 1]))], -1))
    return np.stack(images).astype(np.float32), cams


def test_patch_reprojection_error_picks_the_true_depth():
    images, cams = _plane_views()
    pixel = np.array([[20, 20], [24, 30], [15, 25]])
    view, target = np.zeros(3, np.int64), np.ones(3, np.int64)
    e_true = patch_reprojection_error(images, cams, view, pixel, np.full(3, 4.0), target)
    e_wrong = patch_reprojection_error(images, cams, view, pixel, np.full(3, 2.5), target)
    assert (e_true < 2e-3).all() and (e_wrong > 5 * e_true).all()
    m_a, m_m = reliable_depth_masks(torch.from_numpy(e_true), torch.from_numpy(e_wrong), 0.1)  # main right
    assert m_m.all() and not m_a.any()
    m_a, m_m = reliable_depth_masks(torch.from_numpy(e_wrong), torch.from_numpy(e_true), 0.1)  # augmented right
    assert m_a.all() and not m_m.any()
    m_a, m_m = reliable_depth_masks(torch.from_numpy(e_true), torch.from_numpy(e_wrong), 1e-9)  # both above e_tau
    assert not (m_a | m_m).any()
    # no depth, a patch leaving the image, or a point behind the target: never reliable
    bad = patch_reprojection_error(images, cams, np.zeros(3, np.int64), np.array([[20, 20], [1, 20], [20, 20]]),
                                   np.array([np.inf, 4.0, -1.0]), np.ones(3, np.int64))
    assert np.isinf(bad).all()


# ----------------------------------------------------------------------------------------------------
# ViP-NeRF


def test_plane_sweep_marks_an_occluded_region_invisible():
    """Primary at the origin, secondary 1.26 to the right (f b = 63 px, so the 64 planes from near 1 to
    infinity sit at integer disparities 63..0). Background at disparity 10 (Z = 6.3), a foreground square
    at disparity 30 (Z = 2.1) over columns 40-59 of the primary. In the secondary the square covers columns
    10-29, hiding the background of primary columns 20-39; background columns < 10 leave the secondary."""
    h = w = 80
    rng = np.random.default_rng(3)
    background = rng.integers(0, 256, (h, w + 80, 3)).astype(np.float32)  # indexed by primary column + 40
    square = rng.integers(0, 256, (h, 20, 3)).astype(np.float32)
    rows = slice(20, 60)
    primary = background[:, 40:40 + w].copy()
    primary[rows, 40:60] = square[rows]
    secondary = background[:, 50:50 + w].copy()  # secondary column x2 sees background column x2 + 10
    secondary[rows, 10:30] = square[rows]
    k = np.array([[50.0, 0, w / 2], [0, 50.0, h / 2], [0, 0, 1.0]])
    w2c_b = np.eye(4)
    w2c_b[0, 3] = -1.26
    np.testing.assert_allclose(63.0 / plane_depths_inverse(1.0, np.inf, 64), np.arange(63, -1, -1), atol=1e-9)
    visible, error = plane_sweep_visibility(primary, secondary, Camera(k, np.eye(4)), Camera(k, w2c_b), 1.0, np.inf)
    assert not visible[rows, 22:38].any()  # occluded by the square in the secondary
    assert not visible[:, :8].any()  # outside the secondary image
    assert visible[rows, 42:58].all() and visible[:, 62:78].all() and visible[:15, 15:75].all()
    assert np.isfinite(error[rows, 42:58]).all() and error[rows, 42:58].max() < 1e-2  # float32 warp, 0-255 scale


# ----------------------------------------------------------------------------------------------------
# Switching and training


def test_each_prior_switches_on_and_off_via_config(tmp_path):
    config = tiny_config(steps=4)
    assert prior_loss_terms(config.priors, config.steps) == () and build_priors(None, config, None) is None
    expected = {"depth": {"sift_depth"}, "simple": {"augmented_photometric", "mass_concentration", "augmented_depth"},
                "vip": {"visibility_prior", "visibility_consistency"}, "distortion": {"distortion"}}
    views = sphere_views([0, 40, 80], size=16)
    for name in PRIOR_NAMES:
        on = dataclasses.replace(config, rays_per_batch=64, priors=with_priors(config.priors, [name]))
        assert on.priors.enabled() == [name]
        assert {t.name for t in prior_loss_terms(on.priors, on.steps)} == expected[name]
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            run = train_field(views, on, tmp_path / name, progress=False)
        logged = set(json.loads((run / "log.jsonl").read_text().splitlines()[-1]))
        others = set().union(*(expected[n] for n in PRIOR_NAMES if n != name))
        assert expected[name] - {"augmented_depth"} <= logged and not logged & others
        saved = FieldTrainConfig.from_dict(json.loads((run / "config.json").read_text()))
        assert saved.priors.enabled() == [name]
    off = dataclasses.replace(config, priors=with_priors(with_priors(config.priors, ["vip"]), []))
    assert off.priors.enabled() == []
    with pytest.raises(InputError):
        with_priors(config.priors, ["dept"])
    with pytest.raises(InputError):
        dataclasses.replace(config, priors=dataclasses.replace(
            config.priors, simple=dataclasses.replace(config.priors.simple, patch_size=4))).validate()


def test_all_priors_train_finite_resume_and_keep_only_the_main_field(tmp_path):
    views = sphere_views([0, 40, 80], size=24)
    config = dataclasses.replace(tiny_config(steps=40, rays_per_batch=128, occupancy_warmup=10, occupancy_every=10,
                                             log_every=10), priors=with_priors(PriorsConfig(), PRIOR_NAMES))
    config.priors.simple.depth_start_fraction = 0.0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        run = train_field(views, dataclasses.replace(config, steps=20), tmp_path / "run", progress=False)
        run = train_field(views, config, tmp_path / "run", progress=False)  # resumed and extended
    lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert lines[-1]["step"] == 40
    for line in lines:
        assert all(np.isfinite(v) for v in line.values())
    assert {"sift_depth", "augmented_depth", "visibility_prior", "mass_concentration"} <= set(lines[-1])
    state = torch.load(run / "checkpoint.pt", weights_only=True)
    assert any(k.startswith("simple.model.") for k in state["priors"]) and any(k.startswith("vip.head.")
                                                                              for k in state["priors"])
    model = load_model(run)  # the main field alone
    assert all(torch.isfinite(p).all() for p in model.parameters())
    assert (run / "priors" / "visibility.npz").is_file() and (run / "priors" / "sparse_depth.npz").is_file()


def test_interrupted_run_with_all_priors_resumes_exactly(tmp_path):
    views = sphere_views([0, 40, 80], size=16)
    config = dataclasses.replace(tiny_config(steps=10, rays_per_batch=64, warmup_steps=2, occupancy_warmup=3,
                                             occupancy_every=3, checkpoint_every=5, log_every=1),
                                 priors=with_priors(PriorsConfig(), PRIOR_NAMES))

    def crash(model, batch, outputs, step):
        if step == 7:
            raise KeyboardInterrupt
        return {}

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        straight = train_field(views, config, tmp_path / "straight", progress=False)
        with pytest.raises(KeyboardInterrupt):
            train_field(views, config, tmp_path / "resumed", progress=False, extras_fn=crash)
        resumed = train_field(views, config, tmp_path / "resumed", progress=False)
    a = torch.load(straight / "checkpoint.pt", weights_only=True)
    b = torch.load(resumed / "checkpoint.pt", weights_only=True)
    for part in ("model", "priors"):
        for name in a[part]:
            assert torch.equal(a[part][name], b[part][name]), (part, name)


def test_command_line_priors_flag(tmp_path):
    write_blender(tmp_path / "scene", sphere_views([0, 40, 80]), "train")
    write_blender(tmp_path / "scene", sphere_views([20]), "test")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = main(["--dataset", "nerf-synthetic", "--data", str(tmp_path / "scene"), "--out", str(tmp_path / "run"),
                     "--views", "3", "--downscale", "2", "--steps", "3", "--rays-per-batch", "64",
                     "--field.resolutions", "8,16", "--render.num-samples", "16", "--priors", "depth,vip",
                     "--priors.vip.rays", "32"])
    assert code == 0
    saved = FieldTrainConfig.from_dict(json.loads((tmp_path / "run" / "config.json").read_text()))
    assert saved.priors.enabled() == ["depth", "vip"] and saved.priors.vip.rays == 32


def test_ablation_command_prints_a_table_and_writes_json(tmp_path, capsys):
    write_blender(tmp_path / "scene", sphere_views([0, 40, 80]), "train")
    write_blender(tmp_path / "scene", sphere_views([20]), "test")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        code = ablation_main(["--dataset", "nerf-synthetic", "--data", str(tmp_path / "scene"), "--out",
                              str(tmp_path / "abl"), "--views", "3", "--downscale", "2", "--steps", "2",
                              "--rays-per-batch", "64", "--field.resolutions", "8,16", "--render.num-samples",
                              "16", "--variants", "plain,+simple", "--threads", "1"])
    assert code == 0
    report = json.loads((tmp_path / "abl" / "ablation.json").read_text())
    assert [r["variant"] for r in report["rows"]] == ["plain", "+simple"]
    assert report["rows"][1]["priors"] == ["simple"] and np.isfinite(report["rows"][1]["psnr"])
    out = capsys.readouterr().out
    assert "| variant | PSNR (dB) |" in out and "| +simple |" in out
    assert ablation_main(["--dataset", "nerf-synthetic", "--data", str(tmp_path / "scene"), "--out",
                          str(tmp_path / "abl2"), "--variants", "+nothing"]) == 2


def test_triangulation_angle_drops_points_whose_depth_the_baseline_cannot_fix():
    from models.fields.priors.depth import triangulate_checked, triangulation_angles

    k = np.array([[100.0, 0, 50], [0, 100.0, 50], [0, 0, 1]])
    cams = []
    for x in (0.0, 0.1):  # two cameras 0.1 apart looking down +z
        w2c = np.eye(4)
        w2c[0, 3] = -x
        cams.append(Camera(k, w2c))
    world = np.array([[0.05, 0.0, 1.0], [0.05, 0.0, 1000.0]])
    angles = triangulation_angles(world, cams)
    np.testing.assert_allclose(angles, np.degrees(2 * np.arctan(0.05 / np.array([1.0, 1000.0]))), rtol=1e-6)
    obs = np.stack([np.stack([k[0, 0] * (p[0] - c.world_to_camera[0, 3] * -1) / p[2] + k[0, 2] for c in cams])
                    for p in world])
    pix = np.stack([obs, np.full_like(obs, 50.0)], axis=-1)  # (M, V, 2)
    keep, depths, _ = triangulate_checked(cams, pix, max_error=2.0, min_angle=1.0)
    assert keep.tolist() == [True, False]  # the far point reprojects perfectly but its depth is unknown
    np.testing.assert_allclose(depths[0], [1.0, 1.0], rtol=1e-6)


def test_forward_facing_sparse_depth_compares_disparities():
    from models.fields.components.render import RayOutputs

    near = 2.0
    t = torch.tensor([[2.0, 4.0, 8.0, 1e10]])
    weights = torch.tensor([[0.0, 1.0, 0.0, 0.0]], requires_grad=True)
    out = RayOutputs(torch.zeros(1, 3), torch.tensor([4.0]), (weights * t).sum(-1), weights.sum(-1), weights,
                     torch.ones(1, 4), t)
    extras = {"sift_depth": {"outputs": out, "depth": torch.tensor([4.0]), "scale": near, "disparity": True}}
    term = LOSS_TERMS["sift_depth"]
    zero = term(LossInputs(None, None, out, 0, LossTerm("sift_depth"), extras))
    assert float(zero) == 0.0
    extras["sift_depth"]["depth"] = torch.tensor([8.0])  # truth farther: |2/4 - 2/8| = 0.25
    loss = term(LossInputs(None, None, out, 0, LossTerm("sift_depth"), extras))
    assert float(loss) == pytest.approx(0.25)
    loss.backward()
    g = weights.grad[0]  # descent moves mass from the sample at 4 towards the farther ones
    assert torch.isfinite(g).all() and g[3] < g[2] < g[1]


def test_forward_facing_augmented_depth_compares_disparities_and_stays_bounded():
    from models.fields.components.render import RayOutputs

    def outputs(depth):
        d = torch.tensor(depth, requires_grad=True)
        return d, RayOutputs(torch.zeros(len(depth), 3), d, d, torch.ones(len(depth)), torch.ones(len(depth), 1),
                             torch.ones(len(depth), 1), torch.ones(len(depth), 1))

    z_main, main = outputs([2.0, 1e10])
    _, aug = outputs([4.0, 4.0])
    mask = torch.tensor([True, True])
    extras = {"augmented": {"outputs": aug, "mask_main": ~mask, "mask_aug": mask, "scale": 2.0, "disparity": True}}
    loss = LOSS_TERMS["augmented_depth"](LossInputs(None, None, main, 0, LossTerm("augmented_depth"), extras))
    # disparities near / z: main (1, 2e-10) against the augmented model's (0.5, 0.5)
    assert float(loss) == pytest.approx((0.5 ** 2 + 0.5 ** 2) / 2, rel=1e-6)
    loss.backward()
    assert torch.isfinite(z_main.grad).all()
    extras["augmented"]["disparity"] = False  # bounded scenes: depth / scale, which a far depth blows up
    assert float(LOSS_TERMS["augmented_depth"](LossInputs(None, None, main, 0, LossTerm("augmented_depth"),
                                                           extras))) > 1e18


def _textured_pair(shift: int = 6, size: tuple[int, int] = (120, 160)) -> np.ndarray:
    """Two linear-RGB views of a blurred noise texture, the second shifted by ``shift`` px (SIFT finds hundreds
    of keypoints in each)."""
    import cv2

    rng = np.random.default_rng(5)
    h, w = size
    texture = cv2.GaussianBlur(rng.random((h, w + shift)).astype(np.float32), (0, 0), 1.5)
    texture = (texture - texture.min()) / (texture.max() - texture.min())
    views = np.stack([texture[:, shift:], texture[:, :w]])
    return np.repeat(views[..., None], 3, axis=-1) ** 2.2


@pytest.mark.parametrize("brute_force", [False, True])
def test_numpy_matching_is_colmaps_matcher(brute_force):
    """``match_descriptors`` against ``pycolmap.FeatureMatcher`` (cross check, the ratio test), its oracle:
    the same matches. Measured on a 4-camera rig (240 views, 120 pairs): 36,484 of 36,484 equal, 28 against
    92 ms a pair."""
    import pycolmap

    from models.fields.priors.depth import match_descriptors, sift_features

    from engine.core.colorspace import display_encode
    from models.fields.priors.depth import _extractor

    views = _textured_pair()
    features = sift_features(views, 1024)
    assert min(len(f[0]) for f in features) > 100
    extractor = _extractor(1024)  # pycolmap's own objects of the same features, for its matcher
    colmap = [extractor.extract_from_float32_array(np.ascontiguousarray(
        np.clip(display_encode(v).mean(axis=-1), 0.0, 1.0).astype(np.float32))) for v in views]
    for (_, descriptors), f in zip(colmap, features):
        assert np.array_equal(np.asarray(descriptors.data), f[1])
    options = pycolmap.FeatureMatchingOptions()
    options.num_threads = 1
    options.sift.max_ratio, options.sift.cross_check = 0.8, True
    options.sift.cpu_brute_force_matcher = brute_force
    matcher = pycolmap.FeatureMatcher.create(options, pycolmap.Device.cpu)
    want = np.asarray(matcher.match(colmap[0][0], colmap[0][1], colmap[1][0], colmap[1][1]), np.int64).reshape(-1, 2)
    got = match_descriptors(features[0][1], features[1][1], 0.8)
    assert len(got) > 50
    assert set(map(tuple, got.tolist())) == set(map(tuple, want.tolist()))
    assert len(match_descriptors(features[0][1][:0], features[1][1])) == 0
    assert match_descriptors(features[0][1], features[1][1][:1]).shape[1] == 2  # one candidate: no ratio test


def test_sift_features_are_extracted_once_per_view(tmp_path, monkeypatch):
    from models.fields.priors import depth

    views = _textured_pair()
    first = depth.sift_features(views, 512, cache_dir=tmp_path)
    assert len(list(tmp_path.glob("*.npz"))) == 2

    def no_extraction(*_):
        raise AssertionError("extracted again")

    monkeypatch.setattr(depth, "_extractor", no_extraction)
    again = depth.sift_features(views[::-1], 512, cache_dir=tmp_path)  # any order, any run
    for (xy, d), (xy2, d2) in zip(first, again[::-1]):
        assert np.array_equal(xy, xy2) and np.array_equal(d, d2)
    with pytest.raises(AssertionError, match="extracted again"):  # another image, or another feature budget
        depth.sift_features(views[:1] * 0.5, 512, cache_dir=tmp_path)
    with pytest.raises(AssertionError, match="extracted again"):
        depth.sift_features(views[:1], 256, cache_dir=tmp_path)
    next(tmp_path.glob("*.npz")).write_bytes(b"damaged")  # a damaged entry is extracted again, not an error
    monkeypatch.undo()
    assert len(depth.sift_features(views, 512, cache_dir=tmp_path)) == 2


# ----------------------------------------------------------------------------------------------------
# Plane-sweep stereo depth (the depth prior's stereo source)


def _layered_views(size: tuple[int, int] = (72, 96)) -> Views:
    """Three cameras 0.25 apart along x looking down +z at a noise-textured wall (Z = 6) and a textured square
    (Z = 2.5, |x|, |y| < 0.5) in front of it; linear colours, true planar depth."""
    h, w = size
    rng = np.random.default_rng(5)
    grid = rng.random((200, 200)).astype(np.float32)

    def texture(x, y, offset):   # bilinear value noise, ~12 cells a unit
        gx, gy = (x + 8.0 + offset) * 12.0, (y + 8.0) * 12.0
        x0, y0 = np.floor(gx).astype(int), np.floor(gy).astype(int)
        fx, fy = gx - x0, gy - y0
        return ((grid[y0, x0] * (1 - fx) + grid[y0, x0 + 1] * fx) * (1 - fy)
                + (grid[y0 + 1, x0] * (1 - fx) + grid[y0 + 1, x0 + 1] * fx) * fy)

    k = np.array([[80.0, 0, w / 2], [0, 80.0, h / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(w) + 0.5, np.arange(h) + 0.5)
    images, depths, cams = [], [], []
    for cx in (-0.25, 0.0, 0.25):
        w2c = np.eye(4)
        w2c[0, 3] = -cx
        rx, ry = (u - w / 2) / 80.0, (v - h / 2) / 80.0
        near_x, near_y = cx + 2.5 * rx, 2.5 * ry
        on_square = (np.abs(near_x) < 0.5) & (np.abs(near_y) < 0.5)
        depth = np.where(on_square, 2.5, 6.0)
        x, y = cx + depth * rx, depth * ry
        value = np.where(on_square, texture(x, y, 1.3), texture(x, y, 0.0))
        images.append(np.repeat(value[..., None], 3, -1).astype(np.float32) ** 2.2)
        depths.append(depth.astype(np.float32))
        cams.append(Camera(k.copy(), w2c))
    return Views(images=np.stack(images), cameras=cams, near_far=np.tile([1.0, np.inf], (3, 1)),
                 scene_type="forward-facing", depth=np.stack(depths))


def test_plane_homography_maps_pixels_as_the_engines_reprojection():
    from engine.geometry import reproject
    from models.fields.priors.stereo import plane_homography

    a, b = _camera([0.0, -3.0, 1.0]), _camera([0.8, -2.8, 1.3], look_at=(0.2, 0.0, 0.1))
    for z in (1.5, 4.0):
        uv, _, _ = reproject(np.full((64, 64), z, np.float32), a.intrinsics, a.world_to_camera, b.intrinsics,
                             b.world_to_camera)
        h = plane_homography(a, b, z)
        px = np.stack(np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5), -1).reshape(-1, 2)
        mapped = np.concatenate([px, np.ones((len(px), 1))], 1) @ h.T
        np.testing.assert_allclose(mapped[:, :2] / mapped[:, 2:], uv.reshape(-1, 2), atol=2e-3)


def test_stereo_depth_points_find_the_true_depths_and_drop_what_no_view_confirms():
    from models.fields.priors.stereo import StereoDepth, consistent_depth_points

    views = _layered_views()
    view, xy, depth, error = consistent_depth_points(views, StereoDepth(planes=64))
    per_view = np.bincount(view, minlength=3)
    assert (per_view > 0.25 * 72 * 96).all(), per_view
    true = views.depth[view, (xy[:, 1] - 0.5).astype(int), (xy[:, 0] - 0.5).astype(int)]
    steps = np.abs(1.0 / depth - 1.0 / true) * 63.0   # in plane steps: 64 planes, disparity 1 (near) to 0
    assert np.median(steps) < 0.3 and np.quantile(steps, 0.95) < 1.0, (np.median(steps), np.quantile(steps, 0.95))
    assert (error <= 1.0).all()
    both = set(np.round(true, 3).tolist())
    assert both == {2.5, 6.0}   # the square and the wall behind it
    # a blank view matches nothing
    flat = dataclasses.replace(views, images=np.full_like(views.images, 0.5))
    assert len(consistent_depth_points(flat, StereoDepth(planes=16))[0]) == 0
    with pytest.raises(InputError, match="window"):
        StereoDepth(window=4).validate()


def test_depth_prior_sources_add_stereo_points_and_check_the_name():
    views = _layered_views()
    prior = SparseDepthPrior(enabled=True, source="stereo", stereo=dataclasses.replace(SparseDepthPrior().stereo,
                                                                                      planes=32))
    points = sparse_depth_points(views, prior)
    assert len(points) == points.matches["stereo"] > 1000 and set(np.unique(points.view)) == {0, 1, 2}
    with pytest.raises(InputError, match="priors.depth.source"):
        sparse_depth_points(views, dataclasses.replace(prior, source="lidar"))
    from models.fields.priors.depth import depth_source
    assert SparseDepthPrior().source == "auto"
    assert depth_source(SparseDepthPrior(), "forward-facing") == "sift+stereo"
    assert depth_source(SparseDepthPrior(), "bounded-360") == "sift"
    assert depth_source(prior, "bounded-360") == "stereo"
    with pytest.raises(InputError, match="priors.depth.source"):
        PriorsConfig(depth=dataclasses.replace(prior, source="lidar")).validate()


def test_epipolar_share_is_low_on_edges_along_the_baseline():
    from models.fields.priors.stereo import epipolar_share

    views = _layered_views()
    grey = np.zeros((72, 96), np.float32)
    grey[30:, :] = 1.0           # a horizontal edge: along the x baseline's epipolar lines
    grey[:, 60:] += 0.5          # a vertical edge: across them
    for other in (0, 2):
        share = epipolar_share(grey, views.cameras[1], views.cameras[other], 7)
        assert share[30, 20] < 0.05 and share[15, 60] > 0.95
        assert share[5, 5] == 0.0    # blank
    # a view below the reference sees the horizontal edge across its epipolar lines
    below = Camera(views.cameras[1].intrinsics, views.cameras[1].world_to_camera @ np.diag([1.0, 1.0, 1.0, 1.0]))
    below.world_to_camera[1, 3] -= 0.3
    share = epipolar_share(grey, views.cameras[1], below, 7)
    assert share[30, 20] > 0.95 and share[15, 60] < 0.05
