"""``tools.motion_ablation`` (the rules between DIS and extrapolation) and ``tools.flow_reach`` (DIS's reach)."""
import json

import numpy as np
import pytest

from engine.predict import Flow2D
from tests.synthetic import two_layer_sequence
from tools import error_regions, extrapolation_ablation, flow_reach, motion_ablation


def test_ablation_rules_reproduce_what_flow2d_ships_and_what_it_replaced():
    frames, _ = two_layer_sequence(6, width=160, height=96, camera_speed=0.3, object_speed=0.1)
    history = [frames[2], frames[4]]
    rules = motion_ablation.rules(margin=1.0)
    flows = {name: motion_ablation.RuleFlow2D(rule).prepare(history).data.flow_back for name, rule in rules.items()
             if name != "network_veto"}
    np.testing.assert_array_equal(flows["trusted"], Flow2D().prepare(history).data.flow_back)
    assert np.abs(flows["dis"]).max() > 0 and (flows["dis"] != flows["seen"]).any()  # entering columns
    for name in ("confidence", "seen", "trusted", "gated", "depth_static", "behind_edge"):  # each only removes
        kept = (flows[name] != 0).any(axis=-1)
        np.testing.assert_array_equal(flows[name][kept], flows["dis"][kept])
    assert np.isfinite(flows["regions"]).all()
    veto = motion_ablation.RuleFlow2D(rules["network_veto"], "corr").prepare(history).data.flow_back
    started = motion_ablation.RuleFlow2D(rules["trusted"], "corr").prepare(history).data.flow_back
    kept = (veto != 0).any(axis=-1)
    np.testing.assert_array_equal(veto[kept], started[kept])
    with pytest.raises(ValueError, match="estimator corr"):
        motion_ablation.RuleFlow2D(rules["network_veto"]).prepare(history)


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


@pytest.fixture(scope="module")
def small_fast_sequence(tmp_path_factory):
    from engine.scenegen import SceneConfig, generate_sequence

    return generate_sequence(SceneConfig(seed=7005, width=96, height=64, num_frames=7, supersample=1, fps=10.0,
                                         object_speed=2.0), tmp_path_factory.mktemp("fast") / "seq", progress=False)


def test_extrapolation_variants_from_the_true_flow(small_fast_sequence):
    from engine.eval.protocol import evaluate_sequence
    from engine.io.rgbd import read_sequence
    from engine.predict import registry

    seq = read_sequence(small_fast_sequence)
    names = []
    for variant in extrapolation_ablation.VARIANTS:
        registry.METHODS[f"x:{variant}"] = lambda objects, v=variant: extrapolation_ablation.Extrapolated(v, "truth",
                                                                                                            objects)
        names.append(f"x:{variant}")
    try:
        results = {r.method: r for r in evaluate_sequence(seq, ["reproject", "flow2d", *names], 2, with_flip=False)}
    finally:
        for name in names:
            del registry.METHODS[name]
    for name in names:  # every variant moves the objects with their true motion: ahead of the camera-only warp
        assert results[name].psnr_moving > results["reproject"].psnr_moving + 1.0
    # 2d is flow2d's extrapolation of the true flow: never behind it on moving pixels here
    assert results["x:2d"].psnr_moving >= results["flow2d"].psnr_moving - 0.05


def test_flow_vectors_of_a_static_scene_are_the_camera_vectors(small_fast_sequence):
    from engine.geometry.motion import camera_motion_vectors
    from engine.io.rgbd import read_sequence
    from engine.predict.base import Target, Timer, warp_fill_depth

    seq = read_sequence(small_fast_sequence)
    older, newest = seq[2], seq[4]
    _, depth_w, holes = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index), Timer())
    zero = np.zeros(newest.depth.shape + (2,), np.float32)
    vectors = extrapolation_ablation.flow_vectors(zero, newest, older, np.where(holes, np.inf, depth_w))
    np.testing.assert_allclose(vectors, camera_motion_vectors(newest.depth, newest.camera, older.camera), atol=1e-5)


def test_error_regions_split_each_frame_and_add_up(small_fast_sequence, tmp_path, capsys):
    moving_n = np.zeros((40, 60), bool)
    moving_n[10:15, 10:15] = True
    moving_t = np.roll(moving_n, 3, axis=1)
    masks = error_regions.region_masks(moving_n, moving_t, near=4)
    total = sum(m.astype(int) for m in masks.values())
    assert (total == 1).all()  # disjoint and covering
    assert masks["vacated"][12, 10] and masks["moving"][12, 17] and masks["near"][12, 21] and masks["far"][30, 50]
    error_regions.main([str(small_fast_sequence), "--k", "2", "--methods", "reproject,oracle",
                        "--json", str(tmp_path / "r.json")])
    rows = {r["method"]: r for r in json.loads((tmp_path / "r.json").read_text())["rows"]}
    assert rows["oracle"]["far"] == pytest.approx(rows["reproject"]["far"], abs=1e-6)  # true motion: static alike
    assert rows["oracle"]["moving"] < rows["reproject"]["moving"]
    assert "| oracle |" in capsys.readouterr().out
