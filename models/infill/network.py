"""Disocclusion infilling in the MPI (thesis Sec. 6.3.4): a 3D U-Net predicts 2D infilling vectors.

After the newest frame is splatted into the predicted view, some pixels received nothing (disocclusions,
``holes``). The predicted frame is re-binned into a one-hot MPI on frame n's planes (holes have alpha 0
on every plane); per plane, the network predicts a 2D vector for every hole pixel pointing to a known
point of the same plane, and colour, depth and alpha are copied from there (``apply_vectors``). Where a
vector lands on an empty point of its plane, nothing is copied on that plane; the composite then shows the
nearest plane that did receive a copy. Passes are repeated ``g`` times (each fills what the previous one
left open, thesis: g = 3).

The *residual* head (the thesis's free vectors) learns a correction of a classical vector: the background-biased row fill of
``engine.geometry.holefill`` gives every hole pixel a source (the farther of its nearest known left / right
pixels; ``fill_sources``), the *prior* vector, fed to the network and added to its output (the last
layer starts at zero, so the untrained network is exactly that fill). Every filled pixel is a copy of a
known pixel: the engine samples the nearest point (``mode='nearest'``), training samples bilinearly so
the vectors get gradients.

The *choice* head (``InfillConfig.head='choice'``) scores K candidate sources per pixel instead (the prior,
and the nearest known pixel left, right, above and below: ``engine.predict.decomp.infill.candidate_vectors``) and the
engine copies the best-scored one; it is trained on the expected error of its choice (``choice_loss``),
which a network cannot lower by blending.

Tensors follow ``models/geometry.py``: MPIs (B, C, Z, H, W), planes near (0) to far, pixel centres at
+0.5, vectors (B, 2, Z, H, W) = (dx, dy) in pixels of the MPI's grid. The engine's numpy mirror is
``engine/predict/decomp/infill.py``.
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from engine.core.config import option
from engine.core.errors import InputError
from models.flow.network import encode_color, mpi_features, stack_planes
from models.geometry import Mpi, composite_unchecked

__all__ = ["InfillConfig", "InfillNet", "infill_inputs", "apply_vectors", "infill", "infill_loss", "choice_loss",
           "PRIOR_SCALE", "RESIDUAL_SCALE", "NUM_CANDIDATES"]

#: The prior vectors enter the network divided by this (pixels -> about unit range).
PRIOR_SCALE = 16.0
#: The network's raw output is multiplied by this to give the residual vector in pixels.
RESIDUAL_SCALE = 4.0
#: Candidate source vectors of the choice head (``engine.predict.decomp.infill.candidate_vectors``): the prior, then the
#: nearest known pixel to the left, right, above and below.
NUM_CANDIDATES = 5


@dataclass(frozen=True)
class InfillConfig:
    """The infilling U-Net: Conv3d levels that halve H and W (never the planes), skip connections."""

    num_planes: int = option(4, "MPI planes Z")
    channels: tuple[int, ...] = option((8, 16, 24), "channels per U-Net level (one level per entry; every "
                                                     "level halves H and W, the first included: the vectors "
                                                     "are estimated per 2 x 2 block and repeated)")
    negative_slope: float = option(0.1, "LeakyReLU slope")
    head: str = option("residual", "'residual': a correction (B, 2, Z, H, W) of the prior vectors, pixels (the "
                                   "thesis's free vectors); 'choice': logits (B, K, H, W) over K candidate "
                                   "source vectors (engine.predict.decomp.infill.candidate_vectors), the highest is copied")

    def __post_init__(self) -> None:
        if self.num_planes < 1 or not self.channels or min(self.channels) < 1:
            raise InputError("num_planes >= 1 and channels must be positive", field="InfillConfig")
        if self.head not in ("residual", "choice"):
            raise InputError(f"head must be 'residual' or 'choice', got {self.head!r}", field="InfillConfig")

    @property
    def in_channels(self) -> int:
        """Input channels per plane (``infill_inputs``): features 4, alpha, holes, then 2 per vector given."""
        return 6 + 2 * (1 if self.head == "residual" else NUM_CANDIDATES)

    @property
    def stride(self) -> int:
        """H and W of the network's input must be multiples of this (the engine pads)."""
        return 2 ** len(self.channels)


class PlaneConv3d(nn.Conv3d):
    """``nn.Conv3d`` with a 3 x 3 x 3 kernel, padding 1 and stride (1, s, s), run as one Conv2d over the
    planes with each plane's two neighbours stacked as channels (``models.flow.network.stack_planes``): the same
    linear map (tested against ``F.conv3d``), several times faster on torch's CPU build."""

    def __init__(self, c_in: int, c_out: int, stride: int = 1) -> None:
        super().__init__(c_in, c_out, kernel_size=3, stride=(1, stride, stride), padding=1)

    def forward(self, x: Tensor) -> Tensor:
        b, _, z = x.shape[:3]
        c_out, c_in = self.weight.shape[:2]
        weight = self.weight.transpose(1, 2).reshape(c_out, 3 * c_in, 3, 3)
        y = F.conv2d(stack_planes(x, 3), weight, self.bias, self.stride[1:], 1)
        return y.reshape(b, z, c_out, y.shape[-2], y.shape[-1]).transpose(1, 2)


