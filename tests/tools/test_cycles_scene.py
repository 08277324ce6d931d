"""``tools.cycles_scene import`` on a real Cycles render (a committed 64x36, 3-frame fixture made with bpy 5.0.1):
the imported sequence's object ids, moving masks and per-frame object transforms agree with Cycles' own
Vector pass, so ``oracle`` and the moving-pixel scores mean on it what they mean on generated sequences."""
import json
from pathlib import Path

import numpy as np
import pytest

from engine.core.frames import rigid_inverse
from engine.geometry.motion import rigid_motion_vectors
from engine.io.rgbd import read_sequence
from engine.predict.base import true_object_flow
from tools.cycles_scene import import_sequence

FIXTURE = Path(__file__).resolve().parents[1] / "io" / "data" / "cycles_scene"


@pytest.fixture(scope="module")
def sequence(tmp_path_factory):
    return read_sequence(import_sequence(FIXTURE, tmp_path_factory.mktemp("cycles") / "seq"))


def _single_surface(ids: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood is one object (Cycles anti-aliases the Vector pass, not Depth or Index)."""
    key = np.where(np.isfinite(depth), ids, -1)
    pad = np.pad(key, 1, mode="edge")
    inner = np.isfinite(depth)
    for dy in range(3):
        for dx in range(3):
            inner &= pad[dy:dy + key.shape[0], dx:dx + key.shape[1]] == key
    return inner


def test_ids_masks_and_transforms_are_imported(sequence):
    assert len(sequence) == 3 and sequence[0].color.shape == (36, 64, 3)
    ids = {o.id for o in sequence.objects}
    assert ids == {1, 2} and all(o.moving and o.world_from_object.shape == (3, 4, 4) for o in sequence.objects)
    for i in range(3):
        frame = sequence[i]
        assert frame.object_id is not None and set(np.unique(frame.object_id)) <= {0, 1, 2}
        np.testing.assert_array_equal(frame.moving, np.isin(frame.object_id, [1, 2]))
    assert any(sequence[i].moving.any() for i in range(3))


def test_object_transforms_reproduce_the_cycles_vector_pass(sequence):
    """Exact rigid vectors from the imported depth, cameras, ids and object transforms against Cycles' Vector
    pass (imported as motion_vectors), on single-surface pixels of the moving objects and the background."""
    assert _vectors_checked(sequence) > 50  # the objects do move across pixels the check covers


def _vectors_checked(sequence) -> int:
    """Check every frame after the first as above; returns how many moving single-surface pixels it covered."""
    objects = {o.id: o for o in sequence.objects}
    checked = 0
    for n in range(1, len(sequence)):
        frame, previous = sequence[n], sequence[n - 1]
        motions = {oid: o.world_from_object[n - 1] @ rigid_inverse(o.world_from_object[n])
                   for oid, o in objects.items()}
        exact = rigid_motion_vectors(frame.depth, frame.camera, previous.camera, frame.object_id, motions)
        inner = _single_surface(frame.object_id, frame.depth)
        error = np.linalg.norm(frame.motion_vectors[inner] - exact[inner], axis=-1)
        assert np.median(error) < 0.05 and np.percentile(error, 95) < 0.5, (n, np.median(error), error.max())
        moving = inner & frame.moving
        # the oracle's object flow: zero on the static scene, the objects' own motion on theirs
        truth = true_object_flow(frame, objects, n - 1)[..., :2]
        assert not truth[~frame.moving].any() and np.linalg.norm(truth[moving], axis=-1).min() > 0.0
        checked += int(moving.sum())
    return checked


RIG = Path(__file__).resolve().parents[1] / "io" / "data" / "cycles_rig"


def test_a_rig_render_is_imported_as_an_rgbd_rig(tmp_path):
    """``tools.cycles_scene import-rig`` on a committed Cycles rig (3 static cameras, 2 frames, 48x27, made with
    bpy 5.0.1): the rgbd-rig's split is render-rig's (the middle camera held out), every camera is static with
    the same orientation, on a row ``baseline`` apart along its x axis, and sees the same moving objects, whose
    imported transforms reproduce that camera's own Vector pass."""
    from engine.io.rgbd import read_rig
    from tools.cycles_scene import import_rig

    rig = read_rig(import_rig(RIG, tmp_path / "rig"))
    assert list(rig.cameras) == ["cam0", "cam1", "cam2"]
    assert rig.train_cameras == ["cam0", "cam2"] and rig.test_cameras == ["cam1"]
    first = rig.cameras["cam0"]
    rotation = first[0].camera.world_to_camera[:3, :3]
    centres = []
    for name, sequence in rig.cameras.items():
        assert len(sequence) == 2 and sequence[0].color.shape == (27, 48, 3)
        for i in range(2):
            np.testing.assert_allclose(sequence[i].camera.world_to_camera, sequence[0].camera.world_to_camera)
            assert sequence[i].moving.any()  # every camera sees objects move
        np.testing.assert_allclose(sequence[0].camera.world_to_camera[:3, :3], rotation, atol=1e-7)
        centres.append(sequence[0].camera.camera_to_world[:3, 3])
        assert [(o.id, o.name) for o in sequence.objects] == [(o.id, o.name) for o in first.objects]
        for mine, theirs in zip(sequence.objects, first.objects):
            np.testing.assert_array_equal(mine.world_from_object, theirs.world_from_object)
        assert _vectors_checked(sequence) > 10
    steps = np.diff(np.stack(centres), axis=0) @ rotation.T  # in camera axes: x right
    np.testing.assert_allclose(steps, [[0.4, 0.0, 0.0]] * 2, atol=1e-6)



@pytest.mark.parametrize("edit, where", [
    ({"test_cameras": 2}, "field 'test_cameras'"),     # 3 cameras in a row have one that may be held out
    ({"cameras": "cam0"}, "field 'cameras'"),
    ({"cameras": None}, "field 'cameras'"),
    ({"test_cameras": "1"}, "field 'test_cameras'"),
    ({"cameras": ["cam0", "cam1", "cam9"]}, "cam9"),   # a camera folder that is not there
])
def test_a_bad_rig_render_is_one_line_and_exit_2(tmp_path, capsys, edit, where):
    """``import-rig`` on a rig render whose cameras.json names a bad split, no camera list or a missing camera:
    exit 2 and one line naming the file and the field, no traceback and no rig written."""
    import shutil

    from tools.cycles_scene import main

    render = tmp_path / "render"
    shutil.copytree(RIG, render)
    meta = json.loads((render / "cameras.json").read_text())
    (render / "cameras.json").write_text(json.dumps({**meta, **edit}))
    assert main(["import-rig", str(render), str(tmp_path / "rig")]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: file ") and "cameras.json" in err and where in err and "\n" not in err
    assert not (tmp_path / "rig" / "rig.json").exists()

CAPTURE = Path(__file__).resolve().parents[1] / "io" / "data" / "cycles_capture"


def test_a_static_capture_is_written_as_llff_ships_it(tmp_path):
    """``tools.cycles_scene llff`` on a committed 3-view Cycles capture (48x36): images_2/ and poses_bounds.npy
    that engine.io.llff reads back to the rendered cameras (intrinsics halved) with bounds around every view's
    depth."""
    from engine.io.importers import frames_from_blender
    from engine.io.llff import read_llff
    from tools.cycles_scene import write_capture

    root = write_capture(CAPTURE, tmp_path / "llff", factor=2)
    assert sorted(p.name for p in root.iterdir()) == ["images_2", "poses_bounds.npy"]
    capture = read_llff(root)
    frames = list(frames_from_blender(CAPTURE / "cameras.json").frames)
    assert capture.images.shape == (3, 18, 24, 3) and capture.factor == 2
    for camera, frame, (near, far) in zip(capture.cameras, frames, capture.near_far):
        np.testing.assert_allclose(camera.world_to_camera, frame.camera.world_to_camera, atol=1e-6)
        np.testing.assert_allclose(camera.intrinsics[:2], frame.camera.intrinsics[:2] / 2, rtol=1e-6)
        depth = frame.depth[np.isfinite(frame.depth)]
        assert near < np.percentile(depth, 1) and far > np.percentile(depth, 99)
    # the views differ only by the camera: parallel axes, positions on a grid
    rotations = np.stack([f.camera.world_to_camera[:3, :3] for f in frames])
    np.testing.assert_allclose(rotations, rotations[:1].repeat(3, 0), atol=1e-6)
    assert np.ptp(np.stack([f.camera.camera_to_world[:3, 3] for f in frames]), axis=0).max() > 0.1
