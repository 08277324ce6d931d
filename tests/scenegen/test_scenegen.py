"""Tests of the procedural scene generator: determinism, exact ground truth, variety, validity.

The ground-truth oracle here is independent numpy geometry (unproject with depth + K + pose, move by
the known rigid transforms, project), never the renderer's own shader code.
"""
from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.core.frames import validate_frame
from engine.scenegen import CAMERA_PATHS, SceneConfig, SceneRenderer, make_scene, render_scene
from engine.scenegen.render import clip_from_camera
from engine.scenegen.scene import Motion, MovingObject, Part, rotation_about

W, H = 64, 48


def _config(seed: int, **kw) -> SceneConfig:
    base = dict(width=W, height=H, num_frames=3, seed=seed, shadow_map_size=512)
    base.update(kw)
    return SceneConfig(**base)


def _render(scene) -> list:
    return list(render_scene(scene))


def _pixels(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    v, u = np.nonzero(mask)
    return u, v


def _unproject(frame, u: np.ndarray, v: np.ndarray) -> np.ndarray:
    """World points (N, 3) seen at pixel centres (u + 0.5, v + 0.5) with planar depth (OpenCV camera)."""
    k, w2c = frame.camera.intrinsics, frame.camera.world_to_camera
    z = frame.depth[v, u].astype(np.float64)
    cam = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0] * z, (v + 0.5 - k[1, 2]) / k[1, 1] * z, z], -1)
    return (cam - w2c[:3, 3]) @ w2c[:3, :3]  # R^T (p - t)


def _project(points: np.ndarray, camera) -> np.ndarray:
    """Pixel coordinates (N, 2) of world points (pixel centres at +0.5)."""
    cam = points @ camera.world_to_camera[:3, :3].T + camera.world_to_camera[:3, 3]
    k = camera.intrinsics
    return np.stack([k[0, 0] * cam[:, 0] / cam[:, 2] + k[0, 2], k[1, 1] * cam[:, 1] / cam[:, 2] + k[1, 2]], -1)


