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
    assert got == [0.01] * 7 and r.calls[-1] == 7
    warm = sum(r.calls[:-1])
    assert 50 <= warm < 150 and max(r.calls[:-1]) <= 50  # at least 0.5 s of frames, in calls of at most 50


def test_dispatch_times_stops_warming_after_a_thousand_frames_and_skips_a_zero_warmup():
    fast = _Clock(1e-6)
    dispatch_times(fast, None, None, frames=3, warmup_s=10.0)
    assert 1000 <= sum(fast.calls[:-1]) < 1050
    none = _Clock(0.01)
    assert dispatch_times(none, None, None, frames=2, warmup_s=0.0) == [0.01, 0.01] and none.calls == [2]
