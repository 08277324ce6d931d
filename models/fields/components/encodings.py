"""Field components: multi-resolution tri-plane features (K-Planes), direction encodings, a tiny MLP.

Pure functions do the work; the ``nn.Module`` classes only hold parameters and hyper-parameters and call
them, so training and ONNX export run the same code. Everything is plain torch: the planes are read with
``torch.nn.functional.grid_sample`` (2D, bilinear, ``align_corners=True``), which ONNX exports (opset >= 16).

Coordinates: plane features are looked up at *contracted* coordinates in [-1, 1]^3 (see
``models/fields/components/sampling.py`` for the world -> contracted maps). The three planes of one scale are, in
this order, ``xy``, ``xz`` and ``yz``; plane ``ab`` is indexed with ``a`` along its width (grid_sample's
x) and ``b`` along its height (grid_sample's y).
"""
from __future__ import annotations

from typing import Sequence

import torch
from torch import Tensor, nn

__all__ = ["PLANE_AXES", "sample_planes", "plane_grid", "read_planes", "plane_tv", "plane_l1", "TriPlaneEncoding",
           "sh_encoding", "fourier_encoding", "direction_encoding_dim", "DirectionEncoding", "MLP",
           "channel_first"]

#: Coordinate pairs of the three spatial planes of one scale, in storage order: xy, xz, yz.
PLANE_AXES: tuple[tuple[int, int], ...] = ((0, 1), (0, 2), (1, 2))


# ----------------------------------------------------------------------------------------------------
# Tri-planes


def sample_planes(planes: Sequence[Tensor], coords: Tensor) -> Tensor:
    """Multi-resolution tri-plane features: product across the 3 planes, concatenated across scales.

    Args:
        planes: one tensor per scale, each (3, C, R, R) (the xy, xz, yz planes of that scale; R may differ
            between scales).
        coords: (..., 3) contracted coordinates; [-1, 1] spans the planes (``align_corners=True``: -1 and
            +1 are the centres of the first and last texels). Points outside read the border texels.

    Returns:
        (..., C * len(planes)) features, scale 0 first.

    Example:
        >>> planes = [torch.ones(3, 4, 8, 8), torch.full((3, 4, 16, 16), 0.5)]
        >>> sample_planes(planes, torch.zeros(5, 3)).shape
        torch.Size([5, 8])
    """
    lead = coords.shape[:-1]
    grid = plane_grid(coords.reshape(-1, 3))
    feats = [read_planes(plane, grid) for plane in planes]  # (C, N) each
    out = torch.cat(feats, dim=0).transpose(0, 1)  # (N, C * scales)
    return out.reshape(*lead, out.shape[-1])


def plane_grid(coords: Tensor) -> Tensor:
    """(N, 3) contracted coordinates -> the (3, 1, N, 2) ``grid_sample`` grid of the xy, xz, yz planes (plane k
    reads the coordinate pair ``PLANE_AXES[k]``): built once and shared by every scale.

    The grid is contiguous, stacked from the coordinate columns: ``grid_sample`` reads and differentiates a
    permuted (strided) grid markedly slower on the CPU, and the backward of a gather by index (an accumulating
    ``index_put``) is slow too (``docs/results/2026-11-28-dynamic-cost-2.md``). Same values and gradients.
    """
    cols = coords.unbind(-1)
    return torch.stack([torch.stack([cols[a], cols[b]], dim=-1) for a, b in PLANE_AXES]).unsqueeze(1)


def read_planes(plane: Tensor, grid: Tensor) -> Tensor:
    """The Hadamard product across the three planes of one scale: ``plane`` (3, C, H, W) read bilinearly
    (``align_corners=True``, border) at ``grid`` (3, 1, N, 2) -> (C, N).

    The product is two multiplications of the unbound planes (not ``prod``, nor indexing): the same values,
    and a backward without ``prod``'s zero checks and division or a zero-filled gradient per plane read.
    """
    f = torch.nn.functional.grid_sample(plane, grid.to(plane.dtype), mode="bilinear", padding_mode="border",
                                        align_corners=True)
    a, b, c = f.squeeze(2).unbind(0)  # (C, N) each
    return a * b * c


