"""A small all-pairs-correlation optical flow network (RAFT-style) for large object motion.

It estimates u(n -> n-k), the object motion between frame n and the camera-compensated frame n-k (what
``flow2d`` gives OpenCV DIS), where objects move farther than DIS's coarse-to-fine search follows: the
correlation of every 1/8-resolution feature of frame n with every one of the other image, pooled into a
4-level pyramid, is looked up around the current estimate by a recurrent update, so a lookup of radius
``radius`` at level 3 reaches ``radius * 64`` pixels of the working resolution.

Conventions: images (B, 3, H, W) display-encoded sRGB in [0, 1], or (B, 4, H, W) with the depth code of
``engine.predict.corrflow.depth_code`` as a fourth channel (``CorrFlowConfig.depth``: RGB-D frames, frame n's
depth and the camera-compensated frame n-k's, both coded against frame n's median depth), H and W multiples
of 8; flow (B, 2, H, W)
in pixels of the input, (du, dv), pixel centres at +0.5 (a pixel's flow is where its centre lies in the
other image, minus that centre).
"""
from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

__all__ = ["CorrFlowConfig", "CorrFlow"]


@dataclass
class CorrFlowConfig:
    """Widths of the encoder stages (1/2, 1/4, 1/8), feature and context channels, GRU hidden size,
    correlation pyramid levels and lookup radius (in cells of each level), update iterations; ``depth``: the
    images carry a fourth channel, the depth code."""

    encoder_channels: tuple[int, ...] = (16, 32, 64)
    feature_channels: int = 64
    context_channels: int = 32
    hidden_channels: int = 48
    levels: int = 4
    radius: int = 3
    iterations: int = 4
    depth: bool = False

    @property
    def in_channels(self) -> int:
        """Channels of each input image: sRGB, plus the depth code with ``depth``."""
        return 4 if self.depth else 3


class _Residual(nn.Module):
    def __init__(self, channels: int) -> None:
        super().__init__()
        self.a = nn.Conv2d(channels, channels, 3, padding=1)
        self.b = nn.Conv2d(channels, channels, 3, padding=1)
        self.norm_a = nn.InstanceNorm2d(channels)
        self.norm_b = nn.InstanceNorm2d(channels)

    def forward(self, x: Tensor) -> Tensor:
        y = F.relu(self.norm_a(self.a(x)))
        return F.relu(x + self.norm_b(self.b(y)))


class _Encoder(nn.Module):
    """Three stride-2 stages to 1/8 resolution, instance-normalised; the 1/4 and 1/8 stages are followed by
    a residual block."""

    def __init__(self, widths: tuple, in_channels: int = 3) -> None:
        super().__init__()
        layers, c_in = [], in_channels
        for i, c in enumerate(widths):
            layers += [nn.Conv2d(c_in, c, 5 if i == 0 else 3, stride=2, padding=2 if i == 0 else 1),
                       nn.InstanceNorm2d(c), nn.ReLU(inplace=True)] + ([_Residual(c)] if i else [])
            c_in = c
        self.trunk = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        return self.trunk(x)


class _Update(nn.Module):
    """Motion encoder (correlation lookups + current flow), a convolutional GRU, and a flow-delta head."""

    def __init__(self, config: CorrFlowConfig) -> None:
        super().__init__()
        taps = config.levels * (2 * config.radius + 1) ** 2
        self.corr = nn.Sequential(nn.Conv2d(taps, 64, 1), nn.ReLU(inplace=True))
        self.flow = nn.Sequential(nn.Conv2d(2, 16, 7, padding=3), nn.ReLU(inplace=True),
                                  nn.Conv2d(16, 16, 3, padding=1), nn.ReLU(inplace=True))
        self.motion = nn.Sequential(nn.Conv2d(80, 46, 3, padding=1), nn.ReLU(inplace=True))
        h, x = config.hidden_channels, config.context_channels + 48
        self.zr = nn.Conv2d(h + x, 2 * h, 3, padding=1)
        self.q = nn.Conv2d(h + x, h, 3, padding=1)
        self.head = nn.Sequential(nn.Conv2d(h, 32, 3, padding=1), nn.ReLU(inplace=True), nn.Conv2d(32, 2, 3, padding=1))

    def forward(self, hidden: Tensor, context: Tensor, lookups: Tensor, flow: Tensor) -> tuple[Tensor, Tensor]:
        motion = self.motion(torch.cat([self.corr(lookups), self.flow(flow)], dim=1))
        x = torch.cat([context, motion, flow], dim=1)
        hx = torch.cat([hidden, x], dim=1)
        z, r = torch.sigmoid(self.zr(hx)).chunk(2, dim=1)
        q = torch.tanh(self.q(torch.cat([r * hidden, x], dim=1)))
        hidden = (1 - z) * hidden + z * q
        return hidden, self.head(hidden)


