"""Tests of the multi-camera rig renderer: layout, split, clearance, multi-view geometry, files, command line.

The geometric oracle is ``engine.geometry.reproject`` (true depth + K + poses) and plain numpy, never the
renderer's shaders.
"""
from __future__ import annotations

import json
import math

import numpy as np
import pytest

from engine.cli import build_parser, main
from engine.core.errors import InputError
from engine.geometry import reproject
from engine.io.rgbd import read_rig
from engine.scenegen import RigConfig, SceneConfig, generate_rig, make_rig, render_rig
from engine.scenegen.rig import MIN_CAMERA_HEIGHT
from engine.scenegen.sample import box_distance
from engine.scenegen.scene import CAMERA_CLEARANCE

W, H = 96, 64
CHANNELS = ("color", "depth", "object_id", "moving", "flow", "object_flow")


def _scene(seed: int, **kw) -> SceneConfig:
    base = dict(width=W, height=H, seed=seed, supersample=1, shadow_map_size=512)
    base.update(kw)
    return SceneConfig(**base)


def _static(seed: int = 7, **kw) -> RigConfig:
    return RigConfig(scene=_scene(seed), static=True, **kw)


def _dynamic(seed: int = 2, **kw) -> RigConfig:
    return RigConfig(scene=_scene(seed, num_frames=3, num_objects=(2, 4), pause_probability=0.0), **kw)


@pytest.fixture(scope="module")
def static_capture(tmp_path_factory):
    config = _static()
    return config, generate_rig(config, tmp_path_factory.mktemp("rig") / "static", progress=False)


@pytest.fixture(scope="module")
def dynamic_capture(tmp_path_factory):
    config = _dynamic()
    return config, generate_rig(config, tmp_path_factory.mktemp("rig") / "dynamic", progress=False)


def _compare_depth(a, b, tol: float = 0.01) -> dict[str, np.ndarray]:
    """Lift frame a's true depth to 3D, project it into frame b and compare with b's depth there.

    b's depth is taken at the 4 pixel centres around the projected point: ``agree`` when the projected
    depth lies within their range (widened by ``tol``, relative), ``occluded`` when it lies behind all of
    them (b sees something nearer), ``violates`` when it lies in front of all of them (b should have seen
    it). ``error`` is the relative difference to b's depth interpolated there (bilinear in 1 / depth, exact
    on a plane); ``smooth`` marks points whose 4 depths are finite and within 10 % of each other.
    """
    uv, z, valid = reproject(a.depth, a.camera.intrinsics, a.camera.world_to_camera, b.camera.intrinsics,
                             b.camera.world_to_camera)
    x, y = uv[..., 0] - 0.5, uv[..., 1] - 0.5  # continuous index coordinates of b's pixel centres
    inside = np.isfinite(a.depth) & valid & (x >= 0) & (x <= W - 1) & (y >= 0) & (y <= H - 1)
    x0, y0 = np.clip(np.floor(x).astype(int), 0, W - 2), np.clip(np.floor(y).astype(int), 0, H - 2)
    corners = np.stack([b.depth[y0, x0], b.depth[y0, x0 + 1], b.depth[y0 + 1, x0], b.depth[y0 + 1, x0 + 1]], -1)
    lo, hi = corners.min(-1), corners.max(-1)
    violates = inside & (z < lo * (1 - tol))
    occluded = inside & (z > hi * (1 + tol))
    fx, fy = np.clip(x - x0, 0, 1), np.clip(y - y0, 0, 1)
    inverse = 1.0 / corners  # affine in the image on a plane: interpolates planar surfaces exactly
    with np.errstate(divide="ignore", invalid="ignore"):
        bilinear = 1.0 / ((1 - fy) * ((1 - fx) * inverse[..., 0] + fx * inverse[..., 1])
                          + fy * ((1 - fx) * inverse[..., 2] + fx * inverse[..., 3]))
        error = np.abs(z - bilinear) / z
    return dict(inside=inside, agree=inside & ~violates & ~occluded, violates=violates, occluded=occluded,
                smooth=inside & np.isfinite(hi) & (hi < lo * 1.1), error=error)


# ----------------------------------------------------------------------------------------------------

