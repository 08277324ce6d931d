"""The all-pairs-correlation flow network (``models.flow.corrflow``) as the engine runs it: onnxruntime on
frame n and the camera-compensated frame n-k, at the network's working width, for ``flow2d[estimator=corr]``.

Flows are (H, W, 2) float32 pixels of the full frame, u(n -> n-k) (du, dv), pixel centres at +0.5; colours
are linear RGB, display-encoded to 8 bits (``engine.predict.dis.encode8``) before the network reads them.
"""
from __future__ import annotations

from pathlib import Path
from typing import Optional

import cv2
import numpy as np

from engine.core.checks import checked_array
from engine.predict.dis import encode8
from engine.predict.onnx import open_network
from engine.weights import CORRFLOW

__all__ = ["METADATA_KEY", "MIN_MOTION", "working_size", "network_image", "dis_start", "CorrFlowNetwork"]

#: ONNX metadata key of the exported network (``export.corrflow``): its config and working width.
METADATA_KEY = "interleave.corrflow"
#: ``dis_start``: the network's motion under this many pixels of the frame is not given to DIS as its start
#: (DIS finds small motion itself, finer than the network's 1/8-resolution estimate). Chosen on the
#: validation sequences: docs/results/2026-11-25-corrflow.md
MIN_MOTION = 8.0


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


def network_image(color: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """(h, w, 3) uint8: (H, W, 3) linear RGB display-encoded to 8 bits and resized to ``size`` = (w, h), by
    area means down, bilinearly up. What the network reads (training pairs are made with it too)."""
    w, h = size
    interpolation = cv2.INTER_AREA if w <= color.shape[1] else cv2.INTER_LINEAR
    return cv2.resize(encode8(color), (w, h), interpolation=interpolation)


class CorrFlowNetwork:
    """``estimate(color_n, warped)`` -> u(n -> n-k) (H, W, 2) of the full frame: both (H, W, 3) linear RGB
    images as ``network_image`` at ``working_size``, the network's last
    estimate bilinearly resized back and scaled to full-frame pixels."""

    def __init__(self, path: Optional[str | Path] = None, threads: int = 2) -> None:
        self.path = Path(path) if path is not None else CORRFLOW
        self.session, info = open_network(self.path, threads, METADATA_KEY, "model",
                                          "correlation flow network not found (export one with python -m "
                                          "export.corrflow)")
        self.working_width = int(info["working_width"])
        self.iterations = int(info["model"]["iterations"])  # update iterations the graph runs

    def estimate(self, color_n: np.ndarray, warped: np.ndarray) -> np.ndarray:
        color_n = checked_array(color_n, "color_n", ("H", "W", 3), {})
        h0, w0 = color_n.shape[:2]
        warped = checked_array(warped, "warped", ("H", "W", 3), {"H": h0, "W": w0})
        w, h = working_size(w0, h0, self.working_width)
        images = [network_image(x, (w, h)) for x in (color_n, warped)]
        inputs = {name: (x.astype(np.float32) / 255).transpose(2, 0, 1)[None]
                  for name, x in zip(("image_a", "image_b"), images)}
        flow = self.session.run(None, inputs)[0][0].transpose(1, 2, 0)
        if (w, h) == (w0, h0):
            return np.ascontiguousarray(flow, dtype=np.float32)
        flow = cv2.resize(np.ascontiguousarray(flow), (w0, h0), interpolation=cv2.INTER_LINEAR)
        return (flow * np.array([w0 / w, h0 / h], np.float32)).astype(np.float32)
