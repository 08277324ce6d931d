"""The live mode of the scene renderer (engine/scenegen/live.py) against the ground-truth mode it stands in for.

Tolerances (llvmpipe measured them at 0 for colour and depth and at most 1.4e-3 px for the vectors):
- colour and depth: the live pass runs the ground-truth mode's shading (``glsl.SHADING``) and the same vertex
  transform, so the same fragments with the same inputs: equal up to float32 rounding of a compiler that
  schedules the two programs differently (1e-5 absolute on colour, 1e-6 relative on depth); surfaces and sky
  exactly the same pixels.
- vectors: the ground truth computes them in float64 from the float32 depth at pixel centres; the shader
  interpolates the previous camera-space point in float32 and divides in float32 (24-bit mantissas: about 1e-3
  px at these sizes). 1/256 px is 8x below the 1/32 px within which ``mvec`` calls a surface static, so both
  give ``mvec`` the same static and moving pixels; pixels without a vector are exactly the same.
"""
from __future__ import annotations

import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry.backends import gl_renderer
from engine.geometry.motion import camera_motion_vectors
from engine.scenegen import SceneRenderer, make_scene
from engine.scenegen.presets import preset_config

pytestmark = pytest.mark.skipif(not gl_renderer()[0], reason="no OpenGL 4.5 context (EGL) here")

VECTOR_TOLERANCE = 1.0 / 256.0
#: Relative vector tolerance added on a GPU: on an H200 (2026-11-30) 3 of 30720 vector components, near 100 px
#: (k = 4 back), were 5.0e-3 px (5.0e-5 of their length) from the ground-truth mode's; llvmpipe meets the
#: absolute tolerance alone.
VECTOR_RTOL = 1e-4 if gl_renderer()[1] else 0.0


def _scene(**overrides):
    # fast preset, seed 1: two spinning objects among five moving ones, and an orbiting camera (its turn moves
    # the sky too)
    return make_scene(preset_config("fast", seed=1, width=160, height=96, num_frames=12, supersample=1,
                                    render_noise=0.0, camera_path="orbit", **overrides))


def test_live_colour_depth_and_vectors_equal_the_ground_truth_mode():
    from engine.scenegen.live import LiveSceneRenderer

    scene = _scene()
    spinning = [o.id for o in scene.objects if o.motion.kind == "spin"]
    assert len(spinning) == 2
    with SceneRenderer(scene) as truth, LiveSceneRenderer(scene) as live:
        for index, previous in ((2, None), (5, 3), (10, 6)):  # one frame back, and k = 2, 4 frames back
            want = truth.render_frame(index)
            vectors = truth.motion_vectors(index, want.depth, want.object_id, want.camera,
                                           index - 1 if previous is None else previous)
            got = live.render(index, previous).frame()
            assert got.index == index and got.time == want.time
            np.testing.assert_array_equal(got.camera.world_to_camera, want.camera.world_to_camera)
            np.testing.assert_allclose(got.color, want.color, rtol=0, atol=1e-5)
            surface = np.isfinite(want.depth)
            assert (~surface).sum() > 1000  # sky, whose vectors come from the camera's turn alone
            assert np.array_equal(np.isfinite(got.depth), surface) and np.isinf(got.depth[~surface]).all()
            np.testing.assert_allclose(got.depth[surface], want.depth[surface], rtol=1e-6, atol=0)
            missing = np.isnan(vectors).any(axis=2)
            assert np.array_equal(np.isnan(got.motion_vectors).any(axis=2), missing)
            np.testing.assert_allclose(got.motion_vectors[~missing], vectors[~missing], rtol=VECTOR_RTOL,
                                       atol=VECTOR_TOLERANCE)
            # the frames test what they should: the camera moves and the spinning objects move on their own
            static = camera_motion_vectors(want.depth, want.camera, live.scene.camera_at(got.index - 1 if previous
                                                                                         is None else previous))
            assert np.nanmedian(np.abs(static)) > 0.5
            spins = np.isin(want.object_id, spinning)
            assert spins.sum() > 50
            assert np.abs(got.motion_vectors[spins] - static[spins]).max() > 1.0


def test_live_frames_stay_on_the_gpu_and_are_the_backends_frame_layout():
    """The renderer draws on the frame backend's shared context: a live frame's buffers are read back only when
    asked, and they are the layout the warps take (rows top to bottom, +inf sky)."""
    from engine.geometry.backends.gl import shared_context
    from engine.scenegen.live import LiveSceneRenderer

    scene = _scene(shadows=False)
    with LiveSceneRenderer(scene) as live:
        frame = live.render(4, 2)
        assert frame.image.gl is shared_context() and frame.shape == (96, 160) and frame.previous == 2
        host = frame.frame(color=False)
        assert host.color is None and host.depth.shape == (96, 160) and host.motion_vectors.shape == (96, 160, 2)
        np.testing.assert_array_equal(frame.read_color(), frame.frame().color)
    with SceneRenderer(scene) as truth:
        want = truth.render_frame(4)
    np.testing.assert_array_equal(host.depth, want.depth)


def test_live_mode_refuses_what_it_does_not_draw():
    from engine.scenegen.live import LiveSceneRenderer

    with pytest.raises(InputError, match="supersample must be 1"):
        LiveSceneRenderer(make_scene(preset_config("gentle", seed=1, width=32, height=24, supersample=2)))
    with pytest.raises(InputError, match="render_noise must be 0"):
        LiveSceneRenderer(make_scene(preset_config("fast", seed=1, width=32, height=24, supersample=1)))
    with LiveSceneRenderer(make_scene(preset_config("gentle", seed=1, width=32, height=24, num_frames=3,
                                                    supersample=1))) as live:
        with pytest.raises(InputError, match="index"):
            live.render(3)