def _conv(c_in: int, c_out: int, stride: int = 1) -> PlaneConv3d:
    return PlaneConv3d(c_in, c_out, stride)


class InfillNet(nn.Module):
    """A 3D U-Net: (B, C, Z, H, W) inputs (``infill_inputs``) -> (B, 2, Z, H, W) residual vectors, pixels
    (residual head), or (B, K, H, W) candidate logits, the per-plane scores averaged over the planes
    (choice head)."""

    def __init__(self, config: InfillConfig = InfillConfig()) -> None:
        super().__init__()
        if not isinstance(config, InfillConfig):
            raise InputError(f"must be an InfillConfig, got {type(config).__name__}", field="config")
        self.config = config
        ch = config.channels
        self.down = nn.ModuleList()
        c_prev = config.in_channels
        for i, c in enumerate(ch):
            self.down.append(nn.ModuleList([_conv(c_prev, c, 2), _conv(c, c)]))
            c_prev = c
        self.up = nn.ModuleList()
        for i in range(len(ch) - 1, 0, -1):
            self.up.append(nn.ModuleList([_conv(ch[i] + ch[i - 1], ch[i - 1]), _conv(ch[i - 1], ch[i - 1])]))
        self.head = PlaneConv3d(ch[0], 2 if config.head == "residual" else NUM_CANDIDATES)
        nn.init.zeros_(self.head.weight)
        nn.init.zeros_(self.head.bias)

    def forward(self, x: Tensor) -> Tensor:
        act = lambda t: F.leaky_relu(t, self.config.negative_slope)  # noqa: E731
        size = x.shape[2:]
        skips = []
        for first, second in self.down:
            x = act(second(act(first(x))))
            skips.append(x)
        for (first, second), skip in zip(self.up, reversed(skips[:-1])):
            x = F.interpolate(x, size=skip.shape[2:], mode="nearest")
            x = act(second(act(first(torch.cat([x, skip], dim=1)))))
        out = F.interpolate(self.head(x), size=size, mode="nearest")
        return out * RESIDUAL_SCALE if self.config.head == "residual" else out.mean(dim=2)


def infill_inputs(mpi: Mpi, holes: Tensor, prior: Tensor) -> Tensor:
    """Network input (B, ``InfillConfig.in_channels``, Z, H, W): encoded colour and depth code times alpha
    (``mpi_features``), alpha, the hole mask and the vectors / ``PRIOR_SCALE`` (both the same on every plane).

    Args:
        mpi: the predicted frame's MPI (holes: alpha 0 on every plane); holes: (B, H, W) bool or {0, 1};
        prior: (B, 2, H, W) prior vectors (residual head) or (B, 2 K, H, W) candidate vectors (choice head),
            pixels (0 outside holes and where the fill found no source).
    """
    z = mpi.alpha.shape[2]
    holes = holes.to(mpi.alpha.dtype)[:, None, None].expand(-1, 1, z, -1, -1)
    prior = (prior / PRIOR_SCALE)[:, :, None].expand(-1, -1, z, -1, -1)
    return torch.cat([mpi_features(mpi, mpi.plane_depths), mpi.alpha, holes, prior], dim=1)