def plane_tv(planes: Sequence[Tensor]) -> Tensor:
    """Total variation of plane groups: mean squared difference of neighbouring texels, summed over planes.

    Args:
        planes: tensors (..., C, H, W) (e.g. one (3, C, R, R) tensor per scale).

    Returns:
        scalar; every plane weighs the same whatever its resolution (means, not sums); 0 for an empty group.
    """
    total = planes[0].new_zeros(()) if planes else torch.zeros(())
    for p in planes:
        dh = (p[..., 1:, :] - p[..., :-1, :]).square().mean()
        dw = (p[..., :, 1:] - p[..., :, :-1]).square().mean()
        total = total + dh + dw
    return total


def plane_l1(planes: Sequence[Tensor], target: float = 0.0) -> Tensor:
    """Mean absolute deviation of plane features from ``target``, summed over the tensors of the group.

    With ``target=0`` it pushes features (hence density and colour features) towards empty space; K-Planes
    uses ``target=1`` on its time planes (a static point = a product of ones). 0 for an empty group (a DeRF
    field with motion slots and tri-planes has no time planes).
    """
    total = planes[0].new_zeros(()) if planes else torch.zeros(())
    for p in planes:
        total = total + (p - target).abs().mean()
    return total


class TriPlaneEncoding(nn.Module):
    """Thin module holding the multi-resolution tri-planes read by :func:`sample_planes`.

    Args:
        resolutions: plane side R per scale.
        feature_dim: feature channels C per plane.
        init_range: features start uniform in this range (K-Planes: [0.1, 0.5] for space planes).
    """

    def __init__(self, resolutions: Sequence[int], feature_dim: int, init_range: tuple[float, float] = (0.1, 0.5)):
        super().__init__()
        self.resolutions = tuple(int(r) for r in resolutions)
        self.feature_dim = int(feature_dim)
        lo, hi = init_range
        self.planes = nn.ParameterList(
            nn.Parameter(torch.empty(3, self.feature_dim, r, r).uniform_(lo, hi)) for r in self.resolutions)

    @property
    def output_dim(self) -> int:
        return self.feature_dim * len(self.resolutions)

    def spatial_planes(self) -> list[Tensor]:
        """The spatial plane group: one (3, C, R, R) tensor (xy, xz, yz) per scale, coarse to fine."""
        return list(self.planes)

    def forward(self, coords: Tensor) -> Tensor:
        """(..., 3) contracted coordinates -> (..., C * scales) features."""
        return sample_planes(self.spatial_planes(), coords)


# ----------------------------------------------------------------------------------------------------
# Directions

# Real spherical-harmonic constants (the usual graphics basis, Sloan's "Stupid SH tricks" ordering), shared
# with the engine's torch-free renderer.
from engine.fields.encoding import SH_C0 as _C0  # noqa: E402
from engine.fields.encoding import SH_C1 as _C1
from engine.fields.encoding import SH_C2 as _C2
from engine.fields.encoding import SH_C3 as _C3


def sh_encoding(directions: Tensor, bands: int) -> Tensor:
    """Real spherical harmonics of unit directions, bands l = 0 .. ``bands`` - 1 (1 <= bands <= 4).

    Args:
        directions: (..., 3) unit vectors (world axes).
        bands: number of SH bands; the output has ``bands ** 2`` channels.

    Returns:
        (..., bands ** 2).
    """
    x, y, z = directions.unbind(-1)
    out = [torch.full_like(x, _C0)]
    if bands > 1:
        out += [-_C1 * y, _C1 * z, -_C1 * x]
    if bands > 2:
        xx, yy, zz = x * x, y * y, z * z
        out += [_C2[0] * x * y, -_C2[1] * y * z, _C2[2] * (3 * zz - 1), -_C2[3] * x * z, _C2[4] * (xx - yy)]
    if bands > 3:
        out += [-_C3[0] * y * (3 * xx - yy), _C3[1] * x * y * z, -_C3[2] * y * (5 * zz - 1),
                _C3[3] * z * (5 * zz - 3), -_C3[4] * x * (5 * zz - 1), _C3[5] * z * (xx - yy),
                -_C3[6] * x * (xx - 3 * yy)]
    return torch.stack(out, dim=-1)


def fourier_encoding(values: Tensor, num_frequencies: int, *, include_input: bool = True) -> Tensor:
    """NeRF's positional encoding gamma(x, 0, L) (thesis Eq. 4.4): [x, sin(2^k x), cos(2^k x)], k < L.

    Args:
        values: (..., D).
        num_frequencies: L.

    Returns:
        (..., D * (2 L + include_input)).
    """
    freqs = 2.0 ** torch.arange(num_frequencies, dtype=values.dtype, device=values.device)
    scaled = (values[..., None, :] * freqs[:, None]).flatten(-2)  # (..., L * D)
    parts = [values] if include_input else []
    parts += [torch.sin(scaled), torch.cos(scaled)]
    return torch.cat(parts, dim=-1)


