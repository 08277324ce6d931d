"""The GL backend's optical flow (engine/geometry/backends/gl/flow.py) on Mesa llvmpipe.

No bit-exact oracle exists for the flow itself (it is not OpenCV's DIS), so it is held to what a flow must do,
with stated tolerances: the luma pass equals ``luma8`` exactly; known translations (0.5, 3 and 12 px) of a
multi-scale texture recovered in the interior (median error <= 0.1 px, 95th percentile <= 0.25 px); on the
analytic two-layer scene, prepared as ``flow2d`` prepares it, the median end-point error over the moving
square at most 1.5 times OpenCV DIS medium's on the same inputs; zero flow on a constant image; finite flows
of the right shape on 1 x 1, 1 x N, N x 1 and 7 x 5 images; ``GlImage`` and raw-buffer inputs giving the
numpy inputs' result; bad inputs raising InputError naming the field.
"""
from __future__ import annotations

import cv2
import numpy as np
import pytest

from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.geometry.backends.gl.flow import (COARSE_PIXELS, PATCH_LANES, GlFlowConfig, GlOpticalFlow, dispatch_counts,
                                              pyramid_levels)
from engine.predict.base import Target, Timer, true_object_flow, warp_and_fill
from engine.predict.dis import dis_calc, dis_estimator, luma8
from tests.synthetic import two_layer_sequence

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)

_FLOW: list = []


def estimator() -> GlOpticalFlow:
    if not _FLOW:
        _FLOW.append(GlOpticalFlow())
    return _FLOW[0]


