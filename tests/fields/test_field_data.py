"""Loaders and the split of models.fields.data.views, on small files written here."""
from __future__ import annotations

import json
import math
from pathlib import Path

import cv2
import numpy as np
import pytest

from engine.core.colorspace import srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame
from engine.io.rgbd import write_rig
from models.fields.data.views import (Views, box_from_cameras, check_views, load_llff, load_nerf_synthetic, load_rig,
                                      split_indices)


def _project(camera: Camera, point: np.ndarray) -> tuple[np.ndarray, float]:
    cam = camera.world_to_camera[:3, :3] @ point + camera.world_to_camera[:3, 3]
    uvw = camera.intrinsics @ cam
    return uvw[:2] / uvw[2], float(cam[2])


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q, r = np.linalg.qr(rng.normal(size=(3, 3)))
    q = q * np.sign(np.diag(r))
    return q * np.sign(np.linalg.det(q))


# ----------------------------------------------------------------------------------------------------
# NeRF-synthetic


def _write_png_rgba(path: Path, rgba: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    cv2.imwrite(str(path), rgba[..., [2, 1, 0, 3]])


def _blender_scene(root: Path, width: int = 8, height: int = 6) -> None:
    """Three listed frames, r_1's image missing. Camera r_0 sits at (0, 0, 4) looking down -z (OpenGL)."""
    c2w0 = np.eye(4)
    c2w0[2, 3] = 4.0
    c2w2 = np.eye(4)  # at (4, 0, 0), looking towards the origin (camera -z = world -x), y up
    c2w2[:3, :3] = np.array([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0]])
    c2w2[0, 3] = 4.0
    frames = [{"file_path": f"./train/r_{i}", "rotation": 0.0, "transform_matrix": m.tolist()}
              for i, m in enumerate([c2w0, c2w0, c2w2])]
    (root / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 2 * math.atan(0.5), "frames": frames}))
    rgba = np.zeros((height, width, 4), np.uint8)
    rgba[..., :3] = (200, 100, 50)
    rgba[..., 3] = 255
    rgba[0, 0, 3] = 128   # half transparent
    rgba[0, 1, 3] = 0     # fully transparent
    _write_png_rgba(root / "train" / "r_0.png", rgba)
    _write_png_rgba(root / "train" / "r_2.png", rgba)


def test_nerf_synthetic_skips_missing_frames_with_a_warning(tmp_path):
    _blender_scene(tmp_path)
    with pytest.warns(UserWarning, match=r"1 listed frame.*\./train/r_1"):
        views = load_nerf_synthetic(tmp_path, "train")
    assert len(views) == 2 and views.names == ["./train/r_0", "./train/r_2"]
    assert views.scene_type == "bounded-360" and views.images.dtype == np.float32
    assert views.near_far.tolist() == [[2.0, 6.0], [2.0, 6.0]]


def test_nerf_synthetic_composites_on_white_in_display_values(tmp_path):
    _blender_scene(tmp_path)
    with pytest.warns(UserWarning):
        white = load_nerf_synthetic(tmp_path, "train")
    with pytest.warns(UserWarning):
        black = load_nerf_synthetic(tmp_path, "train", white_background=False)
    rgb = np.array([200, 100, 50]) / 255.0
    a = 128 / 255.0
    np.testing.assert_allclose(white.images[0, 0, 0], srgb_to_linear(rgb * a + (1 - a)), atol=1e-6)
    np.testing.assert_allclose(white.images[0, 0, 1], 1.0, atol=1e-6)
    np.testing.assert_allclose(white.images[0, 1, 1], srgb_to_linear(rgb), atol=1e-6)
    np.testing.assert_allclose(black.images[0, 0, 0], srgb_to_linear(rgb * a), atol=1e-6)
    assert black.images[0, 0, 1].tolist() == [0.0, 0.0, 0.0]
    assert white.background.tolist() == [1.0, 1.0, 1.0] and black.background.tolist() == [0.0, 0.0, 0.0]


def test_nerf_synthetic_cameras_are_opencv(tmp_path):
    _blender_scene(tmp_path)
    with pytest.warns(UserWarning):
        views = load_nerf_synthetic(tmp_path, "train")
    cam = views.cameras[0]
    np.testing.assert_allclose(cam.intrinsics, [[8.0, 0, 4.0], [0, 8.0, 3.0], [0, 0, 1]])  # f = (W/2)/tan(fov/2)
    np.testing.assert_allclose(cam.position, [0, 0, 4])
    uv, z = _project(cam, np.zeros(3))
    np.testing.assert_allclose(uv, [4.0, 3.0])
    assert z == pytest.approx(4.0)
    uv_up, _ = _project(cam, np.array([0.0, 0.5, 0.0]))      # world +y is up in the image: smaller row
    uv_right, _ = _project(cam, np.array([0.5, 0.0, 0.0]))   # world +x is to the right
    assert uv_up[1] < 3.0 and uv_right[0] > 4.0
    uv2, z2 = _project(views.cameras[1], np.zeros(3))        # the side camera also looks at the origin
    np.testing.assert_allclose(uv2, [4.0, 3.0], atol=1e-9)
    assert z2 == pytest.approx(4.0)


