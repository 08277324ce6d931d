"""The GL backend's two splats side by side on the frame path (``GlFrameWarper``: warp + hole fill, output left
on the GPU), per frame size: GPU ms per stage and per pass, wall ms, the splat's work buffers, and whether both
give the same bits.

``python -m tools.bench_gl_warp [--sizes 1920x1080,3840x2160] [--repeats 20] [--frames 4]
[--out out/bench_backends] [--json FILE]``

The frame is ``tools.bench_backends``' scene (the fast held-out scene, rendered once at the first size and
cached under ``--out``): its first frame warped to the second frame's camera, once by the camera alone (what
``reproject`` warps) and once with the frame's true object flow too (what ``mvec`` warps: its points moved).
The other sizes resample that frame (nearest pixel, intrinsics and flow scaled), so a 4K run needs no 4K
render. Per (size, case, splat of ``engine.geometry.backends.gl.splat.SPLATS``): one warm-up, then
``--repeats`` warps with the GL stage queries (medians of ``warp`` and ``fill``; wall ms per warp, queries
read), then ``--repeats`` under ``GlContext.pass_timing`` (GPU ms per pass and warp: shares, as a query per
dispatch adds waits of its own), the bytes of the splat's work buffers (``splat_bytes``), and the largest
difference from the atomic splat's filled frame (0: the same bits). On a software renderer (Mesa llvmpipe)
the stage queries time nothing (``-``) and the passes are the clock ms of the CPU's execution of each.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from engine.geometry.backends.gl import GlFrameWarper, shared_context
from engine.geometry.backends.gl.splat import SPLATS, splat_bytes
from engine.geometry.camera import reprojection_matrix
from engine.io.rgbd import read_sequence
from tools.bench_backends import SCENE, gl_or_exit, parse_sizes
from tools.heldout import render_set, write_json

CASES = ("camera", "object_flow")


def resampled(frame, size: tuple[int, int]):
    """(colour, depth, object flow, intrinsics) of ``frame`` resampled to ``size`` = (width, height) by the
    nearest pixel centre (the frame itself at its own size)."""
    h, w = frame.depth.shape
    width, height = size
    ys = np.minimum(((np.arange(height) + 0.5) * h / height).astype(int), h - 1)
    xs = np.minimum(((np.arange(width) + 0.5) * w / width).astype(int), w - 1)
    scale = np.array([width / w, height / h], np.float32)
    flow = np.ascontiguousarray(frame.object_flow[ys][:, xs] * scale)
    k = np.diag([width / w, height / h, 1.0]) @ frame.camera.intrinsics
    return (np.ascontiguousarray(frame.color[ys][:, xs]), np.ascontiguousarray(frame.depth[ys][:, xs]), flow, k)


def bench_splat(splat: str, color, depth, flow, k, t_src, t_dst, repeats: int) -> dict:
    """One splat on one frame (see the module docstring); ``flow`` None warps by the camera alone."""
    gl = shared_context()
    warper = GlFrameWarper(splat=splat)
    image = warper.upload(color, depth)
    moved = None if flow is None else warper.upload_flow(flow)

    def warp(gpu_ms=None):
        return warper.warp_and_fill(image, k, t_src, k, t_dst, moved, gpu_ms=gpu_ms, readback=False)

    filled = warp().read()[0]  # warm-up: programs compiled, buffers grown
    stages, wall = [], []
    for _ in range(repeats):
        gpu_ms: dict = {}
        start = time.perf_counter()
        warp(gpu_ms)
        wall.append(1e3 * (time.perf_counter() - start))
        stages.append(gpu_ms)
    passes: dict = {}
    with gl.pass_timing(passes):
        for _ in range(repeats):
            warp()
    matrix = reprojection_matrix(k, t_src, k, t_dst)
    moved_buffer = None if moved is None else (moved.buffer, moved.channels)

    def splat_alone() -> float:  # the splat's passes alone, until the context finished them
        start = time.perf_counter()
        warper.splat(image, matrix, moved=moved_buffer)
        gl.ctx.finish()
        return 1e3 * (time.perf_counter() - start)
    splat_wall = [gl.call(splat_alone) for _ in range(repeats)]
    h, w = depth.shape
    work = splat_bytes(splat, (h + 2) * (w + 2), h * w)
    warper.release()
    return {"gpu_stage_ms": {name: float(statistics.median(s.get(name, 0.0) for s in stages))
                             for name in sorted({n for s in stages for n in s})},
            "wall_ms": float(statistics.median(wall)), "splat_wall_ms": float(statistics.median(splat_wall)),
            "passes": {name: (calls / repeats, ms / repeats) for name, (calls, ms) in sorted(passes.items())},
            "work_bytes": work, "filled": filled}


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1920x1080,3840x2160")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--frames", type=int, default=4, help="frames of the rendered scene (its cache key)")
    parser.add_argument("--out", default="out/bench_backends")
    parser.add_argument("--json", default=None)
    args = parser.parse_args(argv)
    hardware, renderer = gl_or_exit("bench_gl_warp")
    sizes = parse_sizes(args.sizes)
    name, overrides, preset = SCENE
    sequence = read_sequence(render_set(args.out, name, overrides, *sizes[0], max(2, args.frames), preset))
    frame, target = sequence[0], sequence[1]
    t_src, t_dst = frame.camera.world_to_camera, target.camera.world_to_camera
    doc = {"renderer": renderer, "hardware": hardware, "scene": name, "repeats": args.repeats, "runs": []}
    pass_ms = "GPU ms, a query each" if hardware else "software renderer: clock ms between finishes"
    print(f"\nMedians of {args.repeats} warps. warp, fill: GPU ms (GL stage queries; - on a software renderer); "
          f"splat wall: the splat's passes alone until finished; warp + fill wall: a warp_and_fill call, output left "
          f"on the GPU, queries read; work: the splat's work buffers; diff: largest difference of the filled frame "
          f"from the atomic splat's; passes: dispatches x ms ({pass_ms})\n\n| size | case | splat | warp GPU ms | "
          f"fill GPU ms | splat wall ms | warp + fill wall ms | work MB | diff | passes |\n"
          f"|---|---|---|---|---|---|---|---|---|---|")
    for size in sizes:
        color, depth, flow, k = resampled(frame, size)
        for case in CASES:
            runs = {splat: bench_splat(splat, color, depth, flow if case == "object_flow" else None, k, t_src,
                                       t_dst, args.repeats) for splat in SPLATS}
            reference = runs["atomic"]["filled"]
            for splat, run in runs.items():
                diff = float(np.abs(run.pop("filled") - reference).max())
                run.update(size=list(size), case=case, splat=splat, max_diff_from_atomic=diff)
                doc["runs"].append(run)
            for splat in SPLATS:
                run = runs[splat]
                stage = {n: f"{v:.3f}" if hardware else "-" for n, v in run["gpu_stage_ms"].items()}
                passes = ", ".join(f"{n} {c:.0f}x {ms:.3f}" for n, (c, ms) in run["passes"].items())
                print(f"| {size[0]}x{size[1]} | {case} | {splat} | {stage.get('warp', '-')} | {stage.get('fill', '-')} "
                      f"| {run['splat_wall_ms']:.2f} | {run['wall_ms']:.2f} | "
                      f"{sum(run['work_bytes'].values()) / 1e6:.1f} | {run['max_diff_from_atomic']:.1e} | {passes} |",
                      flush=True)
    write_json(args.json, doc)


if __name__ == "__main__":
    main()