@pytest.mark.parametrize("kw,name", [
    (dict(num_cameras=1), "num_cameras"),
    (dict(num_cameras=6, rows=4), "rows"),
    (dict(arrangement="ring"), "arrangement"),
    (dict(baseline=0.0), "baseline"),
    (dict(baseline=2.5), "baseline"),
    (dict(arrangement="orbit", baseline=7.0), "baseline"),
    (dict(num_cameras=4, test_cameras=3), "test_cameras"),
    (dict(num_cameras=4, rows=2), "test_cameras"),  # rows of 2: no camera lies between two others
    (dict(test_cameras=-1), "test_cameras"),
    (dict(scene="seed=3"), "scene"),
])
def test_bad_options_name_the_option(kw, name):
    with pytest.raises(InputError, match=name) as exc:
        RigConfig(**kw)
    assert exc.value.field == name


def test_static_sets_one_frame_and_no_objects():
    config = RigConfig(scene=SceneConfig(num_frames=30, num_objects=(2, 5)), static=True)
    assert config.scene.num_frames == 1 and config.scene.num_objects == (0, 0)
    rig = make_rig(_static(seed=4))
    assert rig.num_frames == 1 and rig.scene.objects == ()


@pytest.mark.parametrize("n,rows,m,expected", [(4, 1, 1, ["cam2"]), (5, 1, 1, ["cam2"]), (8, 1, 2, ["cam2", "cam5"]),
                                               (8, 2, 2, ["cam2", "cam6"]), (9, 3, 1, ["cam4"]), (3, 1, 0, []),
                                               (4, 2, 0, [])])
def test_default_split_holds_out_cameras_between_train_cameras(n, rows, m, expected):
    rig = make_rig(_static(num_cameras=n, rows=rows, test_cameras=m))
    assert list(rig.test_cameras) == expected
    assert list(rig.train_cameras) == [c for c in rig.names if c not in expected]
    assert RigConfig().test_cameras == 1 and RigConfig().num_cameras == 4
    # every test camera has train cameras to its left and to its right along the rig's right axis
    right = rig.camera_at(0).world_to_camera[0, :3]
    along = {name: float(rig.camera_at(name).position @ right) for name in rig.names}
    for name in rig.test_cameras:
        train = np.array([along[t] for t in rig.train_cameras])
        assert (train < along[name] - 1e-6).any() and (train > along[name] + 1e-6).any()


@pytest.mark.parametrize("arrangement,baseline,rows", [("forward-facing", 0.2, 1), ("forward-facing", 0.3, 2),
                                                       ("orbit", 1.0, 1)])
def test_cameras_are_fixed_distinct_and_look_at_the_target(arrangement, baseline, rows):
    config = _dynamic(seed=5, arrangement=arrangement, baseline=baseline, rows=rows, num_cameras=4 * rows)
    rig = make_rig(config)
    assert rig.spread == 1.0
    positions = np.array([rig.camera_at(k).position for k in range(len(rig.names))])
    distance = float(np.linalg.norm(rig.target - rig.centre))
    gaps = np.linalg.norm(positions[:, None] - positions[None], axis=-1) + np.eye(len(positions)) * 1e9
    assert gaps.min() > 0.05 * distance  # distinct
    for k in range(len(rig.names)):
        cam = rig.camera_at(k)
        assert all(np.array_equal(cam.world_to_camera, rig.camera_at(k, i).world_to_camera) for i in range(1, 4))
        assert np.array_equal(cam.intrinsics, rig.camera_at(0).intrinsics)
        p = cam.world_to_camera[:3, :3] @ rig.target + cam.world_to_camera[:3, 3]
        uv = (cam.intrinsics @ p)[:2] / p[2]
        assert p[2] > 0 and np.allclose(uv, [W / 2, H / 2], atol=1e-6)  # the target is at the image centre
    cols = 4
    if arrangement == "forward-facing":  # a grid perpendicular to the viewing direction, one spacing apart
        spacing = baseline * distance / (cols - 1)
        forward = (rig.target - rig.centre) / distance
        assert np.allclose((positions - rig.centre) @ forward, 0, atol=1e-9)
        assert np.allclose(np.linalg.norm(positions[1:cols] - positions[:cols - 1], axis=1), spacing)
        assert np.allclose(positions[-cols:].mean(0), rig.centre)  # the bottom row is centred on the path's eye
        if rows == 2:  # the top row is one spacing above, along the up axis of the view from the centre
            right = np.cross(forward, [0.0, 0.0, 1.0])
            up = np.cross(right / np.linalg.norm(right), forward)
            assert np.allclose(positions[:cols] - positions[cols:], spacing * up)
    else:  # an arc about the vertical through the target, at the centre's radius and height
        offsets = positions[:, :2] - rig.target[:2]
        radius = np.linalg.norm(rig.centre[:2] - rig.target[:2])
        assert np.allclose(np.linalg.norm(offsets, axis=1), radius) and np.allclose(positions[:, 2], rig.centre[2])
        angles = np.unwrap(np.arctan2(offsets[:, 1], offsets[:, 0]))
        assert np.allclose(np.diff(angles), baseline / (cols - 1))