def texture(h: int, w: int, seed: int) -> np.ndarray:
    """(h, w, 3) linear RGB: smooth random noise at three scales (32, 12, 4 px cells)."""
    rng = np.random.default_rng(seed)
    out = np.zeros((h, w, 3), np.float32)
    for cell, amp in ((32, 0.5), (12, 0.3), (4, 0.2)):
        noise = rng.uniform(-1, 1, (h // cell + 3, w // cell + 3, 3)).astype(np.float32)
        out += amp * cv2.resize(noise, (w + 3 * cell, h + 3 * cell), interpolation=cv2.INTER_CUBIC)[:h, :w]
    return (0.3 + 0.25 * out).clip(0.0, 1.0)


def shifted_pair(h: int, w: int, shift, margin: int = 24, seed: int = 3):
    """(a, b): b shows a's content moved by ``shift`` (dx, dy) px, so the flow a -> b is ``shift`` everywhere."""
    base = texture(h + 2 * margin, w + 2 * margin, seed)
    matrix = np.float32([[1, 0, shift[0]], [0, 1, shift[1]]])
    moved = cv2.warpAffine(base, matrix, (base.shape[1], base.shape[0]), flags=cv2.INTER_LINEAR)
    return base[margin:margin + h, margin:margin + w].copy(), moved[margin:margin + h, margin:margin + w].copy()


def test_luma_equals_luma8():
    rng = np.random.default_rng(0)
    color = rng.uniform(-0.2, 1.3, (37, 53, 3)).astype(np.float32)
    color[0, 0, 0], color[1, 1, 1], color[2, 2, 2] = np.nan, np.inf, 0.0031308
    color[3] = np.linspace(0.0, 1.0, 53 * 3, dtype=np.float32).reshape(53, 3)
    np.testing.assert_array_equal(estimator().luma(color), luma8(color))


@pytest.mark.parametrize("t", [0.5, 3.0, 12.0])
def test_translation_recovered(t):
    h, w, margin = 96, 160, 24
    shift = np.array([t, -0.5 * t])
    a, b = shifted_pair(h, w, shift, margin)
    flow = estimator().estimate(a, b)
    assert flow.shape == (h, w, 2) and flow.dtype == np.float32 and np.isfinite(flow).all()
    error = np.linalg.norm(flow - shift, axis=-1)[margin:-margin, margin:-margin]
    assert np.median(error) <= 0.1
    assert np.percentile(error, 95) <= 0.25


@pytest.mark.parametrize("config", [GlFlowConfig(sweeps=1, refine_iterations=0), GlFlowConfig(finest_level=0),
                                    GlFlowConfig(patch_size=6, patch_stride=6, iterations=4),
                                    GlFlowConfig(search="group"),
                                    GlFlowConfig(search="group", patch_size=12, patch_stride=4, iterations=4),
                                    GlFlowConfig(coarse_pixels=COARSE_PIXELS, sor="tile"),
                                    GlFlowConfig(coarse_pixels=1 << 20, finest_level=0, sweeps=2)])
def test_other_configs(config):
    """Variants of the passes (no propagation and no refinement, full-resolution search, patches that do not
    overlap with few iterations, the cooperative search with 64 and with 144 pixels a patch: 3 a lane, the coarse
    levels in one dispatch with the tiled SOR on the others, every level in one dispatch) still recover a 3 px
    translation (median within 0.1 px)."""
    a, b = shifted_pair(64, 96, (3.0, -1.5))
    flow = GlOpticalFlow(config=config).estimate(a, b)
    assert np.isfinite(flow).all()
    assert np.median(np.linalg.norm(flow - (3.0, -1.5), axis=-1)[24:-24, 24:-24]) <= 0.1


def test_two_layer_scene_against_dis():
    frames, objects = two_layer_sequence(num_frames=3, width=160, height=96)
    older, newest = frames[0], frames[2]
    truth = true_object_flow(newest, {o.id: o for o in objects}, 0)[..., :2]
    moving = np.linalg.norm(truth, axis=-1) > 0.5
    assert moving.sum() > 1000
    warped, _ = warp_and_fill(older, Target(newest.camera, newest.time, newest.index), Timer())
    flow = estimator().estimate(newest.color, warped)
    reference = dis_calc(dis_estimator("medium"), luma8(newest.color), luma8(warped))
    gl_epe = np.median(np.linalg.norm(flow - truth, axis=-1)[moving])
    dis_epe = np.median(np.linalg.norm(reference - truth, axis=-1)[moving])
    assert gl_epe <= 1.5 * dis_epe, (gl_epe, dis_epe)
    assert gl_epe < 0.2 * np.median(np.linalg.norm(truth, axis=-1)[moving])  # far better than no motion


def test_constant_image_has_zero_flow():
    color = np.full((40, 56, 3), 0.3, np.float32)
    flow = estimator().estimate(color, color)
    np.testing.assert_array_equal(flow, np.zeros((40, 56, 2), np.float32))


@pytest.mark.parametrize("size", [(1, 1), (1, 23), (23, 1), (7, 5), (33, 9)])
def test_small_images(size):
    rng = np.random.default_rng(size[0] * 100 + size[1])
    a = rng.uniform(0, 1, (*size, 3)).astype(np.float32)
    b = np.roll(a, 1, axis=1)
    flow = estimator().estimate(a, b)
    assert flow.shape == (*size, 2) and flow.dtype == np.float32 and np.isfinite(flow).all()
    config = GlFlowConfig()  # a sweep moves a patch at most a patch from its start: the flow is bounded
    assert np.abs(flow).max() <= config.sweeps * config.patch_size * 2 ** (pyramid_levels(size, config)[1] + 1)


@pytest.mark.parametrize("size", [(1, 1), (7, 5), (33, 9), (40, 56)])
def test_cooperative_search_finds_what_one_invocation_a_patch_finds(size):
    """``search=group`` is ``thread``'s search with its sums in another order: on a shifted pair every pixel's
    flow agrees within 0.01 px but for the odd near-tie (a patch's start and its last iterate, or two
    candidates, of almost equal cost); degenerate sizes (a level smaller than a patch, a last workgroup of
    stand-in patches) stay finite. ``auto`` is ``thread`` on a software renderer."""
    a, b = shifted_pair(*size, (1.5, -0.75), margin=8, seed=11)
    thread = GlOpticalFlow(config=GlFlowConfig(search="thread")).estimate(a, b)
    group = GlOpticalFlow(config=GlFlowConfig(search="group")).estimate(a, b)
    assert np.isfinite(group).all()
    assert np.mean(np.abs(group - thread).max(axis=-1) < 1e-2) >= 0.98
    assert GlOpticalFlow().search == ("thread" if glb.shared_context().software else "group")


@pytest.mark.parametrize("size", [(1, 1), (7, 5), (40, 56), (96, 160)])
def test_coarse_pass_gives_the_flow_of_the_passes(size):
    """Pass ``flow_coarse`` runs the coarse levels with the passes' arithmetic: the flow equals that of every
    level by its passes (measured on llvmpipe: the same bits; a GPU's compiler may round an expression of one
    program another way than the other's, and a near-tie of the search then goes the other way: 98 % of the
    pixels within 1e-3 px), with only the coarsest level in it, with a few and with every level. ``None`` is 0
    on a software renderer and ``COARSE_PIXELS`` on a GPU."""
    a, b = shifted_pair(*size, (2.5, -1.25), margin=8, seed=5)
    passes = GlOpticalFlow(config=GlFlowConfig(coarse_pixels=0, search="thread")).estimate(a, b)
    sizes, coarsest, finest = pyramid_levels(size, GlFlowConfig())
    for level in range(coarsest, finest - 1, -1):
        pixels = sizes[level][0] * sizes[level][1]
        coarse = GlOpticalFlow(config=GlFlowConfig(coarse_pixels=pixels, search="thread")).estimate(a, b)
        assert np.mean(np.abs(coarse - passes).max(axis=-1) <= 1e-3) >= 0.98, (level, pixels)
    software = glb.shared_context().software
    assert GlOpticalFlow().coarse_pixels == (0 if software else COARSE_PIXELS)
    assert GlOpticalFlow().sor == ("passes" if software else "tile")


def test_coarse_pass_matches_its_reference():
    """``flow_coarse`` on a 3-level pyramid (levels 2 and 1 run in it, 4 sweeps, 3 x 3 SOR) against
    ``coarse_reference``: float32 Gauss-Newton and SOR against float64, through two levels (measured: 1.7e-6 px
    apart at most on llvmpipe), so 97 % of the pixels within 1e-3 px (a near-tie of the search may go the
    other way); and it finds the shift."""
    from engine.geometry.backends.gl.reference import coarse_reference, downsample_reference

    size, patch, stride, iterations, sweeps = (36, 44), 8, 3, 6, 3
    rng = np.random.default_rng(17)
    base = cv2_blur(rng.uniform(0, 255, (size[0] + 8, size[1] + 8)).astype(np.float32))
    firsts, seconds = [base[4:-4, 4:-4].copy()], [base[2:-6, 6:-2].copy()]  # first(y, x) = second(y + 2, x - 2)
    for _ in range(2):
        firsts.append(downsample_reference(firsts[-1]))
        seconds.append(downsample_reference(seconds[-1]))
    refine = dict(alpha=20.0, delta=5.0, gamma=10.0, omega=1.6, iterations=3, sor_iterations=3)
    expected = coarse_reference(firsts, seconds, 1, patch, stride, iterations, sweeps, refine)
    largest = max(f.size for f in firsts[1:])
    gl = glb.shared_context()

    def run():
        bound = {1: gl.ctx.buffer(np.concatenate([f.ravel() for f in firsts])),
                 3: gl.ctx.buffer(np.concatenate([f.ravel() for f in seconds]))}
        for binding, nbytes in ((4, 8), (5, 8), (6, 8), (8, 8), (9, 8), (10, 8), (11, 32), (12, 32)):
            bound[binding] = gl.ctx.buffer(reserve=nbytes * largest)
        try:
            for binding, buf in bound.items():
                buf.bind_to_storage_buffer(binding)
            gl.dispatch_groups(gl.program("flow_coarse", {"PATCH": patch}), 1, {
                "full_size": size, "coarsest": 2, "last": 1, "stride": stride, "iterations": iterations,
                "sweeps": sweeps, "refine_iterations": refine["iterations"],
                "sor_iterations": refine["sor_iterations"], "alpha": 20.0, "delta": 5.0, "gamma": 10.0, "omega": 1.6})
            n = firsts[1].size
            return np.frombuffer(bound[6].read(), np.float32)[:2 * n].reshape(firsts[1].shape + (2,))
        finally:
            for buf in bound.values():
                buf.release()
    got = gl.call(run)
    close = np.abs(got - expected).max(axis=-1) < 1e-3
    assert close.mean() >= 0.97, close.mean()
    assert np.abs(np.median(expected.reshape(-1, 2), axis=0) - (-1.0, 1.0)).max() < 0.25  # 2 px at level 1


@pytest.mark.parametrize("size, config", [((96, 160), GlFlowConfig(coarse_pixels=0, search="thread")),
                                          ((96, 160), GlFlowConfig(coarse_pixels=COARSE_PIXELS, search="thread")),
                                          ((96, 160), GlFlowConfig(coarse_pixels=0, sor="tile", search="thread")),
                                          ((64, 96), GlFlowConfig(sor="tile", sor_iterations=0, coarse_pixels=0)),
                                          ((40, 56), GlFlowConfig(coarse_pixels=1 << 20, search="group")),
                                          ((64, 96), GlFlowConfig(refine_iterations=0, sweeps=2, search="group"))])
def test_dispatch_counts_are_the_dispatches_run(size, config):
    """``dispatch_counts`` (what ``tools.profile_gl_flow`` prints) is what an estimate dispatches, pass by pass."""
    a, b = shifted_pair(*size, (1.0, 0.5), margin=8)
    estimator = GlOpticalFlow(config=config)
    estimator.estimate(a, b)  # programs compiled
    gl = glb.shared_context()
    passes: dict = {}
    with gl.pass_timing(passes):
        estimator.estimate(a, b)
    estimator.release()
    assert {name: calls for name, (calls, _) in passes.items()} == dispatch_counts(size, config, gl.software)


def test_gpu_inputs_give_the_numpy_result():
    a, b = shifted_pair(48, 64, (2.5, 1.0))
    flow = estimator().estimate(a, b)
    warper = glb.GlFrameWarper()
    depth = np.ones((48, 64), np.float32)
    image_a, image_b = warper.upload(a, depth), warper.upload(b, depth)
    np.testing.assert_array_equal(estimator().estimate(image_a, image_b), flow)
    np.testing.assert_array_equal(estimator().estimate(image_a, b), flow)
    np.testing.assert_array_equal(estimator().estimate_buffers(image_a.color, image_b.color, (48, 64)), flow)
    gpu_ms: dict = {}
    on_gpu = estimator().estimate(image_a, image_b, as_gl=True, gpu_ms=gpu_ms)
    assert isinstance(on_gpu, glb.GlFlow) and on_gpu.shape == (48, 64) and on_gpu.channels == 2
    assert {"luma", "pyramid", "search"} <= set(gpu_ms) and all(v >= 0 for v in gpu_ms.values())
    np.testing.assert_array_equal(np.frombuffer(warper.gl.call(on_gpu.buffer.read), np.float32).reshape(48, 64, 2),
                                  flow)
    # the warper moves points by the resident flow exactly as by the same flow uploaded
    k = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]])
    pose = np.eye(4)
    by_resident = warper.warp_and_fill(image_a, k, pose, k, pose, on_gpu, -1.0)
    by_upload = warper.warp_and_fill(image_a, k, pose, k, pose, warper.upload_flow(flow), -1.0)
    np.testing.assert_array_equal(by_resident[0], by_upload[0])


