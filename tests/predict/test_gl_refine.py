"""``decomp``'s boxes on the GPU (``engine.geometry.backends.gl.refine.GlFlowRefine``) against the CPU, their
oracle, on the same inputs: the block-averaged initial flow against ``geometry.downsample_flow``, and the
refinement check against ``refine_box`` (with ``geometry.plane_index`` and ``geometry.seen_before``). The
plane index, the upsampling, both photometric errors (OpenCV's remap), the window means in double, the choice
and the reprojection are the CPU's arithmetic: on llvmpipe the flows are equal to the bit; the tests allow
0.1 % of pixels a hair apart for a GPU driver."""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.refine import GlFlowRefine
from engine.geometry.camera import reprojection_matrix
from engine.geometry.mpi import plane_bounds
from engine.predict.base import Timer
from engine.predict.decomp.predictor import REFINE_MARGIN, REFINE_WINDOW, InitialFlow, full_box, refine_box
from engine.predict.decomp.upsample import spread_plane
from tests.synthetic import smooth_noise, turned_pose

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


def inputs(seed: int, size=(70, 101), factor=3):
    """A frame n (colour, depth with sky, camera) and n-k's camera (moved: its view misses a band of frame n),
    both lumas, an initial flow (some of it pointing outside the frame), and the network's planes."""
    rng = np.random.default_rng(seed)
    h, w = size
    luma_n = np.clip(128 + smooth_noise(rng, size, 60), 0, 255).astype(np.uint8)
    target = np.clip(luma_n.astype(np.float32) + smooth_noise(rng, size, 12), 0, 255).astype(np.uint8)
    flow = smooth_noise(rng, size + (2,), 4.0)
    flow[:3, :5] = -30.0  # samples outside the target: an error of 255
    depth = np.exp(1.0 + smooth_noise(rng, size, 0.6, cell=10)).astype(np.float32)
    depth[:6, 40:70] = np.inf  # sky
    k = np.array([[60.0, 0, w / 2], [0, 60.0, h / 2], [0, 0, 1]])
    t_n, t_p = turned_pose(0.0, 0.0), turned_pose(0.4, 0.12)
    planes = geometry.plane_depths(depth[::factor, ::factor], 2)
    seen = geometry.seen_before(depth, k, t_n, k, t_p, size)
    assert 0.05 < (~seen).mean() < 0.6
    initial = InitialFlow(flow, target, luma_n, seen)
    scene = dict(depth=depth, k=k, t_n=t_n, t_p=t_p, planes=planes)
    return rng, initial, scene, (h // factor, w // factor)


def residual(rng, box, num_z=2):
    hl, wl = box[1] - box[0], box[3] - box[2]
    low = np.zeros((3, num_z, hl, wl), np.float32)
    owner = rng.integers(0, num_z + 1, (hl, wl))  # num_z: an empty block (no plane here)
    alpha = np.stack([(owner == z).astype(np.float32) for z in range(num_z)])
    low[:2] = rng.normal(0, 1.5, (2, num_z, hl, wl)).astype(np.float32) * alpha[None]
    return low, alpha


def gpu_refine(initial, scene, boxes, factor, low_size):
    """The GPU's block-averaged initial flow of every box, and its flow after refining every box in turn (each
    from the initial flow), read back."""
    gl = glb.shared_context()
    warper = glb.GlFrameWarper()
    depth = scene["depth"]
    frame_n = warper.upload(np.zeros(depth.shape + (3,), np.float32), depth)
    flow = warper.upload_flow(initial.flow)
    start = flow if len(boxes) == 1 else flow.copy()
    lumas = [gl.call(lambda a=a: gl.ctx.buffer(np.ascontiguousarray(a, np.float32))) for a in
             (initial.luma_n, initial.target)]
    refine = GlFlowRefine(REFINE_MARGIN, REFINE_WINDOW)
    matrix = reprojection_matrix(scene["k"], scene["t_n"], scene["k"], scene["t_p"])
    gpu_ms: dict = {}
    try:
        fulls = [full_box(box, factor, low_size, depth.shape) for box, _ in boxes]
        lows = [refine.initial_low(start, full, factor) for full in fulls]
        for full, (_, (low, alpha)) in zip(fulls, boxes):
            packed = np.stack([spread_plane(low[:, z], alpha[z]) for z in range(alpha.shape[0])])
            refine.apply(flow, start, lambda: tuple(lumas), frame_n, matrix, depth.shape, plane_bounds(scene["planes"]),
                         full, packed, factor, gpu_ms=gpu_ms)
        return lows, flow.read(), gpu_ms
    finally:
        refine.release()
        gl.call(lambda: [b.release() for b in lumas])


def cpu_refine(initial, scene, boxes, factor, low_size):
    plane_index = geometry.plane_index(scene["depth"], scene["planes"])
    out, lows = initial.flow.copy(), []
    for box, (low, alpha) in boxes:
        fy0, fy1, fx0, fx1 = full = full_box(box, factor, low_size, plane_index.shape)
        lows.append(geometry.downsample_flow(initial.flow[fy0:fy1, fx0:fx1], factor))
        part = refine_box(full, low, alpha, factor, plane_index, initial, Timer())
        out[fy0:fy1, fx0:fx1] = np.moveaxis(part[:2, 0], 0, -1)
        out[fy0:fy1, fx0:fx1][~initial.seen[fy0:fy1, fx0:fx1]] = 0.0
    return lows, out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gpu_boxes_equal_the_cpus(seed):
    rng, initial, scene, low_size = inputs(seed)
    # an inner box, one at the last block row and column (full rows past the last block), overlapping boxes
    cases = [[(4, 14, 6, 20)], [(10, low_size[0], 20, low_size[1])], [(0, 12, 0, 16), (6, 20, 10, 30)]]
    for boxes in cases:
        boxes = [(b, residual(rng, b)) for b in boxes]
        gpu_lows, gpu, gpu_ms = gpu_refine(initial, scene, boxes, 3, low_size)
        cpu_lows, cpu = cpu_refine(initial, scene, boxes, 3, low_size)
        assert "refine" in gpu_ms
        for a, b in zip(gpu_lows, cpu_lows):  # the network's initial flow: the same float32 sums and quotients
            np.testing.assert_array_equal(a, b)
        same = (np.abs(gpu - cpu) <= 1e-6 * np.maximum(1.0, np.abs(cpu))).all(axis=-1)
        assert same.mean() >= 0.999, same.mean()
        changed = np.abs(cpu - initial.flow).max(axis=-1) > 1e-3
        assert changed.any() and (~changed).any()  # the check kept the refined flow in places, not all


def test_bad_inputs_are_refused():
    rng, initial, scene, low_size = inputs(5)
    warper = glb.GlFrameWarper()
    depth = scene["depth"]
    frame_n = warper.upload(np.zeros(depth.shape + (3,), np.float32), depth)
    flow = warper.upload_flow(initial.flow)
    refine = GlFlowRefine(REFINE_MARGIN, REFINE_WINDOW)
    packed = np.zeros((2, 4, 4, 4), np.float32)
    matrix = reprojection_matrix(scene["k"], scene["t_n"], scene["k"], scene["t_p"])
    bounds = plane_bounds(scene["planes"])
    lumas = lambda: (flow.buffer, flow.buffer)  # noqa: E731 (never reached)

    def apply(**change):
        args = dict(flow=flow, initial=flow, lumas=lumas, frame_n=frame_n, matrix=matrix, prev_size=depth.shape,
                    bounds=bounds, box=(0, 12, 0, 12), packed=packed, factor=3)
        refine.apply(**{**args, **change})

    for change, field in ((dict(box=(0, 12, 0, 200)), "box"), (dict(box=(5, 5, 0, 12)), "box"),
                          (dict(packed=np.zeros((2, 5, 4, 4), np.float32)), "packed"),
                          (dict(bounds=np.zeros(3, np.float32)), "bounds"), (dict(matrix=np.eye(3)), "matrix"),
                          (dict(flow=warper.upload_flow(np.zeros(depth.shape + (3,), np.float32))), "flow"),
                          (dict(initial=warper.upload_flow(np.zeros((8, 8, 2), np.float32))), "initial"),
                          (dict(frame_n=warper.upload(np.zeros((8, 8, 3), np.float32), np.ones((8, 8), np.float32))),
                           "frame_n")):
        with pytest.raises(InputError) as err:
            apply(**change)
        assert err.value.field == field
    for factor in (0, 40):
        with pytest.raises(InputError) as err:
            refine.initial_low(flow, (0, 12, 0, 12), factor)
        assert err.value.field == "factor"
    with pytest.raises(InputError):
        GlFlowRefine(REFINE_MARGIN, 4)
