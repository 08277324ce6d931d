"""Motion presets of the scene generator and their command-line option."""
import json

import numpy as np
import pytest

from engine.cli import main
from engine.core.errors import InputError
from engine.io.rgbd import read_sequence
from engine.scenegen import SceneConfig
from engine.scenegen.presets import PRESETS, preset_config
from tools.heldout import motion_speed


def test_gentle_is_the_generator_defaults_and_options_win_over_a_preset():
    assert preset_config("gentle", seed=4) == SceneConfig(seed=4)
    fast = preset_config("fast", seed=4, render_noise=0.0)
    assert fast.render_noise == 0.0 and fast.thin_structures == "on" and fast.object_travel > 1
    assert set(PRESETS) == {"gentle", "medium", "fast", "extreme", "smooth"}
    with pytest.raises(InputError, match="preset 'fastest'"):
        preset_config("fastest")
    with pytest.raises(InputError, match="object_sped"):
        preset_config("fast", object_sped=2.0)


def test_render_scene_preset_moves_the_same_scene_faster(tmp_path):
    common = ["--width", "96", "--height", "64", "--num-frames", "6", "--seed", "7005", "--supersample", "1"]
    assert main(["render-scene", str(tmp_path / "gentle"), *common]) == 0
    assert main(["render-scene", str(tmp_path / "fast"), "--preset", "fast", "--render-noise", "0", *common]) == 0
    saved = json.loads((tmp_path / "fast" / "scenegen_config.json").read_text())
    assert saved["fps"] == PRESETS["fast"].get("fps", 30.0) and saved["render_noise"] == 0.0
    assert saved["thin_structures"] == "on"
    gentle, fast = (motion_speed(read_sequence(tmp_path / n)) for n in ("gentle", "fast"))
    assert fast[0] > 2.0 * gentle[0] and np.isfinite(fast).all()


def test_render_scene_rejects_an_unknown_preset(tmp_path, capsys):
    with pytest.raises(SystemExit) as stop:
        main(["render-scene", str(tmp_path / "x"), "--preset", "fastest"])
    assert stop.value.code == 2


def test_smooth_moves_every_object_at_constant_linear_and_angular_velocity():
    from engine.scenegen.sample import make_scene

    for seed in (7201, 7205):
        config = preset_config("smooth", seed=seed, num_frames=12)
        scene = make_scene(config)
        assert scene.objects and not scene.camera.shake_position.any() and not scene.camera.shake_rotation.any()
        assert scene.camera.kind != "handheld" and all(o.motion.kind == "linear" for o in scene.objects)
        times = np.arange(13) / config.fps
        for obj in scene.objects:
            positions = obj.motion.position(times)
            np.testing.assert_allclose(np.diff(positions, 2, axis=0), 0.0, atol=1e-9)  # constant velocity
            rotations = obj.motion.rotation(times)
            steps = [r1 @ r0.T for r0, r1 in zip(rotations[:-1], rotations[1:])]
            np.testing.assert_allclose(steps, np.broadcast_to(steps[0], np.shape(steps)), atol=1e-9)  # constant spin
            turn = np.degrees(np.arccos(np.clip((np.trace(steps[0]) - 1) / 2, -1, 1)))
            assert turn <= 10.0 + 1e-6
    assert preset_config("smooth", seed=1).camera_path == "random"


def test_a_subset_of_motions_keeps_the_other_draws_of_a_seed():
    from engine.scenegen.sample import make_scene

    full, only = make_scene(SceneConfig(seed=3)), make_scene(SceneConfig(seed=3, object_motions=("linear",)))
    assert [o.kind for o in full.objects] == [o.kind for o in only.objects]
    assert all(o.motion.kind == "linear" for o in only.objects)
    with pytest.raises(InputError, match="object_motions"):
        SceneConfig(object_motions=("teleport",))
    with pytest.raises(InputError, match="camera_paths"):
        SceneConfig(camera_paths=())