def apply_vectors(mpi: Mpi, holes: Tensor, vectors: Tensor, mode: str = "bilinear") -> tuple[Mpi, Tensor]:
    """Copy colour, depth and alpha along ``vectors`` into the hole pixels, per plane.

    Each plane of each hole pixel p takes the plane's values at p + v (pixel centres at +0.5; outside the
    frame counts as empty). ``mode='nearest'`` copies one point exactly (the engine); ``'bilinear'`` blends
    the four around it (differentiable in ``vectors``), colour and inverse depth weighted by alpha, so an
    empty neighbour lowers alpha but never darkens the colour; ``'straight_through'`` (training) returns the
    nearest point's values with the bilinear sample's gradient, so training optimises what the engine
    computes (trained bilinearly, the network learnt to blend, which the nearest copy cannot reproduce:
    held-out loss 7 % above the prior's after 800 steps). Known pixels are unchanged.

    Returns:
        the infilled MPI and the holes left (B, H, W) bool: hole pixels where no plane received alpha.
    """
    if mode not in ("bilinear", "nearest", "straight_through"):
        raise InputError(f"mode must be 'bilinear', 'nearest' or 'straight_through', got {mode!r}", field="mode")
    b, _, z, h, w = mpi.alpha.shape
    sky = torch.isinf(mpi.depth)
    inv = torch.where(sky | (mpi.alpha <= 0), torch.zeros_like(mpi.depth), 1.0 / torch.where(sky, 1.0, mpi.depth))
    # channels sampled per plane: colour * alpha (3), inverse depth * alpha (1), sky * alpha (1), alpha (1)
    values = torch.cat([mpi.color * mpi.alpha, inv * mpi.alpha, sky.to(inv.dtype) * mpi.alpha, mpi.alpha], dim=1)
    values = values.permute(0, 2, 1, 3, 4).reshape(b * z, 6, h, w)
    ys, xs = torch.meshgrid(torch.arange(h, dtype=vectors.dtype), torch.arange(w, dtype=vectors.dtype),
                            indexing="ij")
    x = xs + 0.5 + vectors[:, 0]  # (B, Z, H, W) continuous coordinates
    y = ys + 0.5 + vectors[:, 1]
    grid = torch.stack([2.0 * x / w - 1.0, 2.0 * y / h - 1.0], dim=-1).reshape(b * z, h, w, 2)
    if mode == "straight_through":  # the nearest point's values, the bilinear sample's gradient
        soft = F.grid_sample(values, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
        hard = F.grid_sample(values, grid.detach(), mode="nearest", padding_mode="zeros", align_corners=False)
        sampled = soft + (hard - soft).detach()
    else:
        sampled = F.grid_sample(values, grid, mode=mode, padding_mode="zeros", align_corners=False)
    sampled = sampled.reshape(b, z, 6, h, w).permute(0, 2, 1, 3, 4)
    alpha_s = sampled[:, 5:6]
    has = alpha_s > 1e-6
    norm = torch.where(has, alpha_s, torch.ones_like(alpha_s))
    color_s = torch.where(has, sampled[:, 0:3] / norm, torch.zeros_like(sampled[:, 0:3]))
    is_sky = has & (sampled[:, 4:5] / norm > 0.5)
    inv_s = sampled[:, 3:4] / norm
    depth_s = torch.where(is_sky, torch.full_like(inv_s, float("inf")),
                          torch.where(has & (inv_s > 0), 1.0 / torch.where(inv_s > 0, inv_s, 1.0), torch.zeros_like(inv_s)))
    hole = holes.bool()[:, None, None]
    alpha = torch.where(hole, alpha_s, mpi.alpha)
    color = torch.where(hole, color_s, mpi.color)
    depth = torch.where(hole, depth_s, mpi.depth)
    left = holes.bool() & ~(alpha > 1e-6).any(dim=2)[:, 0]
    return Mpi(color, depth, alpha, mpi.plane_depths), left


def infill(net: InfillNet, mpi: Mpi, holes: Tensor, prior: Tensor,
           mode: str = "straight_through") -> tuple[Mpi, Tensor]:
    """One pass of a residual-head network: vectors = prior + network residual (on every plane), applied
    with ``apply_vectors`` (a choice head is trained on ``choice_loss`` instead)."""
    if net.config.head != "residual":
        raise InputError("infill applies a residual head's vectors; a choice head trains on choice_loss",
                         field="net")
    vectors = prior[:, :, None] + net(infill_inputs(mpi, holes, prior))
    return apply_vectors(mpi, holes, vectors, mode)


def choice_loss(logits: Tensor, errors: Tensor, holes: Tensor, kind: str = "expected") -> Tensor:
    """Loss of the choice head per batch item (B,), averaged over the hole pixels. ``errors`` (B, K, H, W):
    squared error (encoded colour, as ``infill_loss``) of copying candidate k's source into each pixel.

    ``kind='expected'``: sum_k softmax(logits)_k * errors_k, the expected error of the choice: minimised by
    all weight on the best candidate (no blending), but its gradient vanishes once the softmax saturates
    (Adam drove it onto the prior, the best candidate on average, within 25 steps here).
    ``kind='weighted_ce'``: cross-entropy towards each pixel's best candidate, weighted by how much the
    choice matters there (max_k errors_k - min_k errors_k). (Weighting by the gain over the prior instead
    gave pixels where the prior is best no weight, and the network left the prior far too often: held-out
    error 2.5-3.5x the prior's after 100-200 steps.)"""
    mask = holes.to(errors.dtype)
    if kind == "expected":
        err = (torch.softmax(logits, dim=1) * errors).sum(dim=1)
    elif kind == "weighted_ce":
        best_err, best = errors.min(dim=1)
        err = F.cross_entropy(logits, best, reduction="none") * (errors.max(dim=1).values - best_err)
    else:
        raise InputError(f"kind must be 'expected' or 'weighted_ce', got {kind!r}", field="kind")
    return (err * mask).sum(dim=(1, 2)) / mask.sum(dim=(1, 2)).clamp(min=1.0)


def infill_loss(mpi: Mpi, holes: Tensor, truth: Tensor) -> Tensor:
    """Mean squared error of the composited infilled MPI against the true frame (encoded colour, thesis:
    MSE), over the pixels that were holes; per batch item (B,). Holes left open composite to black."""
    color, _, _ = composite_unchecked(mpi)
    err = ((encode_color(color) - encode_color(truth)) ** 2).mean(dim=-1)
    mask = holes.to(err.dtype)
    return (err * mask).sum(dim=(1, 2)) / mask.sum(dim=(1, 2)).clamp(min=1.0)
