"""``tools.mvec_extrapolation`` on exact trajectories: a uniformly accelerating square and a bounce."""
import numpy as np

from engine.io.rgbd import read_sequence, write_sequence
from tests.synthetic import two_layer_sequence
from tools import mvec_extrapolation


def _rows(tmp_path, path):
    frames, objects = two_layer_sequence(12, width=96, height=64, camera_speed=0.02, object_path=path)
    seq = read_sequence(write_sequence(tmp_path / "seq", frames, fps=30.0, objects=objects))
    return mvec_extrapolation.measure(seq, 2)


def test_uniform_acceleration_is_exact_for_the_parabola_and_not_for_constant_velocity(tmp_path):
    rows = _rows(tmp_path, lambda i: 0.004 * i * i)
    for row in rows:
        assert row["epe_acceleration"] < 1e-6 < row["epe_velocity"]
        assert row["epe_guarded"] <= row["epe_velocity"] and row["epe_still"] > row["epe_velocity"]
    # early on the change of velocity is large against the velocity (the guard keeps constant velocity there)
    assert rows[0]["epe_guarded"] > 0


def test_rotation_power_and_rigid_fit():
    rotation = mvec_extrapolation.rotation_power(np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]]), 0.5)
    np.testing.assert_allclose(rotation @ [1.0, 0, 0], [np.sqrt(0.5), np.sqrt(0.5), 0], atol=1e-12)
    rng = np.random.default_rng(0)
    before = rng.normal(size=(20, 3))
    now = before @ rotation.T + [1.0, 2.0, 3.0]
    fitted, cb, cn = mvec_extrapolation.rigid_fit(before, now)
    np.testing.assert_allclose(fitted, rotation, atol=1e-9)
