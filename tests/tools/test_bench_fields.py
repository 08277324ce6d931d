"""tools.bench_fields' timing without the readback: the warm-up before the timed frames; the motion-vector pass's
timing."""
import numpy as np
import pytest

from engine.fields import gl as glfield
from engine.fields.dynamic import COHERENCE, field_motion_vectors
from tools.bench_fields import dispatch_times


class _Clock:
    """A renderer whose frames each take ``seconds``; records how many frames each call drew."""

    def __init__(self, seconds: float):
        self.seconds, self.calls = seconds, []

    def dispatch_seconds(self, k, w2c, frames: int = 1) -> list[float]:
        self.calls.append(frames)
        return [self.seconds] * frames


def test_dispatch_times_warms_up_for_the_time_asked_then_times_the_frames_asked():
    r = _Clock(0.01)
    got = dispatch_times(r, None, None, frames=7, warmup_s=0.5)
    assert got == [0.01] * 7
    warm = sum(r.calls) - 7
    assert 50 <= warm < 150 and max(r.calls) <= 50  # at least 0.5 s of frames, in calls of at most 50


def test_dispatch_times_stops_warming_after_a_thousand_frames_and_skips_a_zero_warmup():
    fast = _Clock(1e-6)
    assert len(dispatch_times(fast, None, None, frames=3, warmup_s=10.0)) == 3
    assert 1000 <= sum(fast.calls) - 3 < 1050
    none = _Clock(0.01)
    assert dispatch_times(none, None, None, frames=2, warmup_s=0.0) == [0.01, 0.01] and sum(none.calls) == 2


def test_dispatch_times_stops_timing_once_the_frames_fill_the_budget():
    """A software renderer's slow frames: timed until they add up to the budget, at least one."""
    slow = _Clock(1.0)
    assert dispatch_times(slow, None, None, frames=20, warmup_s=0.0, budget_s=2.0) == [1.0, 1.0]
    assert dispatch_times(_Clock(5.0), None, None, frames=20, warmup_s=0.0, budget_s=2.0) == [5.0]


@pytest.mark.skipif(not glfield.available(), reason="no EGL context with OpenGL 4.3 compute shaders")
def test_the_vector_timing_draws_the_frame_and_the_vectors_mvec_is_fed(tmp_path):
    """``_vector_outs`` times the GL renderer with its motion-vector pass: the colour of the plain render, and the
    numpy oracle's vectors (coherence as for ``mvec``) to the earlier time; at the range's start, a later one."""
    from engine.fields.dynamic import load_dynamic_field
    from engine.fields.gldynamic import GlDynamicRenderer
    from tests.fields.test_field_motion import camera
    from tools.bench_fields import VECTOR_TIME_STEP, _vector_outs
    from tools.programmed_field import write_export

    assets = load_dynamic_field(write_export(tmp_path / "box"))
    cam = camera(0.0, size=24)
    t0, t1 = assets.time_range
    for t, earlier in ((t0 + 0.5 * (t1 - t0), t0 + (0.5 - VECTOR_TIME_STEP) * (t1 - t0)),
                       (t0, t0 + VECTOR_TIME_STEP * (t1 - t0))):
        outs = _vector_outs(assets, 24, 24, cam.intrinsics, cam.world_to_camera, t, repeat=2)
        out, walls, cpus, _ = outs["gl + motion vectors"]
        assert len(walls) == len(cpus) == 2 and min(walls) > 0
        with GlDynamicRenderer(assets, 24, 24) as r:
            plain = r.render(cam.intrinsics, cam.world_to_camera, t)
        np.testing.assert_array_equal(out["color"], plain["color"])
        want = field_motion_vectors(assets, cam.intrinsics, cam.world_to_camera, out["depth"], t,
                                    cam.world_to_camera, earlier, coherence=COHERENCE)
        got = out["motion_vectors"]
        assert np.array_equal(np.isnan(got), np.isnan(want)) and np.isfinite(want).any()
        np.testing.assert_allclose(got[np.isfinite(want)], want[np.isfinite(want)], atol=1e-3)
        assert np.nanmax(np.abs(want)) > 0.02  # the box moved between the two times (about 0.1 px at 24 px)