def test_bad_inputs_name_the_field():
    gl_flow = estimator()
    a = np.zeros((8, 9, 3), np.float32)
    with pytest.raises(InputError) as err:
        gl_flow.estimate(a, np.zeros((8, 10, 3), np.float32))
    assert err.value.field == "second"
    with pytest.raises(InputError) as err:
        gl_flow.estimate(np.zeros((8, 9, 4), np.float32), a)
    assert err.value.field == "first"
    with pytest.raises(InputError) as err:
        gl_flow.estimate(a, np.zeros((8, 9, 3), np.uint8))
    assert err.value.field == "second"
    image = glb.GlFrameWarper().upload(np.zeros((8, 10, 3), np.float32), np.ones((8, 10), np.float32))
    with pytest.raises(InputError) as err:
        gl_flow.estimate(a, image)
    assert err.value.field == "second"
    with pytest.raises(InputError) as err:
        gl_flow.estimate_buffers(image.color, image.color, (9, 10))
    assert err.value.field == "first_buffer"
    with pytest.raises(InputError) as err:
        gl_flow.estimate_buffers(image.color, image.color, (0, 10))
    assert err.value.field == "shape"
    with pytest.raises(InputError) as err:
        gl_flow.luma(np.zeros((8, 9), np.float32))
    assert err.value.field == "image"
    with pytest.raises(InputError) as err:
        GlFlowConfig(patch_stride=9)
    assert err.value.field == "patch_stride"
    with pytest.raises(InputError) as err:
        GlFlowConfig(sweeps=0)
    assert err.value.field == "sweeps"
    with pytest.raises(InputError) as err:
        GlFlowConfig(search="warp")
    assert err.value.field == "search"
    with pytest.raises(InputError) as err:
        GlFlowConfig(sor="red")
    assert err.value.field == "sor"
    with pytest.raises(InputError) as err:
        GlFlowConfig(coarse_pixels=-1)
    assert err.value.field == "coarse_pixels"


