"""DeCOMPnet's 3D object-motion network on MPIs (thesis Sec. 6.3.3, Eq. 6.3-6.7, 6.13).

Estimates the local (object) 3D flow ``u(n -> n-k)`` between the MPI of frame n and the MPI of frame n-k
warped into frame n's view (camera motion cancelled), per MPI point: ``(du, dv)`` pixels and ``dz`` scene
units, the same ``object_flow`` layout that ``models.geometry.forward_warp_mpi`` takes. Design note:
``docs/flow3d.md``.

Layout and conventions (``models/geometry.py``): MPI tensors are (B, C, Z, H, W), Conv3d's (N, C, D, H, W)
with the plane axis as D, planes near (0) to far (Z - 1); pixel centres at +0.5; planar depth, +inf for
sky. Flows are (B, 3, Z, H, W) = (du, dv, dz) in the view of the first MPI (frame n), pointing from a
point of frame n to where it was at frame n-k.

Pieces (pure functions; the modules only hold weights and hyper-parameters):

- ``partial_conv3d`` / ``PartialConv3d``: convolution over alpha = 1 only, mask-normalised (Liu et al.),
  the mask is *not* dilated (output mask = input mask, max-pooled where strided);
- ``masked_correlation``: the masked cost volume of Eq. 6.3-6.4 by padding + shifts (exportable);
- ``backward_warp``: bilinear in x/y with ``grid_sample`` on each plane, linear along the plane axis at
  the plane offset implied by dz (``plane_offset``); used for the pyramid features and for the losses;
- ``flow_from_output``: displacement + softmax over plane offsets -> real 3D flow (Eq. 6.5-6.6);
- ``Flow3D``: the PWC-style coarse-to-fine network (Eq. 6.7); ``extrapolate`` (Eq. 6.13).

>>> net = Flow3D(Flow3DConfig())                         # doctest: +SKIP
>>> mpi_n, mpi_prev_w = mpi_pair(color_n, depth_n, K_n, T_n, color_p, depth_p, K_p, T_p, 4)  # doctest: +SKIP
>>> flow_back = net(mpi_n, mpi_prev_w)                   # (B, 3, Z, H, W), u(n -> n-k)   # doctest: +SKIP
>>> flow_next = extrapolate(flow_back, 1.0 / k)          # u(n -> n+1)                    # doctest: +SKIP
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from engine.core.checks import check_shape
from engine.core.config import option
from engine.core.errors import InputError
from models.geometry import Mpi, build_mpi, check_mpi, forward_warp_mpi, visibility

__all__ = ["Flow3DConfig", "PartialConv3d", "partial_conv3d", "masked_correlation", "plane_offset",
           "backward_warp", "flow_from_output", "extrapolate", "encode_color", "mpi_features", "mpi_pair",
           "surface_flow", "Flow3D", "pyramid_stride", "set_direct_conv3d"]

#: Logit added to plane offsets that leave the MPI (z + z' < 0 or >= Z): exp(-1e4) is exactly 0 in float32.
_OUTSIDE_LOGIT = -1.0e4
#: Smallest mask sum a partial convolution divides by (the masks are alphas in [0, 1]).
_MIN_MASK_SUM = 1.0e-6



@dataclass(frozen=True)
class Flow3DConfig:
    """Hyper-parameters of the 3D flow network. The defaults are the thesis' (Z = 4, s_z = 1, range 4)."""

    mode: str = option("3d", "'3d': DeCOMPnet on MPIs; '2d': the ablation on frames (needs num_planes = 1)")
    num_planes: int = option(4, "MPI planes Z the network is built for (1 in 2d mode)")
    encoder_channels: tuple[int, ...] = option(
        (8, 16, 24, 32), "feature channels of pyramid level 1..L (level l is at 1/2^l of the input size)")
    reduce_channels: int = option(32, "channels the frame-n features are reduced to (1x1x1) before the decoder")
    decoder_channels: tuple[int, ...] = option(
        (32, 24, 16), "hidden channels of the flow decoder (shared by all levels, as in ARFlow)")
    search_range: int = option(4, "correlation search radius in x and y, pixels of each level (9 x 9)")
    plane_search_range: int = option(1, "correlation and flow radius s_z along the planes (3d mode; 2d: 0)")
    negative_slope: float = option(0.1, "LeakyReLU slope")
    initial_flow: bool = option(False, "refine a given 2D flow u(n -> n-k) (pixels, per pixel of the input; e.g. "
                                       "OpenCV DIS between frame n and the camera-compensated frame n-k, "
                                       "engine.predict.dis.initial_flow) lifted onto every plane, instead of "
                                       "starting the coarsest level from zero")

    def __post_init__(self) -> None:
        checks = [
            (self.mode in ("3d", "2d"), f"mode must be '3d' or '2d', got {self.mode!r}"),
            (self.num_planes >= 1, "num_planes must be >= 1"),
            (self.mode == "3d" or self.num_planes == 1, "mode '2d' runs on frames: use num_planes = 1"),
            (len(self.encoder_channels) >= 3, "encoder_channels needs >= 3 levels (flow is estimated "
                                              "from level L down to level 2, 1/4 resolution)"),
            (all(c >= 1 for c in self.encoder_channels) and self.reduce_channels >= 1, "channels must be >= 1"),
            (len(self.decoder_channels) >= 1 and all(c >= 1 for c in self.decoder_channels),
             "decoder_channels needs >= 1 entry, all >= 1"),
            (self.search_range >= 0 and self.plane_search_range >= 0, "search ranges must be >= 0"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="Flow3DConfig")

    @property
    def plane_range(self) -> int:
        """s_z actually used: ``plane_search_range`` in 3d mode, 0 in 2d mode (no plane softmax)."""
        return self.plane_search_range if self.mode == "3d" else 0

    @property
    def kernel_planes(self) -> int:
        """Kernel size along the planes: 3 in 3d mode, 1 in 2d mode."""
        return 3 if self.mode == "3d" else 1

    @property
    def levels(self) -> int:
        return len(self.encoder_channels)


def pyramid_stride(config: Flow3DConfig) -> int:
    """2^L: ``Flow3D`` pads H and W with alpha = 0 up to multiples of this (16 for the default 4 levels)."""
    return 2 ** config.levels


# ----------------------------------------------------------------------------------------------------
# Helpers on (B, C, Z, H, W) tensors


def _fold(x: Tensor) -> Tensor:
    """(B, C, Z, H, W) -> (B * Z, C, H, W): the planes as images, for 2D ops."""
    b, c, z, h, w = x.shape
    return x.permute(0, 2, 1, 3, 4).reshape(b * z, c, h, w)


def _unfold(x: Tensor, batch: int, planes: int) -> Tensor:
    """(B * Z, C, H, W) -> (B, C, Z, H, W)."""
    _, c, h, w = x.shape
    return x.reshape(batch, planes, c, h, w).permute(0, 2, 1, 3, 4)


def _safe_divide(num: Tensor, den: Tensor, ok: Tensor) -> Tensor:
    """num / den where ``ok``, else 0; the discarded branch divides by 1 (no inf/NaN in values or grads)."""
    return torch.where(ok, num / torch.where(ok, den, torch.ones_like(den)), torch.zeros_like(num))


def _masked_upsample(x: Tensor, mask: Tensor, factor: int, fine_mask: Tensor) -> Tensor:
    """Mask-normalised bilinear upsampling in x/y by ``factor``: invalid coarse values never leak in.

    x (B, C, Z, h, w), mask (B, 1, Z, h, w) -> (B, C, Z, h * factor, w * factor), 0 where ``fine_mask`` is 0.
    Every valid fine point has its valid parent among its bilinear taps (masks are max-pooled), so the
    normalised value is always defined there.
    """
    b, _, z = x.shape[:3]
    num = F.interpolate(_fold(x * mask), scale_factor=factor, mode="bilinear", align_corners=False)
    den = F.interpolate(_fold(mask), scale_factor=factor, mode="bilinear", align_corners=False)
    out = _unfold(_safe_divide(num, den, den > _MIN_MASK_SUM), b, z)
    return out * (fine_mask > 0).to(x.dtype)


def _downsample_mask(mask: Tensor, stride: tuple[int, int, int]) -> Tensor:
    """Any-valid (max-pool) downsampling of a (B, 1, Z, H, W) mask by ``stride``; sizes as a k=3, p=1 conv."""
    if stride == (1, 1, 1):
        return mask
    return F.max_pool3d(mask, kernel_size=stride, stride=stride, ceil_mode=True)


# ----------------------------------------------------------------------------------------------------
# Partial convolution (no mask dilation)


def stack_planes(x: Tensor, kz: int) -> Tensor:
    """(B, C, Z, H, W) -> (B * Z, kz * C, H, W): each plane with its kz - 1 neighbours (zeros beyond the ends).

    Channel ``i * C + c`` of plane z holds channel c of plane ``z + i - kz // 2``. Works in plane-major
    memory (B, Z, C, H, W), so outputs of this module's convolutions are never permuted back and forth.
    """
    b, c, z, h, w = x.shape
    planes = x.transpose(1, 2)  # (B, Z, C, H, W); contiguous when x came out of _conv_planes
    if kz > 1:
        p = kz // 2
        padded = F.pad(planes, (0, 0, 0, 0, 0, 0, p, p))
        planes = torch.cat([padded[:, i:i + z] for i in range(kz)], dim=2)
    return planes.reshape(b * z, kz * c, h, w)


def _count_weight(weight: Tensor) -> Tensor:
    """Weight of the partial conv with its mask count: (C_out, C_in, kz, ky, kx) -> (C_out + 1, C_in + 1, kz, ky, kx);
    the direct form convolves with it as is, the plane-stacked one rearranged (``_plane_weight``).

    Input channel C_in is the mask count (no data weight); output C_out sums it over the window (weights 1).
    """
    c_out, c_in, kz, ky, kx = weight.shape
    data = F.pad(weight, (0, 0, 0, 0, 0, 0, 0, 1))
    ones = torch.ones((1, 1, kz, ky, kx), dtype=weight.dtype, device=weight.device)
    count = F.pad(ones, (0, 0, 0, 0, 0, 0, c_in, 0))
    return torch.cat([data, count], dim=0)


def _plane_weight(weight: Tensor) -> Tensor:
    """Conv2d weight of the plane-stacked partial conv, with one extra input and output channel for the mask.

    (C_out, C_in, kz, ky, kx) -> (C_out + 1, kz (C_in + 1), ky, kx): ``_count_weight`` with the planes moved
    ahead of the channels. Input channel ``i (C_in + 1) + c`` is channel c of plane ``z + i - kz // 2`` (c =
    C_in: the mask count); outputs 0..C_out-1 apply ``weight`` to the data channels, output C_out sums the
    mask count over the window (weights 1).
    """
    c_out, c_in, kz, ky, kx = weight.shape
    return _count_weight(weight).transpose(1, 2).reshape(c_out + 1, kz * (c_in + 1), ky, kx)


def _partial_conv3d(x: Tensor, mask: Tensor, weight: Tensor, bias: Optional[Tensor],
                    stride: tuple[int, int, int] = (1, 1, 1), direct: bool = False) -> tuple[Tensor, Tensor]:
    """Unvalidated body of ``partial_conv3d``."""
    c_in = x.shape[1]
    c_out, _, kz, ky, kx = weight.shape
    b, _, z = x.shape[:3]
    hw_stride = (int(stride[1]), int(stride[2]))
    if mask.shape[1] == 1:
        location, counts = mask, mask * float(c_in)
    else:
        location, counts = mask.amax(dim=1, keepdim=True), mask.sum(dim=1, keepdim=True)
    if direct:
        # an explicit zero bias: onnxruntime rejected the exporter's Conv without one for a computed weight
        y = F.conv3d(torch.cat([x * mask, counts], dim=1), _count_weight(weight),
                     torch.zeros(c_out + 1, dtype=x.dtype, device=x.device), (1, *hw_stride),
                     (kz // 2, ky // 2, kx // 2))
    else:
        y = F.conv2d(stack_planes(torch.cat([x * mask, counts], dim=1), kz), _plane_weight(weight), None,
                     hw_stride, (ky // 2, kx // 2))
        y = y.reshape(b, z, c_out + 1, y.shape[-2], y.shape[-1]).transpose(1, 2)
    raw, window = y[:, :c_out], y[:, c_out:]
    out_mask = _downsample_mask(location, (1, *hw_stride))
    # out_mask > 0 implies a positive window count (the pooled block lies inside the kernel window)
    out = raw * (float(c_in * kz * ky * kx) / window.clamp(min=_MIN_MASK_SUM))
    if bias is not None:
        out = out + bias.reshape(1, -1, 1, 1, 1)
    return out * (out_mask > 0).to(x.dtype), out_mask


def partial_conv3d(x: Tensor, mask: Tensor, weight: Tensor, bias: Optional[Tensor],
                   stride: tuple[int, int, int] = (1, 1, 1), direct: bool = False) -> tuple[Tensor, Tensor]:
    """3D partial convolution (Liu et al. 2018) that does not dilate the mask (thesis Sec. 6.3.3).

    ``out = W^T (x * mask) * (C_in k_vol / sum(mask in window)) + bias`` where the output location is valid,
    0 elsewhere. The mask may have one channel (shared by all input channels) or C_in channels (one per
    channel, e.g. the cost-volume mask of Eq. 6.4); the window sum then counts channels too. Padding is
    'same' (``kernel // 2``) with zeros, which count as mask 0, so borders are handled like holes.

    The output mask is the *location* mask: the max over the mask's channels, max-pooled by ``stride``
    (any valid input pixel in the stride window, e.g. (1, 2, 2) on (Z, H, W)); it is never dilated by the
    kernel. Mask values are kept (warped alphas may be fractional); output values are zeroed where it is 0.
    The plane axis is never strided (``stride[0] == 1``).

    Runs as one Conv2d over the planes, each stacked with its kz - 1 neighbours as extra channels, with the
    mask count as one more input/output channel (``_plane_weight``): the same linear map as
    ``F.conv3d(x * mask, weight, None, stride, kernel // 2)`` plus the window count, but the CPU build of
    torch runs Conv3d through its slow im2col path and Conv2d through oneDNN (about 3x faster here).
    ``direct=True`` runs the same map as one ``F.conv3d`` (the mask count as an extra input channel,
    ``_count_weight``): what the ONNX export uses, because onnxruntime's Conv3d is fast and the plane
    stacking costs the exported graph a transpose, padding and concatenations per layer.

    Args:
        x: (B, C_in, Z, H, W); mask: (B, 1 or C_in, Z, H, W) in [0, 1].
        weight: (C_out, C_in, kz, ky, kx), odd kernel sizes; bias: (C_out,) or None.
        stride: (1, sy, sx).

    Returns:
        out (B, C_out, Z, H', W'), out_mask (B, 1, Z, H', W'), with H' = ceil(H / sy), W' = ceil(W / sx).
    """
    sizes: dict = {}
    check_shape(x, "x", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(mask, "mask", ("B", "M", "Z", "H", "W"), sizes)
    check_shape(weight, "weight", ("O", "C", "kz", "ky", "kx"), sizes)
    if sizes["M"] not in (1, sizes["C"]) or any(k % 2 == 0 for k in weight.shape[2:]) or int(stride[0]) != 1:
        raise InputError(f"needs a mask with 1 or C_in channels, odd kernels and stride[0] = 1, got mask "
                         f"{tuple(mask.shape)}, weight {tuple(weight.shape)}, stride {stride}", field="partial_conv3d")
    return _partial_conv3d(x, mask, weight, bias, stride, direct)


class PartialConv3d(nn.Module):
    """Thin module over ``partial_conv3d``: holds the weights (Conv3d's default init), kernel and stride.

    ``direct`` (default False: the plane-stacked Conv2d, fast in torch) selects the single-Conv3d form, which
    ``export.flow`` switches on for the ONNX graph (``set_direct_conv3d``).
    """

    def __init__(self, in_channels: int, out_channels: int, kernel_size: tuple[int, int, int] = (3, 3, 3),
                 stride: tuple[int, int, int] = (1, 1, 1), bias: bool = True) -> None:
        super().__init__()
        if stride[0] != 1 or any(k % 2 == 0 for k in kernel_size):
            raise InputError(f"needs odd kernel sizes and no stride along the planes, got kernel "
                             f"{kernel_size}, stride {stride}", field="PartialConv3d")
        conv = nn.Conv3d(in_channels, out_channels, kernel_size, bias=bias)
        self.weight = conv.weight
        self.bias = conv.bias
        self.stride = tuple(stride)
        self.direct = False

    def forward(self, x: Tensor, mask: Tensor) -> tuple[Tensor, Tensor]:
        return _partial_conv3d(x, mask, self.weight, self.bias, self.stride, self.direct)


def set_direct_conv3d(module: nn.Module, direct: bool = True) -> nn.Module:
    """Switch every ``PartialConv3d`` in ``module`` to the single-Conv3d form (or back); returns ``module``.

    The two forms are the same linear map (tested to 1e-5); the choice only changes speed: plane-stacked
    Conv2d in torch, one Conv3d in onnxruntime.
    """
    for layer in module.modules():
        if isinstance(layer, PartialConv3d):
            layer.direct = bool(direct)
    return module


# ----------------------------------------------------------------------------------------------------
# Masked correlation (Eq. 6.3-6.4)


def _masked_correlation(h1: Tensor, alpha1: Tensor, h2: Tensor, alpha2: Tensor, search_range: int,
                       plane_search_range: int) -> tuple[Tensor, Tensor]:
    """Unvalidated body of ``masked_correlation``."""
    r, s = search_range, plane_search_range
    b, c, z, h, w = h1.shape
    n = 2 * r + 1
    # plane-major (B, Z, C, H, W) memory, as the partial convolutions leave their outputs; the n x-shifts
    # of the padded h2 are stacked once (B, Z + 2s, C, n, H + 2r, W), then each (dz, dy) is one slice
    f1 = (h1 * alpha1).transpose(1, 2).contiguous()[:, :, :, None]
    f2 = F.pad((h2 * alpha2).transpose(1, 2), (r, r, r, r, 0, 0, s, s))
    f2 = torch.stack([f2[..., dx:dx + w] for dx in range(n)], dim=3)
    a2 = F.pad(alpha2[:, 0], (r, r, r, r, s, s))
    a2 = torch.stack([a2[..., dx:dx + w] for dx in range(n)], dim=2)  # (B, Z + 2s, n, H + 2r, W)
    costs, masks = [], []
    for dz in range(2 * s + 1):
        for dy in range(n):
            costs.append((f1 * f2[:, dz:dz + z, :, :, dy:dy + h]).sum(dim=2))  # (B, Z, n, H, W)
            masks.append(a2[:, dz:dz + z, :, dy:dy + h])
    # (B, (2s+1) n, Z, n_dx, H, W) -> (B, D, Z, H, W), D ordered (dz, dy, dx)
    d = (2 * s + 1) * n * n
    cv = torch.stack(costs, dim=1).transpose(2, 3).reshape(b, d, z, h, w) * (1.0 / c)
    cv_mask = torch.stack(masks, dim=1).transpose(2, 3).reshape(b, d, z, h, w)
    return cv, cv_mask * alpha1


def masked_correlation(h1: Tensor, alpha1: Tensor, h2: Tensor, alpha2: Tensor, search_range: int,
                       plane_search_range: int) -> tuple[Tensor, Tensor]:
    """Masked cost volume (thesis Eq. 6.3-6.4) by zero padding + shifted slices (no custom op, exportable).

    ``cv[d](x, z) = <h1(x, z) alpha1(x, z), h2(x + (dx, dy), z + dz) alpha2(x + (dx, dy), z + dz)> / C`` and
    ``cv_mask[d](x, z) = alpha1(x, z) alpha2(x + (dx, dy), z + dz)``, for every displacement
    ``d = (dz, dy, dx)`` in ``[-s_z, s_z] x [-r, r] x [-r, r]``, ordered dz (outermost), dy, dx. Outside the
    volume h2 and alpha2 are 0. The division by C (PWC-Net's normalisation) only scales Eq. 6.3.

    Args:
        h1, h2: (B, C, Z, H, W) features; alpha1, alpha2: (B, 1, Z, H, W) masks in [0, 1].
        search_range: r (pixels); plane_search_range: s_z (planes).

    Returns:
        cv (B, D, Z, H, W), cv_mask (B, D, Z, H, W), D = (2 s_z + 1)(2 r + 1)^2 (243 for r = 4, s_z = 1).
    """
    sizes: dict = {}
    check_shape(h1, "h1", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(h2, "h2", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(alpha1, "alpha1", ("B", 1, "Z", "H", "W"), sizes)
    check_shape(alpha2, "alpha2", ("B", 1, "Z", "H", "W"), sizes)
    if search_range < 0 or plane_search_range < 0:
        raise InputError("search ranges must be >= 0", field="search_range")
    return _masked_correlation(h1, alpha1, h2, alpha2, int(search_range), int(plane_search_range))


# ----------------------------------------------------------------------------------------------------
# 3D flow: plane offsets, backward warping, network output -> flow (Eq. 6.5-6.6), extrapolation (Eq. 6.13)


def _plane_gaps(plane_depths: Tensor) -> tuple[Tensor, Tensor]:
    """Depth gaps to the next farther / nearer plane, (B, Z) each; 0 at the ends and for non-finite planes."""
    d = torch.where(torch.isfinite(plane_depths), plane_depths, torch.zeros_like(plane_depths))
    gap = d[:, 1:] - d[:, :-1]
    finite = torch.isfinite(plane_depths[:, 1:]) & torch.isfinite(plane_depths[:, :-1])
    gap = torch.where(finite, gap, torch.zeros_like(gap))
    zero = torch.zeros_like(d[:, :1])
    return torch.cat([gap, zero], dim=1), torch.cat([zero, gap], dim=1)


def plane_offset_unchecked(flow_z: Tensor, plane_depths: Tensor) -> Tensor:
    """Unvalidated body of ``plane_offset``."""
    far, near = _plane_gaps(plane_depths)
    far = far[:, None, :, None, None]
    near = near[:, None, :, None, None]
    gap = torch.where(flow_z >= 0, far, near)
    return _safe_divide(flow_z, gap, gap > 0).clamp(-1.0, 1.0)


def plane_offset(flow_z: Tensor, plane_depths: Tensor) -> Tensor:
    """Fractional plane offset of a depth change dz, the inverse of Eq. 6.6 within one plane gap.

    ``dz >= 0``: ``dz / (d(z + 1) - d(z))``; ``dz < 0``: ``dz / (d(z) - d(z - 1))``; clipped to [-1, 1]
    (the plane window of s_z = 1), 0 where the gap is 0 (end planes, equal or non-finite plane depths).
    Eq. 6.6 with its probability on two neighbouring planes maps back exactly to ``b(z+1) - b(z-1)``.

    Args:
        flow_z: (B, 1, Z, H, W) dz in scene units; plane_depths: (B, Z).

    Returns:
        (B, 1, Z, H, W) offset in planes.
    """
    sizes: dict = {}
    check_shape(flow_z, "flow_z", ("B", 1, "Z", "H", "W"), sizes)
    check_shape(plane_depths, "plane_depths", ("B", "Z"), sizes)
    return plane_offset_unchecked(flow_z, plane_depths)


def backward_warp_unchecked(values: Tensor, flow: Tensor, plane_depths: Tensor) -> Tensor:
    """Unvalidated body of ``backward_warp``."""
    b, c, z, h, w = values.shape
    offsets = (-1, 0, 1) if z > 1 else (0,)
    grid_x = (torch.arange(w, dtype=flow.dtype, device=flow.device) * 2.0 + 1.0).reshape(1, 1, 1, w)
    grid_y = (torch.arange(h, dtype=flow.dtype, device=flow.device) * 2.0 + 1.0).reshape(1, 1, h, 1)
    gx = (grid_x + 2.0 * flow[:, 0]) / w - 1.0  # (B, Z, H, W)
    gy = (grid_y + 2.0 * flow[:, 1]) / h - 1.0
    grid = torch.stack([gx, gy], dim=-1).reshape(b * z, h, w, 2)
    if len(offsets) > 1:
        padded = F.pad(values, (0, 0, 0, 0, 1, 1))
        shifted = torch.cat([padded[:, :, 1 + o:1 + o + z] for o in offsets], dim=1)  # (B, 3C, Z, H, W)
    else:
        shifted = values
    sampled = _unfold(F.grid_sample(_fold(shifted), grid, mode="bilinear", padding_mode="zeros",
                                    align_corners=False), b, z)
    if len(offsets) == 1:
        return sampled
    e = plane_offset_unchecked(flow[:, 2:3], plane_depths)
    out = sampled[:, :c] * torch.relu(-e)  # tent weights max(0, 1 - |e - o|) for o = -1, 0, 1
    out = out + sampled[:, c:2 * c] * (1.0 - e.abs())
    return out + sampled[:, 2 * c:] * torch.relu(e)


def backward_warp(values: Tensor, flow: Tensor, plane_depths: Tensor) -> Tensor:
    """Sample ``values`` at the other end of a 3D flow: ``out(x, z) = values(x + (du, dv), z + e)``.

    Bilinear in x/y (``grid_sample`` per plane, zeros outside the frame; pixel centres at +0.5,
    ``align_corners=False``) and linear along the planes at ``e = plane_offset(dz)`` in [-1, 1] (zeros
    beyond the first / last plane). This is the warp of Eq. 6.8 (reconstruct ``m_hat_n`` from
    ``m^w_{n-k}``), of Eq. 6.10 (``v_hat_n``) and of the pyramid features; differentiable w.r.t. ``values``
    and ``flow``.

    Args:
        values: (B, C, Z, H, W) MPI channels or features of the *second* MPI (frame n-k).
        flow: (B, 3, Z, H, W) (du, dv) pixels, dz scene units, in the first MPI's grid.
        plane_depths: (B, Z) plane depths of the first MPI.

    Returns:
        (B, C, Z, H, W).
    """
    sizes: dict = {}
    check_shape(values, "values", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(flow, "flow", ("B", 3, "Z", "H", "W"), sizes)
    check_shape(plane_depths, "plane_depths", ("B", "Z"), sizes)
    return backward_warp_unchecked(values, flow, plane_depths)


def _check_planes(plane_depths: Tensor, sizes: dict) -> None:
    check_shape(plane_depths, "plane_depths", ("B", "Z"), sizes)


def _flow_from_output(displacement: Tensor, plane_logits: Tensor, plane_depths: Tensor) -> Tensor:
    b, p, z, h, w = plane_logits.shape
    s = (p - 1) // 2
    if s == 0:
        return torch.cat([displacement, torch.zeros_like(displacement[:, :1])], dim=1)
    plane = torch.arange(z, device=plane_logits.device)
    offsets = torch.arange(-s, s + 1, device=plane_logits.device)
    target = plane[None, :] + offsets[:, None]  # (P, Z)
    inside = (target >= 0) & (target < z)
    logits = plane_logits + torch.where(inside, 0.0, _OUTSIDE_LOGIT).to(plane_logits.dtype)[None, :, :, None, None]
    prob = torch.softmax(logits, dim=1)  # Eq. 6.5
    finite = torch.isfinite(plane_depths)
    d = torch.where(finite, plane_depths, torch.zeros_like(plane_depths))
    d_pad = F.pad(d[:, None], (s, s), mode="replicate")[:, 0]  # (B, Z + 2s): the outside has prob 0
    expected = torch.zeros_like(displacement[:, :1])
    for i in range(p):
        expected = expected + prob[:, i:i + 1] * d_pad[:, i:i + z][:, None, :, None, None]
    here = d[:, None, :, None, None]
    dz = torch.where(finite[:, None, :, None, None], expected - here, torch.zeros_like(expected))  # Eq. 6.6
    return torch.cat([displacement, dz], dim=1)


def flow_from_output(displacement: Tensor, plane_logits: Tensor, plane_depths: Tensor) -> Tensor:
    """Real 3D flow from the network's output (thesis Eq. 6.5-6.6).

    ``b = softmax(plane_logits)`` over the plane offsets z' in [-s_z, s_z] (offsets that leave the MPI get
    probability exactly 0), ``dz = sum_z' b_z' d(z + z') - d(z)`` with ``d`` the plane depths. With one
    offset (s_z = 0, the 2d mode) dz = 0. Non-finite plane depths (an all-sky frame) give dz = 0.

    Args:
        displacement: (B, 2, Z, H, W) real (du, dv) in pixels (Eq. 6.6's a).
        plane_logits: (B, 2 s_z + 1, Z, H, W) logits of z' = -s_z .. s_z.
        plane_depths: (B, Z).

    Returns:
        (B, 3, Z, H, W) flow (du, dv, dz).

    >>> logits = torch.zeros(1, 3, 2, 1, 1); logits[:, 2] = 50.0  # plane 0 -> plane 1; plane 1's +1 leaves the MPI
    >>> flow_from_output(torch.zeros(1, 2, 2, 1, 1), logits, torch.tensor([[2.0, 3.0]]))[0, 2, :, 0, 0].tolist()
    [1.0, -0.5]
    """
    sizes: dict = {}
    check_shape(displacement, "displacement", ("B", 2, "Z", "H", "W"), sizes)
    check_shape(plane_logits, "plane_logits", ("B", "P", "Z", "H", "W"), sizes)
    _check_planes(plane_depths, sizes)
    if sizes["P"] % 2 != 1:
        raise InputError(f"needs an odd number 2 s_z + 1 of plane offsets, got {sizes['P']}", field="plane_logits")
    return _flow_from_output(displacement, plane_logits, plane_depths)


def extrapolate(flow_back: Tensor, steps: float) -> Tensor:
    """Linear motion model (thesis Eq. 6.13): ``u(n -> n+k') = -(k' / k) u(n -> n-k)``; ``steps = k' / k``.

    Works on any flow layout ((B, 3, Z, H, W) 3D flow, (B, H, W, 2) ...): every component is scaled.

    >>> extrapolate(torch.tensor([2.0, -4.0, 0.5]), 0.5).tolist()
    [-1.0, 2.0, -0.25]
    """
    return flow_back * (-float(steps))


# ----------------------------------------------------------------------------------------------------
# Inputs


def encode_color(color: Tensor) -> Tensor:
    """Linear (HDR) RGB -> [0, 1) for the network and the photometric loss: ``sqrt(c / (1 + c) + 1e-4) - 0.01``.

    A tone curve (highlights compressed) and a square-root gamma (dark regions spread out), finite slope at 0.
    """
    c = color.clamp(min=0.0)
    return torch.sqrt(c / (1.0 + c) + 1.0e-4) - 0.01


def _reference_depth(plane_depths: Tensor) -> Tensor:
    """1 / d_ref = (1 / d_near + 1 / d_far) / 2, (B,); +inf for an all-sky MPI."""
    return 2.0 / (1.0 / plane_depths[:, 0] + 1.0 / plane_depths[:, -1])


def mpi_features(mpi: Mpi, plane_depths: Tensor) -> Tensor:
    """Network input of an MPI, (B, 4, Z, H, W): encoded colour and a scale-free depth code, times alpha.

    The depth code is ``d_ref / d - 1`` (inverse depth relative to the middle of the planes, in inverse
    depth: -1 for sky, 0 at the middle plane, 1 at the nearest plane of ``plane_depths``; clipped to
    [-1, 3] for points nearer than it). ``plane_depths`` are the first MPI's for both MPIs of a pair, so
    depths compare across the pair; the code does not change when the scene is scaled.
    """
    d = mpi.depth
    ref = _reference_depth(plane_depths)[:, None, None, None, None]
    ok = torch.isfinite(d) & (d > 0) & torch.isfinite(ref)
    code = torch.where(ok, _safe_divide(ref.expand_as(d), d, ok) - 1.0, torch.full_like(d, -1.0))
    code = code.clamp(-1.0, 3.0)
    return torch.cat([encode_color(mpi.color), code], dim=1) * mpi.alpha


def mpi_pair(color_n: Tensor, depth_n: Tensor, K_n: Tensor, T_n: Tensor, color_prev: Tensor, depth_prev: Tensor,
             K_prev: Tensor, T_prev: Tensor, num_planes: int) -> tuple[Mpi, Mpi]:
    """The network's inputs from two RGB-D frames: ``m_n`` and ``m^w_{n-k}`` (camera motion cancelled).

    ``m_{n-k}`` is built on its own planes (one-hot) and forward-warped (``forward_warp_mpi``) into frame
    n's view onto *frame n's planes*, so plane indices (and Eq. 6.6's plane depths) mean the same depths
    in both MPIs.

    Args:
        color_n, color_prev: (B, H, W, 3) linear RGB; depth_n, depth_prev: (B, H, W) planar, +inf sky.
        K_n, K_prev: (B, 3, 3); T_n, T_prev: (B, 4, 4) world-to-camera.
        num_planes: Z (1 for the 2d mode: frames with depth as an extra channel).

    Returns:
        ``(m_n, m^w_{n-k})``, both with ``plane_depths`` of frame n.
    """
    mpi_n = build_mpi(color_n, depth_n, num_planes)
    mpi_prev = build_mpi(color_prev, depth_prev, num_planes)
    warped, _ = forward_warp_mpi(mpi_prev._replace(plane_depths=mpi_n.plane_depths), K_prev, T_prev, K_n, T_n)
    return mpi_n, warped


def surface_flow(flow: Tensor, mpi: Mpi) -> Tensor:
    """Per-pixel flow of the visible surface, (B, H, W, 3): planes weighted by alpha * visibility (Eq. 6.9).

    For a one-hot MPI this is the flow of the plane each pixel was assigned to; 0 where nothing is covered.
    Compare its (du, dv) with a frame's ``object_flow`` (``train_flow.endpoint_error``).
    """
    sizes: dict = {}
    mpi = check_mpi(mpi, sizes)
    check_shape(flow, "flow", ("B", 3, "Z", "H", "W"), sizes)
    weight = mpi.alpha * visibility(mpi)
    return (flow * weight).sum(dim=2).permute(0, 2, 3, 1)


# ----------------------------------------------------------------------------------------------------
# Network


class FeaturePyramid(nn.Module):
    """Shared encoder: per level a strided (1, 2, 2) and a stride-1 partial conv, LeakyReLU after each."""

    def __init__(self, in_channels: int, channels: tuple[int, ...], kernel_planes: int, slope: float) -> None:
        super().__init__()
        kernel = (kernel_planes, 3, 3)
        self.down = nn.ModuleList()
        self.conv = nn.ModuleList()
        for c in channels:
            self.down.append(PartialConv3d(in_channels, c, kernel, stride=(1, 2, 2)))
            self.conv.append(PartialConv3d(c, c, kernel))
            in_channels = c
        self.slope = slope

    def forward(self, x: Tensor, mask: Tensor) -> list[tuple[Tensor, Tensor]]:
        """x (B, C, Z, H, W), mask (B, 1, Z, H, W) -> [(features, mask) at 1/2, 1/4, ..., 1/2^L]."""
        levels = []
        for down, conv in zip(self.down, self.conv):
            x, mask = down(x, mask)
            x, mask = conv(F.leaky_relu(x, self.slope), mask)
            x = F.leaky_relu(x, self.slope)
            levels.append((x, mask))
        return levels


class FlowDecoder(nn.Module):
    """Residual flow estimator: 1x1x1 partial conv, then (kz, 3, 3) partial convs; outputs 2 + P channels."""

    def __init__(self, in_channels: int, channels: tuple[int, ...], out_channels: int, kernel_planes: int,
                 slope: float) -> None:
        super().__init__()
        kernel = (kernel_planes, 3, 3)
        sizes = [in_channels, *channels]
        self.layers = nn.ModuleList(
            [PartialConv3d(sizes[0], sizes[1], (1, 1, 1))]
            + [PartialConv3d(a, b, kernel) for a, b in zip(sizes[1:-1], sizes[2:])])
        self.head = PartialConv3d(sizes[-1], out_channels, kernel)
        with torch.no_grad():  # small initial residuals
            self.head.weight.mul_(0.1)
            self.head.bias.zero_()
        self.slope = slope

    def forward(self, x: Tensor, mask: Tensor) -> Tensor:
        for layer in self.layers:
            x, mask = layer(x, mask)
            x = F.leaky_relu(x, self.slope)
        return self.head(x, mask)[0]


class Flow3D(nn.Module):
    """DeCOMPnet's flow network F_Theta (Eq. 6.7): 3D flow ``u(n -> n-k)`` from ``m_n`` and ``m^w_{n-k}``.

    Coarse to fine from pyramid level L (1/2^L) to level 2 (1/4): at each level the previous flow is
    upsampled (x2, mask-normalised), the frame n-k features are backward-warped with it (``backward_warp``),
    correlated with the frame n features (``masked_correlation``), and a shared decoder adds a residual
    displacement (pixels of that level) and residual plane logits. The 1/4 flow is upsampled x4 and turned
    into 3D flow (``flow_from_output``). Inputs are padded with alpha = 0 to multiples of
    ``pyramid_stride`` and the output is cropped back, so any H, W >= 1 works.

    ``forward(mpi_n, mpi_prev_warped)`` validates once and returns (B, 3, Z, H, W) flow (du, dv, dz), zero
    where ``mpi_n.alpha`` is 0; ``flow_unchecked`` is the same without validation (export).
    """

    def __init__(self, config: Flow3DConfig = Flow3DConfig()) -> None:
        super().__init__()
        self.config = config
        kz, slope = config.kernel_planes, config.negative_slope
        self.num_offsets = 2 * config.plane_range + 1
        self.pyramid = FeaturePyramid(4, config.encoder_channels, kz, slope)
        # per estimating level (L .. 2): 1x1x1 reduction of the frame-n features
        self.reduce = nn.ModuleList([PartialConv3d(c, config.reduce_channels, (1, 1, 1))
                                     for c in config.encoder_channels[1:]])
        corr = (2 * config.plane_range + 1) * (2 * config.search_range + 1) ** 2
        self.decoder = FlowDecoder(corr + config.reduce_channels + 2 + self.num_offsets, config.decoder_channels,
                                   2 + self.num_offsets, kz, slope)

    def forward(self, mpi_n: Mpi, mpi_prev_warped: Mpi, initial_flow: Optional[Tensor] = None) -> Tensor:
        """(Mpi (B, ..., Z, H, W), Mpi[, initial flow (B, 2, H, W)]) -> flow (B, 3, Z, H, W).

        Z must equal ``config.num_planes``; ``initial_flow`` is required exactly when ``config.initial_flow``.
        """
        sizes: dict = {}
        mpi_n = check_mpi(mpi_n, sizes)
        mpi_prev_warped = check_mpi(mpi_prev_warped, sizes)
        if sizes["Z"] != self.config.num_planes:
            raise InputError(f"has Z = {sizes['Z']} planes, the network is built for {self.config.num_planes}",
                             field="mpi_n")
        if self.config.initial_flow != (initial_flow is not None):
            raise InputError(f"the network {'needs' if self.config.initial_flow else 'takes no'} initial flow",
                             field="initial_flow")
        if initial_flow is not None:
            check_shape(initial_flow, "initial_flow", ("B", 2, "H", "W"), sizes)
            if not bool(torch.isfinite(initial_flow).all()):
                raise InputError("has NaN or inf values", field="initial_flow")
        return self.flow_unchecked(mpi_n, mpi_prev_warped, initial_flow)

    def flow_unchecked(self, mpi_n: Mpi, mpi_prev_warped: Mpi, initial_flow: Optional[Tensor] = None,
                       depth_flow: bool = True) -> Tensor:
        """``forward`` without validation (for ``torch.export``: no shape is read as a Python int).

        ``depth_flow=False`` returns dz = 0 without computing it (no plane softmax, no logits upsampling at
        full size): (du, dv) are the same; for engines that use only those (``DecompConfig.depth_flow=0``).
        """
        planes = mpi_n.plane_depths
        h, w = mpi_n.alpha.shape[-2:]
        stride = pyramid_stride(self.config)
        pad = (0, (stride - w % stride) % stride, 0, (stride - h % stride) % stride)
        x1, a1 = F.pad(mpi_features(mpi_n, planes), pad), F.pad(mpi_n.alpha, pad)
        x2, a2 = F.pad(mpi_features(mpi_prev_warped, planes), pad), F.pad(mpi_prev_warped.alpha, pad)
        init = None if initial_flow is None else F.pad(initial_flow, pad)
        # both MPIs through the shared encoder as one batch
        batch = x1.shape[0]
        pyramid = self.pyramid(torch.cat([x1, x2]), torch.cat([a1, a2]))
        pyr1 = [(f[:batch], m[:batch]) for f, m in pyramid]
        pyr2 = [(f[batch:], m[batch:]) for f, m in pyramid]
        disp, logits, coarse_mask = self._coarse_to_fine(pyr1, pyr2, planes, init)
        disp = _masked_upsample(disp, coarse_mask, 4, a1) * 4.0
        if init is not None:  # the given flow at full detail on every plane, plus the network's residual
            disp = disp + init[:, :, None] * (a1 > 0).to(disp.dtype)
        if depth_flow:
            logits = _masked_upsample(logits, coarse_mask, 4, a1)
            flow = _flow_from_output(disp, logits, planes) * a1
        else:
            flow = torch.cat([disp * a1, torch.zeros_like(a1)], dim=1)
        return flow[..., :h, :w]

    def _coarse_to_fine(self, pyr1, pyr2, planes: Tensor,
                        initial_flow: Optional[Tensor] = None) -> tuple[Tensor, Tensor, Tensor]:
        """Levels L .. 2 -> (displacement (B, 2, ...), plane logits (B, P, ...), mask (B, 1, ...)) at 1/4.

        With an initial flow, the displacement each level warps and decodes with is that flow block-averaged
        to the level (in its pixels, on every plane) plus the network's residual; only the residual is
        upsampled from level to level and returned (``flow_unchecked`` adds the flow back at full resolution).
        """
        cfg = self.config
        resid = logits = None
        prev_mask = None
        for level in range(cfg.levels - 1, 0, -1):  # index 0 is level 1 (1/2): not estimated
            f1, m1 = pyr1[level]
            f2, m2 = pyr2[level]
            if resid is None:
                b, _, z, h, w = f1.shape
                resid = torch.zeros((b, 2, z, h, w), dtype=f1.dtype, device=f1.device)
                logits = torch.zeros((b, self.num_offsets, z, h, w), dtype=f1.dtype, device=f1.device)
            else:
                resid = _masked_upsample(resid, prev_mask, 2, m1) * 2.0
                logits = _masked_upsample(logits, prev_mask, 2, m1)
            disp = resid
            if initial_flow is not None:
                scale = 2 ** (level + 1)
                base = F.avg_pool2d(initial_flow, scale, scale) * (1.0 / scale)
                disp = resid + base[:, :, None] * (m1 > 0).to(f1.dtype)
            if initial_flow is None and level == cfg.levels - 1:
                f2w, m2w = f2, m2  # zero flow: nothing to warp
            else:
                warped = backward_warp_unchecked(torch.cat([f2, m2], dim=1), _flow_from_output(disp, logits, planes), planes)
                f2w, m2w = warped[:, :-1], warped[:, -1:]
            cv, cv_mask = _masked_correlation(f1, m1, f2w, m2w, cfg.search_range, cfg.plane_range)
            reduced, _ = self.reduce[level - 1](f1, m1)
            x = torch.cat([F.leaky_relu(cv, cfg.negative_slope), F.leaky_relu(reduced, cfg.negative_slope),
                           disp, logits], dim=1)
            mask = torch.cat([cv_mask, m1.expand(-1, x.shape[1] - cv.shape[1], -1, -1, -1)], dim=1)
            delta = self.decoder(x, mask)
            resid = resid + delta[:, :2]
            logits = logits + delta[:, 2:]
            prev_mask = m1
        return resid, logits, prev_mask
