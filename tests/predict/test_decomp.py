"""The engine's decomp predictor (no torch): downsampling, motion gate, flow upsampling, hard inputs."""
import numpy as np
import pytest

from engine import geometry
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame
from engine.eval.metrics import score_frame
from engine.geometry import seen_before
from engine.predict import (DEFAULT_MODEL, DecompConfig, DecompPredictor, DecompTrueMotion, FlowNetwork, GateConfig,
                            Reproject, Target)
from engine.predict import classic as classic_module
from engine.predict import (decomp_config, dis_block, dis_flow, dis_target, initial_flow, luma8, make_predictor,
                            split_methods, warp_error)
from engine.predict.decomp import predictor as decomp_module
from engine.predict.decomp.gate import motion_boxes
from engine.predict.decomp.predictor import full_box, whole_frame_initial_flow
from engine.predict.decomp.upsample import upsample_blocks, upsample_flow
from engine.predict.dis import trusted_motion
from tests.synthetic import rigid, two_layer_sequence


@pytest.fixture(scope="module")
def network():
    return FlowNetwork(DEFAULT_MODEL, threads=1)


def _target(frame):
    return Target(frame.camera, frame.time, frame.index)


# --------------------------------------------------------------------------------------------------
# downsampling shared by training and the engine


def test_downsample_keeps_projection_consistent():
    rng = np.random.default_rng(0)
    color = rng.random((12, 18, 3), dtype=np.float32)
    depth = (1.0 + rng.random((12, 18))).astype(np.float32)
    depth[0, :4] = np.inf
    k = np.array([[20.0, 0.0, 9.0], [0.0, 22.0, 6.0], [0.0, 0.0, 1.0]])
    c2, d2, k2 = geometry.downsample_frame(color, depth, k, 3)
    assert c2.shape == (4, 6, 3) and d2.shape == (4, 6)
    np.testing.assert_allclose(c2[1, 2], color[3:6, 6:9].mean(axis=(0, 1)), rtol=1e-6)
    assert d2[1, 2] == depth[3:6, 6:9].min()
    assert np.isinf(d2[0, 0]) == np.isinf(depth[:3, :3]).all()
    point = np.array([0.3, -0.2, 2.0])  # a camera-space point lands at pixel / 3 in the low-resolution frame
    full = (k @ point)[:2] / point[2]
    low = (k2 @ point)[:2] / point[2]
    np.testing.assert_allclose(low, full / 3.0)


def test_downsample_flow_is_the_block_mean_in_low_resolution_pixels():
    flow = np.zeros((7, 9, 2), np.float32)
    flow[:3, :3, 0] = 6.0  # one 3 x 3 block moving 6 px right; row 6 and columns 6-8 lie past the last block
    low = geometry.downsample_flow(flow, 3)
    assert low.shape == (2, 3, 2)
    np.testing.assert_allclose(low[0, 0], [2.0, 0.0])
    assert (low[1:] == 0).all() and (low[:, 1:] == 0).all()
    with pytest.raises(InputError, match="flow"):
        geometry.downsample_flow(np.zeros((4, 4, 3)), 2)


@pytest.mark.parametrize("factor", [1, 2, 3, 4, 8])
def test_downsample_flow_equals_numpys_block_mean_to_the_bit(factor):
    """The explicit block sum (rows, then columns, float32) is numpy's strided mean over the block axes, the
    definition the committed networks were trained with, to the bit: sizes that are not multiples of the
    factor, values over five orders of magnitude, NaN."""
    rng = np.random.default_rng(factor)
    flow = (rng.normal(0, 20, (53, 71, 2)) * 10.0 ** rng.uniform(-3, 2, (53, 71, 1))).astype(np.float32)
    flow[5, 7, 0] = np.nan
    h, w = 53 // factor, 71 // factor
    numpy_mean = (flow[:h * factor, :w * factor].reshape(h, factor, w, factor, 2).mean(axis=(1, 3)) / factor)
    np.testing.assert_array_equal(geometry.downsample_flow(flow, factor), numpy_mean.astype(np.float32))


