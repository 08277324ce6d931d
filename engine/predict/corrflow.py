"""The all-pairs-correlation flow network (``models.flow.corrflow``) as the engine runs it: onnxruntime on
frame n and the camera-compensated frame n-k, at the network's working width, for ``flow2d[estimator=corr]``.

Flows are (H, W, 2) float32 pixels of the full frame, u(n -> n-k) (du, dv), pixel centres at +0.5; colours
are linear RGB, display-encoded to 8 bits (``engine.predict.dis.encode8``) before the network reads them. A
network trained on RGB-D (its config's ``depth``) also reads both frames' planar depths (+inf for sky) as
``depth_code``s against frame n's median depth: scale-free, 8 bits like the colours.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from engine.core.checks import checked_array
from engine.core.errors import InputError
from engine.predict.dis import dis_calc, encode8
from engine.predict.onnx import open_network
from engine.weights import CORRFLOW

__all__ = ["METADATA_KEY", "MIN_MOTION", "DEPTH_SPAN", "working_size", "network_image", "depth_reference",
           "depth_code", "network_depth", "dis_start", "CorrFlowNetwork", "corr_dis_flow"]

#: ONNX metadata key of the exported network (``export.corrflow``): its config and working width.
METADATA_KEY = "interleave.corrflow"
#: ``dis_start``: the network's motion under this many pixels of the frame is not given to DIS as its start
#: (DIS finds small motion itself, finer than the network's 1/8-resolution estimate). Chosen on the
#: validation sequences: docs/results/2026-11-25-corrflow.md
MIN_MOTION = 8.0
#: ``depth_code``: natural-log depth units either side of the reference depth that the code spans (a factor of
#: e^3 = 20 nearer or farther; beyond, the code saturates)
DEPTH_SPAN = 3.0


def dis_start(flow: np.ndarray, min_motion: Optional[float] = None) -> np.ndarray:
    """The network's estimate (H, W, 2) as DIS's initial flow: 0 where it moves under ``min_motion`` px
    (default ``MIN_MOTION``); a new array."""
    limit = MIN_MOTION if min_motion is None else float(min_motion)
    return np.where((np.einsum("hwc,hwc->hw", flow, flow) < limit * limit)[..., None], np.float32(0), flow)


def working_size(width: int, height: int, net_width: int) -> tuple[int, int]:
    """(w, h) the network sees: the frame scaled so its longer side is ``net_width`` px (down or up: the
    network was trained on content at that scale and misses motion on smaller images), both sides rounded to
    multiples of 8 (at least 8)."""
    scale = net_width / max(width, height)
    return max(8, int(round(width * scale / 8)) * 8), max(8, int(round(height * scale / 8)) * 8)


def _to_working_size(image: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """``image`` (H, W[, C]) resized to ``size`` = (w, h): by area means down, bilinearly up."""
    interpolation = cv2.INTER_AREA if size[0] <= image.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(image, size, interpolation=interpolation)


def network_image(color: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) uint8: (H, W, 3) linear RGB display-encoded to 8 bits and resized to ``size`` = (w, h), by
    area means down, bilinearly up. What the network reads (training pairs are made with it too)."""
    return _to_working_size(encode8(color), tuple(size))


def depth_reference(depth: np.ndarray) -> float:
    """The depth the codes of a pair are relative to: the median finite, positive depth of frame n (sampled
    every 4th row and column), 1 when there is none (all sky)."""
    sample = depth[::4, ::4]
    sample = sample[np.isfinite(sample) & (sample > 0)]
    return float(np.median(sample)) if sample.size else 1.0


def depth_code(depth: np.ndarray, reference: float) -> np.ndarray:
    """(H, W) float32 in [0, 1]: 0.5 + ln(depth / reference) / (2 ``DEPTH_SPAN``), clipped; sky (+inf) is 1.
    Scale-free (a scene scaled with its reference codes alike) and uniform in log depth."""
    with np.errstate(divide="ignore", invalid="ignore"):
        code = 0.5 + np.log(np.maximum(depth, 1e-30) / reference) / (2.0 * DEPTH_SPAN)
    return np.clip(np.where(np.isnan(code), 1.0, code), 0.0, 1.0).astype(np.float32)


