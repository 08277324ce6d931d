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
    assert set(PRESETS) == {"gentle", "medium", "fast", "extreme"}
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