@pytest.mark.parametrize("factor", [0, 13, -1])
def test_downsample_rejects_bad_factor(factor):
    with pytest.raises(InputError, match="factor"):
        geometry.downsample_frame(np.zeros((12, 18, 3)), np.ones((12, 18)), np.eye(3), factor)


def test_downsample_factor_rounds_to_working_width():
    assert geometry.downsample_factor(1920, 480) == 4
    assert geometry.downsample_factor(100, 480) == 1
    with pytest.raises(InputError):
        geometry.downsample_factor(960, 0)


def test_build_mpi_with_given_planes_matches_own_planes_and_validates():
    rng = np.random.default_rng(1)
    depth = (1.0 + 9.0 * rng.random((8, 10))).astype(np.float32)
    color = rng.random((8, 10, 3), dtype=np.float32)
    own = geometry.build_mpi(color, depth, 4)
    given = geometry.build_mpi(color, depth, 4, own.plane_depths)
    for a, b in zip(own, given):
        np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match="plane_depths"):
        geometry.build_mpi(color, depth, 4, own.plane_depths[::-1])
    with pytest.raises(InputError, match="plane_depths"):
        geometry.build_mpi(color, depth, 4, own.plane_depths[:3])


# --------------------------------------------------------------------------------------------------
# motion gate and flow upsampling


def test_motion_boxes_empty_single_and_full_frame():
    changed = np.zeros((64, 96), dtype=bool)
    assert motion_boxes(changed, 8, 0.15, 8, 16, 0.5) == []
    changed[20:30, 40:50] = True
    boxes = motion_boxes(changed, 8, 0.15, 8, 16, 0.5)
    assert len(boxes) == 1
    y0, y1, x0, x1 = boxes[0]
    assert y0 <= 20 and y1 >= 30 and x0 <= 40 and x1 >= 50
    assert y0 % 16 == 0 and x0 % 16 == 0 and (y1 % 16 == 0 or y1 == 64) and (x1 % 16 == 0 or x1 == 96)
    changed[:] = True
    assert motion_boxes(changed, 8, 0.15, 8, 16, 0.5) == [(0, 64, 0, 96)]


def test_motion_boxes_min_tiles_drops_isolated_tiles():
    changed = np.zeros((64, 96), dtype=bool)
    changed[2:6, 2:6] = True  # one tile
    changed[30:50, 40:70] = True  # a 3 x 4 group of tiles
    boxes = motion_boxes(changed, 8, 0.15, 0, 16, 0.9, min_tiles=3)
    assert len(boxes) == 1 and boxes[0][0] <= 30 and boxes[0][3] >= 70
    assert len(motion_boxes(changed, 8, 0.15, 0, 16, 0.9, min_tiles=1)) == 2


def test_motion_boxes_ignore_sparse_noise():
    changed = np.zeros((64, 96), dtype=bool)
    changed[::9, ::9] = True  # isolated pixels: < 15 % of any tile
    assert motion_boxes(changed, 8, 0.15, 8, 16, 0.5) == []


def test_upsample_flow_scales_and_reaches_pixels_of_other_blocks():
    z, h, w, f = 2, 4, 6, 2
    alpha = np.zeros((z, h, w), np.float32)
    alpha[0, :, :3] = 1.0
    alpha[1, :, 3:] = 1.0
    flow = np.zeros((3, z, h, w), np.float32)
    flow[:, 0] = np.array([1.0, -2.0, 0.5])[:, None, None]
    flow[:, 1] = np.array([3.0, 0.0, -1.0])[:, None, None]
    full = np.zeros((z, h * f + 1, w * f + 1), np.float32)  # one extra row/column past the last block
    full[0, :, :7] = 1.0  # column 6 is in plane 0 at full res, its low-res block went to plane 1
    full[1, :, 7:] = 1.0
    out = upsample_flow(flow * alpha[None], alpha, f, full)
    np.testing.assert_allclose(out[:, 0, :, :7], np.broadcast_to(np.array([2.0, -4.0, 0.5])[:, None, None], (3, 9, 7)),
                               atol=1e-6)
    np.testing.assert_allclose(out[:, 1, :, 7:], np.broadcast_to(np.array([6.0, 0.0, -1.0])[:, None, None], (3, 9, 6)),
                               atol=1e-6)
    assert (out[:, 0, :, 7:] == 0).all() and (out[:, 1, :, :7] == 0).all()


