"""Training, resuming, loss assembly, evaluation and the command line of models.fields, on a tiny sphere scene."""
from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from engine.conventions.cameras import look_at
from engine.core.colorspace import linear_to_srgb
from engine.core.errors import InputError
from engine.core.frames import Camera
from models.fields.data.views import Views
from models.fields.losses import LOSS_TERMS, LossTerm, ray_distortion, register_loss_term
from models.fields.static.field import FieldConfig
from models.fields.static.model import RenderConfig
from models.fields.train_static import FieldTrainConfig, build_model, evaluate_field, load_model, main, train_field

pytestmark = pytest.mark.usefixtures("one_torch_thread")


# ----------------------------------------------------------------------------------------------------
# A textured sphere rendered in closed form (white background, true planar depth)


def look_at_origin(eye: np.ndarray) -> np.ndarray:
    """World-to-camera (OpenCV axes) of a camera at ``eye`` looking at the origin, z up."""
    rot = look_at(eye, np.zeros(3), (0.0, 0.0, 1.0))
    w2c = np.eye(4)
    w2c[:3, :3], w2c[:3, 3] = rot, -rot @ eye
    return w2c


def sphere_views(azimuths_deg, size: int = 32, radius: float = 0.8, distance: float = 3.0) -> Views:
    focal = size / (2 * np.tan(np.radians(25.0)))
    k = np.array([[focal, 0, size / 2], [0, focal, size / 2], [0, 0, 1.0]])
    u, v = np.meshgrid(np.arange(size) + 0.5, np.arange(size) + 0.5)
    images, depths, cams = [], [], []
    for az in azimuths_deg:
        a, e = np.radians(az), np.radians(25.0)
        eye = distance * np.array([np.cos(a) * np.cos(e), np.sin(a) * np.cos(e), np.sin(e)])
        w2c = look_at_origin(eye)
        d = np.stack([(u - k[0, 2]) / focal, (v - k[1, 2]) / focal, np.ones_like(u)], -1) @ w2c[:3, :3]
        qa, qb, qc = (d * d).sum(-1), 2 * (d @ eye), eye @ eye - radius ** 2
        disc = qb * qb - 4 * qa * qc
        hit = disc > 0
        t = np.where(hit, (-qb - np.sqrt(np.maximum(disc, 0))) / (2 * qa), np.inf)  # planar depth (d_z = 1)
        p = eye + np.where(hit, t, 0)[..., None] * d
        tex = 0.5 + 0.4 * np.stack([np.sin(4 * p[..., 0] + 1), np.sin(3 * p[..., 1] - 2 * p[..., 2]),
                                    np.cos(5 * p[..., 2] + p[..., 0])], -1)
        images.append(np.where(hit[..., None], tex, 1.0).astype(np.float32))
        depths.append(t.astype(np.float32))
        cams.append(Camera(k.copy(), w2c))
    return Views(images=np.stack(images), cameras=cams, near_far=np.tile([1.0, 5.0], (len(cams), 1)),
                 scene_type="bounded-360", depth=np.stack(depths), bounds=np.array([[-1.0] * 3, [1.0] * 3]),
                 background=np.ones(3, np.float32))


TINY_FIELD = FieldConfig(resolutions=(16, 32), feature_dim=8, density_hidden=32, color_hidden=32, color_layers=1)


def tiny_config(steps: int = 300, **changes) -> FieldTrainConfig:
    base = FieldTrainConfig(steps=steps, rays_per_batch=512, lr=0.02, warmup_steps=20, occupancy_warmup=50,
                            occupancy_every=16, log_every=50, field=TINY_FIELD,
                            render=RenderConfig(num_samples=48, occupancy_resolution=32))
    return dataclasses.replace(base, **changes)


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """3 train views 40 degrees apart, 2 held-out views between them; 300 steps (a few seconds)."""
    train, test = sphere_views([0, 40, 80]), sphere_views([20, 60])
    run = train_field(train, tiny_config(), tmp_path_factory.mktemp("sphere"), progress=False)
    return train, test, run


