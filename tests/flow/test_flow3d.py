"""The DeCOMPnet 3D flow network (models/flow/network.py): partial convs, masked correlation, Eq. 6.5-6.6, 6.13.

Matrix per op (kornia style): shapes (incl. an empty batch), equivalence to slow references (F.conv3d for
the plane-stacked partial conv, Python loops for the cost volume, Eq. 6.6 by hand), invariances (values
under alpha = 0 never matter, masks never dilate), degenerate inputs (empty MPIs, one plane, sky),
exceptions, gradients. Tiny sizes (Z = 4, 32 x 48) keep the file fast.
"""
from __future__ import annotations

import itertools

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from engine.core.errors import InputError
from models.flow.network import (Flow3D, Flow3DConfig, PartialConv3d, backward_warp, encode_color, extrapolate,
                                 flow_from_output, masked_correlation, mpi_features, mpi_pair, partial_conv3d,
                                 plane_offset, pyramid_stride, set_direct_conv3d, surface_flow)
from models.geometry import Mpi, build_mpi

pytestmark = pytest.mark.usefixtures("one_torch_thread")


def random_mpi(batch=2, height=32, width=48, planes=4, seed=0, sky_rows=0) -> Mpi:
    g = torch.Generator().manual_seed(seed)
    depth = 2.0 + 8.0 * torch.rand(batch, height, width, generator=g)
    if sky_rows:
        depth[:, :sky_rows] = float("inf")
    color = torch.rand(batch, height, width, 3, generator=g)
    return build_mpi(color, depth, planes)


def random_mask(shape, seed=0, p=0.6) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return (torch.rand(shape, generator=g) < p).float()


@pytest.fixture(scope="module")
def net() -> Flow3D:
    torch.manual_seed(0)
    return Flow3D(Flow3DConfig()).eval()


# ----------------------------------------------------------------------------------------------------
# Partial convolution