def test_release_frees_the_work_buffers_and_estimates_again():
    gl_flow = GlOpticalFlow()
    a, b = shifted_pair(40, 56, (1.0, 0.5))
    first = gl_flow.estimate(a, b)
    gl_flow.release()
    assert not gl_flow._pool
    np.testing.assert_array_equal(gl_flow.estimate(a, b), first)
    gl_flow.release()


def test_warped_frame_read_from_the_gpu():
    """The integration path: frame n-k warped by ``GlFrameWarper`` and left on the GPU (``readback=False``) is
    read from there and gives the flow of the same colours passed as numpy."""
    a, b = shifted_pair(48, 64, (2.0, -1.0))
    warper = glb.GlFrameWarper()
    k, pose = np.array([[50.0, 0, 32], [0, 50.0, 24], [0, 0, 1]]), np.eye(4)
    image_b = warper.upload(b, np.full((48, 64), 2.0, np.float32))
    warped = warper.warp_and_fill(image_b, k, pose, k, pose, readback=False)
    filled, _ = warped.read()
    image_a = warper.upload(a, np.ones((48, 64), np.float32))  # kept: its buffers live as long as it does
    on_gpu = estimator().estimate_buffers(image_a.color, warped.color, (48, 64))
    np.testing.assert_array_equal(on_gpu, estimator().estimate(a, filled))


