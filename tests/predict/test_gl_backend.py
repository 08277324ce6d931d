"""Predictors on the GL backend against the same predictors on the CPU (their oracle), and the choice of
backend (``make_predictor(..., backend=)``, ``engine.geometry.backends.resolve_backend``).

Tolerance: the predicted colour within 1e-3 of max(1, value) on >= 99.5 % of the pixels and the holes equal
on >= 99.9 % (the GL splat's sums are exact fixed point where the CPU's are float64:
tests/geometry/test_gl_frame.py).
"""
from __future__ import annotations


import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry import backends
from engine.geometry.backends import gl as glb
from engine.predict import GlFrames, Target, make_predictor
from engine.predict.base import Timer
from tests.synthetic import two_layer_sequence, with_vectors

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


def _target(frame):
    return Target(frame.camera, frame.time, frame.index)


def _close(a, b) -> float:
    return float(np.mean((np.abs(a - b) <= 1e-3 * np.maximum(1.0, np.abs(a))).all(axis=-1)))


@pytest.mark.parametrize("method", ["reproject", "flow2d", "flow2d[estimator=corr]", "mvec", "oracle", "decomp",
                                    "decomp[estimator=gl]", "decomp[motion=truth]"])
def test_gl_predicts_what_the_cpu_predicts(method):
    frames, objects = two_layer_sequence(8, width=160, height=96, camera_speed=0.03, object_speed=0.12)
    history = [frames[2], with_vectors(frames, objects, 2, 4)]
    cpu = make_predictor(method, objects, backend="cpu")
    gl = make_predictor(method, objects, backend="gl")
    assert (cpu.backend, gl.backend) == ("cpu", "gl")
    cpu_state, gl_state = cpu.prepare(history), gl.prepare(history)
    for truth in (frames[5], frames[6], frames[7]):  # one preparation, several predicted frames
        a, b = cpu.render(cpu_state, _target(truth)), gl.render(gl_state, _target(truth))
        assert np.isfinite(b.color).all() and b.color.dtype == np.float32
        assert _close(a.color, b.color) >= 0.995 and np.mean(a.holes == b.holes) >= 0.999
        assert {"warp", "fill", "readback"} <= set(b.gpu_ms) and not a.gpu_ms
        if method not in ("oracle", "decomp[motion=truth]"):  # frame, flow or motion went up once, in prepare
            assert "upload" not in b.stages_ms
        if method == "mvec":  # the motion is extrapolated on the GPU (on the CPU: in the warp's first pass)
            assert "motion" in b.gpu_ms and "motion" not in a.stages_ms
    assert "upload" in gl_state.stages_ms
    if method == "flow2d[estimator=corr]":  # the RGB-D network's frame n-k (colour and depth) warped on the GPU
        assert "warp" in gl_state.gpu_ms and "warp" not in cpu_state.gpu_ms


def test_a_frame_is_uploaded_once():
    """``GlFrames.resident`` keeps the two frames asked for last: frame n of one preparation is frame n-k of the
    next, and ``flow2d`` on ``gl`` uploads one frame per rendered frame."""
    frames, _ = two_layer_sequence(5, width=32, height=24)
    backend = GlFrames()
    timer = Timer()
    first = backend.resident(frames[0], timer)
    assert "upload" in timer.into and backend.resident(frames[0], Timer()) is first
    backend.resident(frames[1], Timer())
    backend.resident(frames[2], Timer())  # frames[0] was asked for least recently: dropped
    again = Timer()
    assert backend.resident(frames[0], again) is not first and "upload" in again.into
    predictor = make_predictor("flow2d", backend="gl")
    predictor.prepare([frames[1], frames[2]])
    timer = Timer()
    state = predictor.prepare([frames[2], frames[3]])
    assert state.data.frame.frame is frames[3] and predictor.frames.resident(frames[2], timer).frame is frames[2]
    assert "upload" not in timer.into


def test_methods_without_gl_passes_stay_on_the_cpu():
    for name in ("repeat", "decomp[fill=infill]"):
        assert make_predictor(name, backend="gl").backend == "cpu"


def test_backend_choice():
    runs, hardware, renderer = backends.gl_renderer()
    assert runs and renderer
    assert backends.resolve_backend("cpu") == "cpu" and backends.resolve_backend("gl") == "gl"
    assert backends.resolve_backend("auto") == ("gl" if hardware else "cpu")
    assert make_predictor("reproject").backend == backends.resolve_backend("auto")
    with pytest.raises(InputError) as err:
        make_predictor("reproject", backend="vulkan")
    assert err.value.field == "backend"



