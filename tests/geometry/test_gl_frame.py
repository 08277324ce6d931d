"""The GL backend's frame warp + hole fill (engine/geometry/backends/gl/frame.py) against its oracle, the CPU
``forward_warp_frame`` + ``fill_holes`` (what ``engine.predict.base.warp_and_fill`` runs).

Tolerances (those of the splat's parity test, tests/geometry/test_gl_splat.py): the holes identical on
>= 99.9 % of the pixels and the colour within 1e-3 of max(1, value) on >= 99.5 %; no NaN. The hole fill
copies pixels, so where the warps agree the fills agree exactly. Cases: sky, depths 1e-3..1e5, points
behind the camera, rows and columns longer than a workgroup, rows with no surface (filled along columns),
frames that are all hole, 1x1 frames, object flow of 2 and 3 channels scaled on the GPU.
"""
from __future__ import annotations

import gc

import numpy as np
import pytest

from engine import geometry
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.holefill import fill_holes
from tests.random_scenes import extreme_scene, intrinsics, moving_cameras, pose, random_scene

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)

_WARPER: list = []


def warper() -> glb.GlFrameWarper:
    if not _WARPER:
        _WARPER.append(glb.GlFrameWarper())
    return _WARPER[0]


def cpu_warp_and_fill(color, depth, k, t_src, t_dst, flow=None):
    warped, warped_depth, holes = geometry.forward_warp_frame(color, depth, k, t_src, k, t_dst, flow)
    filled, _ = fill_holes(warped, warped_depth, holes, color)
    return filled, holes


def assert_parity(color, depth, k, t_src, t_dst, flow=None, scale=1.0) -> np.ndarray:
    """Warp on both backends, check the tolerances; returns the CPU holes."""
    ref_color, ref_holes = cpu_warp_and_fill(color, depth, k, t_src, t_dst, None if flow is None else scale * flow)
    gl = warper()
    image = gl.upload(color, depth)
    gl_flow = None if flow is None else gl.upload_flow(flow)
    gpu_ms: dict = {}
    out, holes = gl.warp_and_fill(image, k, t_src, k, t_dst, gl_flow, scale, gpu_ms=gpu_ms)
    assert out.shape == color.shape and out.dtype == np.float32 and holes.shape == depth.shape
    assert holes.dtype == bool and np.isfinite(out).all()
    assert set(gpu_ms) == {"warp", "fill", "readback"} and all(v >= 0 for v in gpu_ms.values())
    assert np.mean(holes == ref_holes) >= 0.999
    ok = (np.abs(out - ref_color) <= 1e-3 * np.maximum(1.0, np.abs(ref_color))).all(axis=-1)
    assert np.mean(ok) >= 0.995
    return ref_holes


@pytest.mark.parametrize("size", [(12, 16), (48, 300), (300, 40), (1, 1), (1, 7), (7, 1)])
@pytest.mark.parametrize("flow_channels", [0, 2, 3])
def test_random_frames(size, flow_channels):
    h, w = size
    rng = np.random.default_rng(h * 1000 + w * 10 + flow_channels)
    if min(h, w) >= 4:
        color, depth = random_scene(rng, h, w, sky=0.2)
    else:
        color = rng.uniform(0, 1, (h, w, 3)).astype(np.float32)
        depth = rng.uniform(1, 5, (h, w)).astype(np.float32)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.05, shift=0.2)
    flow = rng.normal(0, 2.0, (h, w, flow_channels)).astype(np.float32) if flow_channels else None
    if flow is not None and flow_channels == 3:
        flow[..., 2] *= 0.05
    assert_parity(color, depth, k, t_src, t_dst, flow, scale=-1.5 if flow is not None else 1.0)


@pytest.mark.parametrize("seed", [0, 1])
def test_extreme_depths_and_poses(seed):
    color, depth, k, poses = extreme_scene(seed)
    for t_dst in poses:  # behind the camera, far off screen, far ahead
        assert_parity(color, depth, k, np.eye(4), t_dst)