# --------------------------------------------------------------------------------------------------
# the predictor


def test_static_scene_skips_the_network_and_matches_reproject(network):
    frames, _ = two_layer_sequence(5, width=128, height=96, camera_speed=0.06, object_speed=0.0)
    pred = DecompPredictor(DecompConfig(), network)
    state = pred.prepare(frames[1:3])
    assert state.data.boxes == [] and state.data.flow is None
    # no box: the network's 4-plane MPIs, camera warp, initial flow and network never run
    assert not {"flow", "camera_warp", "initial_flow", "upsample"} & set(state.stages_ms)
    out = pred.render(state, _target(frames[3]))
    ref = Reproject().predict(frames[1:3], _target(frames[3]))
    truth = frames[3].color
    assert score_frame(truth, out.color).psnr > score_frame(truth, ref.color).psnr - 0.5


def _noisy(frames, sigma):
    """The frames with the colour noise of a path tracer at few samples per pixel (the scene generator's)."""
    import dataclasses

    from engine.scenegen.render import monte_carlo_noise

    return [dataclasses.replace(f, color=monte_carlo_noise(f.color, sigma, np.random.default_rng([7, f.index])))
            for f in frames]


@pytest.mark.parametrize("sigma", [0.05, 0.15])
def test_render_noise_keeps_a_static_view_off_the_motion_path(network, sigma):
    """Independent per-frame noise is a colour residual everywhere; the gate must not read it as motion."""
    frames, _ = two_layer_sequence(5, width=192, height=128, camera_speed=0.06, object_speed=0.0)
    frames = _noisy(frames, sigma)
    pred = DecompPredictor(DecompConfig(), network)
    state = pred.prepare(frames[1:3])
    assert state.data.boxes == [] and state.data.flow is None
    if sigma >= 0.15:  # hard enough that the gate's 3 x 3 erosion is what keeps it off the motion path
        assert DecompPredictor(DecompConfig(gate=GateConfig(erode=False)), network).prepare(frames[1:3]).data.boxes
    out = pred.render(state, _target(frames[3]))
    ref = Reproject().predict(frames[1:3], _target(frames[3]))
    assert np.isfinite(out.color).all()
    assert score_frame(frames[3].color, out.color).psnr > score_frame(frames[3].color, ref.color).psnr - 0.5


def _crop_columns(frame, x0, x1):
    """The frame's columns [x0, x1) as a frame of its own (principal point shifted)."""
    import dataclasses

    k = frame.camera.intrinsics.copy()
    k[0, 2] -= x0
    cut = lambda a: None if a is None else np.ascontiguousarray(a[:, x0:x1])  # noqa: E731
    return dataclasses.replace(frame, color=cut(frame.color), depth=cut(frame.depth),
                               camera=Camera(k, frame.camera.world_to_camera), object_id=cut(frame.object_id),
                               moving=cut(frame.moving), flow=cut(frame.flow), object_flow=cut(frame.object_flow))


def test_seen_before_marks_what_the_older_view_contained():
    frames, _ = two_layer_sequence(3, width=96, height=64, camera_speed=0.15, object_speed=0.0)
    old, new = frames[0], frames[2]
    size = old.depth.shape
    same = seen_before(new.depth, new.camera.intrinsics, new.camera.world_to_camera, new.camera.intrinsics,
                       new.camera.world_to_camera, size)
    assert same.all()
    seen = seen_before(new.depth, new.camera.intrinsics, new.camera.world_to_camera, old.camera.intrinsics,
                       old.camera.world_to_camera, size)
    # the camera moved +x: frame n's right border shows what frame n-k had right of its image
    uv, _, _ = geometry.reproject(new.depth, new.camera.intrinsics, new.camera.world_to_camera,
                                  old.camera.intrinsics, old.camera.world_to_camera)
    np.testing.assert_array_equal(seen, uv[..., 0] < size[1])
    assert seen[:, :40].all() and not seen[:, -4:].any()
    sky = np.full(size, np.inf, np.float32)  # sky moves with the rotation alone: a translation keeps it in view
    assert seen_before(sky, new.camera.intrinsics, new.camera.world_to_camera, old.camera.intrinsics,
                       old.camera.world_to_camera, size).all()