def reference_partial_conv(x, mask, weight, bias, stride):
    """Liu et al.'s partial conv with F.conv3d, the location mask max-pooled (not dilated)."""
    kz, ky, kx = weight.shape[2:]
    pad = (kz // 2, ky // 2, kx // 2)
    c_in = x.shape[1]
    raw = F.conv3d(x * mask, weight, None, stride, pad)
    counts = mask.expand(-1, c_in, -1, -1, -1).sum(1, keepdim=True)
    window = F.conv3d(counts, torch.ones(1, 1, kz, ky, kx), None, stride, pad)
    loc = mask.amax(1, keepdim=True)
    if stride != (1, 1, 1):
        loc = F.max_pool3d(loc, stride, stride, ceil_mode=True)
    valid = (loc > 0) & (window > 0)
    out = raw * (c_in * kz * ky * kx) / window.clamp(min=1e-6) + bias.reshape(1, -1, 1, 1, 1)
    return torch.where(valid, out, torch.zeros_like(out)), loc


@pytest.mark.parametrize("kernel,stride,channel_mask,size", [
    ((3, 3, 3), (1, 1, 1), False, (4, 10, 12)), ((3, 3, 3), (1, 2, 2), False, (4, 10, 12)),
    ((1, 3, 3), (1, 2, 2), False, (3, 9, 7)), ((1, 1, 1), (1, 1, 1), True, (4, 6, 8)),
    ((3, 3, 3), (1, 1, 1), True, (2, 5, 6))])
@pytest.mark.parametrize("direct", [False, True])
def test_partial_conv_matches_conv3d_reference(kernel, stride, channel_mask, size, direct):
    torch.manual_seed(1)
    layer = PartialConv3d(5, 7, kernel, stride)
    layer.direct = direct  # the plane-stacked Conv2d (torch) or the one Conv3d the ONNX export uses
    x = torch.randn(2, 5, *size)
    mask = random_mask((2, 5 if channel_mask else 1, *size), seed=2)
    out, out_mask = layer(x, mask)
    ref, ref_mask = reference_partial_conv(x, mask, layer.weight, layer.bias, stride)
    assert out.shape == ref.shape and out_mask.shape == (2, 1, *ref.shape[2:])
    torch.testing.assert_close(out, ref, atol=1e-5, rtol=1e-5)
    torch.testing.assert_close(out_mask, ref_mask)


def test_network_with_direct_conv3d_equals_plane_stacked(net):
    """``set_direct_conv3d`` (the export's form) changes no flow beyond float rounding, with and without dz."""
    import copy

    mpi_n = random_mpi(batch=1, height=48, width=64, seed=11, sky_rows=4)
    mpi_p = random_mpi(batch=1, height=48, width=64, seed=12)._replace(plane_depths=mpi_n.plane_depths)
    direct = set_direct_conv3d(copy.deepcopy(net))
    assert all(m.direct for m in direct.modules() if isinstance(m, PartialConv3d))
    assert not any(m.direct for m in net.modules() if isinstance(m, PartialConv3d))
    with torch.no_grad():
        want = net(mpi_n, mpi_p)
        got = direct(mpi_n, mpi_p)
        xy = direct.flow_unchecked(mpi_n, mpi_p, depth_flow=False)
    assert float(want[:, 2].abs().max()) > 0  # the comparison of dz is not between zeros
    torch.testing.assert_close(got, want, atol=1e-5, rtol=1e-5)
    # depth_flow=False: the same (du, dv), dz exactly 0 (not computed)
    torch.testing.assert_close(xy[:, :2], got[:, :2], atol=0, rtol=0)
    assert torch.equal(xy[:, 2], torch.zeros_like(xy[:, 2]))


def test_partial_conv_ignores_values_under_alpha_zero():
    torch.manual_seed(2)
    layer = PartialConv3d(4, 6)
    x = torch.randn(1, 4, 4, 12, 16)
    mask = random_mask((1, 1, 4, 12, 16), seed=3)
    garbage = x + 100.0 * torch.randn_like(x) * (1.0 - mask)
    out_a, _ = layer(x, mask)
    out_b, _ = layer(garbage, mask)
    assert torch.equal(out_a, out_b)


def test_partial_conv_mask_not_dilated():
    torch.manual_seed(3)
    layer = PartialConv3d(3, 3)
    mask = torch.zeros(1, 1, 4, 16, 16)
    mask[:, :, 1, 4:8, 6:10] = 1.0  # one square on one plane
    out, out_mask = layer(torch.randn(1, 3, 4, 16, 16), mask)
    assert torch.equal(out_mask, mask)  # stride 1: output mask = input mask
    assert torch.all(out[:, :, mask[0, 0] == 0] == 0)
    down = PartialConv3d(3, 3, stride=(1, 2, 2))
    out2, mask2 = down(torch.randn(1, 3, 4, 16, 16), mask)
    assert torch.equal(mask2, F.max_pool3d(mask, (1, 2, 2), (1, 2, 2)))  # any valid in each 2x2 block
    assert int(mask2.sum()) == 4


def test_partial_conv_rejects_plane_stride():
    with pytest.raises(InputError):
        PartialConv3d(2, 2, stride=(2, 2, 2))


# ----------------------------------------------------------------------------------------------------
# Masked correlation (Eq. 6.3-6.4)


def test_correlation_matches_loop_reference():
    torch.manual_seed(4)
    b, c, z, h, w, r, s = 1, 3, 3, 5, 6, 2, 1
    h1, h2 = torch.randn(b, c, z, h, w), torch.randn(b, c, z, h, w)
    a1, a2 = random_mask((b, 1, z, h, w), 5), torch.rand(b, 1, z, h, w)
    cv, cv_mask = masked_correlation(h1, a1, h2, a2, r, s)
    n = 2 * r + 1
    assert cv.shape == cv_mask.shape == (b, (2 * s + 1) * n * n, z, h, w)
    f1, f2 = (h1 * a1).numpy(), (h2 * a2).numpy()
    ref = np.zeros(cv.shape, np.float64)
    ref_mask = np.zeros(cv.shape, np.float64)
    for d, (dz, dy, dx) in enumerate(itertools.product(range(-s, s + 1), range(-r, r + 1), range(-r, r + 1))):
        for zz, yy, xx in itertools.product(range(z), range(h), range(w)):
            z2, y2, x2 = zz + dz, yy + dy, xx + dx
            if 0 <= z2 < z and 0 <= y2 < h and 0 <= x2 < w:
                ref[0, d, zz, yy, xx] = f1[0, :, zz, yy, xx] @ f2[0, :, z2, y2, x2] / c
                ref_mask[0, d, zz, yy, xx] = a1[0, 0, zz, yy, xx] * a2[0, 0, z2, y2, x2]
    np.testing.assert_allclose(cv.numpy(), ref, atol=1e-5)
    np.testing.assert_allclose(cv_mask.numpy(), ref_mask, atol=1e-6)


def test_correlation_planar_mode_and_default_size():
    cv, _ = masked_correlation(torch.randn(1, 2, 1, 8, 8), torch.ones(1, 1, 1, 8, 8),
                               torch.randn(1, 2, 1, 8, 8), torch.ones(1, 1, 1, 8, 8), 4, 0)
    assert cv.shape == (1, 81, 1, 8, 8)
    cv, _ = masked_correlation(torch.randn(1, 2, 4, 8, 8), torch.ones(1, 1, 4, 8, 8),
                               torch.randn(1, 2, 4, 8, 8), torch.ones(1, 1, 4, 8, 8), 4, 1)
    assert cv.shape == (1, 243, 4, 8, 8)  # the thesis' 9 x 9 x 3


# ----------------------------------------------------------------------------------------------------
# Eq. 6.5-6.6, plane offsets, warping, Eq. 6.13


def test_flow_from_output_matches_eq_6_6_by_hand():
    planes = torch.tensor([[2.0, 3.0, 5.0, 9.0]])
    logits = torch.randn(1, 3, 4, 2, 2, generator=torch.Generator().manual_seed(6))
    disp = torch.randn(1, 2, 4, 2, 2)
    flow = flow_from_output(disp, logits, planes)
    assert torch.equal(flow[:, :2], disp)
    d = planes[0].tolist()
    for z in range(4):
        offsets = [o for o in (-1, 0, 1) if 0 <= z + o < 4]  # offsets leaving the MPI get probability 0
        lg = torch.stack([logits[0, o + 1, z] for o in offsets])
        b = torch.softmax(lg, dim=0)
        expected = sum(b[i] * d[z + o] for i, o in enumerate(offsets)) - d[z]
        torch.testing.assert_close(flow[0, 2, z], expected, atol=1e-6, rtol=1e-6)


def test_flow_from_output_zero_displacement_centre_softmax_is_exactly_zero():
    planes = torch.tensor([[2.0, 3.0, 5.0, 9.0], [1.0, 1.5, 2.5, 7.0]])
    logits = torch.zeros(2, 3, 4, 3, 5)
    logits[:, 1] = 1.0e4  # one-hot on z' = 0
    flow = flow_from_output(torch.zeros(2, 2, 4, 3, 5), logits, planes)
    assert torch.equal(flow, torch.zeros_like(flow))


def test_flow_from_output_degenerate_planes_and_2d():
    logits = torch.randn(1, 3, 4, 2, 2)
    flow = flow_from_output(torch.zeros(1, 2, 4, 2, 2), logits, torch.full((1, 4), float("inf")))
    assert torch.isfinite(flow).all() and torch.equal(flow[:, 2], torch.zeros_like(flow[:, 2]))
    flow = flow_from_output(torch.ones(1, 2, 1, 2, 2), torch.randn(1, 1, 1, 2, 2), torch.tensor([[3.0]]))
    assert torch.equal(flow[:, 2], torch.zeros_like(flow[:, 2]))  # 2d mode: no plane softmax, dz = 0
    with pytest.raises(InputError):
        flow_from_output(torch.zeros(1, 2, 4, 2, 2), torch.zeros(1, 2, 4, 2, 2), torch.ones(1, 4))


def test_plane_offset_inverts_eq_6_6_on_neighbouring_planes():
    planes = torch.tensor([[2.0, 3.0, 5.0, 9.0]])
    for z, (b_minus, b_plus) in itertools.product(range(1, 3), [(0.0, 0.3), (0.6, 0.0), (0.0, 1.0)]):
        logits = torch.log(torch.tensor([b_minus, 1 - b_minus - b_plus, b_plus]) + 1e-30)
        full = torch.full((1, 3, 4, 1, 1), -1e4)
        full[0, :, z, 0, 0] = logits
        dz = flow_from_output(torch.zeros(1, 2, 4, 1, 1), full, planes)[:, 2:3]
        e = plane_offset(dz, planes)[0, 0, z, 0, 0]
        assert abs(float(e) - (b_plus - b_minus)) < 1e-5


def test_backward_warp_integer_shift_and_plane_offset():
    g = torch.Generator().manual_seed(7)
    values = torch.rand(1, 2, 3, 6, 8, generator=g)
    planes = torch.tensor([[2.0, 4.0, 8.0]])
    flow = torch.zeros(1, 3, 3, 6, 8)
    torch.testing.assert_close(backward_warp(values, flow, planes), values)  # identity
    flow[:, 0] = 2.0  # sample 2 px to the right
    out = backward_warp(values, flow, planes)
    torch.testing.assert_close(out[..., :6], values[..., 2:])
    assert torch.all(out[..., 6:] == 0)  # outside the frame: zeros
    flow = torch.zeros(1, 3, 3, 6, 8)
    flow[:, 2, 0] = 2.0  # plane 0 -> plane 1 (gap 2)
    flow[:, 2, 1] = -1.0  # plane 1 -> halfway to plane 0 (gap 2)
    out = backward_warp(values, flow, planes)
    torch.testing.assert_close(out[:, :, 0], values[:, :, 1])
    torch.testing.assert_close(out[:, :, 1], 0.5 * (values[:, :, 0] + values[:, :, 1]))
    torch.testing.assert_close(out[:, :, 2], values[:, :, 2])


def test_extrapolate_eq_6_13():
    back = torch.randn(1, 3, 4, 2, 2)
    torch.testing.assert_close(extrapolate(back, 1 / 2), -0.5 * back)
    torch.testing.assert_close(extrapolate(back, 3 / 4), -0.75 * back)
    assert torch.equal(extrapolate(back, 0), torch.zeros_like(back))


# ----------------------------------------------------------------------------------------------------
# Inputs


def test_mpi_features_scale_free_and_masked():
    mpi = random_mpi(sky_rows=4)
    feats = mpi_features(mpi, mpi.plane_depths)
    assert feats.shape == (2, 4, 4, 32, 48) and torch.isfinite(feats).all()
    assert torch.all(feats * (1 - mpi.alpha) == 0)
    scaled = Mpi(mpi.color, mpi.depth * 7.0, mpi.alpha, mpi.plane_depths * 7.0)
    torch.testing.assert_close(mpi_features(scaled, scaled.plane_depths), feats)
    assert float(encode_color(torch.zeros(1))) == 0.0 and float(encode_color(torch.tensor([1e6]))) < 1.0


def test_mpi_pair_static_camera_shares_planes():
    g = torch.Generator().manual_seed(8)
    depth = 2.0 + 3.0 * torch.rand(1, 16, 24, generator=g)
    color = torch.rand(1, 16, 24, 3, generator=g)
    k = torch.tensor([[[20.0, 0, 12], [0, 20.0, 8], [0, 0, 1]]])
    t = torch.eye(4)[None]
    m_n, m_p = mpi_pair(color, depth, k, t, color, depth * 1.1, k, t, 4)
    assert torch.equal(m_p.plane_depths, m_n.plane_depths)
    ref = build_mpi(color, depth, 4)
    torch.testing.assert_close(m_n.alpha, ref.alpha)
    assert torch.all(m_p.alpha.sum(dim=2) <= 1)


def test_surface_flow_picks_the_visible_plane():
    mpi = random_mpi(batch=1, height=4, width=5)
    flow = torch.arange(4.0).reshape(1, 1, 4, 1, 1).expand(1, 3, 4, 4, 5)
    out = surface_flow(flow, mpi)
    plane = mpi.alpha[0, 0].argmax(dim=0).float()
    torch.testing.assert_close(out[0, ..., 0], plane)


# ----------------------------------------------------------------------------------------------------
# The network


def test_shapes_odd_sizes_and_empty_batch(net):
    for h, w in [(32, 48), (30, 45)]:
        mpi = random_mpi(height=h, width=w, seed=h)
        flow = net(mpi, mpi)
        assert flow.shape == (2, 3, 4, h, w) and torch.isfinite(flow).all()
        assert torch.all(flow * (1 - mpi.alpha) == 0)  # zero where alpha_n = 0
    assert pyramid_stride(net.config) == 16
    empty = random_mpi(batch=0)
    assert net(empty, empty).shape == (0, 3, 4, 32, 48)


def test_network_ignores_colours_under_alpha_zero(net):
    mpi = random_mpi(seed=9)
    other = random_mpi(seed=10)._replace(plane_depths=mpi.plane_depths)
    garbage = torch.rand(mpi.color.shape) * 50.0
    dirty_n = mpi._replace(color=torch.where(mpi.alpha > 0, mpi.color, garbage),
                           depth=torch.where(mpi.alpha > 0, mpi.depth, garbage[:, :1]))
    dirty_p = other._replace(color=torch.where(other.alpha > 0, other.color, garbage))
    with torch.no_grad():
        torch.testing.assert_close(net(dirty_n, dirty_p), net(mpi, other), atol=1e-5, rtol=1e-5)


def test_empty_mpis_single_plane_and_sky_are_finite(net):
    mpi = random_mpi(sky_rows=6)
    empty = Mpi(torch.zeros_like(mpi.color), torch.zeros_like(mpi.depth), torch.zeros_like(mpi.alpha),
                mpi.plane_depths)
    with torch.no_grad():
        assert torch.equal(net(empty, empty), torch.zeros(2, 3, 4, 32, 48))
        assert torch.isfinite(net(mpi, empty)).all() and torch.isfinite(net(empty, mpi)).all()
        assert torch.isfinite(net(mpi, mpi)).all()
        all_sky = build_mpi(torch.rand(1, 32, 48, 3), torch.full((1, 32, 48), float("inf")), 4)
        assert torch.isfinite(net(all_sky, all_sky)).all()
    torch.manual_seed(1)
    one_plane = Flow3D(Flow3DConfig(num_planes=1)).eval()
    single = random_mpi(planes=1)
    with torch.no_grad():
        flow = one_plane(single, single)
    assert flow.shape == (2, 3, 1, 32, 48) and torch.isfinite(flow).all()


def test_gradients_reach_every_parameter():
    torch.manual_seed(2)
    model = Flow3D(Flow3DConfig())
    mpi = random_mpi(seed=11)
    other = random_mpi(seed=12)._replace(plane_depths=mpi.plane_depths)
    flow = model(mpi, other)
    (flow * torch.randn_like(flow)).sum().backward()
    missing = [name for name, p in model.named_parameters() if p.grad is None or not torch.any(p.grad != 0)]
    assert not missing
    assert all(torch.isfinite(p.grad).all() for p in model.parameters())


def test_small_model_parameter_budget(net):
    count = sum(p.numel() for p in net.parameters())
    assert 50_000 < count < 300_000


def test_2d_mode_runs():
    torch.manual_seed(3)
    model = Flow3D(Flow3DConfig(mode="2d", num_planes=1)).eval()
    g = torch.Generator().manual_seed(13)
    depth = 2.0 + 3.0 * torch.rand(1, 32, 48, generator=g)
    color = torch.rand(1, 32, 48, 3, generator=g)
    k = torch.tensor([[[40.0, 0, 24], [0, 40.0, 16], [0, 0, 1]]])
    t_prev = torch.eye(4)[None].clone()
    t_prev[0, 0, 3] = 0.05
    m_n, m_p = mpi_pair(color, depth, k, torch.eye(4)[None], color, depth, k, t_prev, 1)
    with torch.no_grad():
        flow = model(m_n, m_p)
    assert flow.shape == (1, 3, 1, 32, 48) and torch.isfinite(flow).all()
    assert torch.all(flow[:, 2] == 0)  # no plane softmax: dz = 0
    assert model.decoder.head.weight.shape[0] == 3  # 2 displacement + 1 plane logit


def test_config_and_input_errors(net):
    with pytest.raises(InputError):
        Flow3DConfig(mode="2d")  # needs num_planes = 1
    with pytest.raises(InputError):
        Flow3DConfig(mode="4d")
    with pytest.raises(InputError):
        Flow3DConfig(encoder_channels=(8, 16))
    mpi = random_mpi(planes=3)
    with pytest.raises(InputError, match="planes"):
        net(mpi, mpi)
    a, b = random_mpi(), random_mpi(height=16)
    with pytest.raises(InputError):
        net(a, b)


def test_initial_flow_is_lifted_onto_every_plane_and_refined_from():
    torch.manual_seed(0)
    config = Flow3DConfig(encoder_channels=(4, 4, 4), reduce_channels=4, decoder_channels=(4,), search_range=1,
                          initial_flow=True)
    net = Flow3D(config).eval()
    with torch.no_grad():  # a decoder that adds nothing: the output is the given flow itself
        net.decoder.head.weight.zero_()
        net.decoder.head.bias.zero_()
    depth = torch.full((1, 32, 48), 4.0)
    depth[:, 8:20, 10:30] = 2.0
    mpi = build_mpi(torch.rand(1, 32, 48, 3), depth, 4)
    init = torch.zeros(1, 2, 32, 48)
    init[:, 0], init[:, 1] = -3.0, 1.5
    flow = net(mpi, mpi, init)
    on = mpi.alpha[:, 0] > 0
    torch.testing.assert_close(flow[:, 0][on], torch.full_like(flow[:, 0][on], -3.0))
    torch.testing.assert_close(flow[:, 1][on], torch.full_like(flow[:, 1][on], 1.5))
    assert (flow[:, :2][(mpi.alpha == 0).expand(-1, 2, -1, -1, -1)] == 0).all()
    with pytest.raises(InputError, match="initial flow"):
        net(mpi, mpi)
    with pytest.raises(InputError, match="initial_flow"):
        net(mpi, mpi, torch.full((1, 2, 32, 48), float("nan")))
    with pytest.raises(InputError, match="initial flow"):
        Flow3D(Flow3DConfig(encoder_channels=(4, 4, 4), reduce_channels=4, decoder_channels=(4,)))(mpi, mpi, init)