def test_rows_without_a_surface_are_filled_along_columns():
    rng = np.random.default_rng(3)
    h, w = 280, 64  # taller than a workgroup: the links scan runs over several chunks
    color, depth = random_scene(rng, h, w, sky=0.0, near=2.0, far=4.0)
    k = intrinsics(h, w)
    t_dst = pose(translation=(0.0, 1.5, 0.0))  # the camera moves down: whole rows at the bottom see nothing
    holes = assert_parity(color, depth, k, np.eye(4), t_dst)
    assert holes.all(axis=1).any() and not holes.all()


def test_all_hole_frame_takes_the_fallback():
    rng = np.random.default_rng(4)
    h, w = 20, 30
    color, depth = random_scene(rng, h, w, sky=0.0)
    k = intrinsics(h, w)
    t_dst = pose((0.0, np.pi, 0.0))  # facing away: nothing lands
    holes = assert_parity(color, depth, k, np.eye(4), t_dst)
    assert holes.all()
    out, _ = warper().warp_and_fill(warper().upload(color, depth), k, np.eye(4), k, t_dst)
    np.testing.assert_array_equal(out, color)


def test_all_sky_frame_moves_with_rotation_only():
    rng = np.random.default_rng(5)
    h, w = 24, 40
    color = rng.uniform(0, 4, (h, w, 3)).astype(np.float32)
    depth = np.full((h, w), np.inf, np.float32)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    assert_parity(color, depth, k, t_src, t_dst)


def test_one_upload_serves_many_targets():
    rng = np.random.default_rng(6)
    h, w = 40, 60
    color, depth = random_scene(rng, h, w)
    k, t_src, _ = moving_cameras(rng, h, w)
    gl = warper()
    image = gl.upload(color, depth)
    for step in range(3):
        t_dst = pose((0.0, 0.02 * step, 0.0), (0.05 * step, 0.0, 0.0)) @ t_src
        out, holes = gl.warp_and_fill(image, k, t_src, k, t_dst)
        ref, ref_holes = cpu_warp_and_fill(color, depth, k, t_src, t_dst)
        assert np.mean(holes == ref_holes) >= 0.999 and np.mean(np.abs(out - ref).max(-1) < 1e-3) >= 0.995


def test_a_resident_flow_copies_on_the_gpu():
    gl = warper()
    flow = np.random.default_rng(4).normal(size=(9, 7, 2)).astype(np.float32)
    resident = gl.upload_flow(flow)
    copy = resident.copy()
    assert copy.buffer is not resident.buffer and (copy.shape, copy.channels) == (resident.shape, 2)
    np.testing.assert_array_equal(copy.read(), flow)


def test_bad_inputs_are_refused():
    gl = warper()
    k = intrinsics(8, 12)
    image = gl.upload(np.zeros((8, 12, 3), np.float32), np.ones((8, 12), np.float32))
    with pytest.raises(InputError) as err:
        gl.upload(np.zeros((8, 12, 3), np.float32), np.ones((8, 13), np.float32))
    assert err.value.field == "color"
    with pytest.raises(InputError):
        gl.upload_flow(np.zeros((8, 12, 4), np.float32))
    other = gl.upload_flow(np.zeros((8, 11, 2), np.float32))
    with pytest.raises(InputError) as err:
        gl.warp_and_fill(image, k, np.eye(4), k, np.eye(4), other)
    assert err.value.field == "flow"
    with pytest.raises(InputError) as err:
        gl.warp_and_fill(image, k, np.eye(4), k, np.eye(4), flow_scale=float("nan"))
    assert err.value.field == "flow_scale"
    with pytest.raises(InputError):
        gl.warp_and_fill(np.zeros((8, 12)), k, np.eye(4), k, np.eye(4))


