"""Frames handed out as textures (engine/geometry/backends/gl/texture.py, ``Target.resident``,
``Session.predict_texture``) against the numpy output they stand in for.

Tolerances: ``rgba32f`` and ``srgb8`` hold the numpy output exactly (the float colour as it is; the codes of
``encode8``, bit for bit); ``rgba16f`` within one half-float step (relative 2^-10 above 2^-14: GL leaves the
driver to round or truncate, llvmpipe truncates).
"""
from __future__ import annotations

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.encoding import encode8
from engine.predict import Target, make_predictor
from engine.runtime.session import Session, SessionConfig
from tests.synthetic import two_layer_sequence, turned_pose, with_vectors

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)

W, H = 96, 64


def _half_close(got: np.ndarray, want: np.ndarray) -> bool:
    return bool((np.abs(got - want) <= 2.0 ** -10 * np.maximum(np.abs(want), 2.0 ** -14)).all())


def _session(method: str, backend: str = "gl", **config) -> tuple[Session, list]:
    frames, objects = two_layer_sequence(6, width=W, height=H, camera_speed=0.03, object_speed=0.12)
    session = Session(SessionConfig(width=W, height=H, method=method, **config), backend=backend)
    for i in (1, 3):
        f = with_vectors(frames, objects, i - 2, i) if i > 1 else frames[i]
        color, depth = (f.color[::-1], f.depth[::-1]) if config.get("flip_rows") else (f.color, f.depth)
        vectors = f.motion_vectors if i > 1 and method == "mvec" else None  # mvec runs without flip_rows here
        session.submit(color, depth, f.camera.world_to_camera, f.camera.intrinsics, f.time, motion_vectors=vectors)
    return session, frames


@pytest.mark.parametrize("method", ["reproject", "mvec"])
def test_a_texture_holds_what_predict_returns(method):
    session, frames = _session(method)
    target = frames[5].camera
    want = session.predict(target.world_to_camera, target.intrinsics, frames[5].time)
    assert want.method == method and want.fallback is None
    for fmt in ("rgba32f", "rgba16f", "srgb8"):
        out = session.predict_texture(target.world_to_camera, target.intrinsics, frames[5].time, format=fmt)
        tex = out.texture
        assert (out.method, out.fallback, out.frame) == (method, None, want.frame)
        assert tex.size == (W, H) and tex.format == fmt and tex.valid and isinstance(tex.glo, int) and tex.glo > 0
        assert tex.color_space == ("srgb" if fmt == "srgb8" else "linear")
        got = tex.read()
        if fmt == "rgba32f":
            np.testing.assert_array_equal(got, want.color)
        elif fmt == "srgb8":
            np.testing.assert_array_equal(got, encode8(want.color))
        else:
            assert _half_close(got, want.color)
        assert "readback" not in out.gpu_ms and {"warp", "fill"} <= set(out.gpu_ms)  # nothing came back


def test_texture_rows_are_gls_and_a_cpu_made_frame_is_uploaded():
    """Texel row 0 is the picture's bottom, whatever flip_rows says (read() gives rows top to bottom); a camera
    cut's frame (repeat, made on the CPU) is uploaded into the texture."""
    session, frames = _session("reproject", flip_rows=True)
    cam = frames[5].camera
    want = session.predict(cam.world_to_camera, cam.intrinsics, frames[5].time)
    got = session.predict_texture(cam.world_to_camera, cam.intrinsics, frames[5].time, format="rgba32f")
    np.testing.assert_array_equal(got.texture.read(), want.color[::-1])  # the caller's rows are bottom-up
    turned = turned_pose(0.0, np.radians(90.0)) @ cam.world_to_camera
    cut = session.predict_texture(turned, cam.intrinsics, frames[5].time, format="rgba32f")
    assert cut.fallback == "camera_cut" and cut.method == "repeat"
    np.testing.assert_array_equal(cut.texture.read(), frames[3].color)


def test_a_texture_lives_until_two_more_are_made_or_it_is_released():
    session, frames = _session("reproject")
    cam = frames[5].camera
    first, second, third = (session.predict_texture(cam.world_to_camera, cam.intrinsics, frames[5].time + dt)
                            for dt in (0.0, 0.01, 0.02))
    assert not first.texture.valid and second.texture.valid and third.texture.valid
    with pytest.raises(InputError, match="reused by a later frame"):
        first.texture.read()
    second.texture.release()
    assert not second.texture.valid and third.texture.valid
    session.release_textures()
    assert not third.texture.valid


def test_textures_need_the_gl_backend_and_a_known_format():
    session, frames = _session("reproject", backend="cpu")
    cam = frames[5].camera
    with pytest.raises(InputError, match="textures need the gl backend: this session runs on cpu") as err:
        session.predict_texture(cam.world_to_camera, cam.intrinsics, frames[5].time)
    assert "\n" not in str(err.value)
    gl_session, _ = _session("reproject")
    with pytest.raises(InputError, match="rgba16f, rgba32f, srgb8"):
        gl_session.predict_texture(cam.world_to_camera, cam.intrinsics, frames[5].time, format="rgb565")


def test_a_resident_target_leaves_the_prediction_on_the_gpu():
    """``Target(resident=True)``: on gl the predictor returns the frame as GPU buffers (``Prediction.resident``),
    equal to what it reads back otherwise; on cpu it returns host arrays; it cannot be 8-bit."""
    frames, objects = two_layer_sequence(6, width=W, height=H, camera_speed=0.03, object_speed=0.12)
    history = [frames[1], with_vectors(frames, objects, 1, 3)]
    gl, cpu = make_predictor("mvec", objects, backend="gl"), make_predictor("mvec", objects, backend="cpu")
    state = gl.prepare(history)
    host = gl.render(state, Target(frames[5].camera, frames[5].time, 5))
    kept = gl.render(state, Target(frames[5].camera, frames[5].time, 5, resident=True))
    assert kept.color is None and kept.holes is None and kept.encoding == "linear"
    color, holes = kept.resident.read()
    np.testing.assert_array_equal(color, host.color)
    np.testing.assert_array_equal(holes, host.holes)
    on_cpu = cpu.render(cpu.prepare(history), Target(frames[5].camera, frames[5].time, 5, resident=True))
    assert on_cpu.resident is None and on_cpu.color.shape == (H, W, 3)
    with pytest.raises(InputError, match="a frame left on the GPU is linear"):
        Target(frames[5].camera, frames[5].time, 5, encoding="srgb8", resident=True)
