"""``tools.motion_ablation`` (the rules between DIS and extrapolation) and ``tools.flow_reach`` (DIS's reach)."""
import json

import numpy as np
import pytest

from engine.predict import Flow2D
from tests.synthetic import two_layer_sequence
from tools import flow_reach, motion_ablation


def test_ablation_rules_reproduce_what_flow2d_ships_and_what_it_replaced():
    frames, _ = two_layer_sequence(6, width=160, height=96, camera_speed=0.3, object_speed=0.1)
    history = [frames[2], frames[4]]
    rules = motion_ablation.rules(margin=1.0)
    flows = {name: motion_ablation.RuleFlow2D(rule).prepare(history).data.flow_back for name, rule in rules.items()}
    np.testing.assert_array_equal(flows["trusted"], Flow2D().prepare(history).data.flow_back)
    assert np.abs(flows["dis"]).max() > 0 and (flows["dis"] != flows["seen"]).any()  # entering columns
    for name in ("confidence", "seen", "trusted", "gated"):  # each only removes motion DIS found
        kept = (flows[name] != 0).any(axis=-1)
        np.testing.assert_array_equal(flows[name][kept], flows["dis"][kept])
    assert np.isfinite(flows["regions"]).all()


def test_ablation_rules_apply_to_the_gpu_flow_as_flow2d_with_it_does():
    from engine.geometry.backends import gl as glb

    if not glb.available():
        pytest.skip("no EGL context with compute shaders")
    frames, _ = two_layer_sequence(6, width=160, height=96, camera_speed=0.3, object_speed=0.1)
    history = [frames[2], frames[4]]
    trusted = motion_ablation.RuleFlow2D(motion_ablation.rules(margin=1.0)["trusted"], "gl").prepare(history)
    shipped = Flow2D(estimator="gl").prepare(history)
    np.testing.assert_array_equal(trusted.data.flow_back, shipped.data.flow_back)
    with pytest.raises(ValueError):
        motion_ablation.Precomputed(np.zeros((4, 4, 2), np.float32)).calc(np.zeros((2, 2)), np.zeros((2, 2)), None)


def test_flow_reach_prints_each_variant_and_writes_json(tmp_path, capsys):
    from engine.scenegen import SceneConfig, generate_sequence

    path = generate_sequence(SceneConfig(seed=7005, width=96, height=64, num_frames=5, supersample=1, fps=10.0,
                                         object_speed=2.0), tmp_path / "seq", progress=False)
    flow_reach.main([str(path), "--k", "2", "--json", str(tmp_path / "reach.json")])
    printed = capsys.readouterr().out
    rows = json.loads((tmp_path / "reach.json").read_text())["rows"]
    assert [r["estimate"] for r in rows][:len(flow_reach.VARIANTS) + 1] == ["zero motion", *flow_reach.VARIANTS]
    assert [r["estimate"] for r in rows][-2:] == ["correlation network alone",
                                                  "medium from the network (flow2d[estimator=corr])"]
    assert all(r["pairs"] == rows[0]["pairs"] > 0 for r in rows)
    assert "| medium |" in printed
