"""The calling thread's CPU time of each of ``mvec``'s steps, on the CPU backend (issue 42's cost, the serial part).

``python -m tools.profile_mvec_steps [--out out/bench_mvec] [--size 960x540] [--frames 16] [--k 2]
[--methods mvec[fallback=false],reproject] [--sequences spin4101] [--repeats 5] [--json FILE]``

``tools.profile_mvec`` times whole methods (and each stage's wall time); this tool splits the calling thread's
CPU time (``time.thread_time``) further, for one method at a time, warm (one pass first), ``--repeats`` passes
over every evaluation pair of the sequence in order (as a stream prepares them: frame n-k's velocity is reused).
It wraps, for the run, the functions that ``engine.predict.mvec`` and the CPU backend's render call
(``fn:<name>``: ``scene_velocity``, ``moving_points``, ``motion_components``, ``find_parts``, ``part_paths``,
``kept_part_motion``, ``forward_warp_moved_frame`` (the warp of a moving frame, its extrapolation inside),
``forward_warp_frame``, ``fill_holes`` ..) and the predictor's timed stages (``stage:<name>``: ``velocity``,
``rigid.groups`` .., ``warp``, ``fill``). Per entry it prints ms per predicted frame, wall and calling thread,
and calls per frame; ``total`` is the whole prepare and render. The split kernels' other threads are not in the
thread figures: on a quiet machine with a core per kernel thread and even shares, the calling thread is what the
wall time waits for. A step that runs beside the calling thread (``kernels.run_beside``: ``previous_positions``)
is timed on the thread that runs it, outside its stage's calling-thread time.
"""
from __future__ import annotations

import time
from collections import defaultdict
from contextlib import contextmanager

import engine.predict.base as base
import engine.predict.mvec as mvec
from engine.predict import make_predictor, split_methods
from tools.heldout import timing_cases, write_json
from tools.profile_mvec import named_sequences, sequences_parser

#: the functions timed, by module: what ``mvec``'s passes call, and the CPU backend's render
STEPS = {mvec: ("scene_velocity", "velocity_change", "velocity_change_args", "upsample_motion_vectors",
                "moving_points", "motion_components", "previous_positions", "refined_before", "find_parts",
                "part_paths", "apply_parts", "hindcast_keeps", "kept_part_motion"),
         base: ("fill_holes",),
         base.geometry: ("forward_warp_frame", "forward_warp_moved_frame")}


class StepClock:
    """Wall and calling-thread seconds and calls per name, while ``installed``: the ``STEPS`` functions wrapped
    and ``Timer``'s stages recorded too."""

    def __init__(self) -> None:
        self.wall: dict[str, float] = defaultdict(float)
        self.cpu: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)

    def add(self, name: str, wall: float, cpu: float) -> None:
        self.wall[name] += wall
        self.cpu[name] += cpu
        self.calls[name] += 1

    def clear(self) -> None:
        for table in (self.wall, self.cpu, self.calls):
            table.clear()

    def _wrapped(self, fn, name: str):
        def timed(*args, **kwargs):
            wall, cpu = time.perf_counter(), time.thread_time()
            try:
                return fn(*args, **kwargs)
            finally:
                self.add(name, time.perf_counter() - wall, time.thread_time() - cpu)
        return timed

    @contextmanager
    def installed(self):
        saved = [(module, name, getattr(module, name)) for module, names in STEPS.items() for name in names
                 if hasattr(module, name)]
        saved.append((base.Timer, "__call__", base.Timer.__call__))
        clock = self

        @contextmanager
        def stage(timer, name: str):
            wall, cpu = time.perf_counter(), time.thread_time()
            try:
                yield
            finally:
                seconds = time.perf_counter() - wall
                timer.into[name] = timer.into.get(name, 0.0) + 1e3 * seconds
                clock.add(f"stage:{name}", seconds, time.thread_time() - cpu)

        try:
            for module, name, fn in saved[:-1]:
                setattr(module, name, self._wrapped(fn, f"fn:{name}"))
            base.Timer.__call__ = stage
            yield self
        finally:
            for module, name, fn in saved:
                setattr(module, name, fn)


def profile_steps(sequence, method: str, k: int, repeats: int) -> dict:
    """``{"frames", "total_ms": [wall, thread], "ms": {name: [wall, thread, calls]}}`` per predicted frame."""
    predictor = make_predictor(method, sequence.objects)
    cases = timing_cases(sequence, k)
    clock = StepClock()

    def run() -> int:
        frames = 0
        for history, targets in cases:
            state = predictor.prepare(history[-3:])
            for target in targets:
                predictor.render(state, target)
                frames += 1
        return frames

    with clock.installed():
        run()  # warm: kernels compiled, the previous velocity cached
        clock.clear()
        wall, cpu = time.perf_counter(), time.thread_time()
        frames = sum(run() for _ in range(repeats))
        wall, cpu = time.perf_counter() - wall, time.thread_time() - cpu
    per = 1e3 / frames
    return {"frames": frames, "total_ms": [wall * per, cpu * per],
            "ms": {name: [clock.wall[name] * per, clock.cpu[name] * per, clock.calls[name] / frames]
                   for name in sorted(clock.wall, key=lambda n: (n.split(":")[0], -clock.cpu[n]))}}


def main(argv=None) -> None:
    parser = sequences_parser(__doc__, "960x540", "2", "spin4101")
    parser.add_argument("--methods", default="mvec[fallback=false],reproject")
    parser.add_argument("--repeats", type=int, default=5)
    args = parser.parse_args(argv)
    rows = []
    for name, sequence, ks in named_sequences(args):
        for k in ks:
            for method in split_methods(args.methods):
                result = profile_steps(sequence, method, k, args.repeats)
                wall, cpu = result["total_ms"]
                print(f"\n{name} k={k} {method}: ms per predicted frame (wall / calling thread), "
                      f"{result['frames']} frames: total {wall:.2f} / {cpu:.2f}")
                for step, (w, c, calls) in result["ms"].items():
                    print(f"  {step:28s} {w:7.3f} {c:7.3f}  calls/frame {calls:.2f}")
                rows.append({"sequence": name, "k": k, "method": method, **result})
    write_json(args.json, {"repeats": args.repeats, "rows": rows})


if __name__ == "__main__":
    main()
