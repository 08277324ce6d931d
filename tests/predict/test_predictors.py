"""Baseline predictors on the analytic two-layer scene, where the true frames are known exactly."""
import numpy as np
import pytest

from engine.core.errors import InputError
from engine.eval.metrics import score_frame
from engine.predict import Flow2D, Oracle, Repeat, Reproject, Target, make_predictor
from tests.synthetic import two_layer_sequence


def _target(frame):
    return Target(frame.camera, frame.time, frame.index)


def _interior_error(truth, pred, margin=4):
    return float(np.abs(truth[margin:-margin, margin:-margin] - pred[margin:-margin, margin:-margin]).mean())


def test_repeat_returns_last_frame():
    frames, _ = two_layer_sequence(3)
    out = Repeat().predict(frames[:2], _target(frames[2]))
    np.testing.assert_array_equal(out.color, frames[1].color)
    assert not out.holes.any()


def test_reproject_identity_camera_returns_frame():
    frames, _ = two_layer_sequence(2)
    out = Reproject().predict(frames[:1], _target(frames[0]))
    np.testing.assert_allclose(out.color, frames[0].color, atol=1e-5)
    assert not out.holes.any()


def test_reproject_is_exact_for_camera_motion_in_a_static_scene():
    frames, _ = two_layer_sequence(4, width=96, height=64, camera_speed=0.1, object_speed=0.0)
    truth = frames[2]
    out = Reproject().predict([frames[0]], _target(truth))
    rep = Repeat().predict([frames[0]], _target(truth))
    assert _interior_error(truth.color, out.color) < 0.25 * _interior_error(truth.color, rep.color)
    assert {"warp", "fill"} <= set(out.stages_ms)


def test_oracle_and_flow2d_beat_reproject_on_moving_pixels():
    frames, objects = two_layer_sequence(6, width=192, height=128, camera_speed=0.02, object_speed=0.15)
    history, truth = [frames[2], frames[4]], frames[5]
    scores = {}
    for predictor in (Reproject(), Flow2D(), Oracle(objects)):
        pred = predictor.predict(history, _target(truth))
        assert np.all(np.isfinite(pred.color))
        scores[predictor.name] = score_frame(truth.color, pred.color, truth.moving, with_flip=False)
    assert scores["oracle"].psnr_moving > scores["reproject"].psnr_moving + 3.0
    assert scores["flow2d"].psnr_moving > scores["reproject"].psnr_moving
    assert scores["oracle"].psnr > scores["reproject"].psnr


def test_prepare_once_render_many():
    frames, objects = two_layer_sequence(7)
    predictor = Flow2D()
    state = predictor.prepare([frames[2], frames[4]])
    assert "flow" in state.stages_ms and "warp" in state.stages_ms
    a = predictor.render(state, _target(frames[5]))
    b = predictor.render(state, _target(frames[6]))
    assert a.color.shape == b.color.shape == frames[0].color.shape
    assert "flow" not in a.stages_ms  # flow is estimated once per rendered frame, not per predicted frame


def test_bad_history_is_rejected():
    frames, objects = two_layer_sequence(4)
    with pytest.raises(InputError, match="needs 2 rendered frames"):
        Flow2D().prepare(frames[:1])
    with pytest.raises(InputError, match="time order"):
        Flow2D().prepare([frames[2], frames[1]])
    small, _ = two_layer_sequence(2, width=32, height=24)
    with pytest.raises(InputError, match="frame size"):
        Flow2D().prepare([small[0], frames[1]])
    with pytest.raises(InputError, match="unknown method 'nope'"):
        make_predictor("nope")
    no_ids = frames[1]
    no_ids.object_id = None
    with pytest.raises(InputError, match="object_id"):
        Oracle(objects).predict([no_ids], _target(frames[2]))


@pytest.mark.parametrize("name", ["reproject", "flow2d", "oracle"])
def test_hard_targets_give_finite_frames(name):
    """A 170-degree turn (nothing lands in view), an all-sky history, and a 1:1e5 depth range."""
    from tests.synthetic import rigid

    frames, objects = two_layer_sequence(5, width=48, height=32)
    predictor = make_predictor(name, objects)
    history = [frames[0], frames[2]] if predictor.history_needed == 2 else [frames[2]]
    turned = Target(type(frames[3].camera)(frames[3].camera.intrinsics,
                                           rigid([0, 1, 0], np.deg2rad(170), [0, 0, 0]) @ frames[3].camera.world_to_camera),
                    frames[3].time, 3)
    out = predictor.predict(history, turned)
    assert np.all(np.isfinite(out.color)) and out.holes.mean() > 0.9
    for f in history:  # all sky, then extreme depth range
        f.depth = np.full_like(f.depth, np.inf)
    out = predictor.predict(history, _target(frames[3]))
    assert np.all(np.isfinite(out.color))
    for f in history:
        f.depth = np.where(f.object_id > 0, 1e-3, 1e5).astype(np.float32)
    out = predictor.predict(history, _target(frames[3]))
    assert np.all(np.isfinite(out.color))