@pytest.mark.parametrize("with_acceleration", [False, True])
def test_motion_extrapolated_on_the_gpu_matches_the_cpu(with_acceleration):
    from engine.geometry.motion import extrapolated_flow

    rng = np.random.default_rng(7 + with_acceleration)
    h, w = 48, 64
    color, depth = random_scene(rng, h, w, sky=0.1, near=1.0, far=6.0)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.03, shift=0.1)
    velocity = np.zeros((h, w, 3), np.float32)
    velocity[10:30, 20:40] = rng.normal(0, 0.05, (20, 20, 3))
    velocity[12, 22] = (0.0, 0.0, -50.0)  # reaches the camera plane: NaN flow, dropped by the splat
    moving = np.flatnonzero(np.any(velocity != 0, axis=-1))
    accel = rng.normal(0, 0.01, (moving.size, 3)).astype(np.float32) if with_acceleration else None
    step = 0.5
    flow = extrapolated_flow(depth, velocity, k, step, moving, accel)
    assert np.isnan(flow[12, 22]).all()
    ref_color, ref_holes = cpu_warp_and_fill(color, depth, k, t_src, t_dst, flow)
    gl = warper()
    motion = gl.upload_motion((h, w), moving, velocity.reshape(-1, 3)[moving], accel)
    gpu_ms: dict = {}
    out, holes = gl.warp_and_fill(gl.upload(color, depth), k, t_src, k, t_dst, flow_scale=step, motion=motion,
                                  gpu_ms=gpu_ms)
    assert "motion" in gpu_ms and np.isfinite(out).all()
    assert np.mean(holes == ref_holes) >= 0.999
    assert np.mean((np.abs(out - ref_color) <= 1e-3 * np.maximum(1.0, np.abs(ref_color))).all(-1)) >= 0.995
    with pytest.raises(InputError) as err:
        gl.upload_motion((h, w), np.array([h * w]), np.zeros((1, 3), np.float32))
    assert err.value.field == "moving"


def test_frames_adopted_from_the_context_and_predictions_left_on_the_gpu():
    from engine.geometry.backends.gl.frame import GlPrediction

    rng = np.random.default_rng(8)
    h, w = 30, 50
    color, depth = random_scene(rng, h, w)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    gl = warper()
    ctx = gl.gl.ctx
    # a renderer on the shared context wrote these buffers: the warper uses them without a copy
    color_buf, depth_buf = gl.gl.call(lambda: (ctx.buffer(color.tobytes()), ctx.buffer(depth.tobytes())))
    image = gl.adopt(color_buf, depth_buf, (h, w))
    out = gl.warp_and_fill(image, k, t_src, k, t_dst, readback=False)
    assert isinstance(out, GlPrediction)
    gl.warp_and_fill(image, k, t_src, k, np.eye(4))  # the next warp does not overwrite what was handed out
    got_color, got_holes = out.read()
    ref_color, ref_holes = gl.warp_and_fill(gl.upload(color, depth), k, t_src, k, t_dst)
    np.testing.assert_array_equal(got_color, ref_color)
    np.testing.assert_array_equal(got_holes, ref_holes)
    del image, out
    gc.collect()  # adopted buffers stay the caller's: still readable after the image is gone
    np.testing.assert_array_equal(gl.gl.call(lambda: np.frombuffer(color_buf.read(), np.float32)), color.ravel())
    with pytest.raises(InputError) as err:
        gl.adopt(color_buf, depth_buf, (h, w + 1))
    assert err.value.field == "color"