def test_nerf_synthetic_downscale_scales_k_and_averages(tmp_path):
    _blender_scene(tmp_path)
    with pytest.warns(UserWarning):
        full = load_nerf_synthetic(tmp_path, "train")
    with pytest.warns(UserWarning):
        half = load_nerf_synthetic(tmp_path, "train", downscale=2)
    assert half.images.shape == (2, 3, 4, 3) and half.downscale == 2
    np.testing.assert_allclose(half.cameras[0].intrinsics, [[4.0, 0, 2.0], [0, 4.0, 1.5], [0, 0, 1]])
    np.testing.assert_allclose(half.images[0, 0, 0], full.images[0, :2, :2].mean(axis=(0, 1)), atol=1e-6)


def test_nerf_synthetic_errors_name_the_file(tmp_path):
    with pytest.raises(InputError, match="transforms_train.json"):
        load_nerf_synthetic(tmp_path, "train")
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": [
        {"file_path": "./train/nothing", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.warns(UserWarning), pytest.raises(InputError, match="no listed frame"):
        load_nerf_synthetic(tmp_path, "train")


# ----------------------------------------------------------------------------------------------------
# LLFF


def _llff_scene(root: Path, rng: np.random.Generator, factor: int = 2, count: int = 3):
    h0, w0, focal = 12, 16, 20.0
    rows, llff = [], []
    for _ in range(count):
        rot = _random_rotation(rng)  # columns: camera axes [down, right, back] in world coordinates
        centre = rng.normal(size=3)
        pose = np.concatenate([rot, centre[:, None], np.array([[h0], [w0], [focal]])], axis=1)  # 3x5
        llff.append(pose)
        rows.append(np.concatenate([pose.reshape(-1), [1.5 + rng.uniform(), 20.0 + rng.uniform()]]))
    np.save(root / "poses_bounds.npy", np.array(rows))
    folder = root / f"images_{factor}"
    folder.mkdir()
    for i in range(count):
        cv2.imwrite(str(folder / f"IMG_{i:04d}.png"), np.full((h0 // factor, w0 // factor, 3), 40 * i, np.uint8))
    return llff, np.array(rows)[:, 15:], (h0, w0, focal)


def test_llff_conversion_projects_like_the_llff_convention(tmp_path):
    rng = np.random.default_rng(0)
    llff, bounds, (h0, w0, focal) = _llff_scene(tmp_path, rng, factor=2)
    views = load_llff(tmp_path, downscale=2, scene_type="forward-facing")
    assert len(views) == 3 and views.images.shape == (3, 6, 8, 3) and views.scene_type == "forward-facing"
    np.testing.assert_allclose(views.near_far, bounds)
    for pose, cam in zip(llff, views.cameras):
        rot, centre = pose[:, :3], pose[:, 3]
        for local in ([0.3, -0.2, -3.0], [-1.0, 0.5, -2.0], [0.0, 0.0, -7.0]):  # (down, right, back); in front
            point = centre + rot @ np.array(local)
            down, right, back = rot.T @ (point - centre)            # by hand, in LLFF's own axes
            u_full = w0 / 2 + focal * right / -back
            v_full = h0 / 2 + focal * down / -back
            uv, z = _project(cam, point)                            # the converted OpenCV camera, images_2
            np.testing.assert_allclose(uv, [u_full / 2, v_full / 2], atol=1e-9)
            assert z == pytest.approx(-back)                        # planar depth = distance along -back


def test_llff_scene_type_follows_the_spread_of_the_cameras(tmp_path):
    from models.fields.data.views import FORWARD_FACING_MAX_DEG, llff_scene_type, optical_axis_spread

    _llff_scene(tmp_path, np.random.default_rng(0), factor=2)  # random orientations: looking around
    assert load_llff(tmp_path, downscale=2).scene_type == "bounded-360"

    def camera(yaw_deg: float) -> Camera:
        yaw = np.radians(yaw_deg)
        rot = np.array([[np.cos(yaw), 0, -np.sin(yaw)], [0, 1, 0], [np.sin(yaw), 0, np.cos(yaw)]])
        w2c = np.eye(4)
        w2c[:3, :3] = rot
        return Camera(np.eye(3), w2c)

    spread = FORWARD_FACING_MAX_DEG
    assert llff_scene_type([camera(-0.9 * spread), camera(0.0), camera(0.9 * spread)]) == "forward-facing"
    assert llff_scene_type([camera(-1.2 * spread), camera(0.0), camera(1.2 * spread)]) == "bounded-360"
    assert llff_scene_type([camera(0.0), camera(180.0)]) == "bounded-360"  # opposite axes: no mean direction
    assert optical_axis_spread([camera(-20.0), camera(0.0), camera(20.0)]) == pytest.approx(20.0, abs=1e-9)
    assert optical_axis_spread([camera(0.0), camera(30.0)]) == pytest.approx(15.0, abs=1e-9)  # from the mean axis
    assert optical_axis_spread([camera(0.0), camera(180.0)]) == 180.0


def test_llff_image_count_mismatch_is_an_error(tmp_path):
    _llff_scene(tmp_path, np.random.default_rng(1), factor=4)
    (tmp_path / "images_4" / "IMG_0000.png").unlink()
    with pytest.raises(InputError, match="has 3 rows but images_4/ holds 2 images") as exc:
        load_llff(tmp_path, downscale=4)
    assert "poses_bounds.npy" in str(exc.value) and "'rows'" in str(exc.value)
    with pytest.raises(InputError, match="images_2.*shipped: images_4"):
        load_llff(tmp_path, downscale=2)


# ----------------------------------------------------------------------------------------------------
# rgbd-rig


def test_load_rig_keeps_true_depth_and_split(tmp_path):
    k = np.array([[5.0, 0, 2.5], [0, 5.0, 2.0], [0, 0, 1]])
    sequences = {}
    for i, name in enumerate(["cam0", "cam1", "cam2"]):
        w2c = np.eye(4)
        w2c[0, 3] = -0.2 * i
        depth = np.full((4, 5), 2.0 + i, np.float32)
        if i == 2:
            depth[0, 0] = np.inf
        color = np.full((4, 5, 3), 0.1 * (i + 1), np.float32)
        sequences[name] = [Frame(index=0, time=0.0, color=color, depth=depth, camera=Camera(k, w2c))]
    write_rig(tmp_path / "rig", sequences, train=["cam0", "cam2"], test=["cam1"], fps=30.0)
    views = load_rig(tmp_path / "rig")
    assert len(views) == 3 and views.depth.shape == (3, 4, 5)
    assert views.default_split == ([0, 2], [1])
    np.testing.assert_allclose(views.images[1], 0.2, atol=1e-6)
    assert views.near_far[0].tolist() == [2.0, 2.0 * 1.01]   # one depth only: a thin range above it
    assert views.near_far[2, 0] == 4.0 and np.isinf(views.near_far[2, 1])
    assert np.isinf(views.depth[2, 0, 0])


# ----------------------------------------------------------------------------------------------------
# split, box, validation


def test_split_matches_the_thesis_llff_protocol():
    assert split_indices(20, views=3) == ([5, 10, 14], [0, 8, 16])   # fern, 3 views (anchor facts)
    train, test = split_indices(20, views=2)
    assert test == [0, 8, 16] and len(train) == 2 and not set(train) & set(test)
    assert split_indices(10, views=None, test_every=0) == (list(range(10)), [])
    assert split_indices(10, train_views=[1, 2], test_views=[5]) == ([1, 2], [5])
    assert split_indices(4, views=3, test_every=0) == ([0, 2, 3], [])  # too few for interior points: ends too


@pytest.mark.parametrize("kwargs, field", [
    (dict(views=0), "views"), (dict(views=18), "views"), (dict(train_views=[0, 1]), "train_views"),
    (dict(test_views=[3, 3]), "test_views"), (dict(train_views=[25]), "train_views")])
def test_split_rejects_bad_requests(kwargs, field):
    with pytest.raises(InputError) as info:
        split_indices(20, **kwargs)
    assert info.value.field == field


def test_box_from_cameras_on_a_ring():
    k = np.array([[50.0, 0, 50], [0, 50.0, 50], [0, 0, 1]])
    cams = []
    for a in np.linspace(0, 2 * np.pi, 6, endpoint=False):
        eye = np.array([4 * np.cos(a), 4 * np.sin(a), 1.0])
        f = -eye / np.linalg.norm(eye)
        r = np.cross(f, [0, 0, 1.0])
        r /= np.linalg.norm(r)
        rot = np.stack([r, np.cross(f, r), f])
        w2c = np.eye(4)
        w2c[:3, :3], w2c[:3, 3] = rot, -rot @ eye
        cams.append(Camera(k, w2c))
    box = box_from_cameras(cams, 100, 100)
    np.testing.assert_allclose((box[0] + box[1]) / 2, 0.0, atol=1e-9)
    np.testing.assert_allclose(box[1] - box[0], 2 * np.sqrt(17.0), rtol=1e-9)  # distance * tan(45 deg) * 2


def test_check_views_names_the_bad_field():
    k = np.array([[5.0, 0, 2], [0, 5.0, 2], [0, 0, 1]])
    good = Views(images=np.zeros((1, 4, 4, 3), np.float32), cameras=[Camera(k, np.eye(4))],
                 near_far=np.array([[1.0, 2.0]]), scene_type="bounded-360")
    check_views(good)
    for change, field in [(dict(near_far=np.array([[2.0, 1.0]])), "near_far"), (dict(scene_type="360"), "scene_type"),
                          (dict(images=np.full((1, 4, 4, 3), np.nan, np.float32)), "images"),
                          (dict(cameras=[]), "cameras"), (dict(bounds=np.zeros((2, 3))), "bounds")]:
        with pytest.raises(InputError) as info:
            check_views(Views(**{**good.__dict__, **change}))
        assert info.value.field == field
    assert len(good.subset([0, 0])) == 2
    with pytest.raises(InputError, match="out of range"):
        good.subset([1])
