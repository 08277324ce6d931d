"""Validation at the public entry points: every rule names the frame and field, nothing is clamped."""
import numpy as np
import pytest

from engine.core.errors import InputError
from engine.core.frames import (Camera, Frame, rigid_inverse, validate_color, validate_depth, validate_frame,
                                validate_intrinsics, validate_pose)
from tests.synthetic import rigid, two_layer_sequence


def test_rigid_inverse_is_exact():
    t = rigid([0.3, -1.0, 0.2], 2.9, [1.0, -4.0, 1e4])
    np.testing.assert_allclose(rigid_inverse(t) @ t, np.eye(4), atol=1e-9)


@pytest.mark.parametrize("matrix,message", [
    (np.diag([1.1, 1.1, 1.1, 1.0]), "not rigid"),
    (np.diag([1.0, 1.0, -1.0, 1.0]), "not rigid"),  # reflection
    (np.array([[1, 0.2, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]), "not rigid"),  # shear
    (np.full((4, 4), np.nan), "non-finite"),
    (np.eye(3), "shape"),
    (np.array([[1, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 1, 1.0]]), "last row"),
    ("abc", "numeric"),
])
def test_bad_poses(matrix, message):
    with pytest.raises(InputError, match=message) as exc:
        validate_pose(matrix, file="cams.json", frame=3)
    assert "cams.json" in str(exc.value) and "frame 3" in str(exc.value) and "world_to_camera" in str(exc.value)


@pytest.mark.parametrize("matrix,message", [
    (np.zeros((3, 3)), "last row"),
    (np.array([[0.0, 0, 5], [0, 10, 5], [0, 0, 1]]), "focal"),
    (np.array([[10.0, 0, 5], [0, -10, 5], [0, 0, 1]]), "focal"),
    (np.array([[np.inf, 0, 5], [0, 10, 5], [0, 0, 1]]), "non-finite"),
    (np.eye(4), "shape"),
])
def test_bad_intrinsics(matrix, message):
    with pytest.raises(InputError, match=message):
        validate_intrinsics(matrix, frame=0)


def test_depth_rules():
    good = np.array([[1e-3, 1e5], [np.inf, 2.0]], np.float32)
    np.testing.assert_array_equal(validate_depth(good), good)  # +inf (sky) is legal, nothing clamped
    for value, message in ((np.nan, "NaN"), (-np.inf, "-inf"), (0.0, "zero or negative"), (-1.0, "zero or negative")):
        bad = good.copy()
        bad[0, 0] = value
        with pytest.raises(InputError, match=message) as exc:
            validate_depth(bad, file="f.exr", frame=7, field_name="Z")
        assert "frame 7" in str(exc.value) and "'Z'" in str(exc.value)
    with pytest.raises(InputError, match="shape"):
        validate_depth(np.ones((2, 2, 1), np.float32))
    with pytest.raises(InputError, match="float"):
        validate_depth(np.ones((2, 2), np.int32))
    with pytest.raises(InputError, match="expected"):
        validate_depth(np.ones((2, 2), np.float32), (3, 2))


def test_color_rules():
    with pytest.raises(InputError, match=r"\(H, W, 3\)"):
        validate_color(np.zeros((2, 2, 4), np.float32))
    with pytest.raises(InputError, match="non-finite"):
        validate_color(np.full((2, 2, 3), np.nan, np.float32))
    with pytest.raises(InputError, match="negative"):
        validate_color(np.full((2, 2, 3), -0.1, np.float32))
    with pytest.raises(InputError, match="float"):
        validate_color(np.zeros((2, 2, 3), np.uint8))


def test_frame_channels_are_checked_against_each_other():
    frames, _ = two_layer_sequence(2)
    frame = frames[0]
    assert validate_frame(frame).object_id.dtype == np.int32
    cases = [("flow", np.zeros((3, 3, 2), np.float32), "shape"),
             ("object_flow", np.full(frame.depth.shape + (2,), np.nan, np.float32), "non-finite"),
             ("object_id", np.full(frame.depth.shape, 0.5), "non-negative integers"),
             ("moving", np.full(frame.depth.shape, 2), "only 0 and 1"),
             ("time", float("nan"), "finite"),
             ("color", frame.color[:-1], "size")]
    for name, value, message in cases:
        bad = Frame(**{**frame.__dict__, name: value})
        with pytest.raises(InputError, match=message) as exc:
            validate_frame(bad, file="x.exr")
        assert "x.exr" in str(exc.value)
    bad_cam = Frame(**{**frame.__dict__, "camera": Camera(frame.camera.intrinsics, np.diag([2.0, 2, 2, 1]))})
    with pytest.raises(InputError, match="not rigid"):
        validate_frame(bad_cam)