def test_flow2d_with_the_gpu_estimator_prepares_on_the_gpu_what_the_cpu_path_prepares():
    frames, objects = two_layer_sequence(8, width=160, height=96, camera_speed=0.03, object_speed=0.12)
    history = [frames[2], frames[4]]
    cpu = make_predictor("flow2d[estimator=gl]", objects, backend="cpu")  # CPU warp and trust, GPU flow
    gl = make_predictor("flow2d[estimator=gl]", objects, backend="gl")    # everything on the GPU
    cpu_state, gl_state = cpu.prepare(history), gl.prepare(history)
    assert gl_state.data.flow_back is None  # the flow stayed on the GPU
    assert {"warp", "flow", "trust"} <= set(gl_state.stages_ms) and {"search", "trust"} <= set(gl_state.gpu_ms)
    a, b = cpu.object_flow(cpu_state), gl.object_flow(gl_state)
    assert b.shape == a.shape and np.isfinite(b).all()
    assert np.mean(np.abs(a - b).max(axis=-1) < 0.05) >= 0.99  # the same lumas but for a rare 8-bit rounding
    moving = frames[4].moving
    assert np.abs(b[moving, 0]).mean() > 1.0  # the square's motion was found and kept
    for truth in (frames[5], frames[6]):
        x, y = cpu.render(cpu_state, _target(truth)), gl.render(gl_state, _target(truth))
        assert _close(x.color, y.color) >= 0.99 and "upload" not in y.stages_ms
    with pytest.raises(InputError) as err:
        make_predictor("flow2d[estimator=raft]")
    assert err.value.field == "estimator"


def test_decomp_with_the_gpu_estimator_prepares_on_the_gpu_what_the_cpu_path_prepares():
    """``decomp[estimator=gl]`` on ``gl``: frame n-k's warp, the flow, its trust rules and the refinement check
    run on the GPU and the flow stays there; only the initial flow is read back, for the network's input. The
    CPU path (the CPU's warp, trust and refinement around the same GPU flow) is its oracle."""
    frames, objects = two_layer_sequence(7, width=192, height=128, camera_speed=0.02, object_speed=0.12,
                                         square_half=0.25)  # a gate box smaller than the frame
    history = [frames[2], frames[4]]
    cpu = make_predictor("decomp[estimator=gl]", objects, backend="cpu")
    gl = make_predictor("decomp[estimator=gl]", objects, backend="gl")
    cpu_state, gl_state = cpu.prepare(history), gl.prepare(history)
    data = gl_state.data
    assert data.boxes == cpu_state.data.boxes and data.network_fraction < 1.0
    assert data.flow is None and {"search", "trust", "refine"} <= set(gl_state.gpu_ms) and not cpu_state.gpu_ms
    assert "refine" in gl_state.stages_ms and "refine_check" in cpu_state.stages_ms
    a, b = cpu.object_flow(cpu_state), gl.object_flow(gl_state)  # b read back from the GPU
    assert b.shape == a.shape and np.isfinite(b).all()
    assert np.mean(np.abs(a - b).max(axis=-1) < 0.05) >= 0.99
    assert np.abs(b[frames[4].moving, 0]).mean() > 1.0  # the square's motion was found and kept
    for truth in (frames[5], frames[6]):
        x, y = cpu.render(cpu_state, _target(truth)), gl.render(gl_state, _target(truth))
        assert _close(x.color, y.color) >= 0.99 and "upload" not in y.stages_ms
    with pytest.raises(InputError) as err:
        make_predictor("decomp[estimator=raft]")
    assert "estimator" in str(err.value)


@pytest.mark.parametrize("size", [(65, 97, 40), (5, 7, 0), (3, 200, 0)])
def test_decomp_with_the_gpu_estimator_on_odd_and_tiny_frames(size):
    """A size that is no multiple of the working-resolution block (blocks of 3: the box takes the rows and
    columns past the last block), frames of a few pixels and a frame 3 px high, the gate off (one box: the
    whole frame): the GPU's boxes give the CPU path's flow and a finite frame."""
    h, w, flow_width = size
    frames, objects = two_layer_sequence(4, width=w, height=h, camera_speed=0.02, object_speed=0.15)
    name = f"decomp[estimator=gl,gate.enabled=false,flow_width={flow_width}]"
    cpu, gl = make_predictor(name, objects, backend="cpu"), make_predictor(name, objects, backend="gl")
    cpu_state, gl_state = cpu.prepare([frames[1], frames[3]]), gl.prepare([frames[1], frames[3]])
    a, b = cpu.object_flow(cpu_state), gl.object_flow(gl_state)
    assert b.shape == (h, w, 2) and np.isfinite(b).all()
    assert np.mean(np.abs(a - b).max(axis=-1) < 0.05) >= 0.95
    out = gl.render(gl_state, _target(frames[3]))
    assert out.color.shape == (h, w, 3) and np.isfinite(out.color).all()