def _transform(m: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ m[:3, :3].T + m[:3, 3]


# ----------------------------------------------------------------------------------------------------

def test_config_rejects_bad_values():
    with pytest.raises(InputError, match="camera_path"):
        SceneConfig(camera_path="spiral")
    with pytest.raises(InputError, match="num_objects"):
        SceneConfig(num_objects=(3, 1))
    with pytest.raises(InputError, match="fog_probability"):
        SceneConfig(fog_probability=2.0)


def test_clip_matrix_matches_intrinsics():
    """GL NDC from clip_from_camera lands on the pixel K says (y flipped, pixel centres at +0.5)."""
    k = np.array([[50.0, 0, 32.0], [0, 50.0, 24.0], [0, 0, 1]])
    p = np.array([0.3, -0.2, 2.0, 1.0])
    clip = clip_from_camera(k, W, H) @ p
    ndc = clip[:3] / clip[3]
    u, v = (ndc[0] + 1) / 2 * W, (1 - ndc[1]) / 2 * H
    assert np.allclose([u, v], [50 * 0.3 / 2 + 32, 50 * -0.2 / 2 + 24])
    assert -1 < ndc[2] < 1


def test_same_seed_same_pixels_and_different_seeds_differ():
    a, b = _render(make_scene(_config(5))), _render(make_scene(_config(5)))
    for fa, fb in zip(a, b):
        for name in ("color", "depth", "object_id", "moving", "flow", "object_flow"):
            assert np.array_equal(getattr(fa, name), getattr(fb, name)), name
        assert np.array_equal(fa.camera.world_to_camera, fb.camera.world_to_camera)
    for frame in a:
        validate_frame(frame)
    c = _render(make_scene(_config(6, num_frames=1)))
    assert not np.array_equal(a[0].color, c[0].color)
    assert make_scene(_config(5)).camera.fov_deg != make_scene(_config(6)).camera.fov_deg


@pytest.mark.parametrize("seed,path,zoom", [(11, "orbit", 0.0), (12, "dolly", 0.0), (13, "handheld", 0.0),
                                            (14, "pan", 0.0), (15, "strafe", 0.0), (16, "crane", 1.0)])
def test_flow_is_consistent_with_depth_poses_and_object_motion(seed, path, zoom):
    """Reprojection with depth, K, poses and object transforms reproduces flow and object_flow exactly."""
    scene = make_scene(_config(seed, width=96, height=72, camera_path=path, num_objects=(3, 5), zoom_probability=zoom,
                               object_speed=2.0, pause_probability=0.0))
    if zoom:
        assert scene.camera_at(0).intrinsics[0, 0] != scene.camera_at(1).intrinsics[0, 0]
    frames = _render(scene)
    checked_static = checked_moving = 0
    for frame in frames:
        validate_frame(frame)
        nxt = scene.camera_at(frame.index + 1)
        finite = np.isfinite(frame.depth)

        # static background: camera motion only
        u, v = _pixels(finite & (frame.object_id == 0))
        pix = np.stack([u + 0.5, v + 0.5], -1)
        world = _unproject(frame, u, v)
        err = np.linalg.norm(_project(world, nxt) - (pix + frame.flow[v, u]), axis=1)
        assert np.median(err) < 0.05 and np.mean(err < 0.05) > 0.97, (np.median(err), np.mean(err < 0.05))
        assert np.percentile(err, 99) < 0.02  # in practice ~1e-4 px: only float32 rounding
        assert np.abs(frame.object_flow[v, u]).max() < 1e-4
        assert not frame.moving[v, u].any()
        checked_static += len(u)

        # moving objects: object motion from the known transforms
        m0, m1 = scene.object_transforms(frame.index), scene.object_transforms(frame.index + 1)
        moves = scene.object_moves(frame.index)
        for i, obj in enumerate(scene.objects):
            u, v = _pixels(frame.object_id == obj.id)
            if len(u) == 0:
                continue
            assert (frame.moving[v, u] == moves[i]).all()
            pix = np.stack([u + 0.5, v + 0.5], -1)
            moved = _transform(m1[i] @ np.linalg.inv(m0[i]), _unproject(frame, u, v))
            err = np.linalg.norm(_project(moved, nxt) - (pix + frame.flow[v, u]), axis=1)
            assert np.median(err) < 0.05 and np.mean(err < 0.05) > 0.97, (obj.name, np.median(err))
            err = np.linalg.norm(_project(moved, frame.camera) - (pix + frame.object_flow[v, u]), axis=1)
            assert np.median(err) < 0.05 and np.mean(err < 0.05) > 0.97, (obj.name, np.median(err))
            checked_moving += int(moves[i]) * len(u)
    assert checked_static > 1000 and checked_moving > 20


def test_sky_is_infinite_background_with_rotation_only_flow():
    scene = make_scene(_config(21, sky_probability=1.0, camera_path="pan", camera_speed=3.0))
    frame = _render(scene)[0]
    sky = np.isinf(frame.depth)
    assert sky.mean() > 0.05
    assert (frame.object_id[sky] == 0).all() and not frame.moving[sky].any()
    assert np.abs(frame.object_flow[sky]).max() == 0
    u, v = _pixels(sky)
    k, w2c = frame.camera.intrinsics, frame.camera.world_to_camera
    rays = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0], (v + 0.5 - k[1, 2]) / k[1, 1], np.ones(len(u))], -1)
    far = (rays @ w2c[:3, :3]) * 1e7 + frame.camera.position  # a very distant point along each ray
    pix = np.stack([u + 0.5, v + 0.5], -1)
    err = np.linalg.norm(_project(far, scene.camera_at(1)) - (pix + frame.flow[v, u]), axis=1)
    assert np.abs(frame.flow[sky]).max() > 0.2  # the pan really turns the camera
    assert err.max() < 0.01


def test_enclosed_scene_has_finite_depth_everywhere():
    scene = make_scene(_config(22, sky_probability=0.0, num_frames=1))
    frame = _render(scene)[0]
    assert np.isfinite(frame.depth).all()
    assert frame.depth.min() > 0.4 and frame.depth.max() < 300


def test_ground_depth_matches_ray_plane_intersection():
    scene = make_scene(_config(31, num_frames=1, sky_probability=1.0))
    ground_only = dataclasses.replace(scene, static_parts=tuple(p for p in scene.static_parts if p.name == "ground"),
                                      objects=())
    frame = _render(ground_only)[0]
    u, v = np.meshgrid(np.arange(W), np.arange(H))
    k, w2c = frame.camera.intrinsics, frame.camera.world_to_camera
    rays = np.stack([(u + 0.5 - k[0, 2]) / k[0, 0], (v + 0.5 - k[1, 2]) / k[1, 1], np.ones_like(u, float)], -1)
    dirs = rays @ w2c[:3, :3]  # world direction per unit of planar depth
    eye = frame.camera.position
    with np.errstate(divide="ignore"):
        z = np.where(dirs[..., 2] < 0, -eye[2] / dirs[..., 2], np.inf)  # ground z = 0
    hit = eye + dirs * np.where(np.isfinite(z), z, 0)[..., None]
    inside = np.isfinite(z) & (np.abs(hit[..., :2]).max(-1) < 190)
    assert inside.mean() > 0.2
    assert np.allclose(frame.depth[inside], z[inside], rtol=1e-4)
    assert np.isinf(frame.depth[~np.isfinite(z)]).all()


