"""Unsupervised losses of the 3D flow network (thesis Eq. 6.8-6.12).

The flow ``u = u(n -> n-k)`` (B, 3, Z, H, W) maps each point of ``m_n`` to where it was in
``m^w_{n-k}`` (frame n-k warped into frame n's view); both MPIs share frame n's plane depths
(``models.flow.network.mpi_pair``). Layout and conventions: ``models/geometry.py`` ((B, C, Z, H, W), planes near
to far, pixel centres at +0.5). Design note: ``docs/flow3d.md``.

- ``reconstruct``: ``m_hat_n`` = backward warp of ``m^w_{n-k}`` by u (``models.flow.network.backward_warp``);
- ``occlusion_mask``: Eq. 6.9-6.10 from the 3D visibility of ``m_n`` forward-warped by u;
- ``photometric_loss``: Eq. 6.8, beta MAE + (1 - beta) (1 - SSIM) / 2 per plane, averaged over planes;
- ``smoothness_loss``: Eq. 6.11, edge-aware (colour and alpha gradients) first-order smoothness;
- ``flow_loss``: Eq. 6.12, the total, per batch item.

Every loss is reduced per batch item ((B,) tensors), so data-parallel training averages the same thing
as one process, and is finite (0) for empty planes and all-empty MPIs.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor

from engine.core.checks import check_shape
from engine.core.config import option
from engine.core.errors import InputError
from engine.geometry import DEFAULT_SHARPNESS
from models.flow.network import backward_warp_unchecked, encode_color, plane_offset_unchecked
from models.geometry import Mpi, alpha_visibility, check_mpi, forward_warp_mpi

__all__ = ["FlowLossConfig", "masked_mean", "ssim", "photometric_loss", "occlusion_mask", "smoothness_loss",
           "photometric_channels", "reconstruct", "flow_loss"]

#: SSIM stabilisers for values in [0, 1] (Wang et al. 2004, as in monodepth / ARFlow).
_SSIM_C1 = 0.01 ** 2
_SSIM_C2 = 0.03 ** 2



@dataclass(frozen=True)
class FlowLossConfig:
    """Weights of Eq. 6.8-6.12 (thesis values: beta 0.15, a 10, lambda 10)."""

    beta: float = option(0.15, "weight of the MAE term in Eq. 6.8 (the SSIM term gets 1 - beta)")
    smoothness_weight: float = option(
        0.1, "lambda of Eq. 6.12. The thesis uses 10, starting from a Sintel-pretrained network; trained from "
             "scratch with this module's normalisation (means per point, flow in working-resolution pixels), "
             "10 makes zero flow score better than the true flow on moving objects, so nothing is learnt")
    edge_weight: float = option(10.0, "a of Eq. 6.11: how fast colour edges switch smoothness off")
    occlusion_threshold: float = option(0.5, "Eq. 6.10: a point is visible in frame n-k where v_hat_n > this")
    sharpness: float = option(DEFAULT_SHARPNESS, "soft z-buffer sharpness of the occlusion forward warp")

    def __post_init__(self) -> None:
        if not (0.0 <= self.beta <= 1.0 and self.smoothness_weight >= 0 and self.edge_weight >= 0
                and 0.0 <= self.occlusion_threshold <= 1.0 and self.sharpness >= 0):
            raise InputError("beta and occlusion_threshold must be in [0, 1], weights and sharpness >= 0",
                             field="FlowLossConfig")


def masked_mean(values: Tensor, mask: Tensor, dims: tuple[int, ...]) -> Tensor:
    """``sum(values * mask) / sum(mask)`` over ``dims`` (mask broadcast over channels); 0 where the mask is empty.

    The mask sum counts each channel of ``values`` (a mean over channels and points).
    """
    mask = mask.expand_as(values)
    total = (values * mask).sum(dim=dims)
    count = mask.sum(dim=dims)
    return total / count.clamp(min=1.0)


def ssim(x: Tensor, y: Tensor) -> Tensor:
    """Per-pixel SSIM of each plane, (B, C, Z, H, W): 3x3 box windows in x/y (no padding counted), values in [0, 1]."""
    def pool(t: Tensor) -> Tensor:
        bb, c, z, h, w = t.shape
        folded = t.transpose(1, 2).reshape(bb * z, c, h, w)
        out = F.avg_pool2d(folded, 3, 1, 1, count_include_pad=False)
        return out.reshape(bb, z, c, h, w).transpose(1, 2)

    mu_x, mu_y = pool(x), pool(y)
    var_x = pool(x * x) - mu_x * mu_x
    var_y = pool(y * y) - mu_y * mu_y
    cov = pool(x * y) - mu_x * mu_y
    num = (2.0 * mu_x * mu_y + _SSIM_C1) * (2.0 * cov + _SSIM_C2)
    den = (mu_x * mu_x + mu_y * mu_y + _SSIM_C1) * (var_x + var_y + _SSIM_C2)
    return num / den


def _per_plane_average(per_plane: Tensor, mask: Tensor) -> Tensor:
    """(B, Z) plane terms -> (B,): mean over the planes with at least one valid point (0 if none)."""
    occupied = (mask.sum(dim=(1, 3, 4)) > 0).to(per_plane.dtype)  # (B, Z)
    return (per_plane * occupied).sum(dim=1) / occupied.sum(dim=1).clamp(min=1.0)


def photometric_loss(target: Tensor, reconstruction: Tensor, mask: Tensor, beta: float = 0.15) -> Tensor:
    """Eq. 6.8 per batch item, (B,): ``beta MAE + (1 - beta) (1 - SSIM) / 2`` on the masked MPIs.

    Both terms are computed in each plane as means over the valid points of that plane (``mask`` > 0,
    all channels) and averaged over the planes that have valid points; SSIM compares ``target * mask``
    with ``reconstruction * mask``. An empty mask gives 0.

    Args:
        target, reconstruction: (B, C, Z, H, W), values in [0, 1] (``photometric_channels``).
        mask: (B, 1, Z, H, W) in {0, 1}: non-occluded points of m_n (o_n times alpha_n).
    """
    sizes: dict = {}
    check_shape(target, "target", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(reconstruction, "reconstruction", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(mask, "mask", ("B", 1, "Z", "H", "W"), sizes)
    return _photometric_loss(target, reconstruction, mask, float(beta))


def _photometric_loss(target: Tensor, reconstruction: Tensor, mask: Tensor, beta: float) -> Tensor:
    t, r = target * mask, reconstruction * mask
    mae = masked_mean((t - r).abs(), mask, (1, 3, 4))  # (B, Z)
    dssim = masked_mean(((1.0 - ssim(t, r)) * 0.5).clamp(0.0, 1.0), mask, (1, 3, 4))
    return _per_plane_average(beta * mae + (1.0 - beta) * dssim, mask)


@torch.no_grad()
def occlusion_mask(mpi_n: Mpi, flow: Tensor, threshold: float = 0.5,
                   sharpness: float = DEFAULT_SHARPNESS) -> Tensor:
    """Eq. 6.9-6.10: 1 where a point of ``m_n`` is still visible at frame n-k under ``flow``, else 0.

    ``m_n`` is forward-warped by the flow (``forward_warp_mpi`` with an identity camera: the flow alone moves
    the points) to ``m_hat_{n-k}``; its visibility ``prod_{y < z} (1 - alpha_hat(x, y))`` (Eq. 6.9) is
    backward-warped by the same flow to ``v_hat_n``; ``o_n = v_hat_n > threshold`` (Eq. 6.10). Points that
    leave the frame sample 0 and count as occluded. Not differentiable (no gradient is needed).

    Args:
        mpi_n: the first MPI (B, ...); flow: (B, 3, Z, H, W) u(n -> n-k).

    Returns:
        (B, 1, Z, H, W) float in {0, 1} (defined everywhere; multiply by alpha_n for the points of m_n).
    """
    sizes: dict = {}
    mpi_n = check_mpi(mpi_n, sizes)
    check_shape(flow, "flow", ("B", 3, "Z", "H", "W"), sizes)
    return _occlusion_mask(mpi_n, flow.detach(), float(threshold), float(sharpness))


def _occlusion_mask(mpi_n: Mpi, flow: Tensor, threshold: float, sharpness: float) -> Tensor:
    b = flow.shape[0]
    eye_k = torch.eye(3, dtype=flow.dtype, device=flow.device).expand(b, 3, 3)
    eye_t = torch.eye(4, dtype=flow.dtype, device=flow.device).expand(b, 4, 4)
    moved, _ = forward_warp_mpi(mpi_n, eye_k, eye_t, eye_k, eye_t, flow, sharpness=sharpness)
    seen = backward_warp_unchecked(alpha_visibility(moved.alpha), flow, mpi_n.plane_depths)
    return (seen > threshold).to(flow.dtype)


def _gradients(x: Tensor) -> tuple[Tensor, Tensor]:
    """Forward differences in x and y of (B, C, Z, H, W): (B, C, Z, H, W - 1) and (B, C, Z, H - 1, W)."""
    return x[..., :, 1:] - x[..., :, :-1], x[..., 1:, :] - x[..., :-1, :]


def smoothness_loss(flow_field: Tensor, color: Tensor, alpha: Tensor, edge_weight: float = 10.0) -> Tensor:
    """Eq. 6.11 per batch item, (B,): ``(1 - |grad alpha|) exp(-a |grad c|) |grad u|`` in x and y, per plane.

    ``|grad c|`` is the mean over colour channels, ``|grad u|`` the mean over the flow channels. The sum
    runs over neighbour pairs of each plane and is divided by the number of pairs whose two points both
    have alpha > 0 (0 when there are none); pairs across an alpha edge get weight 0 from the first factor.

    Args:
        flow_field: (B, C, Z, H, W), e.g. (du, dv, plane offset) (``flow_loss`` uses those).
        color: (B, 3, Z, H, W) in [0, 1] (encoded colour); alpha: (B, 1, Z, H, W).
        edge_weight: a.
    """
    sizes: dict = {}
    check_shape(flow_field, "flow_field", ("B", "C", "Z", "H", "W"), sizes)
    check_shape(color, "color", ("B", 3, "Z", "H", "W"), sizes)
    check_shape(alpha, "alpha", ("B", 1, "Z", "H", "W"), sizes)
    return _smoothness_loss(flow_field, color, alpha, float(edge_weight))


def _smoothness_loss(flow_field: Tensor, color: Tensor, alpha: Tensor, edge_weight: float) -> Tensor:
    total = torch.zeros_like(flow_field[:, 0, 0, 0, 0])
    pairs = torch.zeros_like(total)
    for du, dc, da, (a0, a1) in zip(_gradients(flow_field), _gradients(color), _gradients(alpha),
                                    _pairs(alpha)):
        weight = (1.0 - da.abs()) * torch.exp(-edge_weight * dc.abs().mean(dim=1, keepdim=True))
        term = weight * du.abs().mean(dim=1, keepdim=True)
        both = ((a0 > 0) & (a1 > 0)).to(term.dtype)
        total = total + (term * both).sum(dim=(1, 2, 3, 4))
        pairs = pairs + both.sum(dim=(1, 2, 3, 4))
    return total / pairs.clamp(min=1.0)


def _pairs(alpha: Tensor):
    """The two ends of each x and y neighbour pair of (B, 1, Z, H, W) alpha."""
    return ((alpha[..., :, :-1], alpha[..., :, 1:]), (alpha[..., :-1, :], alpha[..., 1:, :]))


def photometric_channels(mpi: Mpi) -> Tensor:
    """The MPI channels Eq. 6.8 compares, (B, 4, Z, H, W): encoded colour (``encode_color``) times alpha, alpha."""
    return torch.cat([encode_color(mpi.color) * mpi.alpha, mpi.alpha], dim=1)


def reconstruct(mpi_prev_warped: Mpi, flow: Tensor, plane_depths: Tensor) -> Tensor:
    """``m_hat_n``: ``photometric_channels(m^w_{n-k})`` backward-warped by u(n -> n-k), (B, 4, Z, H, W).

    Differentiable w.r.t. the flow (bilinear in x/y, linear along the planes; see ``backward_warp``).
    """
    sizes: dict = {}
    mpi_prev_warped = check_mpi(mpi_prev_warped, sizes)
    check_shape(flow, "flow", ("B", 3, "Z", "H", "W"), sizes)
    check_shape(plane_depths, "plane_depths", ("B", "Z"), sizes)
    return backward_warp_unchecked(photometric_channels(mpi_prev_warped), flow, plane_depths)


def flow_loss(mpi_n: Mpi, mpi_prev_warped: Mpi, flow: Tensor,
              config: FlowLossConfig = FlowLossConfig()) -> tuple[Tensor, dict[str, Tensor]]:
    """Eq. 6.12 per batch item: ``L_ph + lambda L_smooth``, (B,), and its terms (B,) by name.

    The photometric term compares ``m_n`` with ``reconstruct(m^w_{n-k}, u)`` on the points of ``m_n``
    (alpha_n > 0) that are not occluded at frame n-k (``occlusion_mask``). The smoothness term acts on
    (du, dv) in pixels and the plane offset of dz (``plane_offset``, in planes), so it does not depend on
    the scene's scale.

    Returns:
        ``(loss (B,), {"photometric", "smoothness", "visible"})``; "visible" is the fraction of
        m_n's points counted by the photometric term.
    """
    sizes: dict = {}
    mpi_n = check_mpi(mpi_n, sizes)
    mpi_prev_warped = check_mpi(mpi_prev_warped, sizes)
    check_shape(flow, "flow", ("B", 3, "Z", "H", "W"), sizes)
    planes = mpi_n.plane_depths
    valid = _occlusion_mask(mpi_n, flow.detach(), config.occlusion_threshold, config.sharpness)
    valid = valid * (mpi_n.alpha > 0).to(flow.dtype)
    reconstruction = backward_warp_unchecked(photometric_channels(mpi_prev_warped), flow, planes)
    photometric = _photometric_loss(photometric_channels(mpi_n), reconstruction, valid, config.beta)
    field_ = torch.cat([flow[:, :2], plane_offset_unchecked(flow[:, 2:3], planes)], dim=1)
    smooth = _smoothness_loss(field_, encode_color(mpi_n.color) * mpi_n.alpha, mpi_n.alpha, config.edge_weight)
    points = (mpi_n.alpha > 0).to(flow.dtype).sum(dim=(1, 2, 3, 4))
    visible = valid.sum(dim=(1, 2, 3, 4)) / points.clamp(min=1.0)
    loss = photometric + config.smoothness_weight * smooth
    return loss, {"photometric": photometric, "smoothness": smooth, "visible": visible}