def test_gate_ignores_a_static_surface_entering_at_the_border(network):
    """A near static surface entering the view lands on the far background frame n-k saw beside it: a
    colour and depth residual, but not motion (frame n-k never saw the surface)."""
    frames, _ = two_layer_sequence(3, width=384, height=128, camera_speed=0.15, object_speed=0.0)
    left = np.nonzero(frames[2].object_id.any(0))[0].min()  # the square's left edge in frame n
    pair = [_crop_columns(f, left + 30 - 96, left + 30) for f in (frames[0], frames[2])]
    assert not pair[0].object_id.any() and pair[1].object_id.any()  # in view in frame n only
    assert DecompPredictor(DecompConfig(gate=GateConfig(unseen=False)), network).prepare(pair).data.boxes
    state = DecompPredictor(DecompConfig(), network).prepare(pair)
    assert state.data.boxes == [] and state.data.flow is None


def test_identical_frames_give_zero_flow(network):
    frames, _ = two_layer_sequence(2, width=128, height=96)
    still = Frame(index=1, time=frames[0].time + 1 / 30, color=frames[0].color, depth=frames[0].depth,
                  camera=frames[0].camera)
    gated = DecompPredictor(DecompConfig(), network).prepare([frames[0], still])
    assert gated.data.flow is None  # exactly zero: the gate sees no motion
    # without the gate the committed network's residual is not exactly zero on identical frames (measured:
    # under 1 px everywhere); the gate is what guarantees zero, so it is on by default
    ungated = DecompPredictor(DecompConfig(gate=GateConfig(enabled=False)), network).prepare([frames[0], still])
    flow = ungated.data.flow
    assert np.isfinite(flow).all() and np.abs(flow[:2]).max() < 1.5


@pytest.mark.parametrize("sigma", [0.0, 0.1])
def test_moving_object_beats_reproject_on_moving_pixels(network, sigma):
    """Also through a path tracer's colour noise (``sigma``), which must not hide the object from the gate."""
    frames, _ = two_layer_sequence(7, width=192, height=128, camera_speed=0.02, object_speed=0.12)
    frames = _noisy(frames, sigma) if sigma else frames
    pred = DecompPredictor(DecompConfig(), network)
    state = pred.prepare([frames[2], frames[4]])
    assert state.data.boxes and state.data.flow is not None
    truth = frames[5]
    out = pred.render(state, _target(truth))
    ref = Reproject().predict([frames[2], frames[4]], _target(truth))
    ours = score_frame(truth.color, out.color, truth.moving).psnr_moving
    base = score_frame(truth.color, ref.color, truth.moving).psnr_moving
    assert ours > base + 1.0, (ours, base)
    # the estimated flow points the right way: u(n -> n-k) of the square is about -2 frames of motion
    flow_x = pred.object_flow(state)[..., 0][frames[4].moving]
    expected = -2.0 * frames[4].object_flow[..., 0][frames[4].moving]
    assert np.median(np.abs(flow_x - expected)) < 0.35 * np.abs(expected).mean()


