"""The one predictor loop (engine.runtime.stream) that Session, the demo and eval share."""
import numpy as np
import pytest

from engine.predict import Repeat, Target, make_predictor
from engine.runtime.stream import PredictionLoop
from tests.synthetic import two_layer_sequence


def _target(frame):
    return Target(frame.camera, frame.time, frame.index)


def test_falls_back_until_enough_frames_then_matches_the_predictor():
    frames, _ = two_layer_sequence(5, width=48, height=32, camera_speed=0.05, object_speed=0.1)
    loop = PredictionLoop(make_predictor("flow2d"))
    with pytest.raises(RuntimeError, match="before any frame"):
        loop.predict(_target(frames[1]))
    first = loop.submit(frames[0])
    assert first.fallback == "history" and first.predictor.name == "reproject" and len(first.frames) == 1
    np.testing.assert_array_equal(loop.predict(_target(frames[1])).color,
                                  make_predictor("reproject").predict([frames[0]], _target(frames[1])).color)
    loop.submit(frames[2])
    third = loop.submit(frames[4])
    assert third.fallback is None and third.predictor.name == "flow2d"
    assert [f.index for f in third.frames] == [2, 4]  # only the frames the method needs
    np.testing.assert_array_equal(loop.predict(_target(frames[3])).color,
                                  make_predictor("flow2d").predict(frames[2:5:2], _target(frames[3])).color)
    cut = loop.submit(frames[4], restart=True)  # a camera cut: only the new frame, the fallback again
    assert [f.index for f in cut.frames] == [4] and cut.fallback == "history"
    loop.restart()
    assert loop.prepared is None and loop.submit(frames[4]).fallback == "history"


def test_load_replaces_the_history_and_the_fallback_needs_one_frame():
    frames, _ = two_layer_sequence(3, width=48, height=32)
    loop = PredictionLoop(make_predictor("flow2d"), fallback=Repeat())
    assert loop.load(frames[:1]).predictor.name == "repeat"
    assert loop.load(frames[:2]).predictor.name == "flow2d"
    with pytest.raises(ValueError, match="must need one"):
        PredictionLoop(make_predictor("reproject"), fallback=make_predictor("flow2d"))