def direction_encoding_dim(kind: str, degree: int) -> int:
    """Channels produced by :class:`DirectionEncoding` for ``kind`` in {"sh", "fourier", "none"}."""
    if kind == "sh":
        return degree ** 2
    if kind == "fourier":
        return 3 * (2 * degree + 1)
    return 0


class DirectionEncoding(nn.Module):
    """View-direction encoding: low-order spherical harmonics (``"sh"``, ``degree`` bands), a small Fourier
    encoding (``"fourier"``, ``degree`` frequencies) or nothing (``"none"``: a Lambertian colour)."""

    def __init__(self, kind: str = "sh", degree: int = 3):
        super().__init__()
        self.kind, self.degree = kind, int(degree)
        self.output_dim = direction_encoding_dim(kind, degree)

    def forward(self, directions: Tensor) -> Tensor:
        """(..., 3) unit directions -> (..., output_dim)."""
        if self.kind == "sh":
            return sh_encoding(directions, self.degree)
        if self.kind == "fourier":
            return fourier_encoding(directions, self.degree)
        return directions[..., :0]


# ----------------------------------------------------------------------------------------------------
# MLP


class _ChannelFirstLinear(torch.autograd.Function):
    """``nn.Linear`` of (M, in) features stored channel-first, i.e. given as ``xt`` (in, M) contiguous (what
    :func:`sample_planes` and the hex-plane lookups return, transposed): the forward is ``nn.Linear``'s call
    (``addmm(bias, xt.t(), weight.t())``); the backward gives the input's and the bias's gradients as
    autograd does (the same calls) and the weight's as ``(xt @ grad).t()``. Autograd forms that one as
    ``grad.t() @ xt.t()``, both operands transposed, which MKL runs several times slower on the CPU for a
    narrow input (8 channels: 3.4 against 0.4 ms for 59k rows); the value is the same sum, rounded in
    another order (equal bit for bit at 24 channels on this CPU, within float32 round-off at 8)."""

    @staticmethod
    def forward(ctx, xt: Tensor, weight: Tensor, bias: Tensor) -> Tensor:
        ctx.save_for_backward(xt, weight)
        return torch.addmm(bias, xt.t(), weight.t())

    @staticmethod
    def backward(ctx, grad: Tensor):
        xt, weight = ctx.saved_tensors
        grad_x = weight.t().mm(grad.t()) if ctx.needs_input_grad[0] else None
        grad_w = xt.mm(grad).t() if ctx.needs_input_grad[1] else None
        grad_b = grad.sum(0) if ctx.needs_input_grad[2] else None
        return grad_x, grad_w, grad_b


def channel_first(x: Tensor) -> bool:
    """True for a 2-D (M, C) tensor stored channel-first (its transpose is contiguous, it is not), as the
    plane lookups return their features."""
    return x.dim() == 2 and x.shape[0] > 1 and x.shape[1] > 1 and not x.is_contiguous() and x.t().is_contiguous()


class MLP(nn.Module):
    """A plain ReLU MLP (``nn.Linear`` layers only, exportable): in -> hidden x layers -> out, no output
    activation.

    In training (gradients on), a channel-first input (:func:`channel_first`: plane features) goes through
    the first layer's :class:`_ChannelFirstLinear`: the same forward, a faster weight gradient. Export and
    inference run ``nn.Sequential`` as it is."""

    def __init__(self, in_dim: int, hidden: int, out_dim: int, layers: int = 1):
        super().__init__()
        dims = [in_dim] + [hidden] * layers + [out_dim]
        mods: list[nn.Module] = []
        for i, (a, b) in enumerate(zip(dims[:-1], dims[1:])):
            mods.append(nn.Linear(a, b))
            if i < len(dims) - 2:
                mods.append(nn.ReLU())
        self.net = nn.Sequential(*mods)
        self.in_dim, self.out_dim = in_dim, out_dim

    def forward(self, x: Tensor) -> Tensor:
        """(..., in_dim) -> (..., out_dim)."""
        first = self.net[0]
        if (torch.is_grad_enabled() and first.weight.requires_grad and channel_first(x)
                and not torch.jit.is_tracing() and not torch.onnx.is_in_onnx_export()):
            return self.net[1:](_ChannelFirstLinear.apply(x.t(), first.weight, first.bias))
        return self.net(x)

