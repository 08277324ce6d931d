"""``decomp``'s refinement check on the GPU (``engine.geometry.backends.gl.refine.GlFlowRefine``) against the CPU's
``refine_box``, its oracle, on the same inputs: the upsampling, both photometric errors (OpenCV's remap), the
window means in double and the choice are the CPU's arithmetic, so the flows agree to the bit but where a
float32 quotient or sum lands a hair apart."""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.refine import GlFlowRefine, refine_codes
from engine.predict.base import Timer
from engine.predict.decomp.predictor import REFINE_MARGIN, REFINE_WINDOW, InitialFlow, full_box, refine_box
from engine.predict.decomp.upsample import spread_plane

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


def smooth(rng, shape, scale, cell=6):
    noise = rng.normal(0, 1, (shape[0] // cell + 3, shape[1] // cell + 3) + shape[2:]).astype(np.float32)
    big = cv2.resize(noise, (shape[1] + 3 * cell, shape[0] + 3 * cell), interpolation=cv2.INTER_CUBIC)
    return scale * big[:shape[0], :shape[1]]


def inputs(seed: int, size=(70, 101), factor=3, num_z=2):
    """A frame's lumas, initial flow (some of it pointing outside the frame), planes and what frame n-k saw,
    and per box of the working resolution a residual flow with its one-hot alpha."""
    rng = np.random.default_rng(seed)
    h, w = size
    luma_n = np.clip(128 + smooth(rng, size, 60), 0, 255).astype(np.uint8)
    target = np.clip(luma_n.astype(np.float32) + smooth(rng, size, 12), 0, 255).astype(np.uint8)
    flow = smooth(rng, size + (2,), 4.0)
    flow[:3, :5] = -30.0  # samples outside the target: an error of 255
    plane_index = (smooth(rng, size, 1.0, cell=10) > 0).astype(np.int64)
    seen = smooth(rng, size, 1.0, cell=12) > -0.8
    initial = InitialFlow(flow, target, luma_n, seen)
    low_size = (h // factor, w // factor)
    return rng, initial, plane_index, low_size


def residual(rng, box, num_z=2):
    hl, wl = box[1] - box[0], box[3] - box[2]
    low = np.zeros((3, num_z, hl, wl), np.float32)
    owner = rng.integers(0, num_z + 1, (hl, wl))  # num_z: an empty block (no plane here)
    alpha = np.stack([(owner == z).astype(np.float32) for z in range(num_z)])
    low[:2] = rng.normal(0, 1.5, (2, num_z, hl, wl)).astype(np.float32) * alpha[None]
    return low, alpha


def gpu_refine(initial, plane_index, boxes, factor, low_size):
    """The GPU's flow after refining every box in turn (each from the initial flow), read back."""
    gl = glb.shared_context()
    warper = glb.GlFrameWarper()
    flow = warper.upload_flow(initial.flow)
    start = flow if len(boxes) == 1 else flow.copy()
    lumas = [gl.call(lambda a=a: gl.ctx.buffer(np.ascontiguousarray(a, np.float32))) for a in
             (initial.luma_n, initial.target)]
    refine = GlFlowRefine(REFINE_MARGIN, REFINE_WINDOW)
    gpu_ms: dict = {}
    try:
        for box, (low, alpha) in boxes:
            fy0, fy1, fx0, fx1 = full = full_box(box, factor, low_size, plane_index.shape)
            packed = np.stack([spread_plane(low[:, z], alpha[z]) for z in range(alpha.shape[0])])
            codes = refine_codes(plane_index[fy0:fy1, fx0:fx1], initial.seen[fy0:fy1, fx0:fx1])
            refine.apply(flow, start, lambda: tuple(lumas), full, packed, factor, codes, gpu_ms=gpu_ms)
        return flow.read(), gpu_ms
    finally:
        refine.release()
        gl.call(lambda: [b.release() for b in lumas])


def cpu_refine(initial, plane_index, boxes, factor, low_size):
    out = initial.flow.copy()
    for box, (low, alpha) in boxes:
        fy0, fy1, fx0, fx1 = full = full_box(box, factor, low_size, plane_index.shape)
        part = refine_box(full, low, alpha, factor, plane_index, initial, Timer())
        out[fy0:fy1, fx0:fx1] = np.moveaxis(part[:2, 0], 0, -1)
        out[fy0:fy1, fx0:fx1][~initial.seen[fy0:fy1, fx0:fx1]] = 0.0
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_gpu_refinement_equals_the_cpus(seed):
    rng, initial, plane_index, low_size = inputs(seed)
    # an inner box, one at the last block row and column (full rows past the last block), overlapping boxes
    cases = [[(4, 14, 6, 20)], [(10, low_size[0], 20, low_size[1])], [(0, 12, 0, 16), (6, 20, 10, 30)]]
    for boxes in cases:
        boxes = [(b, residual(rng, b)) for b in boxes]
        gpu, gpu_ms = gpu_refine(initial, plane_index, boxes, 3, low_size)
        cpu = cpu_refine(initial, plane_index, boxes, 3, low_size)
        assert "refine" in gpu_ms
        same = (np.abs(gpu - cpu) <= 1e-6 * np.maximum(1.0, np.abs(cpu))).all(axis=-1)
        assert same.mean() >= 0.999, same.mean()
        changed = np.abs(cpu - initial.flow).max(axis=-1) > 1e-3
        assert changed.any() and (~changed).any()  # the check kept the refined flow in places, not all


def test_bad_boxes_and_codes_are_refused():
    rng, initial, plane_index, low_size = inputs(5)
    warper = glb.GlFrameWarper()
    flow = warper.upload_flow(initial.flow)
    refine = GlFlowRefine(REFINE_MARGIN, REFINE_WINDOW)
    packed = np.zeros((2, 4, 4, 4), np.float32)
    codes = np.zeros((12, 12), np.uint8)
    lumas = lambda: (flow.buffer, flow.buffer)  # noqa: E731 (never reached)
    for box, field in (((0, 12, 0, 200), "box"), ((5, 5, 0, 12), "box")):
        with pytest.raises(InputError) as err:
            refine.apply(flow, flow, lumas, box, packed, 3, codes)
        assert err.value.field == field
    with pytest.raises(InputError) as err:
        refine.apply(flow, flow, lumas, (0, 12, 0, 12), packed, 3, codes + 2)  # plane 2 of 2
    assert err.value.field == "codes"
    with pytest.raises(InputError) as err:
        refine.apply(flow, flow, lumas, (0, 12, 0, 12), np.zeros((2, 5, 4, 4), np.float32), 3, codes)
    assert err.value.field == "packed"
    with pytest.raises(InputError) as err:
        refine.apply(warper.upload_flow(np.zeros((70, 101, 3), np.float32)), flow, lumas, (0, 12, 0, 12), packed, 3,
                     codes)
    assert err.value.field == "flow"
    with pytest.raises(InputError):
        refine_codes(np.full((2, 2), 200), np.ones((2, 2), bool))
    with pytest.raises(InputError):
        GlFlowRefine(REFINE_MARGIN, 4)