def network_depth(depth: np.ndarray, reference: float, size: tuple[int, int]) -> np.ndarray:
    """(h, w) uint8: ``depth_code`` of (H, W) planar depth resized to ``size`` = (w, h) as ``network_image``
    resizes colour (area means down, bilinear up)."""
    code = _to_working_size(depth_code(depth, reference), tuple(size))
    return np.rint(np.clip(code, 0.0, 1.0) * 255).astype(np.uint8)


class CorrFlowNetwork:
    """``estimate(color_n, warped, depth_n, depth_w)`` -> u(n -> n-k) (H, W, 2) of the full frame: both
    (H, W, 3) linear RGB images as ``network_image`` at ``working_size`` (and, for a network with ``depth``,
    both (H, W) planar depths as ``network_depth`` against ``depth_reference(depth_n)``), the network's last
    estimate bilinearly resized back and scaled to full-frame pixels."""

    def __init__(self, path: Optional[str | Path] = None, threads: int = 2) -> None:
        self.path = Path(path) if path is not None else CORRFLOW
        self.session, info = open_network(self.path, threads, METADATA_KEY, "model",
                                          "correlation flow network not found (export one with python -m "
                                          "export.corrflow)")
        self.working_width = int(info["working_width"])
        self.iterations = int(info["model"]["iterations"])  # update iterations the graph runs
        self.depth = bool(info["model"].get("depth", False))  # the network reads RGB-D

    def estimate(self, color_n: np.ndarray, warped: np.ndarray, depth_n: Optional[np.ndarray] = None,
                 depth_w: Optional[np.ndarray] = None) -> np.ndarray:
        sizes: dict = {}
        color_n = checked_array(color_n, "color_n", ("H", "W", 3), sizes)
        h0, w0 = color_n.shape[:2]
        warped = checked_array(warped, "warped", ("H", "W", 3), sizes)
        w, h = working_size(w0, h0, self.working_width)
        images = [network_image(x, (w, h)) for x in (color_n, warped)]
        if self.depth:
            if depth_n is None or depth_w is None:
                raise InputError(f"the network {self.path.name} reads RGB-D: give both frames' depths",
                                 file=self.path, field="depth")
            depth_n = checked_array(depth_n, "depth_n", ("H", "W"), sizes)
            depth_w = checked_array(depth_w, "depth_w", ("H", "W"), sizes)
            reference = depth_reference(depth_n)
            images = [np.dstack([x, network_depth(d, reference, (w, h))]) for x, d in zip(images, (depth_n, depth_w))]
        inputs = {name: (x.astype(np.float32) / 255).transpose(2, 0, 1)[None]
                  for name, x in zip(("image_a", "image_b"), images)}
        flow = self.session.run(None, inputs)[0][0].transpose(1, 2, 0)
        if (w, h) == (w0, h0):
            return np.ascontiguousarray(flow, dtype=np.float32)
        flow = cv2.resize(np.ascontiguousarray(flow), (w0, h0), interpolation=cv2.INTER_LINEAR)
        return (flow * np.array([w0 / w, h0 / h], np.float32)).astype(np.float32)


def corr_dis_flow(network: CorrFlowNetwork, dis, color_n: np.ndarray, warped: np.ndarray, luma_n: np.ndarray,
                  luma_w: np.ndarray, depth_n: Optional[np.ndarray] = None,
                  depth_w: Optional[np.ndarray] = None) -> np.ndarray:
    """``flow2d[estimator=corr]``'s flow u(n -> n-k), (H, W, 2) float32 pixels: the OpenCV DIS object ``dis`` from
    ``luma_n`` to ``luma_w`` (``engine.predict.dis.luma8`` of frame n and of the camera-compensated frame n-k,
    ``warped`` (H, W, 3) linear RGB) started from ``network``'s estimate (``dis_start``); the depths (H, W) are
    read by a network trained on RGB-D."""
    start = network.estimate(color_n, warped, depth_n, depth_w)
    return dis_calc(dis, luma_n, luma_w, dis_start(start))