class CorrFlow(nn.Module):
    """``forward(image_a, image_b)`` -> list of (B, 2, H, W) flows a -> b in input pixels, one per iteration
    (the last is the estimate; training supervises all; ``every_iteration=False``: the last only, as the
    engine runs it). Images (B, ``config.in_channels``, H, W) in [0, 1],
    H, W multiples of 8."""

    def __init__(self, config: CorrFlowConfig = CorrFlowConfig()) -> None:
        super().__init__()
        self.config = config
        self.encoder = _Encoder(config.encoder_channels, config.in_channels)
        self.features = nn.Conv2d(config.encoder_channels[-1], config.feature_channels, 1)
        self.context = nn.Conv2d(config.encoder_channels[-1], config.hidden_channels + config.context_channels, 1)
        self.update = _Update(config)

    def correlation_pyramid(self, fa: Tensor, fb: Tensor) -> list[Tensor]:
        """Levels of (B * h * w, 1, h_l, w_l): every cell of a against all of b, average-pooled by 2 per level."""
        b, c, h, w = fa.shape
        corr = torch.matmul(fa.flatten(2).transpose(1, 2), fb.flatten(2)) / c ** 0.5  # (B, hw, hw)
        corr = corr.reshape(b * h * w, 1, h, w)
        pyramid = [corr]
        for _ in range(self.config.levels - 1):
            corr = F.avg_pool2d(corr, 2, stride=2, ceil_mode=True)  # odd and 1-cell sides keep a cell
            pyramid.append(corr)
        return pyramid

    def lookup(self, pyramid: list[Tensor], coords: Tensor) -> Tensor:
        """(B, levels * (2r+1)^2, h, w) correlations around ``coords`` (B, 2, h, w: cell positions x, y in b)."""
        b, _, h, w = coords.shape
        r = self.config.radius
        d = torch.arange(-r, r + 1, dtype=coords.dtype, device=coords.device)
        dy, dx = torch.meshgrid(d, d, indexing="ij")
        delta = torch.stack([dx, dy], dim=-1).reshape(1, 2 * r + 1, 2 * r + 1, 2)
        centre = coords.permute(0, 2, 3, 1).reshape(b * h * w, 1, 1, 2)
        out = []
        for level, corr in enumerate(pyramid):
            hl, wl = corr.shape[-2:]
            # cell x at level l has its centre at (x + 0.5) / 2^l - 0.5; align_corners=False normalisation
            pos = (centre + 0.5) / 2 ** level + delta
            grid = torch.stack([2 * pos[..., 0] / wl - 1, 2 * pos[..., 1] / hl - 1], dim=-1)
            sampled = F.grid_sample(corr, grid, mode="bilinear", padding_mode="zeros", align_corners=False)
            out.append(sampled.reshape(b, h, w, -1).permute(0, 3, 1, 2))
        return torch.cat(out, dim=1)

    def forward(self, image_a: Tensor, image_b: Tensor, iterations: int | None = None,
                every_iteration: bool = True) -> list[Tensor]:
        b, _, height, width = image_a.shape
        trunk = self.encoder(torch.cat([image_a, image_b], dim=0) * 2 - 1)
        both = self.features(trunk)
        fa, fb = both[:b], both[b:]
        pyramid = self.correlation_pyramid(fa, fb)
        ctx = self.context(trunk[:b])
        hidden, context = torch.tanh(ctx[:, :self.config.hidden_channels]), F.relu(ctx[:, self.config.hidden_channels:])
        h, w = fa.shape[-2:]
        ys, xs = torch.meshgrid(torch.arange(h, dtype=fa.dtype, device=fa.device),
                                torch.arange(w, dtype=fa.dtype, device=fa.device), indexing="ij")
        base = torch.stack([xs, ys])[None].expand(b, 2, h, w)
        flow = torch.zeros_like(base)  # in 1/8 cells
        flows = []
        count = iterations or self.config.iterations
        for i in range(count):
            hidden, delta = self.update(hidden, context, self.lookup(pyramid, base + flow), flow)
            flow = flow + delta
            if every_iteration or i == count - 1:
                flows.append(8.0 * F.interpolate(flow, size=(height, width), mode="bilinear", align_corners=False))
        return flows