def test_upsample_stream_shows_rendered_ticks_and_predicts_the_rest():
    from demos.upsample import upsample_stream

    frames, _ = two_layer_sequence(7)
    shown = list(upsample_stream(frames, 3, Flow2D()))
    assert [s.index for s in shown] == list(range(7))
    assert [s.predicted for s in shown] == [i % 3 != 0 for i in range(7)]
    for s in shown:
        assert s.truth is frames[s.index]
        if not s.predicted:
            np.testing.assert_array_equal(s.color, frames[s.index].color)
        assert np.all(np.isfinite(s.color))


@pytest.fixture(scope="module")
def small_frame_predictors():
    """One flow2d and one decomp (one ONNX session) for every small-frame case."""
    return [make_predictor(method) for method in ("flow2d", "decomp[gate.enabled=false]")]


@pytest.mark.parametrize("size", [(1, 1), (5, 7), (3, 200), (12, 200), (200, 12), (31, 33)])
def test_dis_on_images_smaller_than_it_takes(size, small_frame_predictors):
    """OpenCV's DIS raises on, or crashes the process for, images with a side under ~32 px (12 x 200 crashed
    it): ``dis_calc`` pads them by repeating edges and crops the flow; flow2d and decomp run on such frames."""
    from engine.predict import dis_calc, dis_estimator, luma8

    h, w = size
    frames, _ = two_layer_sequence(4, width=w, height=h, camera_speed=0.02, object_speed=0.15)
    a, b = luma8(frames[3].color), luma8(frames[1].color)
    for preset in ("medium", "ultrafast"):
        flow = dis_calc(dis_estimator(preset, 0), a, b)
        assert flow.shape == (h, w, 2) and np.isfinite(flow).all()
    target = Target(frames[3].camera, frames[3].time, frames[3].index)
    for predictor in small_frame_predictors:
        out = predictor.predict([frames[1], frames[3]], target)
        assert out.color.shape == (h, w, 3) and np.isfinite(out.color).all()


def test_dis_calc_leaves_large_images_alone_and_checks_shapes():
    from engine.predict import dis_calc, dis_estimator, luma8

    frames, _ = two_layer_sequence(4, width=96, height=64, camera_speed=0.02, object_speed=0.15)
    a, b = luma8(frames[3].color), luma8(frames[1].color)
    np.testing.assert_array_equal(dis_calc(dis_estimator(), a, b), dis_estimator().calc(a, b, None))
    with pytest.raises(InputError, match="same"):
        dis_calc(dis_estimator(), a, b[:, :-1])


def test_dis_without_a_start_is_unchanged_by_an_earlier_call_with_one():
    """OpenCV's DIS, once given a starting flow, starts every later call from its reused output buffer: a call
    without a start then returned the previous call's flow (69 px off on a fast pair)."""
    from engine.predict import dis_calc, dis_estimator, luma8

    frames, _ = two_layer_sequence(4, width=96, height=64, camera_speed=0.02, object_speed=0.15)
    a, b = luma8(frames[3].color), luma8(frames[1].color)
    estimator = dis_estimator()
    cold = dis_calc(estimator, a, b)
    start = np.full(a.shape + (2,), 9.0, np.float32)
    warm = dis_calc(estimator, a, b, start)
    assert np.abs(warm - cold).max() > 0.1  # the start mattered
    np.testing.assert_array_equal(dis_calc(estimator, a, b), cold)
    np.testing.assert_array_equal(dis_calc(estimator, a, b, start), warm)


def test_decomp2d_reports_its_own_name():
    """Issue 20, D11: a decomp2d session reported its method as decomp."""
    assert make_predictor("decomp2d").name == "decomp2d" and make_predictor("decomp").name == "decomp"
    assert make_predictor("decomp2d[gate.enabled=false]").name == "decomp2d"


def test_method_names_split_into_options_and_back():
    from engine.predict import method_parts, method_with

    assert method_parts("decomp[flow_width=240, gate.tile=16]") == ("decomp", ["flow_width=240", "gate.tile=16"])
    assert method_parts("reproject") == ("reproject", [])
    assert method_with("decomp", ["flow_width=240", "gate.tile=16"]) == "decomp[flow_width=240,gate.tile=16]"
    assert method_with("decomp", []) == "decomp"