# ----------------------------------------------------------------------------------------------------
# Training


def test_training_raises_held_out_psnr_clearly(trained):
    train, test, run = trained
    before = evaluate_field(build_model(train, tiny_config()), test)
    after = evaluate_field(run, test)
    assert after["psnr"] > before["psnr"] + 6.0, (before, after)   # ~15.7 -> ~26.8 dB when written
    assert after["psnr"] > 22.0 and after["ssim"] > before["ssim"] + 0.3
    assert np.isfinite(after["depth_mae"]) and after["depth_mae"] < 0.6
    assert after["render_ms_per_frame"] > 0 and after["num_views"] == 2


def test_run_directory_holds_config_checkpoint_and_log(trained):
    train, _, run = trained
    assert tiny_config().downscale == 0  # auto: the saved config holds the resolution the views had
    assert json.loads((run / "config.json").read_text()) == tiny_config(downscale=1).to_dict()
    lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
    assert lines[-1]["step"] == 300 and "photometric" in lines[-1] and lines[-1]["occupied"] < 1.0
    assert lines[-1]["photometric"] < lines[0]["photometric"]
    model = load_model(run)
    assert not model.training and model.occupancy is not None and int(model.occupancy.updates) > 0


def test_gradient_reaches_every_plane():
    views = sphere_views([0, 90])
    config = tiny_config()
    model = build_model(views, config)
    from models.fields.components.sampling import camera_rays
    from models.fields.losses import RayBatch, assemble_loss

    o, d = camera_rays(views.cameras[0].intrinsics, views.cameras[0].world_to_camera, 32, 32)
    batch = RayBatch(o, d, torch.full((1024,), 1.0), torch.full((1024,), 5.0),
                     torch.from_numpy(views.images[0].reshape(-1, 3)))
    out = model.render_rays(o, d, batch.near, batch.far, jitter=True)
    loss, values = assemble_loss(config.losses, model, batch, out, step=0)
    loss.backward()
    assert set(values) == {"photometric", "plane_tv"}
    for scale, plane in enumerate(model.field.spatial_planes()):
        for k, name in enumerate(("xy", "xz", "yz")):
            assert plane.grad[k].abs().sum() > 0, f"no gradient on plane {name} of scale {scale}"
    for name, p in model.field.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all(), name


def test_interrupted_run_resumes_exactly(tmp_path):
    views = sphere_views([0, 60])
    config = tiny_config(steps=12, rays_per_batch=64, warmup_steps=2, occupancy_warmup=4, occupancy_every=3,
                         checkpoint_every=5, log_every=1)
    straight = train_field(views, config, tmp_path / "straight", progress=False)

    def crash(model, batch, outputs, step):
        if step == 8:
            raise KeyboardInterrupt
        return {}

    with pytest.raises(KeyboardInterrupt):
        train_field(views, config, tmp_path / "resumed", progress=False, extras_fn=crash)
    assert torch.load(tmp_path / "resumed" / "checkpoint.pt", weights_only=True)["step"] == 5
    resumed = train_field(views, config, tmp_path / "resumed", progress=False)
    a, b = load_model(straight).state_dict(), load_model(resumed).state_dict()
    for name in a:
        assert torch.equal(a[name], b[name]), name
    log = [json.loads(line)["step"] for line in (resumed / "log.jsonl").read_text().splitlines()]
    assert log == list(range(1, 13))  # lines past the checkpoint were dropped on resume
    # finished: calling again trains nothing; a larger `steps` extends the run
    train_field(views, config, resumed, progress=False)
    assert torch.load(resumed / "checkpoint.pt", weights_only=True)["step"] == 12
    train_field(views, dataclasses.replace(config, steps=14), resumed, progress=False)
    assert torch.load(resumed / "checkpoint.pt", weights_only=True)["step"] == 14