def test_initial_flow_is_flow2ds_dis_on_the_whole_frame_and_kept_outside_the_boxes(network):
    frames, _ = two_layer_sequence(7, width=192, height=128, camera_speed=0.02, object_speed=0.12,
                                   square_half=0.25)  # a box smaller than the frame
    pred = DecompPredictor(DecompConfig(), network)
    state = pred.prepare([frames[2], frames[4]])
    assert state.data.boxes and "flow" in state.stages_ms
    f = state.data.factor
    y0, y1, x0, x1 = (v * f for v in state.data.boxes[0])
    older, newest = frames[2], frames[4]
    # DIS runs on the whole frame, and its flow is kept outside the boxes too
    moved, _ = geometry.forward_warp_mpi(geometry.build_mpi(older.color, older.depth, 1), older.camera.intrinsics,
                                         older.camera.world_to_camera, np.array(newest.camera.intrinsics, np.float64),
                                         newest.camera.world_to_camera, out_size=(128, 192))
    color_w, depth_w, acc = geometry.composite(moved)
    color_n = newest.color
    dis = dis_flow(luma8(color_n), dis_target(color_n, color_w, acc > 0, depth_w))  # holes: reproject's fill
    initial = whole_frame_initial_flow(older, newest, "medium")
    # ... kept where trusted_motion trusts it, which is flow2d's flow (the same camera warp and hole fill; frames
    # here leave no hole whose row and column are both empty, the one place the two fills' fallbacks differ)
    kept = trusted_motion(initial.luma_n, initial.target, dis, initial.seen)
    assert kept.any() and not kept.all()
    np.testing.assert_allclose(initial.flow, np.where(kept[..., None], dis, 0.0), atol=1e-5)
    flow2d = make_predictor("flow2d").prepare([older, newest]).data.flow_back
    np.testing.assert_allclose(initial.flow, flow2d, atol=1e-5)
    # frame n's own colour in the holes (initial_flow's target, the network's training data) gives another flow
    own = initial_flow(color_n, color_w, acc > 0)
    assert (acc <= 0).any() and np.abs(own - dis).max() > 0.01
    flow = state.data.flow
    outside = np.ones(newest.depth.shape, bool)
    for b in state.data.boxes:
        outside[b[0] * f:b[1] * f, b[2] * f:b[3] * f] = False
    assert outside.any()
    np.testing.assert_allclose(flow[:2, 0][:, outside], np.moveaxis(initial.flow, -1, 0)[:, outside], atol=1e-5)
    assert not flow[2].any()
    # and the network changes that flow inside the boxes
    assert np.abs(flow[:2, 0, y0:y1, x0:x1] - np.moveaxis(initial.flow, -1, 0)[:, y0:y1, x0:x1]).max() > 0.01


def test_warp_error_is_lowest_for_the_true_shift_and_honours_the_offset():
    rng = np.random.default_rng(3)
    import cv2
    target = cv2.GaussianBlur(rng.random((40, 60)).astype(np.float32), (0, 0), 1.5) * 255.0
    luma_n = target[5:25, 12:42] * 1.0  # frame n's part: the target shifted by (+3, +2) from its offset (2, 10)
    flow = np.zeros((20, 30, 2), np.float32)
    flow[..., 0], flow[..., 1] = 2.0, 3.0
    exact = warp_error(luma_n, target, (2, 10), flow, window=3)
    assert np.allclose(exact, 0.0, atol=1e-3)
    assert warp_error(luma_n, target, (2, 10), np.zeros_like(flow), window=3).mean() > 5.0
    far = flow.copy()
    far[..., 0] = 100.0  # samples outside the target cost 255
    assert np.allclose(warp_error(luma_n, target, (2, 10), far, window=1), 255.0)


def test_refine_check_keeps_per_pixel_either_the_refined_or_the_initial_flow(network, monkeypatch):
    frames, _ = two_layer_sequence(7, width=192, height=128, camera_speed=0.02, object_speed=0.12, square_half=0.25)
    pair = [frames[2], frames[4]]

    def flow_with_margin(margin):
        monkeypatch.setattr(decomp_module, "REFINE_MARGIN", margin)
        return DecompPredictor(DecompConfig(estimator="dis"), network).prepare(pair).data.flow  # DIS's start below

    checked = flow_with_margin(1.0)
    refined = flow_with_margin(-np.inf)  # every pixel keeps the refined flow: no check
    initial = np.zeros_like(checked)
    initial[:2, 0] = np.moveaxis(whole_frame_initial_flow(*pair, "medium").flow, -1, 0)
    is_refined = np.isclose(checked, refined, atol=1e-6).all(axis=0)
    is_initial = np.isclose(checked, initial, atol=1e-6).all(axis=0)
    assert (is_refined | is_initial).all()
    differ = ~np.isclose(refined, initial, atol=1e-6).all(axis=0)
    assert (differ & is_refined).any() and (differ & is_initial).any()  # both choices occur where they differ
    # the margin only moves pixels from the refined to the initial flow; an unreachable margin keeps DIS alone
    strict = flow_with_margin(0.0)
    kept_strict = ~np.isclose(strict, initial, atol=1e-6).all(axis=0)
    kept_margin = ~np.isclose(checked, initial, atol=1e-6).all(axis=0)
    assert not (kept_margin & ~kept_strict).any() and kept_margin.sum() <= kept_strict.sum()
    never = flow_with_margin(256.0)
    np.testing.assert_allclose(never, initial, atol=1e-6)