def test_non_finite_colours_give_a_finite_flow():
    """NaN and +-inf colours read as luma8 reads them (NaN and -inf as 0, +inf as 255): the flow stays finite."""
    a, b = shifted_pair(40, 56, (1.5, 0.0))
    a[5:9, 5:30] = np.nan
    b[20:25, 10:40] = np.inf
    b[30:, :8] = -np.inf
    flow = estimator().estimate(a, b)
    assert np.isfinite(flow).all()
    np.testing.assert_array_equal(estimator().luma(b), luma8(b))


def _run_pass(name: str, inputs: dict, outputs: dict, count: int, uniforms: dict) -> dict:
    """Run pass ``name`` on host arrays bound at the given bindings; returns the output bindings' arrays."""
    gl = glb.shared_context()

    def run():
        buffers = {b: gl.ctx.buffer(np.ascontiguousarray(a)) for b, a in inputs.items()}
        buffers.update({b: gl.ctx.buffer(reserve=a.nbytes) for b, a in outputs.items()})
        try:
            for binding, buf in buffers.items():
                buf.bind_to_storage_buffer(binding)
            gl.dispatch(gl.program(name), count, uniforms)
            return {b: np.frombuffer(buffers[b].read(), a.dtype).reshape(a.shape) for b, a in outputs.items()}
        finally:
            for buf in buffers.values():
                buf.release()
    return gl.call(run)