@pytest.mark.parametrize("arrangement,baseline", [("forward-facing", 0.25), ("orbit", 1.5)])
def test_every_camera_is_clear_of_the_scene(arrangement, baseline):
    """The clearance rule, checked over many seeds (pure numpy)."""
    removed = 0
    for seed in range(25):
        config = RigConfig(scene=SceneConfig(seed=seed, num_frames=20), arrangement=arrangement, baseline=baseline,
                           num_cameras=6, rows=2, test_cameras=2)
        rig = make_rig(config)
        eyes = np.array([rig.camera_at(k).position for k in range(6)])
        assert eyes[:, 2].min() >= MIN_CAMERA_HEIGHT
        for part in rig.scene.static_parts:
            if part.shape not in ("plane", "room"):
                assert box_distance(eyes, part).min() > CAMERA_CLEARANCE, (seed, part.name)
        times = np.arange(21) / 30.0
        for obj in rig.scene.objects:
            gap = np.linalg.norm(obj.motion.position(times)[:, None] - eyes[None], axis=-1).min()
            assert gap > obj.bounding_radius() + CAMERA_CLEARANCE, (seed, obj.name)
        removed += len(rig.dropped_parts) + len(rig.dropped_objects)
    assert removed < 10  # the rule removes little (3 and 0 parts or objects in all, measured)


def test_same_seed_gives_identical_pixels(static_capture):
    config, path = static_capture
    written = read_rig(path)
    again = list(render_rig(make_rig(config)))
    assert [name for name, _ in again] == ["cam0", "cam1", "cam2", "cam3"]
    for name, frame in again:
        stored = written.cameras[name][0]
        for channel in CHANNELS:
            assert np.array_equal(np.asarray(getattr(frame, channel), np.float32),
                                  np.asarray(getattr(stored, channel), np.float32)), (name, channel)
        assert np.array_equal(frame.camera.world_to_camera, stored.camera.world_to_camera)
    other = dict(render_rig(make_rig(_static(seed=8))))
    assert not np.array_equal(other["cam0"].color, written.cameras["cam0"][0].color)


def test_capture_reads_back_with_engine_io_and_the_field_loader(static_capture):
    from models.fields.data.views import load_rig

    config, path = static_capture
    rig = read_rig(path)
    assert list(rig.cameras) == ["cam0", "cam1", "cam2", "cam3"] and len(rig) == 1
    assert rig.train_cameras == ["cam0", "cam1", "cam3"] and rig.test_cameras == ["cam2"]
    for seq in rig.cameras.values():
        assert seq.color_space == "linear-srgb" and (seq.width, seq.height) == (W, H)
        assert all(seq.has_channel(c) for c in CHANNELS)
    saved = json.loads((path / "rigscene_config.json").read_text())
    assert saved["scene"]["seed"] == 7 and saved["scene"]["num_frames"] == 1 and saved["static"] is True
    assert saved["num_cameras"] == 4 and saved["arrangement"] == "forward-facing"

    views = load_rig(path)
    assert views.images.shape == (4, H, W, 3) and views.depth.shape == (4, H, W)
    assert views.default_split == ([0, 1, 3], [2])
    assert views.names == ["cam0", "cam1", "cam2", "cam3"]
    for k, name in enumerate(views.names):
        assert np.array_equal(views.cameras[k].world_to_camera, rig.cameras[name].cameras[0].world_to_camera)
        finite = views.depth[k][np.isfinite(views.depth[k])]
        assert views.near_far[k, 0] == pytest.approx(finite.min())


def test_true_depth_is_consistent_across_cameras(static_capture):
    """Camera 0's depth lifted to 3D lands on what the other cameras see, wherever they see it."""
    _, path = static_capture
    rig = read_rig(path)
    a = rig.cameras["cam0"][0]
    for name in ("cam1", "cam2", "cam3"):
        c = _compare_depth(a, rig.cameras[name][0])
        visible = c["agree"].sum() + c["violates"].sum()
        assert c["agree"].sum() > 0.2 * W * H, name  # the views overlap
        assert c["agree"].sum() / visible > 0.9, (name, c["agree"].sum() / visible)
        smooth = c["agree"] & c["smooth"]  # away from edges: the same depth up to float32 rounding (~1e-7)
        assert smooth.sum() > 0.2 * W * H
        assert np.median(c["error"][smooth]) < 1e-5 and np.percentile(c["error"][smooth], 90) < 1e-4