def test_a_frame_collected_while_a_thread_pool_submits_does_not_deadlock():
    # A garbage-collection finalizer can run inside any ThreadPoolExecutor.submit (e.g. the CPU kernels'),
    # which holds concurrent.futures' global lock: freeing GPU buffers there must not wait on the GL thread.
    import concurrent.futures.thread as cft
    import threading

    gl = warper()
    image = gl.upload(np.zeros((4, 5, 3), np.float32), np.ones((4, 5), np.float32))
    done = threading.Event()

    def collect_under_the_lock():
        nonlocal image
        with cft._global_shutdown_lock:
            del image
            gc.collect()
        done.set()

    worker = threading.Thread(target=collect_under_the_lock, daemon=True)
    worker.start()
    assert done.wait(10.0), "the finalizer waited on the GL thread while the pool lock was held"
    assert len(gl.gl._garbage) >= 2  # queued, not freed: no GL call has run since
    kept = gl.upload(np.zeros((2, 2, 3), np.float32), np.ones((2, 2), np.float32))  # the next call frees them
    assert not gl.gl._garbage and kept.shape == (2, 2)


def test_a_forked_child_is_told_the_context_stayed_in_the_parent():
    import multiprocessing

    from engine.geometry import backends
    from engine.geometry.backends.gl.context import shared_context

    parent = shared_context()

    def child(queue):
        answers = []
        for attempt in (lambda: parent.call(lambda: None), shared_context):
            try:
                attempt()
                answers.append("answered")
            except RuntimeError as exc:
                answers.append("refused" if "process" in str(exc) else str(exc))
        answers.append(backends.resolve_backend("auto"))  # no GL here: the CPU
        queue.put(answers)

    ctx = multiprocessing.get_context("fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=child, args=(queue,))
    proc.start()
    proc.join(30)
    assert proc.exitcode == 0 and queue.get(timeout=5) == ["refused", "refused", "cpu"]


@pytest.mark.parametrize("case", ["random", "rows_without_surface", "all_holes"])
def test_filled_depth_matches_the_cpu(case):
    """warp_and_fill(with_depth=True): the same colour and holes as without, and the filled depth of
    engine.predict.base.warp_fill_depth (the warp's depth, a hole's source depth, +inf with no source)."""
    rng = np.random.default_rng(11)
    h, w = (280, 64) if case == "rows_without_surface" else (40, 56)
    color, depth = random_scene(rng, h, w, sky=0.0 if case != "random" else 0.2, near=2.0, far=4.0)
    k = intrinsics(h, w)
    t_dst = {"random": moving_cameras(rng, h, w, angle=0.05, shift=0.2)[2],
             "rows_without_surface": pose(translation=(0.0, 1.5, 0.0)),
             "all_holes": pose((0.0, np.pi, 0.0))}[case]
    warped, warped_depth, ref_holes = geometry.forward_warp_frame(color, depth, k, np.eye(4), k, t_dst)
    _, ref_depth = fill_holes(warped, warped_depth, ref_holes, color)
    gl = warper()
    image = gl.upload(color, depth)
    plain, plain_holes = gl.warp_and_fill(image, k, np.eye(4), k, t_dst)
    out, holes, filled = gl.warp_and_fill(image, k, np.eye(4), k, t_dst, with_depth=True)
    np.testing.assert_array_equal(out, plain)
    np.testing.assert_array_equal(holes, plain_holes)
    assert filled.shape == (h, w) and filled.dtype == np.float32 and not np.isnan(filled).any()
    both_inf = np.isinf(filled) & np.isinf(ref_depth)
    finite = np.isfinite(filled) & np.isfinite(ref_depth)
    same = both_inf | (finite & (np.abs(np.where(finite, filled - ref_depth, 0.0)) <= 1e-5 * np.abs(ref_depth)))
    assert np.mean(same) >= 0.995
    if case == "all_holes":
        assert holes.all() and np.isinf(filled).all()
    with pytest.raises(InputError, match="with_depth"):
        gl.warp_and_fill(image, k, np.eye(4), k, t_dst, readback=False, with_depth=True)


def test_dropped_frame_buffers_are_reused_at_their_size_within_the_cap():
    """GlContext.new_buffer: a dropped frame's buffers serve the next frame of the same size (same GL object,
    the new contents), other sizes get new buffers, and no more than recycle_bytes are kept."""
    gl = warper().gl
    rng = np.random.default_rng(5)
    color, depth = random_scene(rng, 24, 32, sky=0.1)
    image = warper().upload(color, depth)
    names = {image.color.glo, image.depth.glo}
    del image
    gc.collect()
    second = warper().upload(color[::-1].copy(), depth[::-1].copy())
    assert {second.color.glo, second.depth.glo} == names
    got = gl.call(lambda: np.frombuffer(second.color.read(), np.float32).reshape(color.shape))
    np.testing.assert_array_equal(got, color[::-1])
    other = warper().upload(color[:, :16].copy(), depth[:, :16].copy())
    assert not {other.color.glo, other.depth.glo} & names
    saved = gl.recycle_bytes
    try:
        gl.recycle_bytes = 0  # nothing kept: dropped buffers are freed
        del other
        gc.collect()
        gl.call(lambda: None)
        assert not gl._free.get(12 * 24 * 16) and not gl._free.get(4 * 24 * 16)
    finally:
        gl.recycle_bytes = saved


def test_srgb8_encoded_on_the_gpu_equals_the_cpu_codes_at_every_step():
    """Pass ``encode8`` (GlFrameWarper.encode8): bit for bit ``encoding.encode8`` on the table's every step and
    its float32 neighbours, NaN, +-inf, negatives, values above 1 and denormals, for pixel counts whose code
    bytes do not fill the last 32-bit word."""
    from engine.core.colorspace import encode8_table
    from engine.geometry.encoding import encode8

    gl = warper()
    _, step = encode8_table()
    steps = step[np.isfinite(step)]
    rng = np.random.default_rng(12)
    hard = np.array([np.nan, -np.nan, np.inf, -np.inf, 0.0, -0.0, 1.0, 1e-45, -1e-45, 1e30, 0.0031308], np.float32)
    values = np.concatenate([hard, steps, np.nextafter(steps, np.float32(0)), np.nextafter(steps, np.float32(2)),
                             rng.uniform(-0.5, 1.5, 3000), rng.uniform(0, 1e-3, 300)]).astype(np.float32)
    for n in (1, 2, 3, 5, values.size // 3):  # 3 n codes: 3, 6, 9, 15 bytes and the whole sample
        color = np.resize(values, 3 * n).reshape(1, n, 3)
        buffer = gl.gl.call(lambda: gl.gl.new_buffer(data=color))
        codes = gl.encode8(buffer, (1, n))
        assert codes.dtype == np.uint8 and codes.shape == (1, n, 3)
        np.testing.assert_array_equal(codes, encode8(color))
        gl.gl.discard([buffer])


def test_warp_read_back_as_srgb8_is_the_encoded_float_warp():
    """warp_and_fill(encoding="srgb8"): the codes of the float colour the same warp reads back, the same
    holes, an ``encode`` GPU stage; bad encodings and a GPU-resident srgb8 prediction are refused."""
    from engine.geometry.encoding import encode8

    gl = warper()
    rng = np.random.default_rng(13)
    color, depth = random_scene(rng, 41, 67)
    k, t_src, t_dst = moving_cameras(rng, 41, 67)
    color = (color * 1.4 - 0.2).astype(np.float32)  # values outside [0, 1] clip
    image = gl.upload(color, depth)
    linear, holes = gl.warp_and_fill(image, k, t_src, k, t_dst)
    gpu_ms: dict = {}
    codes, codes_holes = gl.warp_and_fill(image, k, t_src, k, t_dst, encoding="srgb8", gpu_ms=gpu_ms)
    assert codes.dtype == np.uint8 and codes.shape == color.shape
    np.testing.assert_array_equal(codes, encode8(linear))
    np.testing.assert_array_equal(codes_holes, holes)
    assert set(gpu_ms) == {"warp", "fill", "encode", "readback"}
    codes_d, _, depth_d = gl.warp_and_fill(image, k, t_src, k, t_dst, encoding="srgb8", with_depth=True)
    np.testing.assert_array_equal(codes_d, codes)
    assert depth_d.dtype == np.float32 and depth_d.shape == depth.shape
    with pytest.raises(InputError, match="encoding"):
        gl.warp_and_fill(image, k, t_src, k, t_dst, encoding="srgb")
    with pytest.raises(InputError, match="encoding"):
        gl.warp_and_fill(image, k, t_src, k, t_dst, encoding="srgb8", readback=False)


@pytest.mark.parametrize("channels", [3, 4])
@pytest.mark.parametrize("size", [(1, 1), (1, 3), (16, 16), (9, 31)])
def test_codes_uploaded_and_decoded_on_the_gpu_are_the_cpu_decoding(size, channels):
    """upload_codes: every code 0..255 decodes as ``encoding.decode8`` does, bit for bit, byte counts that do not
    fill the last 32-bit word included; the image warps as the float upload of the decoded colour does."""
    from engine.geometry.encoding import decode8

    rng = np.random.default_rng(14)
    h, w = size
    codes = rng.integers(0, 256, (h, w, channels), dtype=np.uint8)
    codes.flat[:min(codes.size, 256)] = np.arange(min(codes.size, 256))
    depth = rng.uniform(1.0, 9.0, (h, w)).astype(np.float32)
    depth[0, 0] = np.inf  # sky
    gl = warper()
    image = gl.upload_codes(codes, depth)
    got = gl.gl.call(lambda: np.frombuffer(image.color.read(), np.float32)[:3 * h * w].reshape(h, w, 3).copy())
    np.testing.assert_array_equal(got, decode8(codes[..., :3]))
    k, t_src, t_dst = moving_cameras(rng, h, w)
    for a, b in zip(gl.warp_and_fill(image, k, t_src, k, t_dst),
                    gl.warp_and_fill(gl.upload(decode8(codes[..., :3]), depth), k, t_src, k, t_dst)):
        np.testing.assert_array_equal(a, b)


def test_bad_codes_are_refused():
    gl = warper()
    depth = np.ones((4, 5), np.float32)
    for codes, field in ((np.zeros((4, 5, 3), np.float32), "codes"), (np.zeros((4, 5, 2), np.uint8), "codes"),
                         (np.zeros((4, 6, 3), np.uint8), "codes"), (np.zeros((4, 5), np.uint8), "codes")):
        with pytest.raises(InputError) as err:
            gl.upload_codes(codes, depth)
        assert err.value.field == field


@pytest.mark.parametrize("moved", ["none", "flow", "motion"])
def test_the_binned_and_atomic_splats_warp_a_frame_to_the_same_bits(moved):
    """GlFrameWarper's two splats (engine.geometry.backends.gl.splat.SPLATS) on the frame path: the same warped
    colour, depth and holes, and so the same filled frame, bit for bit (sky, flow scaled on the GPU, motion
    extrapolated on the GPU)."""
    rng = np.random.default_rng(["none", "flow", "motion"].index(moved))
    h, w = 72, 100
    color, depth = random_scene(rng, h, w, sky=0.2, boxes=6)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.04, shift=0.15)
    flow = (rng.normal(0, 2.0, (h, w, 3)) * [1.0, 1.0, 0.05]).astype(np.float32)
    moving = np.arange(0, h * w, 3)
    velocity = rng.normal(0, 0.05, (moving.size, 3)).astype(np.float32)
    results = []
    for splat in ("binned", "atomic"):
        gl = glb.GlFrameWarper(splat=splat)
        kwargs: dict = {}
        if moved == "flow":
            kwargs = {"flow": gl.upload_flow(flow), "flow_scale": -1.5}
        elif moved == "motion":
            kwargs = {"motion": gl.upload_motion((h, w), moving, velocity), "flow_scale": 0.5}
        image = gl.upload(color, depth)
        out, holes, filled_depth = gl.warp_and_fill(image, k, t_src, k, t_dst, with_depth=True, **kwargs)
        results.append((out, holes, filled_depth))
        gl.release()
    (a, a_holes, a_depth), (b, b_holes, b_depth) = results
    np.testing.assert_array_equal(a.view(np.uint32), b.view(np.uint32))
    np.testing.assert_array_equal(a_depth.view(np.uint32), b_depth.view(np.uint32))
    np.testing.assert_array_equal(a_holes, b_holes)
    assert 0.0 < a_holes.mean() < 0.5


@pytest.mark.parametrize("size", [(29, 37), (64, 96)])
def test_the_hole_mask_is_written_whole_without_a_clear(size):
    """fill_apply writes every word of the packed hole mask from its workgroup's shared copy (no clear before):
    a warp with few holes after one that is almost all hole, on the same warper, leaves no stale bit, and the
    mask of the pixels past the last (the last word's high bits) is zero."""
    h, w = size
    rng = np.random.default_rng(h)
    color, depth = random_scene(rng, h, w, sky=0.0)
    k, t_src, t_dst = moving_cameras(rng, h, w, angle=0.02, shift=0.05)
    away = np.eye(4)
    away[:3, 3] = (0.0, 0.0, -50.0)  # the camera turned into a point behind it: every pixel a hole
    gl = glb.GlFrameWarper()
    image = gl.upload(color, depth)
    _, holes_away = gl.warp_and_fill(image, k, np.eye(4), k, away)
    assert holes_away.all()
    _, holes = gl.warp_and_fill(image, k, t_src, k, t_dst)
    np.testing.assert_array_equal(holes, cpu_warp_and_fill(color, depth, k, t_src, t_dst)[1])
    assert 0.0 < holes.mean() < 0.2
    prediction = gl.warp_and_fill(image, k, t_src, k, t_dst, readback=False)
    mask = np.empty(-(-h * w // 32), np.uint32)
    gl.gl.call(lambda: prediction.holes.read_into(mask, size=mask.nbytes))
    assert np.unpackbits(mask.view(np.uint8), bitorder="little")[h * w:].sum() == 0
    gl.release()


@pytest.mark.parametrize("splat", glb.splat.SPLATS)
def test_pass_timing_names_every_pass_of_a_warp(splat):
    """GlContext.pass_timing (tools.profile_gl_passes, tools.bench_gl_warp) counts each dispatch of a warp under
    its pass: the splat's passes and the fill's, once each, with their times (GPU ms, or on a software renderer
    the clock ms of each pass, > 0)."""
    from engine.geometry.backends.gl.splat import BINNED_PASSES, SPLAT_PASSES

    rng = np.random.default_rng(3)
    h, w = 40, 60
    color, depth = random_scene(rng, h, w)
    k, t_src, t_dst = moving_cameras(rng, h, w)
    gl = glb.GlFrameWarper(splat=splat)
    image = gl.upload(color, depth)
    gl.warp_and_fill(image, k, t_src, k, t_dst)
    passes: dict = {}
    with gl.gl.pass_timing(passes):
        gl.warp_and_fill(image, k, t_src, k, t_dst)
    splat_passes = BINNED_PASSES if splat == "binned" else SPLAT_PASSES + ("splat_resolve",)
    expected = {name: 1 for name in splat_passes + ("fill_rows", "fill_links", "fill_apply")}
    if splat == "atomic":
        expected["clear_words"] = 2  # its keys and sums
    assert {name: calls for name, (calls, _) in passes.items()} == expected
    assert all(ms >= 0.0 for _, ms in passes.values())
    if gl.gl.software:
        assert all(ms > 0.0 for _, ms in passes.values())
    gl.release()