def test_run_directory_refuses_a_different_config(tmp_path):
    views = sphere_views([0, 60])
    config = tiny_config(steps=2, rays_per_batch=32)
    train_field(views, config, tmp_path, progress=False)
    with pytest.raises(InputError, match="lr"):
        train_field(views, dataclasses.replace(config, lr=0.5), tmp_path, progress=False)


def test_config_round_trips_through_json():
    config = tiny_config(losses=(LossTerm("photometric"), LossTerm("plane_tv", 0.01, start_step=3)))
    again = FieldTrainConfig.from_dict(json.loads(json.dumps(config.to_dict())))
    assert again == config and isinstance(again.losses[1], LossTerm) and isinstance(again.field.resolutions, tuple)
    with pytest.raises(InputError, match="unknown option"):
        FieldTrainConfig.from_dict({"stepz": 3})
    with pytest.raises(InputError, match="lr_schedule"):
        train_field(sphere_views([0]), tiny_config(lr_schedule="step"), "/nonexistent/never", progress=False)


# ----------------------------------------------------------------------------------------------------
# Loss assembly


def test_loss_terms_are_named_switchable_and_extensible(tmp_path):
    calls = []

    @register_loss_term("test_counter")
    def counter(inputs):
        calls.append(inputs.step)
        assert inputs.extras == {"hello": inputs.step}
        return inputs.outputs.opacity.mean()

    try:
        views = sphere_views([0, 60])
        losses = (LossTerm("photometric"), LossTerm("test_counter", 0.1, start_step=2),
                  LossTerm("plane_l1", 1.0, enabled=False))
        train_field(views, tiny_config(steps=4, rays_per_batch=32, losses=losses), tmp_path / "a", progress=False,
                    extras_fn=lambda model, batch, outputs, step: {"hello": step})
        assert calls == [2, 3]
        lines = [json.loads(line) for line in (tmp_path / "a" / "log.jsonl").read_text().splitlines()]
        assert "test_counter" in lines[-1] and "plane_l1" not in lines[-1]
    finally:
        LOSS_TERMS.pop("test_counter")
    with pytest.raises(InputError, match="unknown loss term"):
        train_field(views, tiny_config(losses=(LossTerm("nope"),)), tmp_path / "b", progress=False)
    no_depth = dataclasses.replace(views, depth=None)
    with pytest.raises(InputError, match="needs true depth"):
        train_field(no_depth, tiny_config(losses=(LossTerm("sparse_depth"),)), tmp_path / "c", progress=False)


def test_sparse_depth_term_pulls_expected_depth(tmp_path):
    """Two views see too little to place the sphere's surface by colour alone; the depth term (on the views'
    true depth) pulls the expected depth onto it: same seed and steps, with and without the term."""
    views = sphere_views([0, 60])
    depth_mae = {}
    for name, extra in (("with", (LossTerm("sparse_depth", 0.1),)), ("without", ())):
        config = tiny_config(steps=40, rays_per_batch=256, losses=(LossTerm("photometric"),) + extra)
        run = train_field(views, config, tmp_path / name, progress=False)
        depth_mae[name] = evaluate_field(run, views, with_flip=False)["depth_mae"]
        if extra:
            lines = [json.loads(line) for line in (run / "log.jsonl").read_text().splitlines()]
            assert np.isfinite(lines[-1]["sparse_depth"])
    assert depth_mae["with"] < 0.5 * depth_mae["without"], depth_mae