def test_depth_lies_on_a_moving_box():
    """Unprojected object pixels, taken back to object space, lie on the box surface (max-norm = 1)."""
    half = np.array([0.6, 0.4, 0.3])
    scene = make_scene(_config(41, num_frames=2, camera_path="static", num_objects=(0, 0)))
    eye = scene.camera.eye(0.0)
    target = scene.camera.target
    anchor = eye + 0.6 * (target - eye)
    anchor[2] = max(anchor[2], 1.0)
    motion = Motion(kind="spin", anchor=anchor, velocity=np.array([0.5, 0.0, 0.2]), spin_axis=np.array([0.3, 0.2, 1.0]),
                    spin_rate=1.0, orientation=rotation_about(np.array([1.0, 0, 0]), 0.4))
    part = Part("box", "box", tuple(half), np.eye(4), 0)
    box = MovingObject(id=1, name="box1", kind="box", parts=(part,), motion=motion)
    scene = dataclasses.replace(scene, objects=(box,))
    for frame in _render(scene):
        u, v = _pixels(frame.object_id == 1)
        assert len(u) > 30
        local = _transform(np.linalg.inv(scene.object_transforms(frame.index)[0]), _unproject(frame, u, v))
        ratio = np.abs(local / half).max(-1)
        assert np.abs(ratio - 1).max() < 1e-3


def test_paused_object_is_not_moving():
    cfg = _config(51, num_frames=30, pause_probability=1.0, num_objects=(2, 2))
    scene = make_scene(cfg)
    obj = scene.objects[0]
    start, end = obj.motion.pause
    index = int(np.ceil(start * cfg.fps)) + 1
    assert (index + 1) / cfg.fps < end
    assert not scene.object_moves(index)[0]
    with SceneRenderer(scene) as renderer:
        frame = renderer.render_frame(index)
    seen = frame.object_id == obj.id
    assert not frame.moving[seen].any()
    assert np.abs(frame.object_flow[seen]).max(initial=0.0) < 1e-4


def test_variety_across_seeds():
    scenes = [make_scene(SceneConfig(seed=s, num_frames=30)) for s in range(8)]
    assert len({len(s.objects) for s in scenes}) >= 3
    assert len({s.camera.kind for s in scenes}) >= 3
    assert len({tuple(np.round(s.lighting.sun_direction, 3)) for s in scenes}) == 8
    assert len({s.lighting.style for s in scenes}) >= 2
    assert len({m.pattern for s in scenes for m in s.materials}) == 6
    assert len({o.kind for s in scenes for o in s.objects}) >= 5
    assert len({o.motion.kind for s in scenes for o in s.objects}) >= 5
    assert len({round(s.camera.fov_deg) for s in scenes}) >= 6
    paths = {make_scene(SceneConfig(seed=s, num_frames=5)).camera.kind for s in range(40)}
    assert paths == set(CAMERA_PATHS)
    assert any(s.thin for s in scenes) and any(s.sky.visible for s in scenes)


def _thin_pixels(depth: np.ndarray) -> int:
    """Pixels at least 20 % nearer than both neighbours 2 px away along a row or a column (1-3 px wide)."""
    d = np.where(np.isfinite(depth), depth, 1e6)
    thin_x = (d[:, 2:-2] < 0.8 * d[:, :-4]) & (d[:, 2:-2] < 0.8 * d[:, 4:])
    thin_y = (d[2:-2] < 0.8 * d[:-4]) & (d[2:-2] < 0.8 * d[4:])
    return int(thin_x.sum() + thin_y.sum())


def test_thin_structures_are_one_or_two_pixels_wide():
    """Pixels of 1-2 px wide structures: nearer than both neighbours 2 px away (rows or columns)."""
    config = SceneConfig(width=160, height=120, num_frames=1, seed=61, thin_structures="on", shadow_map_size=512)
    scene = make_scene(config)
    names = {p.name.rstrip("0123456789") for p in scene.static_parts}
    assert {"pole", "fence_bar"} & names
    off = make_scene(dataclasses.replace(config, thin_structures="off"))
    assert not any(p.name.startswith(("pole", "wire", "fence", "grille")) for p in off.static_parts)
    thin_on = _thin_pixels(_render(scene)[0].depth)
    thin_off = _thin_pixels(_render(off)[0].depth)
    assert thin_on > max(50, 4 * thin_off), (thin_on, thin_off)