@pytest.mark.parametrize("size", [(1, 1), (5, 7), (16, 9), (33, 64)])
def test_downsample_pass_matches_its_reference(size):
    from engine.geometry.backends.gl.reference import downsample_reference

    image = np.random.default_rng(size[0] * size[1]).uniform(0, 255, size).astype(np.float32)
    expected = downsample_reference(image)
    h, w = expected.shape
    pyramid = np.concatenate([image.ravel(), np.zeros(h * w, np.float32)])  # level 0, then level 1
    gl = glb.shared_context()

    def run():
        buf = gl.ctx.buffer(pyramid)
        try:
            buf.bind_to_storage_buffer(1)
            gl.dispatch(gl.program("flow_downsample"), h * w, {"src_size": size, "dst_size": (h, w),
                                                               "src_offset": 0, "dst_offset": image.size})
            return np.frombuffer(buf.read(), np.float32)[image.size:].reshape(h, w)
        finally:
            buf.release()
    np.testing.assert_allclose(gl.call(run), expected, rtol=1e-6)  # the same sums, up to the order of rounding


@pytest.mark.parametrize("coarse, fine, scale", [((3, 4), (6, 8), 2.0), ((5, 5), (9, 10), 2.0), ((2, 3), (8, 12), 4.0),
                                                 ((1, 1), (3, 2), 2.0)])
def test_upsample_pass_matches_its_reference(coarse, fine, scale):
    from engine.geometry.backends.gl.reference import upsample_flow_reference

    flow = np.random.default_rng(fine[0] + fine[1]).normal(0, 3, coarse + (2,)).astype(np.float32)
    flow[0, 0] = np.nan  # a non-finite sample: the result there (and next to it) is 0
    out = _run_pass("flow_upsample", {6: flow}, {7: np.zeros(fine + (2,), np.float32)}, fine[0] * fine[1],
                    {"src_size": coarse, "dst_size": fine, "scale": scale})[7]
    np.testing.assert_allclose(out, upsample_flow_reference(flow, fine, scale), rtol=1e-5, atol=1e-5)


@pytest.mark.parametrize("size, patch, stride", [((20, 27), 8, 3), ((6, 5), 8, 3), ((16, 16), 4, 4)])
def test_densify_pass_matches_its_reference(size, patch, stride):
    from engine.geometry.backends.gl.reference import densify_reference, patch_origins

    rng = np.random.default_rng(size[0] * 31 + patch)
    first = rng.uniform(0, 255, size).astype(np.float32)
    second = rng.uniform(0, 255, size).astype(np.float32)
    rows, cols = (patch_origins(n, patch, stride).size for n in size)
    patch_flows = rng.normal(0, 2, (rows, cols, 2)).astype(np.float32)
    gl = glb.shared_context()

    def run():
        buffers = [gl.ctx.buffer(a) for a in (first, second, patch_flows)]
        out = gl.ctx.buffer(reserve=8 * first.size)
        try:
            for binding, buf in zip((1, 3, 5, 6), (*buffers, out)):
                buf.bind_to_storage_buffer(binding)
            gl.dispatch(gl.program("flow_densify", {"PATCH": patch}), first.size,
                        {"size": size, "offset": 0, "stride": stride})
            return np.frombuffer(out.read(), np.float32).reshape(size + (2,))
        finally:
            for buf in (*buffers, out):
                buf.release()
    np.testing.assert_allclose(gl.call(run), densify_reference(first, second, patch_flows, patch, stride),
                               rtol=1e-4, atol=1e-4)


def cv2_blur(image: np.ndarray) -> np.ndarray:
    import cv2

    return cv2.GaussianBlur(image, (0, 0), 1.5)


