"""LLFF captures as shipped (engine.io.llff): a capture written from the scene generator in LLFF's layout and
axis order, read back; folder choice; bad input as one InputError line naming the file and field."""
from __future__ import annotations

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.io.llff import (LLFF_TO_OPENCV, choose_image_folder, image_folders, read_llff, read_poses_bounds,
                            world_to_camera_to_llff, write_llff)
from engine.io.rgbd import read_rig


def generated_llff(root, factors=(2, 4), num_cameras=6):
    """A static rig from the scene generator (64x48) written as an LLFF capture with ``images_N`` at
    ``factors`` (no ``images/``); returns (capture folder, the generator's cameras, bounds)."""
    from engine.scenegen import RigConfig, SceneConfig, generate_rig

    scene = SceneConfig(seed=7, width=64, height=48, supersample=1, shadow_map_size=256)
    rig = read_rig(generate_rig(RigConfig(scene=scene, static=True, num_cameras=num_cameras, test_cameras=1),
                                root / "rig", progress=False))
    frames = [seq[0] for seq in rig.cameras.values()]
    cameras = [f.camera for f in frames]
    bounds = np.array([[f.depth.min(), f.depth[np.isfinite(f.depth)].max()] for f in frames], dtype=np.float64)
    capture = write_llff(root / "capture", np.stack([f.color for f in frames]), cameras, bounds, factors=factors)
    return capture, cameras, bounds


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    return generated_llff(tmp_path_factory.mktemp("llff"))


def test_llff_poses_round_trip_the_generator_cameras(capture):
    root, cameras, bounds = capture
    raw = np.load(root / "poses_bounds.npy")
    assert raw.shape == (len(cameras), 17)
    poses = read_poses_bounds(root)
    for i, cam in enumerate(cameras):
        np.testing.assert_allclose(poses.world_to_camera[i], cam.world_to_camera, rtol=0, atol=1e-12)
        # LLFF's own axis order in the file: columns [down, right, back] = OpenCV [y, x, -z] of camera-to-world
        c2w = np.linalg.inv(cam.world_to_camera)
        rows = raw[i, :15].reshape(3, 5)
        np.testing.assert_allclose(rows[:, :3], np.stack([c2w[:3, 1], c2w[:3, 0], -c2w[:3, 2]], axis=1), atol=1e-12)
        np.testing.assert_allclose(rows[:, 3], c2w[:3, 3], atol=1e-12)
        assert rows[:, 4].tolist() == [48.0, 64.0, cam.intrinsics[0, 0]]
    np.testing.assert_array_equal(poses.bounds, bounds)
    assert np.linalg.det(raw[0, :15].reshape(3, 5)[:, :3]) == pytest.approx(1.0)  # LLFF's frame is right-handed
    np.testing.assert_array_equal(LLFF_TO_OPENCV @ LLFF_TO_OPENCV, np.eye(3))


def test_llff_reads_each_folder_with_its_intrinsics(capture):
    root, cameras, bounds = capture
    for factor in (2, 4):
        got = read_llff(root, factor)
        assert got.factor == factor and got.images.shape == (len(cameras), 48 // factor, 64 // factor, 3)
        for cam, ref in zip(got.cameras, cameras):
            np.testing.assert_allclose(cam.intrinsics, np.diag([1 / factor, 1 / factor, 1]) @ ref.intrinsics,
                                       rtol=1e-12)
            np.testing.assert_allclose(cam.world_to_camera, ref.world_to_camera, atol=1e-12)
        np.testing.assert_array_equal(got.near_far, bounds)
    assert got.names == [f"image_{i:04d}.png" for i in range(len(cameras))]


def test_llff_folder_choice(capture):
    root, _, _ = capture
    assert sorted(image_folders(root)) == [2, 4]
    assert choose_image_folder(root, None) == (root / "images_4", 4)  # auto: the coarsest shipped
    assert choose_image_folder(root, 2) == (root / "images_2", 2)
    assert choose_image_folder(root, 8) == (root / "images_4", 4)     # downscaled from the nearest finer folder
    assert choose_image_folder(root, 6) == (root / "images_2", 2)
    with pytest.raises(InputError) as exc:
        choose_image_folder(root, 1)
    message = str(exc.value)
    assert "images" in message and "shipped: images_2, images_4" in message and "'downscale'" in message


def _broken(tmp_path, capture, change):
    import shutil

    root = tmp_path / "broken"
    shutil.copytree(capture[0], root)
    change(root)
    return root


@pytest.mark.parametrize("change, file, where", [
    (lambda r: (r / "poses_bounds.npy").unlink(), "poses_bounds.npy", "does not exist"),
    (lambda r: np.save(r / "poses_bounds.npy", np.load(r / "poses_bounds.npy")[:, :15]), "poses_bounds.npy",
     "field 'shape'"),
    (lambda r: np.save(r / "poses_bounds.npy", _with(np.load(r / "poses_bounds.npy"), 2, 16, np.nan)),
     "poses_bounds.npy", "frame 2, field 'bounds'"),
    (lambda r: np.save(r / "poses_bounds.npy", _with(np.load(r / "poses_bounds.npy"), 1, 3, np.inf)),
     "poses_bounds.npy", "frame 1, field 'pose'"),
    (lambda r: np.save(r / "poses_bounds.npy", _with(np.load(r / "poses_bounds.npy"), 0, 14, 0.0)),
     "poses_bounds.npy", "frame 0, field 'hwf'"),
    (lambda r: np.save(r / "poses_bounds.npy", _with(np.load(r / "poses_bounds.npy"), 0, 15, 500.0)),
     "poses_bounds.npy", "frame 0, field 'bounds'"),
    (lambda r: np.save(r / "poses_bounds.npy", _with(np.load(r / "poses_bounds.npy"), 0, 0, 2.0)),
     "poses_bounds.npy", "frame 0, field 'pose'"),
    (lambda r: (r / "images_4" / "image_0003.png").unlink(), "poses_bounds.npy", "field 'rows'"),
])
def test_llff_bad_input_is_one_line_naming_file_and_field(tmp_path, capture, change, file, where):
    root = _broken(tmp_path, capture, change)
    with pytest.raises(InputError) as exc:
        read_llff(root, 4)
    message = str(exc.value)
    assert "\n" not in message and file in message and where in message


def _with(array, row, column, value):
    array = array.copy()
    array[row, column] = value
    return array


def test_llff_writer_refuses_cameras_llff_cannot_hold(capture):
    _, cameras, bounds = capture
    cam = cameras[0]
    off_centre = type(cam)(cam.intrinsics + np.array([[0, 0, 1.0], [0, 0, 0], [0, 0, 0]]), cam.world_to_camera)
    with pytest.raises(InputError, match="centred principal point"):
        write_llff("/nonexistent", np.zeros((1, 48, 64, 3), np.float32), [off_centre], bounds[:1])
    pose = world_to_camera_to_llff(cam.world_to_camera, [48, 64, cam.intrinsics[0, 0]])
    assert pose.shape == (3, 5)
