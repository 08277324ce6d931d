"""tools.bench_fields' timing without the readback: the warm-up before the timed frames."""
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