def test_distortion_is_mip_nerf_360s_pairwise_sum_and_favours_one_compact_interval(tmp_path):
    """``ray_distortion`` against the O(N^2) definition on random weights; one opaque sample scores less than the
    same weight spread over the ray or split between two distant samples; ``--loss distortion=W`` trains with it."""
    gen = torch.Generator().manual_seed(3)
    w = torch.rand(6, 9, generator=gen, dtype=torch.float64)
    n = w.shape[-1]
    mid = (torch.arange(n, dtype=torch.float64) + 0.5) / n
    pairs = (w[:, :, None] * w[:, None, :] * (mid[:, None] - mid[None, :]).abs()).sum(dim=(1, 2))
    expected = pairs + w.square().sum(dim=-1) / (3 * n)
    torch.testing.assert_close(ray_distortion(w), expected, rtol=1e-12, atol=1e-12)
    one = torch.zeros(1, 8, dtype=torch.float64)
    one[0, 2] = 1.0
    split = torch.zeros(1, 8, dtype=torch.float64)
    split[0, [2, 7]] = 0.5
    spread = torch.full((1, 8), 1.0 / 8, dtype=torch.float64)
    assert float(ray_distortion(one)) < float(ray_distortion(spread))
    assert float(ray_distortion(one)) < float(ray_distortion(split))
    views = sphere_views([0, 60])
    losses = (LossTerm("photometric"), LossTerm("distortion", 0.01))
    run = train_field(views, tiny_config(steps=3, rays_per_batch=32, losses=losses), tmp_path, progress=False)
    last = json.loads((run / "log.jsonl").read_text().splitlines()[-1])
    assert np.isfinite(last["distortion"]) and last["distortion"] > 0


# ----------------------------------------------------------------------------------------------------
# Command line, on the sphere written as a NeRF-synthetic scene