def test_no_camera_sees_geometry_right_in_front_of_it():
    for seed, arrangement, baseline in ((1, "forward-facing", 0.2), (2, "orbit", 1.0), (5, "forward-facing", 0.3)):
        rig = make_rig(_static(seed=seed, arrangement=arrangement, baseline=baseline))
        for name, frame in render_rig(rig):
            finite = frame.depth[np.isfinite(frame.depth)]
            assert finite.size and finite.min() > 0.3, (seed, name, finite.min())


def test_dynamic_capture_is_synchronized_with_moving_objects(dynamic_capture):
    config, path = dynamic_capture
    rig = read_rig(path)
    assert len(rig) == 3
    times = [seq.times for seq in rig.cameras.values()]
    assert all(np.array_equal(t, times[0]) for t in times) and np.allclose(times[0], np.arange(3) / 30.0)
    objects = rig.cameras["cam0"].objects
    assert len(objects) >= 2 and all(o.moving for o in objects)
    for seq in rig.cameras.values():  # the same objects, transforms and fixed camera in every sequence
        assert [o.id for o in seq.objects] == [o.id for o in objects]
        assert all(np.array_equal(o.world_from_object, p.world_from_object) for o, p in zip(seq.objects, objects))
        assert all(np.array_equal(c.world_to_camera, seq.cameras[0].world_to_camera) for c in seq.cameras)
    assert not np.allclose(objects[0].world_from_object[0], objects[0].world_from_object[2])
    for name, seq in rig.cameras.items():
        for frame in seq:
            on_object = frame.object_id > 0
            assert on_object.sum() > 50, name
            assert frame.moving[on_object].all() and not frame.moving[~on_object].any()
            assert np.abs(frame.flow[~on_object]).max() < 1e-4  # fixed cameras: the background does not move
            assert np.allclose(frame.flow, frame.object_flow, atol=1e-4)  # all flow is object motion
            assert np.abs(frame.flow[on_object]).max() > 0.1
    # at one instant the moving objects are where every camera sees them
    for index in range(3):
        c = _compare_depth(rig.cameras["cam0"][index], rig.cameras["cam2"][index])
        on_object = c["inside"] & (rig.cameras["cam0"][index].object_id > 0)
        agree = (c["agree"] & on_object).sum()
        assert agree > 50 and agree / (agree + (c["violates"] & on_object).sum()) > 0.85


def test_render_rig_command_end_to_end(tmp_path, capsys):
    out = tmp_path / "rig"
    assert main(["render-rig", str(out), "--width", "64", "--height", "48", "--supersample", "1", "--static",
                 "--seed", "3", "--num-cameras", "5", "--arrangement", "orbit", "--baseline", "0.8",
                 "--shadow-map-size", "512"]) == 0
    rig = read_rig(out)
    assert list(rig.cameras) == [f"cam{k}" for k in range(5)] and len(rig) == 1
    assert rig.test_cameras == ["cam2"]
    assert json.loads((out / "rigscene_config.json").read_text())["arrangement"] == "orbit"
    capsys.readouterr()
    assert main(["render-rig", str(tmp_path / "bad"), "--num-cameras", "6", "--rows", "4"]) == 2
    err = capsys.readouterr().err
    assert "interleave render-rig: error:" in err and "rows" in err and "Traceback" not in err
    assert not (tmp_path / "bad").exists()


def test_render_rig_options_have_help(capsys):
    with pytest.raises(SystemExit) as exc:
        main(["render-rig", "--help"])
    assert exc.value.code == 0
    text = capsys.readouterr().out
    sub = build_parser()._subparsers._group_actions[0].choices["render-rig"]
    flags = [a.option_strings[0] for a in sub._actions if a.option_strings and a.dest != "help"]
    for flag in ("--num-cameras", "--test-cameras", "--arrangement", "--baseline", "--rows", "--static", "--seed",
                 "--width", "--num-frames"):
        assert flag in flags
    for action in sub._actions:
        if action.option_strings and action.dest != "help":
            assert action.help and len(action.help) > 8 and action.option_strings[0] in text
    assert math.isclose(RigConfig().baseline, 0.2)