def test_full_box_takes_the_rows_past_the_last_block():
    assert full_box((0, 5, 2, 8), 4, (5, 8), (22, 35)) == (0, 22, 8, 35)  # last block row/column take the rest
    assert full_box((1, 3, 2, 4), 4, (5, 8), (22, 35)) == (4, 12, 8, 16)


def test_dis_at_its_finest_scale_equals_dis_on_the_full_image():
    """DIS 'medium' (finest scale 1) on a full-size image is DIS with
    finest scale 0 on the image's 2 x 2 block means, bilinearly upsampled (``upsample_blocks``) and doubled."""
    import cv2

    frames, _ = two_layer_sequence(5, width=192, height=128, camera_speed=0.02, object_speed=0.12)
    a, b = luma8(frames[3].color), luma8(frames[1].color)
    assert dis_block("medium") == 2 and dis_block("fast") == 4
    full = dis_flow(a, b, "medium")
    half = [cv2.resize(v, (96, 64), interpolation=cv2.INTER_AREA) for v in (a, b)]
    small = dis_flow(*half, "medium", 0)
    np.testing.assert_allclose(upsample_blocks(small, 2, (128, 192)) * 2, full, atol=1e-4)
    assert np.abs(full).max() > 1.0


def test_upsample_blocks_matches_the_block_grid_and_pads_the_remainder():
    image = np.arange(12, dtype=np.float32).reshape(3, 4)
    up = upsample_blocks(image, 2, (7, 9))
    assert up.shape == (7, 9)
    # pixel centres: full pixel X samples block (X + 0.5) / 2 - 0.5, so pixels 2i and 2i + 1 sit a quarter
    # block before and after block i's centre
    np.testing.assert_allclose(up[0, 2], 0.75 * image[0, 1] + 0.25 * image[0, 0])
    np.testing.assert_allclose(up[0, 3], 0.75 * image[0, 1] + 0.25 * image[0, 2])
    np.testing.assert_array_equal(up[6], up[5])  # the row past the last whole block repeats the edge
    np.testing.assert_array_equal(up[:, 8], up[:, 7])
    np.testing.assert_array_equal(upsample_blocks(image, 1, (3, 4)), image)


@pytest.mark.parametrize("size", [(65, 97), (5, 7), (3, 200)])
def test_odd_and_tiny_frames(network, size):
    """Sizes that are no multiple of the working-resolution block (the last full-size rows / columns take the
    last block's flow), frames of a few pixels and a frame 3 px high (smaller than the network's stride and
    DIS's block on one side): finite output of the frame's size, the initial flow covering every pixel."""
    h, w = size
    frames, _ = two_layer_sequence(4, width=w, height=h, camera_speed=0.02, object_speed=0.15)
    pred = DecompPredictor(DecompConfig(gate=GateConfig(enabled=False)), network)
    state = pred.prepare([frames[1], frames[3]])
    assert state.data.flow.shape[-2:] == (h, w) and np.isfinite(state.data.flow).all()
    out = pred.render(state, _target(frames[3]))
    assert out.color.shape == (h, w, 3) and np.isfinite(out.color).all()