def write_blender(root: Path, views: Views, split: str) -> None:
    frames = []
    (root / split).mkdir(parents=True, exist_ok=True)
    for i, (image, cam) in enumerate(zip(views.images, views.cameras)):
        c2w_gl = cam.camera_to_world @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w_gl.tolist()})
        rgba = np.concatenate([np.round(linear_to_srgb(image) * 255), np.full(image.shape[:2] + (1,), 255)], -1)
        cv2.imwrite(str(root / split / f"r_{i}.png"), rgba.astype(np.uint8)[..., [2, 1, 0, 3]])
    k = views.cameras[0].intrinsics
    angle = 2 * np.arctan(views.width / (2 * k[0, 0]))
    (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def test_command_line_trains_and_scores(tmp_path, capsys):
    write_blender(tmp_path / "scene", sphere_views([0, 40, 80]), "train")
    write_blender(tmp_path / "scene", sphere_views([20]), "test")
    code = main(["--dataset", "nerf-synthetic", "--data", str(tmp_path / "scene"), "--out", str(tmp_path / "run"),
                 "--views", "3", "--downscale", "2", "--steps", "20", "--rays-per-batch", "128",
                 "--field.resolutions", "8,16", "--render.num-samples", "24", "--loss", "plane_tv=0",
                 "--render.occupancy", "false"])
    assert code == 0
    scores = json.loads((tmp_path / "run" / "scores.json").read_text())
    assert len(scores["train_views"]) == 3 and scores["image_size"] == [16, 16] and np.isfinite(scores["psnr"])
    saved = FieldTrainConfig.from_dict(json.loads((tmp_path / "run" / "config.json").read_text()))
    assert saved.field.resolutions == (8, 16) and saved.render.occupancy is False and saved.downscale == 2
    assert not [t for t in saved.losses if t.name == "plane_tv" and t.enabled]
    assert '"psnr"' in capsys.readouterr().out
    assert main(["--dataset", "llff", "--data", str(tmp_path / "missing"), "--out", str(tmp_path / "r2")]) == 2


def test_llff_capture_as_shipped_trains_from_the_default_command(tmp_path, capsys):
    """An LLFF-layout capture from the scene generator (images_2/, images_4/, poses_bounds.npy in LLFF's axis
    order, no images/) trains through 'interleave train field --scene CAPTURE --train-views --test-views'
    without --downscale: the coarsest shipped folder is read, and the run records it."""
    from engine.cli import main as cli_main
    from models.fields.data.select import load_run_views
    from tests.io.test_llff import generated_llff

    capture, cameras, _ = generated_llff(tmp_path)
    run = tmp_path / "run"
    assert cli_main(["train", "field", "--scene", str(capture), "--train-views", "0,2,5", "--test-views", "3",
                     "--steps", "4", "--rays-per-batch", "64", "--field.resolutions", "8,16",
                     "--render.num-samples", "8", "--render.occupancy", "false", "--priors", "", "--no-flip",
                     "--out", str(run)]) == 0
    scores = json.loads((run / "scores.json").read_text())
    assert scores["image_size"] == [12, 16] and np.isfinite(scores["psnr"]) and scores["steps"] == 4
    data = json.loads((run / "data.json").read_text())
    assert data["dataset"] == "llff" and data["downscale"] == 4 and data["image_folder"] == "images_4"
    assert json.loads((run / "config.json").read_text())["downscale"] == 4
    train, test = load_run_views(run)  # what eval and export read back
    np.testing.assert_allclose(test.cameras[0].world_to_camera, cameras[3].world_to_camera, atol=1e-12)
    assert (train.height, train.width) == (12, 16)
    # an explicit --downscale coarser than any folder is reached by area-averaging the nearest finer one
    assert cli_main(["train", "field", "--scene", str(capture), "--train-views", "0,2,5", "--test-views", "3",
                     "--downscale", "8", "--steps", "1", "--rays-per-batch", "64", "--field.resolutions", "8,16",
                     "--render.num-samples", "8", "--render.occupancy", "false", "--priors", "", "--no-flip",
                     "--out", str(tmp_path / "run8")]) == 0
    assert json.loads((tmp_path / "run8" / "scores.json").read_text())["image_size"] == [6, 8]
    capsys.readouterr()


def test_llff_bad_capture_is_one_line_and_exit_2(tmp_path, capsys):
    from engine.cli import main as cli_main
    from tests.io.test_llff import generated_llff

    capture, _, _ = generated_llff(tmp_path, factors=(4,), num_cameras=3)
    rows = np.load(capture / "poses_bounds.npy")
    rows[1, 15] = np.nan
    np.save(capture / "poses_bounds.npy", rows)
    assert cli_main(["train", "field", "--scene", str(capture), "--train-views", "0,2", "--test-views", "1",
                     "--steps", "1", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "poses_bounds.npy" in err and "frame 1, field 'bounds'" in err
    assert not (tmp_path / "run").exists()


def test_auto_priors_follow_the_ablation():
    from models.fields.priors.config import (PRIOR_NAMES, PRIORS_THAT_PAY, auto_field_options, auto_loss_weights,
                                             auto_priors)

    for scene_type, rule in PRIORS_THAT_PAY.items():
        assert set(rule.names) <= set(PRIOR_NAMES) and rule.names
        names, reason = auto_priors(rule.max_views, scene_type)
        assert names == rule.names and reason.startswith(f"{rule.max_views} train views <=")
        names, reason = auto_priors(rule.max_views + 1, scene_type)
        assert names == () and "no prior paid" in reason
    assert auto_priors(4, "bounded-360")[0] == ("depth", "simple", "vip")  # lego, 4 views: all three paid
    assert auto_priors(3, "forward-facing")[0] == ("depth", "distortion")  # sparse depth and the distortion loss
    assert auto_loss_weights(3, "forward-facing") == (("plane_tv", 0.01),)  # and ten times the plane TV
    assert "plane_tv=0.01 and field.resolutions=32,64,128,256 paid" in auto_priors(3, "forward-facing")[1]
    assert auto_loss_weights(4, "forward-facing") == () == auto_loss_weights(4, "bounded-360")
    assert auto_field_options(3, "forward-facing") == (("resolutions", (32, 64, 128, 256)),)  # a fourth scale
    assert auto_field_options(4, "forward-facing") == () == auto_field_options(3, "bounded-360")
    with pytest.raises(InputError, match="scene_type"):
        auto_priors(3, "indoor")


def test_the_rules_field_options_apply_unless_given():
    """``choose_priors`` sets the rule's plane scales on an auto choice, leaves them where the command line gave
    them, and never touches them for more views, bounded scenes or an explicit --priors."""
    from models.fields.train_static import FieldTrainConfig, choose_priors

    base = FieldTrainConfig()
    assert choose_priors(base, 3, "forward-facing").field.resolutions == (32, 64, 128, 256)
    given = dataclasses.replace(base, field=dataclasses.replace(base.field, resolutions=(8, 16)))
    assert choose_priors(given, 3, "forward-facing", given_field=["resolutions"]).field.resolutions == (8, 16)
    assert choose_priors(base, 4, "forward-facing").field.resolutions == base.field.resolutions
    assert choose_priors(base, 3, "bounded-360").field.resolutions == base.field.resolutions
    assert choose_priors(base, 3, "forward-facing", "depth").field.resolutions == base.field.resolutions


def test_the_auto_choice_keeps_the_priors_a_config_switches_on():
    """A recipe's priors (``configs/field-baked.json``'s distortion loss) stay on beside the auto choice, which
    still applies its rule; an explicit ``--priors`` replaces both."""
    from models.fields.priors.config import with_priors
    from models.fields.train_static import FieldTrainConfig, choose_priors

    base = FieldTrainConfig()
    recipe = dataclasses.replace(base, priors=with_priors(base.priors, ["distortion"]))
    ff = choose_priors(recipe, 3, "forward-facing")
    assert ff.priors.enabled() == ["depth", "distortion"] and ff.field.resolutions == (32, 64, 128, 256)
    assert ff.priors_choice.startswith("auto: 3 train views") and ff.priors_choice.endswith("the config enables "
                                                                                            "distortion")
    assert choose_priors(recipe, 4, "bounded-360").priors.enabled() == ["depth", "simple", "vip", "distortion"]
    assert choose_priors(recipe, 8, "bounded-360").priors.enabled() == ["distortion"]
    assert choose_priors(base, 8, "bounded-360").priors.enabled() == []
    assert choose_priors(recipe, 8, "bounded-360", "").priors.enabled() == []


#: A --config file that sets the plane TV weight (as a run's saved config.json does).
TV_FILE = ["--config", json.dumps({"losses": [{"name": "photometric"}, {"name": "plane_tv", "weight": 0.003}]})]


@pytest.mark.parametrize("views, given, loss, enabled, choice, plane_tv", [
    ("0,2,5", None, [], ["depth", "distortion"], "auto: 3 train views <= 3 on a forward-facing scene", 0.01),
    ("0,2,5", None, ["--loss", "plane_tv=0.002"], ["depth", "distortion"], "auto: 3 train views", 0.002),
    ("0,2,5", None, TV_FILE, ["depth", "distortion"], "auto: 3 train views", 0.003),
    ("0,1,2,4", None, [], [], "auto: 4 train views > 3", 0.001),
    ("0,2,5", "", [], [], "explicit: --priors ''", 0.001),
    ("0,1,2,4", "vip", [], ["vip"], "explicit: --priors 'vip'", 0.001),
])
def test_llff_priors_by_default_where_they_pay(tmp_path_factory, capsys, views, given, loss, enabled, choice,
                                               plane_tv):
    """The command line switches on the priors that paid for this few views unless --priors says otherwise,
    and sets the plane TV weight of the same rule unless --loss or a --config file sets it; the choice and its
    reason are printed and saved in config.json."""
    from engine.cli import main as cli_main
    from models.fields.priors.config import PRIOR_NAMES
    from tests.io.test_llff import generated_llff

    root = tmp_path_factory.mktemp("priors")
    capture, _, _ = generated_llff(root)
    run = root / "run"
    if loss[:1] == ["--config"]:  # the file's text stands in the parameter
        (root / "config.json").write_text(loss[1])
        loss = ["--config", str(root / "config.json")]
    argv = ["train", "field", "--scene", str(capture), "--train-views", views, "--test-views", "3", "--steps", "1",
            "--rays-per-batch", "32", "--field.resolutions", "8,16", "--render.num-samples", "8",
            "--render.occupancy", "false", "--priors.vip.num-planes", "4", "--no-flip", "--out", str(run)]
    assert cli_main(argv + loss + ([] if given is None else ["--priors", given])) == 0
    saved = json.loads((run / "config.json").read_text())
    assert [t["weight"] for t in saved["losses"] if t["name"] == "plane_tv"] == [plane_tv]
    assert saved["field"]["resolutions"] == [8, 16]  # given on the command line: the rule's scales do not apply
    assert [n for n in PRIOR_NAMES if saved["priors"][n]["enabled"]] == enabled
    assert saved["priors_choice"].startswith(choice)
    assert f"priors: {', '.join(enabled) or 'none'} ({saved['priors_choice']})" in capsys.readouterr().err


def test_device_names_resolve(monkeypatch):
    from models.trainer_cli import resolve_device

    assert resolve_device("cpu") == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(InputError, match="sees no GPU; use --device cpu or auto") as exc:
        resolve_device("cuda")
    assert "'device'" in str(exc.value) and "\n" not in str(exc.value)
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    assert resolve_device("auto") == torch.device("cuda") and resolve_device("cuda") == torch.device("cuda")
    with pytest.raises(InputError, match="must be one of auto, cpu, cuda"):
        resolve_device("gpu")


@pytest.mark.skipif(torch.cuda.is_available(), reason="needs a machine where torch sees no GPU")
@pytest.mark.parametrize("what", ["field", "dynamic"])
def test_device_cuda_without_a_gpu_is_one_line_and_exit_2(what, tmp_path, capsys):
    from engine.cli import main as cli_main

    scene = tmp_path / "scene"  # never read: the device is checked first
    assert cli_main(["train", what, "--scene", str(scene), "--device", "cuda", "--out", str(tmp_path / "run")]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "field 'device'" in err and "sees no GPU" in err
    assert not (tmp_path / "run").exists()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_cuda_training_draws_what_the_cpu_draws(tmp_path):
    """One CPU generator draws every ray and sample on either device, so a CUDA run differs from the CPU
    run of the same seed by float rounding only."""
    train, test = sphere_views([0, 40, 80]), sphere_views([20, 60])
    cpu = evaluate_field(train_field(train, tiny_config(100), tmp_path / "cpu", progress=False, device="cpu"), test)
    gpu = evaluate_field(train_field(train, tiny_config(100), tmp_path / "gpu", progress=False, device="cuda"), test)
    assert abs(cpu["psnr"] - gpu["psnr"]) < 0.5, (cpu["psnr"], gpu["psnr"])


def test_device_cpu_trains_what_the_api_trains(tmp_path, capsys):
    """'--device cpu' on the command line and train_field(device='cpu') give the same checkpoint, bit for bit
    (the trainer before --device gave the same too: docs/results/2026-11-25-field-device.md)."""
    write_blender(tmp_path / "scene", sphere_views([0, 40, 80]), "train")
    write_blender(tmp_path / "scene", sphere_views([20]), "test")
    options = ["--steps", "12", "--rays-per-batch", "128", "--field.resolutions", "8,16", "--render.num-samples", "16",
               "--occupancy-warmup", "4", "--occupancy-every", "4", "--priors", ""]
    assert main(["--data", str(tmp_path / "scene"), "--out", str(tmp_path / "cli"), "--device", "cpu", "--no-flip",
                 *options]) == 0
    assert json.loads((tmp_path / "cli" / "scores.json").read_text())["device"] == "cpu"
    saved = FieldTrainConfig.from_dict(json.loads((tmp_path / "cli" / "config.json").read_text()))
    from models.fields.data.select import load_run_views

    train, _ = load_run_views(tmp_path / "cli")
    api = train_field(train, saved, tmp_path / "api", progress=False, device="cpu")
    a = torch.load(tmp_path / "cli" / "checkpoint.pt", weights_only=True)["model"]
    b = torch.load(api / "checkpoint.pt", weights_only=True)["model"]
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)
    capsys.readouterr()
