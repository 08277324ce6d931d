"""Benchmark of the compiled kernels (``engine.geometry.kernels``) against their numpy references, in one run.

``python -m tools.bench_kernels [--size 960x540] [--repeats 15] [--json FILE]`` prints, per operation on a
generated frame (sky band, a near disc, a moving camera: ``tests``-free, numpy only), the median
milliseconds of the numpy reference and of the compiled path, their ratio and the largest difference
between their outputs (0 where they are bit-identical). The first compiled call (the JIT, or the load from
the on-disk cache) is excluded and reported separately.
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

from engine import geometry as g
from engine.core.colorspace import encode8_reference
from engine.geometry import holefill, reference, splat


def _scene(h: int, w: int):
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    depth = (4.0 + 2.0 * np.sin(xx / w * 6.0) + yy / h * 3.0).astype(np.float32)
    disc = (xx - 0.4 * w) ** 2 + (yy - 0.55 * h) ** 2 < (0.15 * h) ** 2
    depth[disc] = 1.5
    depth[:h // 8] = np.inf
    color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
    k = np.array([[0.9 * w, 0, w / 2], [0, 0.9 * w, h / 2], [0, 0, 1]], np.float64)
    angle = np.radians(1.1)
    t_dst = np.eye(4)
    t_dst[:3, :3] = [[np.cos(angle), 0, np.sin(angle)], [0, 1, 0], [-np.sin(angle), 0, np.cos(angle)]]
    t_dst[:3, 3] = (0.1, 0.0, 0.0)
    return color, depth, k, t_dst


def _max_diff(a, b) -> float:
    out = 0.0
    for x, y in zip(a, b):
        x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
        same_inf = np.isinf(x) & np.isinf(y) & (np.sign(x) == np.sign(y))
        with np.errstate(invalid="ignore"):  # inf - inf where both are the same infinity: counted as 0
            out = max(out, float(np.max(np.where(same_inf, 0.0, np.abs(x - y)), initial=0.0)))
    return out


def _time(fn, repeats: int) -> list[float]:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(1e3 * (time.perf_counter() - start))
    return times


def cases(h: int, w: int) -> list[tuple[str, callable, callable, callable]]:
    """(name, compiled call, reference call, output flattener) per operation."""
    color, depth, k, t_dst = _scene(h, w)
    eye = np.eye(4)
    mpi1, mpi4 = g.build_mpi(color, depth, 1), g.build_mpi(color, depth, 4)
    warp_args = lambda m: (m, k, eye, k, t_dst, None, (h, w), g.DEFAULT_SHARPNESS)  # noqa: E731
    warped, _ = splat.forward_warp_mpi_unchecked(*warp_args(mpi1))
    holes = warped.alpha[0] <= 0
    warped_depth = np.where(holes, np.float32(np.inf), warped.depth[0])
    flat = lambda out: tuple(out[0]) + (out[1],)  # noqa: E731
    same = lambda out: out  # noqa: E731
    return [
        ("forward_warp_mpi Z=1", lambda: splat.forward_warp_mpi_unchecked(*warp_args(mpi1)),
         lambda: reference.forward_warp_mpi_reference(*warp_args(mpi1)), flat),
        ("forward_warp_mpi Z=4", lambda: splat.forward_warp_mpi_unchecked(*warp_args(mpi4)),
         lambda: reference.forward_warp_mpi_reference(*warp_args(mpi4)), flat),
        ("build_mpi Z=4", lambda: g.build_mpi(color, depth, 4, mpi4.plane_depths),
         lambda: reference.build_mpi_reference(color, depth, 4, mpi4.plane_depths), lambda out: tuple(out)),
        ("composite Z=4", lambda: g.composite(mpi4), lambda: reference.composite_reference(mpi4), same),
        ("hole-fill row sources", lambda: (holefill.row_sources(warped_depth, holes),),
         lambda: (reference.row_sources_reference(warped_depth, holes),), same),
        ("seen_before", lambda: (g.seen_before(depth, k, t_dst, k, eye, (h, w)),),
         lambda: (reference.seen_before_reference(depth, k, t_dst, k, eye, (h, w)),), same),
        ("8-bit display encoding", lambda: (__import__("engine.predict.dis").predict.dis.encode8(color * 1.5),),
         lambda: (encode8_reference(color * 1.5),), same),
    ]


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", default="960x540", help="WIDTHxHEIGHT of the generated frame")
    parser.add_argument("--repeats", type=int, default=15)
    parser.add_argument("--json", type=Path, help="write the table as JSON")
    args = parser.parse_args(argv)
    w, h = (int(v) for v in args.size.lower().split("x"))
    rows = []
    print(f"| operation ({w}x{h}) | numpy ms | compiled ms | x faster | max difference | first call ms |")
    print("| --- | --- | --- | --- | --- | --- |")
    for name, fast, slow, outputs in cases(h, w):
        start = time.perf_counter()
        fast_out = fast()
        first = 1e3 * (time.perf_counter() - start)
        diff = _max_diff(outputs(fast_out), outputs(slow()))
        t_ref, t_fast = statistics.median(_time(slow, args.repeats)), statistics.median(_time(fast, args.repeats))
        rows.append({"operation": name, "numpy_ms": t_ref, "compiled_ms": t_fast, "speedup": t_ref / t_fast,
                     "max_difference": diff, "first_call_ms": first})
        print(f"| {name} | {t_ref:.1f} | {t_fast:.1f} | {t_ref / t_fast:.1f} | {diff:.3g} | {first:.0f} |")
    if args.json:
        args.json.write_text(json.dumps({"size": [w, h], "repeats": args.repeats, "rows": rows,
                                         "command": f"python -m tools.bench_kernels --size {args.size} "
                                                    f"--repeats {args.repeats}"}, indent=1))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