def test_whole_frame_dis_finds_motion_larger_than_a_small_box_reaches(network):
    """A small square moving 29 px a frame (58 px between the two frames): DIS on its gate box alone would
    have too few pyramid levels and stop short; DIS on the whole frame finds the motion."""
    frames, _ = two_layer_sequence(5, width=480, height=256, camera_speed=0.01, object_speed=0.2, square_half=0.2)
    moving = frames[3].moving
    expected = -2.0 * frames[3].object_flow[..., 0][moving]
    assert np.abs(expected).min() > 55
    pred = DecompPredictor(DecompConfig(), network)
    state = pred.prepare([frames[1], frames[3]])
    (y0, y1, x0, x1), = state.data.boxes
    assert (y1 - y0) * (x1 - x0) < 0.3 * 480 * 256  # one box, well inside the frame
    error = float(np.median(np.abs(pred.object_flow(state)[..., 0][moving] - expected)))
    assert error < 0.15 * np.abs(expected).mean(), error


def _sky_frame(index, camera, width=96, height=64):
    color = np.full((height, width, 3), 0.4, np.float32)
    color[..., 2] += np.linspace(0, 0.5, width, dtype=np.float32)[None]
    return Frame(index=index, time=index / 30, color=color, depth=np.full((height, width), np.inf, np.float32),
                 camera=camera)


def test_all_sky_and_one_to_thousand_depth_stay_finite(network):
    k = np.array([[80.0, 0, 48], [0, 80.0, 32], [0, 0, 1]])
    cams = [Camera(k, rigid([0, 1, 0], 0.02 * i, [0.05 * i, 0, 0])) for i in range(3)]
    sky = [_sky_frame(i, cams[i]) for i in range(3)]
    for gate in (True, False):
        out = DecompPredictor(DecompConfig(gate=GateConfig(enabled=gate)), network).predict(sky[:2], _target(sky[2]))
        assert np.isfinite(out.color).all()
    frames = []
    for i in range(3):  # a near square at depth 0.01 in front of a wall at 10 (1:1000), moving
        f = sky[i]
        depth = np.full(f.depth.shape, 10.0, np.float32)
        depth[20:40, 30 + 4 * i:50 + 4 * i] = 0.01
        color = f.color.copy()
        color[20:40, 30 + 4 * i:50 + 4 * i] = [0.9, 0.1, 0.1]
        frames.append(Frame(index=i, time=f.time, color=color, depth=depth, camera=cams[i]))
    for gate in (True, False):
        out = DecompPredictor(DecompConfig(gate=GateConfig(enabled=gate)), network).predict(frames[:2], _target(frames[2]))
        assert np.isfinite(out.color).all() and out.color.shape == frames[2].color.shape


def test_network_on_empty_mpis_and_odd_sizes_returns_finite_zeros(network):
    z = network.num_planes
    for h, w in ((16, 16), (23, 37)):  # 23 x 37 is padded to the pyramid stride inside FlowNetwork
        empty = geometry.Mpi(np.zeros((3, z, h, w), np.float32), np.zeros((z, h, w), np.float32),
                             np.zeros((z, h, w), np.float32), np.array([1.0, 2.0, 4.0, np.inf][-z:], np.float32))
        flow = network(empty, empty, np.zeros((h, w, 2), np.float32))
        assert flow.shape == (3, z, h, w) and (flow == 0).all()


def test_object_leaving_the_frame_and_motion_beyond_search_range(network, monkeypatch):
    # the square moves 40 px per frame (the coarsest level's search range is far smaller) and has left the
    # view by frame 3; the camera stands still
    frames, _ = two_layer_sequence(6, width=96, height=64, camera_speed=0.0, object_speed=0.9)
    assert frames[1].moving.any() and not (frames[3].moving.any() or frames[4].moving.any())
    pred = DecompPredictor(DecompConfig(), network)
    flow2d = make_predictor("flow2d")
    unchecked = make_predictor("flow2d")  # DIS's flow as it comes, without trusted_motion

    def error(predictor, n, truth):
        return np.abs(predictor.predict([frames[n - 1], frames[n]], _target(truth)).color - truth.color).mean()

    for n in (1, 3):  # moving too far to match; leaving between n-k and n
        truth = frames[n + 1]
        out = pred.predict([frames[n - 1], frames[n]], _target(truth))
        assert np.isfinite(out.color).all() and out.color.shape == truth.color.shape
        checked = (np.abs(out.color - truth.color).mean(), error(flow2d, n, truth))
        with monkeypatch.context() as patch:
            patch.setattr(classic_module, "drop_untrusted", lambda flow, luma, target, seen: flow)
            raw = error(unchecked, n, truth)
        # neither is worse than DIS's flow as it comes (decomp refines flow2d's; trusted_motion only removes motion)
        assert max(checked) <= raw + 1e-3, (n, checked, raw)
    # gone from both frames: nothing moves, so the next frame is frame n itself, to the bit
    later = Target(frames[5].camera, frames[5].time + (frames[5].time - frames[4].time), 6)
    out = pred.predict([frames[4], frames[5]], later)
    np.testing.assert_array_equal(out.color, frames[5].color)
    assert not out.holes.any()