def test_supersampled_colour_is_registered_with_the_ground_truth():
    """Supersampling must not shift the image: the least-squares shift between 3x3 and 1x colour is ~0."""
    config = SceneConfig(width=128, height=96, num_frames=1, seed=2, supersample=1, shadow_map_size=512)
    c1 = _render(make_scene(config))[0].color.mean(-1)
    c3 = _render(make_scene(dataclasses.replace(config, supersample=3)))[0].color.mean(-1)
    diff = (c3 - c1)[1:-1, 1:-1]
    gx, gy = (c1[1:-1, 2:] - c1[1:-1, :-2]) / 2, (c1[2:, 1:-1] - c1[:-2, 1:-1]) / 2
    a = np.array([[np.sum(gx * gx), np.sum(gx * gy)], [np.sum(gx * gy), np.sum(gy * gy)]])
    shift = np.linalg.solve(a, [np.sum(diff * gx), np.sum(diff * gy)])
    assert np.abs(shift).max() < 0.1, shift  # a half-sample offset bug gives ~0.33


def test_scene_objects_list_matches_transforms():
    scene = make_scene(_config(71, num_frames=5, num_objects=(2, 4)))
    objects = scene.scene_objects()
    assert [o.id for o in objects] == list(range(1, len(scene.objects) + 1))
    for o in objects:
        assert o.world_from_object.shape == (5, 4, 4)
        assert np.allclose(o.world_from_object[3], scene.object_transforms(3)[o.id - 1])


def test_generate_sequence_writes_rgbd_seq(tmp_path):
    from engine.io.rgbd import read_sequence
    from engine.scenegen import generate_sequence

    config = _config(81, num_frames=2, num_objects=(1, 2))
    out = generate_sequence(config, tmp_path / "seq", progress=False)
    meta = json.loads((out / "sequence.json").read_text())
    assert meta["width"] == W and len(meta["frames"]) == 2
    assert len(meta["objects"]) == len(make_scene(config).objects)
    assert json.loads((out / "scenegen_config.json").read_text())["seed"] == 81
    seq = read_sequence(out)
    assert len(seq) == 2 and seq[1].color.shape == (H, W, 3) and np.isfinite(seq[1].depth).any()


def test_monte_carlo_noise_is_unbiased_non_negative_and_mostly_luminance():
    from engine.scenegen.render import monte_carlo_noise

    color = np.full((200, 200, 3), 0.5, np.float32)
    color[:20] = 0.0  # black stays black
    out = monte_carlo_noise(color, 0.1, np.random.default_rng(0))
    assert out.dtype == np.float32 and out.shape == color.shape and (out >= 0).all()
    assert (out[:20] == 0).all()
    ratio = out[20:] / 0.5
    assert abs(ratio.mean() - 1.0) < 0.003 and abs(ratio.std() - 0.1) < 0.003
    flat = ratio.reshape(-1, 3)
    corr = np.corrcoef(flat[:, 0], flat[:, 1])[0, 1]
    assert 0.75 < corr < 0.85, corr  # 80 % of the variance shared by the channels
    assert monte_carlo_noise(color, 0.0, np.random.default_rng(0)) is color
    np.testing.assert_array_equal(out, monte_carlo_noise(color, 0.1, np.random.default_rng(0)))


def test_render_noise_is_seeded_per_frame_and_camera_and_leaves_the_ground_truth_exact():
    clean_scene = make_scene(_config(21, num_frames=2))
    noisy_scene = make_scene(_config(21, num_frames=2, render_noise=0.2))
    with SceneRenderer(clean_scene) as r:
        clean = [r.render_frame(i) for i in range(2)]
    with SceneRenderer(noisy_scene) as r:
        noisy = [r.render_frame(i) for i in range(2)]
        again, other_camera = r.render_frame(0), r.render_frame(0, camera=1)
    np.testing.assert_array_equal(noisy[0].color, again.color)
    assert not np.array_equal(noisy[0].color, other_camera.color)
    ratios = []
    for c, n in zip(clean, noisy):
        validate_frame(n)
        for name in ("depth", "object_id", "moving", "flow", "object_flow"):
            np.testing.assert_array_equal(getattr(c, name), getattr(n, name), err_msg=name)
        lit = c.color > 1e-3
        ratios.append(n.color[lit] / c.color[lit])
        assert (n.color[c.color == 0] == 0).all() and (n.color >= 0).all()
    for ratio in ratios:
        assert abs(ratio.mean() - 1.0) < 0.02 and abs(ratio.std() - 0.2) < 0.03, (ratio.mean(), ratio.std())
    assert not np.allclose(ratios[0][:100], ratios[1][:100])  # each frame its own noise
    with pytest.raises(InputError, match="render_noise"):
        SceneConfig(render_noise=-0.1)
