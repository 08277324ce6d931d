"""``decomp``'s motion gate on the GPU (``engine.geometry.backends.gl.gate.GlGate``) against the CPU's gate, its
oracle, on the same frames: the changed pixels per tile against ``tile_counts`` of the CPU's mask
(``downsample_frame``, the one-plane warp, ``motion_residual``, ``seen_before``), then the boxes. The
residual's arithmetic is numpy's; the GL splat may differ from the CPU's on rare pixels
(tests/geometry/test_gl_frame.py), so the counts may differ by a few pixels on a GPU driver (on llvmpipe
they are equal)."""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.gate import GlGate
from engine.geometry.holefill import fill_holes
from engine.predict import Target, make_predictor
from engine.predict.base import Timer
from engine.predict.decomp.gate import (GateConfig, boxes_from_counts, gate_boxes, motion_boxes, motion_residual,
                                        tile_counts)
from tests.synthetic import smooth_noise, turned_pose, two_layer_sequence

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


def frames(seed: int, size=(120, 208), move=True):
    """Frames n-k and n of a textured static scene with a sky band, seen from a camera that moved and turned (a
    band of frame n is new to it), and, with ``move``, a box that moved between them."""
    rng = np.random.default_rng(seed)
    h, w = size
    color_p = np.clip(0.4 + smooth_noise(rng, size + (3,), 0.3), 0, None).astype(np.float32)
    depth_p = np.exp(1.2 + smooth_noise(rng, size, 0.5, cell=14)).astype(np.float32)
    depth_p[:10, w // 3:2 * w // 3] = np.inf
    k = np.array([[0.8 * w, 0, w / 2], [0, 0.8 * w, h / 2], [0, 0, 1]])
    t_p, t_n = turned_pose(0.0, 0.0), turned_pose(0.12, 0.06)
    color_n, depth_n, holes = geometry.forward_warp_frame(color_p, depth_p, k, t_p, k, t_n)
    color_n = fill_holes(color_n, depth_n, holes, color_n)[0]
    depth_n = np.where(holes, depth_p.max(where=np.isfinite(depth_p), initial=1.0), depth_n).astype(np.float32)
    if move:
        y, x = h // 3, w // 4
        color_n[y:y + 26, x + 20:x + 56] = [1.5, 0.2, 0.1]
        depth_n[y:y + 26, x + 20:x + 56] = 1.5
        color_p[y + 6:y + 32, x:x + 36] = [1.5, 0.2, 0.1]
        depth_p[y + 6:y + 32, x:x + 36] = 1.5
    return (color_n, depth_n, color_p, depth_p, k, t_n, t_p)


def cpu_counts(scene, factor, config):
    color_n, depth_n, color_p, depth_p, k, t_n, t_p = scene
    low_n = geometry.downsample_frame(color_n, depth_n, k, factor)
    low_p = geometry.downsample_frame(color_p, depth_p, k, factor)
    g_n = geometry.build_mpi(low_n[0], low_n[1], 1)
    g_w, _ = geometry.forward_warp_mpi(geometry.build_mpi(low_p[0], low_p[1], 1), low_p[2], t_p, low_n[2], t_n)
    changed = motion_residual(g_n, g_w, config.color_threshold, config.depth_threshold, config.erode)
    if config.unseen:
        changed &= geometry.seen_before(low_n[1], low_n[2], t_n, low_p[2], t_p, low_p[1].shape)
    return tile_counts(changed, config.tile), (low_n, low_p)


def gpu_counts(scene, factor, config):
    color_n, depth_n, color_p, depth_p, k, t_n, t_p = scene
    warper = glb.GlFrameWarper()
    gate = GlGate(config.color_threshold, config.depth_threshold, config.erode, config.unseen, config.tile)
    return gate.tile_counts(warper.upload(color_n, depth_n), warper.upload(color_p, depth_p), k, t_n, k, t_p, factor)


def assert_counts_match(cpu, gpu):
    assert gpu.shape == cpu.shape and gpu.dtype == np.uint32
    assert np.abs(cpu.astype(np.int64) - gpu).sum() <= max(2, cpu.sum() // 500)


@pytest.mark.parametrize("seed", [0, 1])
@pytest.mark.parametrize("factor", [1, 2, 3, 4])
def test_counts_match_the_cpu(seed, factor):
    scene, config = frames(seed), GateConfig()
    cpu, (low_n, low_p) = cpu_counts(scene, factor, config)
    gpu = gpu_counts(scene, factor, config)
    assert cpu.sum() > 20  # the box moved, and the test sees it
    assert_counts_match(cpu, gpu)
    boxes = boxes_from_counts(gpu, low_n[1].shape, config.tile, config.tile_fraction, config.margin, 8,
                              config.full_frame_fraction, config.min_tiles)
    assert boxes == gate_boxes(config, low_n, low_p, scene[5], scene[6], 8)


@pytest.mark.parametrize("erode,unseen", [(False, True), (True, False), (False, False)])
def test_counts_match_the_cpu_with_each_rule_off(erode, unseen):
    config = GateConfig(erode=erode, unseen=unseen, tile=5)  # tiles that do not divide the frame
    scene = frames(2)
    assert_counts_match(cpu_counts(scene, 2, config)[0], gpu_counts(scene, 2, config))


def test_hard_frames():
    """A view where nothing moved, frame n all sky (no finite depth: the depth test's reference is 1),
    a factor equal to the frame's smaller side (one working-resolution row) and a 1 x 1 frame."""
    config = GateConfig()
    color, depth, _, _, k, t_n, _ = frames(3, move=False)
    static = (color, depth, color, depth, k, t_n, t_n)  # nothing moved
    assert cpu_counts(static, 2, config)[0].sum() == 0 and gpu_counts(static, 2, config).sum() == 0
    color_n, depth_n, *rest = frames(4)
    sky = (color_n, np.full_like(depth_n, np.inf), *rest)
    assert_counts_match(cpu_counts(sky, 2, config)[0], gpu_counts(sky, 2, config))
    scene = frames(5, size=(24, 60))
    assert_counts_match(cpu_counts(scene, 24, config)[0], gpu_counts(scene, 24, config))
    tiny = tuple(a[:1, :1] if isinstance(a, np.ndarray) and a.ndim >= 2 and a.shape[0] > 4 else a
                 for a in frames(6))
    assert gpu_counts(tiny, 1, config).shape == (1, 1)
    assert_counts_match(cpu_counts(tiny, 1, config)[0], gpu_counts(tiny, 1, config))


def test_bad_input():
    config = GateConfig()
    color_n, depth_n, color_p, depth_p, k, t_n, t_p = frames(0, size=(32, 48))
    warper = glb.GlFrameWarper()
    gate = GlGate(config.color_threshold, config.depth_threshold, config.erode, config.unseen, config.tile)
    image_n, image_p = warper.upload(color_n, depth_n), warper.upload(color_p[:16], depth_p[:16])
    with pytest.raises(InputError) as err:
        gate.tile_counts(image_n, image_p, k, t_n, k, t_p, 2)
    assert err.value.field == "frame_p"
    with pytest.raises(InputError) as err:
        gate.tile_counts(image_n, image_n, k, t_n, k, t_p, 33)
    assert err.value.field == "factor"
    with pytest.raises(InputError) as err:
        gate.tile_counts(color_n, image_n, k, t_n, k, t_p, 2)
    assert err.value.field == "frame_n"
    with pytest.raises(InputError):
        GlGate(0.0, config.depth_threshold, True, True, 8)


def test_boxes_from_counts_is_the_mask_rule():
    """``motion_boxes`` of a mask is ``boxes_from_counts`` of its ``tile_counts``; a tile moves above the fraction
    of its tile x tile pixels, partial tiles included."""
    rng = np.random.default_rng(7)
    for _ in range(20):
        mask = rng.random((61, 97)) < rng.uniform(0.0, 0.08)
        counts = tile_counts(mask, 8)
        assert counts.shape == (8, 13) and counts.sum() == mask.sum()
        assert motion_boxes(mask, 8, 0.05, 24, 8, 0.5, 3) == boxes_from_counts(counts, mask.shape, 8, 0.05, 24, 8,
                                                                               0.5, 3)
    edge = np.zeros((10, 10), bool)
    edge[8:, 8:] = True  # 4 pixels of the partial corner tile: 4 / 64 > 0.05
    assert boxes_from_counts(tile_counts(edge, 8), edge.shape, 8, 0.05, 0, 1, 1.0) == [(8, 10, 8, 10)]


def test_decomp_on_gl_gates_on_the_gpu_and_uploads_each_frame_once():
    """``decomp`` on ``gl``: the gate runs on the GPU (GPU stage ``gate``) and finds the CPU's boxes; a static view
    (no boxes) leaves the CPU no downsampling; frame n uploaded for one preparation is frame n-k of the next."""
    frames_, objects = two_layer_sequence(9, width=192, height=128, camera_speed=0.02, object_speed=0.12,
                                          square_half=0.25)
    cpu, gl = make_predictor("decomp", objects, backend="cpu"), make_predictor("decomp", objects, backend="gl")
    first = gl.prepare([frames_[2], frames_[4]])
    assert "gate" in first.gpu_ms and first.data.boxes == cpu.prepare([frames_[2], frames_[4]]).data.boxes
    assert first.data.network_fraction < 1.0
    second = gl.prepare([frames_[4], frames_[6]])
    assert second.data.boxes == cpu.prepare([frames_[4], frames_[6]]).data.boxes
    timer = Timer()
    assert gl.frames.resident(frames_[4], timer) is first.data.frame and "upload" not in timer.into  # kept
    out = gl.render(second, Target(frames_[7].camera, frames_[7].time, frames_[7].index))
    assert np.isfinite(out.color).all()
    still, _ = two_layer_sequence(5, width=96, height=64, camera_speed=0.03, object_speed=0.0)
    state = make_predictor("decomp", backend="gl").prepare([still[1], still[3]])
    assert state.data.boxes == [] and state.data.plane_depths is None and "downsample" not in state.stages_ms