def test_single_plane_network_and_tiny_frames():
    """The 2D ablation network (one plane) runs through the same predictor; frames smaller than a block."""
    pred = make_predictor("decomp2d")
    assert pred.network.num_planes == 1
    frames, _ = two_layer_sequence(3, width=40, height=24, object_speed=0.1)
    out = pred.predict(frames[:2], _target(frames[2]))
    assert np.isfinite(out.color).all() and out.color.shape == (24, 40, 3)


def test_bad_inputs_name_the_problem(network, tmp_path):
    with pytest.raises(InputError, match="flow network not found"):
        FlowNetwork(tmp_path / "missing.onnx")
    with pytest.raises(InputError, match="GateConfig"):
        GateConfig(tile=0)
    with pytest.raises(InputError, match="DecompConfig"):
        DecompConfig(threads=0)
    frames, _ = two_layer_sequence(3)
    pred = DecompPredictor(DecompConfig(), network)
    with pytest.raises(InputError, match="needs 2 rendered frames"):
        pred.prepare(frames[:1])
    with pytest.raises(InputError, match="time order"):
        pred.prepare([frames[1], frames[0]])


def test_method_options_parse_and_reject_bad_ones():
    assert split_methods("reproject, decomp[gate.enabled=false,flow_width=240],flow2d") == [
        "reproject", "decomp[gate.enabled=false,flow_width=240]", "flow2d"]
    config = decomp_config("gate.enabled=0,flow_width=240,gate.tile=16,model=x.onnx")
    assert (config.gate.enabled, config.flow_width, config.gate.tile, config.model) == (False, 240, 16, "x.onnx")
    assert decomp_config("").model == str(DEFAULT_MODEL)
    for bad in ("gate.enabled=maybe", "flow_width=wide", "nonsense=1", "gate", "gate=0"):
        with pytest.raises(InputError, match="option"):
            decomp_config(bad)
    with pytest.raises(InputError, match="only decomp"):
        make_predictor("reproject[gate=0]")
    assert make_predictor("flow2d[preset=fast]").name == "flow2d"
    for bad in ("flow2d[gate=0]", "flow2d[preset=slow]"):
        with pytest.raises(InputError, match="preset"):
            make_predictor(bad)
    # motion=truth: decomp given the true object motion (the bound), which needs the sequence's objects
    _, objects = two_layer_sequence(2)
    assert type(make_predictor("decomp[motion=truth,fill=simple]", objects)) is DecompTrueMotion
    assert type(make_predictor("decomp[motion=predicted]")) is DecompPredictor
    with pytest.raises(InputError, match="motion=truth needs the sequence's moving objects"):
        make_predictor("decomp[motion=truth]")
    with pytest.raises(InputError, match="motion must be 'predicted' or 'truth'"):
        make_predictor("decomp[motion=guess]")
    assert decomp_config("estimator=gl").estimator == "gl" and decomp_config("").estimator == "corr"
    with pytest.raises(InputError, match="estimator=raft': must be one of dis, gl"):
        make_predictor("decomp[estimator=raft]")


def test_committed_networks_and_dz(network):
    """The committed graph is exported without dz (--no-depth-flow); the 2D ablation's computes it. decomp
    uses (du, dv) only either way (dz comes out 0)."""
    assert not network.depth_flow
    with_dz = FlowNetwork(DEFAULT_MODEL.with_name("flow2d.onnx"), threads=1)
    assert with_dz.depth_flow