@pytest.mark.parametrize("search", ["thread", "group"])
@pytest.mark.parametrize("propagate", [False, True])
def test_patch_search_pass_matches_its_reference(propagate, search):
    from engine.geometry.backends.gl.reference import patch_origins, patch_search_reference

    size, patch, stride, iterations = (24, 30), 8, 3, 6
    rng = np.random.default_rng(5 + propagate)
    base = cv2_blur(rng.uniform(0, 255, (size[0] + 8, size[1] + 8)).astype(np.float32))
    first, second = base[4:-4, 4:-4].copy(), base[3:-5, 6:-2].copy()  # first(y, x) = second(y + 1, x - 2)
    rows, cols = (patch_origins(n, patch, stride).size for n in size)
    if propagate:
        start = rng.normal(0, 1.5, (rows, cols, 2)).astype(np.float32)
    else:
        start = rng.normal(0, 0.5, size + (2,)).astype(np.float32)
    gl = glb.shared_context()

    def run():
        buffers = {1: first, 3: second, 4: start if not propagate else np.zeros(2, np.float32),
                   8: start if propagate else np.zeros(2, np.float32)}
        bound = {b: gl.ctx.buffer(np.ascontiguousarray(a)) for b, a in buffers.items()}
        bound[5] = gl.ctx.buffer(reserve=8 * rows * cols)
        try:
            for binding, buf in bound.items():
                buf.bind_to_storage_buffer(binding)
            defines = {"PATCH": patch, **({"PROPAGATE": 1} if propagate else {})}
            name, lanes = "flow_patch", 1
            if search == "group":  # a patch over PATCH_LANES invocations (4 patches a workgroup, the last partly)
                name, lanes, defines = "flow_patch_group", PATCH_LANES, {**defines, "LANES": PATCH_LANES}
            gl.dispatch(gl.program(name, defines), rows * cols * lanes,
                        {"size": size, "offset": 0, "stride": stride, "iterations": iterations})
            return np.frombuffer(bound[5].read(), np.float32).reshape(rows, cols, 2)
        finally:
            for buf in bound.values():
                buf.release()
    got = gl.call(run)
    expected = patch_search_reference(first, second, start, patch, stride, iterations, propagate)
    close = np.abs(got - expected).max(axis=-1) < 1e-2  # float32 Gauss-Newton against float64
    assert close.mean() >= 0.95, close.mean()
    assert np.abs(np.median(expected.reshape(-1, 2), axis=0) - (-2.0, 1.0)).max() < 0.25  # the search works



@pytest.mark.parametrize("sor, size, sor_iterations", [("passes", (18, 23), 4), ("tile", (18, 23), 4),
                                                     ("tile", (37, 50), 5), ("tile", (1, 3), 1),
                                                     ("tile", (40, 21), 9)])
def test_refinement_passes_match_their_reference(sor, size, sor_iterations):
    """The refinement's passes against ``refine_reference``, its SOR as red and black ``flow_refine_sor``
    dispatches after ``flow_refine_system``, or as ``flow_refine_tile`` dispatches of up to ``SOR_STEPS``
    iterations each (``sor_chunks``: 4; 3 and 2; 1; 3, 3 and 3), the system folded into the first of each
    fixed-point iteration; tiles of 16 x 16, the last ones partial, and a level smaller than a tile."""
    from engine.geometry.backends.gl.flow import refine_level
    from engine.geometry.backends.gl.reference import refine_reference

    iterations = 3
    rng = np.random.default_rng(11)
    base = cv2_blur(rng.uniform(0, 255, (size[0] + 6, size[1] + 6)).astype(np.float32))
    first, second = base[3:-3, 3:-3].copy(), base[2:-4, 4:-2].copy()  # first(y, x) = second(y + 1, x - 1)
    flow = (np.array([-1.0, 1.0]) + rng.normal(0, 0.3, size + (2,))).astype(np.float32)
    config = dict(alpha=20.0, delta=5.0, gamma=10.0, omega=1.6)
    gl = glb.shared_context()
    n = first.size

    def run():
        bound = {1: gl.ctx.buffer(first), 3: gl.ctx.buffer(second), 6: gl.ctx.buffer(flow)}
        for binding, nbytes in ((9, 8 * n), (10, 8 * n), (11, 32 * n), (12, 32 * n), (13, 8 * n)):
            bound[binding] = gl.ctx.buffer(reserve=nbytes)
        try:
            for binding, buf in bound.items():
                buf.bind_to_storage_buffer(binding)
            refine_level(gl, size, {"size": size, "offset": 0, **config}, {"PATCH": 8},
                         GlFlowConfig(refine_iterations=iterations, sor_iterations=sor_iterations), sor,
                         [bound[9], bound[13]])
            return np.frombuffer(bound[6].read(), np.float32).reshape(size + (2,))
        finally:
            for buf in bound.values():
                buf.release()
    got = gl.call(run)
    expected = refine_reference(first, second, flow, iterations=iterations, sor_iterations=sor_iterations, **config)
    assert np.abs(expected - flow).max() > 0.01  # the refinement moved the flow
    np.testing.assert_allclose(got, expected, atol=1e-4)  # measured: 2e-5 at most of a change up to 1 px
