"""DeCOMPnet in the engine (thesis Ch. 6): MPI -> camera-motion cancel -> 3D flow (ONNX) -> forward splat.

Per rendered frame n (``DecompPredictor.prepare``), from frames n-k and n:

1. both frames are block-downsampled to the network's working width (``geometry.downsample_frame``, the
   function the training data went through);
2. the *motion gate*: frame n-k (a one-plane MPI) is forward-warped into frame n's view
   (``geometry.forward_warp_mpi``), cancelling camera motion; tiles where colour or depth still changed
   (among pixels frame n-k saw, ``seen_before``) mark object motion; the network runs only on boxes around
   them (``motion_boxes``), and not at all when no tile moved (measured costs, static scene included:
   ``docs/flow3d.md``);
3. for the boxes, both frames become one-hot MPIs on frame n's planes and the MPI of n-k is warped into
   frame n's view (into the boxes' bounding box only): the network's input;
4. OpenCV DIS gives the 2D flow the network refines (``initial_flow``; by default at full resolution on
   the whole frame, ``dis_context``, and kept outside the boxes too, ``dis_outside``: DIS on a small box
   has too few pyramid levels for fast motion), and per box the ONNX flow network (``FlowNetwork``,
   exported by ``export.flow`` from ``models.flow.network.Flow3D``) estimates the flow u(n -> n-k) per MPI
   point, upsampled to full resolution per plane (``upsample_flow``).

Per predicted frame n + k' (``render``): u(n -> n+k') = -(k'/k) u(n -> n-k) (thesis Eq. 6.13, k'/k from
the frame times); frame n at full resolution (by default one plane whose pixels carry their own plane's
flow, ``render_planes``) moves by it and by the camera (forward bilinear splat,
``geometry.forward_warp_mpi``), is composited, and disocclusions are filled the way ``reproject`` fills
them (``engine.geometry.holefill``), or with ``fill=infill`` by the infilling network (``engine.predict.decomp.infill``, thesis
Sec. 6.3.4); with ``motion=truth`` the true object motion replaces the predicted one (the bound of thesis
Table 6.3).

Conventions are ``engine/geometry/ops.py``'s: OpenCV cameras, pixel centres at +0.5, planar depth (+inf sky),
MPI arrays (C, Z, H, W) with planes near (0) to far (Z - 1). No torch: the network runs in onnxruntime.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import numpy as np

from engine import geometry
from engine.core.config import option
from engine.core.errors import InputError, InterleaveError
from engine.core.frames import Frame, SceneObject
from engine.geometry import Mpi
from engine.weights import FLOW3D
from engine.geometry.holefill import fill_holes
from engine.predict.predictors import (PreparedState, Predictor, Target, dis_block, dis_calc, dis_estimator,
                               extrapolation_factor, luma8, true_object_flow)

__all__ = ["DecompConfig", "FlowNetwork", "DecompPredictor", "DEFAULT_MODEL", "motion_residual", "motion_boxes",
           "seen_before", "upsample_flow", "merge_planes", "encode_color", "config_from_options", "initial_flow"]

#: The committed 3D flow network (``configs/flow3d.json``; see ``engine/weights/README.md``).
DEFAULT_MODEL = FLOW3D
#: ONNX metadata key holding the network's ``Flow3DConfig`` and training facts (JSON), set by ``export.flow``.
METADATA_KEY = "interleave.flow3d"


@dataclass(frozen=True)
class DecompConfig:
    """Options of the ``decomp`` predictor; every ``skip`` can be switched off to measure what it saves."""

    model: str = option("", "ONNX flow network (default: the committed engine/weights/flow3d.onnx)")
    flow_width: int = option(0, "widest input in pixels the network runs at (0: the width it was trained at, "
                                "from the ONNX metadata); frames are block-downsampled by ceil(W / flow_width)")
    gate: bool = option(True, "run the network only on boxes around tiles whose camera-compensated residual "
                              "shows object motion, and not at all when none does")
    color_threshold: float = option(0.05, "residual of the encoded colour (0..1, max over RGB) that marks a "
                                         "pixel as changed")
    depth_threshold: float = option(0.02, "relative inverse-depth change that marks a pixel as changed")
    erode: bool = option(True, "erode the changed-pixel mask by 3 x 3 before counting tiles (removes the "
                               "one-pixel seams that resampling leaves along depth edges of a static scene)")
    gate_unseen: bool = option(True, "the gate ignores pixels of frame n whose surface, if static, lay outside "
                                     "frame n-k's view (content entering at the frame border under camera motion: "
                                     "frame n-k holds nothing to compare it with, and no flow can be estimated there)")
    tile: int = option(8, "tile size of the motion gate, in network pixels")
    min_tiles: int = option(3, "smallest group of connected moving tiles that counts as motion (smaller groups: "
                                "resampling noise along depth edges of a static view)")
    tile_fraction: float = option(0.05, "fraction of a tile's pixels that must change for it to count as moving")
    margin: int = option(24, "network pixels of context kept around moving tiles (covers the search range)")
    full_frame_fraction: float = option(0.5, "run on the whole frame when the boxes cover more than this "
                                             "fraction of it")
    min_plane_fraction: float = option(0.0, "before splatting, merge MPI planes holding less than this fraction "
                                            "of the pixels into the nearest kept plane (0: drop only empty "
                                            "planes; -1: keep every plane)")
    depth_flow: bool = option(False, "use the network's depth component dz (Eq. 6.6); off (default): each plane "
                                     "moves by its (du, dv) only (the committed network's plane offsets cost "
                                     "0.9 dB of whole-frame PSNR on held-out scenes, docs/flow3d.md)")
    render_planes: int = option(1, "planes of the MPI that is splatted: 0 = the network's (the thesis); 1 = one "
                                   "plane whose pixels carry their own plane's 3D flow (no cracks where a surface "
                                   "crosses from one plane to the next, half the splat cost)")
    splat: str = option("numpy", "forward splat of the predicted frame: 'numpy' (engine.geometry) or 'gl' (the "
                                 "moderngl compute-shader version, engine.geometry.glsplat; same results, faster only "
                                 "with a GPU driver: on llvmpipe with 2 cores it is about 2x slower)")
    threads: int = option(2, "onnxruntime intra-op threads")
    dis_preset: str = option("medium", "OpenCV DIS preset of the initial flow, for networks that refine one")
    full_resolution_init: bool = option(True, "compute the initial flow at full resolution (frame n-k warped "
                                               "into frame n's view at full size over the dis_context region "
                                               "and DIS on it, as flow2d does) and add the network's upsampled "
                                               "residual to it; off: at the working width, per box")
    dis_context: int = option(-1, "the full-resolution DIS of a gate box runs on a region grown around the box "
                                  "to at least this many pixels a side (clipped to the frame; overlapping "
                                  "regions merged): DIS's pyramid, and so the largest motion it finds, grows "
                                  "with the image it is given; 0: the box alone; -1: the whole frame")
    dis_resolution: str = option("full", "resolution of the initial flow's warp and DIS: 'full' (frame n-k "
                                         "warped at full resolution, DIS on it) or 'finest' (frame n-k "
                                         "block-downsampled to the preset's finest DIS scale, half size for "
                                         "'medium', warped there, reusing the gate's warp when it has that "
                                         "size, and DIS run there with finest scale 0: DIS itself computes "
                                         "nothing finer; 34 ms less at 960x540, k = 2, but the half-size "
                                         "splat blurs the target DIS matches: 0.12 dB less over the whole "
                                         "frame, docs/flow3d.md)")
    dis_holes: str = option("fill", "what the full-resolution initial flow's DIS sees where the camera-compensated "
                                    "frame n-k left a hole: 'fill' (the background-biased row fill of reproject, "
                                    "as flow2d; the DIS flow then equals flow2d's) or 'own' (frame n's own colour, "
                                    "as in the network's training data; 0.4 dB worse over moving pixels at k = 4, "
                                    "docs/flow3d.md)")
    dis_outside: bool = option(True, "keep the DIS flow of the regions outside the gate's boxes too (as "
                                      "flow2d does) instead of zero flow there; the network refines the boxes")
    refine_check: bool = option(True, "keep the network's refinement of the full-resolution initial flow only "
                                       "at pixels where it explains frame n better than the initial flow alone "
                                       "(photometric error of the camera-compensated frame n-k, 9 x 9 mean)")
    refine_margin: float = option(1.0, "the refinement check keeps the refined flow only where its photometric "
                                       "error is lower than the initial flow's by more than this many 8-bit "
                                       "levels (ties and near-ties keep DIS; chosen on training scenes)")
    refine: bool = option(True, "run the flow network on the initial flow; off: the initial flow (DIS) alone in "
                                "the gate's boxes, without the network: what the network adds, and its cost")
    fill: str = option("simple", "disocclusion fill: 'simple' (the background-biased row fill of reproject, "
                                 "engine.geometry.holefill) or 'infill' (the infilling network, engine.predict.decomp.infill: copies "
                                 "known pixels of the same MPI plane along predicted vectors; measured on "
                                 "held-out scenes: the same PSNR for about 240 ms more per frame, docs/infill.md, "
                                 "hence not the default)")
    infill_iterations: int = option(3, "passes g of the infilling network (each fills what the last left open)")
    infill_model: str = option("", "ONNX infilling network (default: the committed engine/weights/infill.onnx)")
    infill_margin: int = option(48, "hole gate of the infilling network: it runs on boxes around the holes with "
                                    "this many of its pixels as context (48 = its receptive radius: the same "
                                    "vectors as the whole frame); -1 = on the whole frame")
    motion: str = option("predicted", "object motion of the predicted frame: 'predicted' (the flow network, "
                                      "extrapolated) or 'truth' (the sequence's true object motion, as the "
                                      "oracle: the bound of thesis Table 6.3; needs object ids and transforms)")

    def __post_init__(self) -> None:
        checks = [
            (self.flow_width >= 0, "flow_width must be >= 0"),
            (self.color_threshold > 0 and self.depth_threshold > 0, "thresholds must be > 0"),
            (self.tile >= 1 and self.margin >= 0 and self.threads >= 1 and self.min_tiles >= 1,
             "tile, min_tiles, threads >= 1, margin >= 0"),
            (0 < self.tile_fraction <= 1 and 0 < self.full_frame_fraction <= 1, "fractions must be in (0, 1]"),
            (self.splat in ("numpy", "gl"), f"splat must be 'numpy' or 'gl', got {self.splat!r}"),
            (self.render_planes in (0, 1), "render_planes must be 0 (the network's planes) or 1"),
            (self.min_plane_fraction == -1 or 0 <= self.min_plane_fraction < 1,
             "min_plane_fraction must be -1 or in [0, 1)"),
            (self.fill in ("infill", "simple"), f"fill must be 'infill' or 'simple', got {self.fill!r}"),
            (self.infill_iterations >= 1, "infill_iterations must be >= 1"),
            (self.dis_context >= -1, "dis_context must be >= 0, or -1 for the whole frame"),
            (math.isfinite(self.refine_margin) and self.refine_margin >= 0, "refine_margin must be finite and >= 0"),
            (self.infill_margin >= -1, "infill_margin must be >= 0, or -1 for the whole frame"),
            (self.dis_holes in ("fill", "own"), f"dis_holes must be 'fill' or 'own', got {self.dis_holes!r}"),
            (self.dis_resolution in ("finest", "full"),
             f"dis_resolution must be 'finest' or 'full', got {self.dis_resolution!r}"),
            (self.motion in ("predicted", "truth"), f"motion must be 'predicted' or 'truth', got {self.motion!r}"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="DecompConfig")


def encode_color(color: np.ndarray) -> np.ndarray:
    """numpy mirror of ``models.flow.network.encode_color``: ``sqrt(c / (1 + c) + 1e-4) - 0.01``, c clipped at 0."""
    c = np.maximum(color, np.float32(0.0))
    return np.sqrt(c / (np.float32(1.0) + c) + np.float32(1.0e-4)) - np.float32(0.01)


def initial_flow(color_n: np.ndarray, warped_color: np.ndarray, covered: np.ndarray,
                 preset: str = "medium") -> np.ndarray:
    """2D flow u(n -> n-k) the network refines: OpenCV DIS from frame n to the camera-compensated frame n-k.

    Both images are display-encoded 8-bit luma; pixels the warp left uncovered (disocclusions) take frame
    n's own colour, so they read as "no motion" instead of as edges. Training (``models.flow.train``) and
    the engine call this same function.

    Args:
        color_n: (H, W, 3) linear RGB of frame n; warped_color: (H, W, 3) composite of m^w_{n-k};
        covered: (H, W) bool, where the warp landed; preset: DIS preset 'ultrafast', 'fast' or 'medium'.

    Returns:
        (H, W, 2) float32 pixels.
    """
    return dis_flow(luma8(color_n), dis_target(color_n, warped_color, covered), preset)


def dis_flow(luma_n: np.ndarray, target: np.ndarray, preset: str = "medium",
             finest_scale: Optional[int] = None) -> np.ndarray:
    """``initial_flow`` on lumas already made: ``luma8`` of frame n and its ``dis_target``, (H, W, 2) float32
    (``finest_scale``: see ``dis_estimator``)."""
    return np.ascontiguousarray(dis_calc(dis_estimator(preset, finest_scale), luma_n, target), dtype=np.float32)


def upsample_blocks(image: np.ndarray, block: int, size: tuple[int, int]) -> np.ndarray:
    """Bilinear upsampling of an image (h, w[, C]) whose pixel ``i`` spans full pixels ``[b i, b (i + 1))``
    (``geometry.downsample_frame``'s grid) to full size (H, W) >= (b h, b w); rows and columns past the last
    whole block repeat the edge. Values are not scaled."""
    import cv2

    h, w = image.shape[:2]
    up = cv2.resize(image, (w * block, h * block), interpolation=cv2.INTER_LINEAR) if block > 1 else image
    pad = [(0, size[0] - h * block), (0, size[1] - w * block)] + [(0, 0)] * (image.ndim - 2)
    return np.pad(up, pad, mode="edge") if pad[0][1] or pad[1][1] else np.ascontiguousarray(up)


def dis_target(color_n: np.ndarray, warped_color: np.ndarray, covered: np.ndarray,
               warped_depth: Optional[np.ndarray] = None) -> np.ndarray:
    """(H, W) uint8 luma of the camera-compensated frame n-k that ``initial_flow`` matches frame n against:
    the warp's colour where it landed; elsewhere frame n's own colour, or, given the warp's depth (H, W),
    the background-biased row fill of ``reproject`` (``engine.geometry.holefill``, frame n's colour where a hole's row
    and column hold no known pixel), which is what ``flow2d`` matches against."""
    if warped_depth is None:
        return luma8(np.where(covered[..., None], warped_color, color_n))
    return luma8(fill_holes(warped_color, warped_depth, ~covered, color_n)[0])


def warp_error(luma_n: np.ndarray, target: np.ndarray, offset: tuple[int, int], flow: np.ndarray,
               window: int = 9) -> np.ndarray:
    """(h, w) photometric error of a flow u(n -> n-k): |luma of frame n - ``target`` sampled at x + u| (8-bit
    levels, bilinear; a sample outside ``target`` costs 255), averaged over ``window`` x ``window`` pixels.

    ``luma_n`` (h, w) is a part of frame n whose top-left pixel is pixel ``offset`` (y, x) of ``target``
    (``dis_target`` of a larger region); ``flow`` (h, w, 2) pixels.
    """
    import cv2

    h, w = luma_n.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32) + np.float32(offset[1]),
                         np.arange(h, dtype=np.float32) + np.float32(offset[0]))
    sampled = cv2.remap(target.astype(np.float32), gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    error = np.where(sampled < 0, np.float32(255.0), np.abs(luma_n.astype(np.float32) - sampled))
    return cv2.blur(error, (window, window), borderType=cv2.BORDER_REFLECT)


def full_box(box: tuple[int, int, int, int], factor: int, low_size: tuple[int, int],
             size: tuple[int, int]) -> tuple[int, int, int, int]:
    """Full-resolution (y0, y1, x0, x1) of a working-resolution box; a box at the last block row or column
    also takes the full-resolution rows or columns past the last whole block."""
    y0, y1, x0, x1 = box
    return (y0 * factor, size[0] if y1 == low_size[0] else y1 * factor,
            x0 * factor, size[1] if x1 == low_size[1] else x1 * factor)


def context_region(box: tuple[int, int, int, int], size: int, frame: tuple[int, int]) -> tuple[int, int, int, int]:
    """A box (y0, y1, x0, x1) grown to at least ``size`` pixels a side within a frame (H, W) (``context_span``)."""
    return context_span(box[0], box[1], size, frame[0]) + context_span(box[2], box[3], size, frame[1])


def merge_regions(regions: list) -> list:
    """Regions (y0, y1, x0, x1) with every overlapping pair replaced by its bounding box, until none overlap.

    >>> merge_regions([(0, 10, 0, 10), (5, 20, 5, 20), (30, 40, 30, 40)])
    [(0, 20, 0, 20), (30, 40, 30, 40)]
    """
    out = list(regions)
    merged = True
    while merged:
        merged = False
        for i in range(len(out)):
            for j in range(i + 1, len(out)):
                a, b = out[i], out[j]
                if a[0] < b[1] and b[0] < a[1] and a[2] < b[3] and b[2] < a[3]:
                    out[i] = (min(a[0], b[0]), max(a[1], b[1]), min(a[2], b[2]), max(a[3], b[3]))
                    del out[j]
                    merged = True
                    break
            if merged:
                break
    return out


def context_span(start: int, stop: int, size: int, limit: int) -> tuple[int, int]:
    """[start, stop) grown on both sides to at least ``size`` (clipped to [0, limit), shifted inward at an edge;
    ``size`` -1: the whole [0, limit)).

    >>> context_span(200, 300, 300, 1000), context_span(0, 50, 300, 1000), context_span(900, 990, 300, 1000)
    ((100, 400), (0, 300), (700, 1000))
    """
    if size < 0 or size > limit:
        return 0, limit
    if stop - start >= size:
        return start, stop
    grow = size - (stop - start)
    start = max(0, min(start - grow // 2, limit - size))
    return start, min(limit, start + size)


def open_network(path: Path, threads: int, metadata_key: str, field: str, missing: str):
    """(onnxruntime CPU session, the JSON metadata under ``metadata_key``) of an exported engine network;
    InputError naming the file when it is missing (``missing``) or lacks the metadata."""
    import onnxruntime as ort

    if not path.is_file():
        raise InputError(missing, file=path, field=field)
    options = ort.SessionOptions()
    options.intra_op_num_threads = int(threads)
    options.inter_op_num_threads = 1
    options.log_severity_level = 3  # errors only (exported graphs trigger harmless folding warnings)
    if os.environ.get("INTERLEAVE_ORT_SPIN", "0") != "1":  # idle pool threads sleep, as the kernels' do
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    session = ort.InferenceSession(str(path), options, providers=["CPUExecutionProvider"])
    meta = session.get_modelmeta().custom_metadata_map
    if metadata_key not in meta:
        raise InputError(f"has no '{metadata_key}' metadata: export it with this project's export command",
                         file=path, field=field)
    return session, json.loads(meta[metadata_key])


class FlowNetwork:
    """The exported flow network in onnxruntime: ``(m_n, m^w_{n-k}) -> u(n -> n-k)`` (3, Z, H, W).

    Reads the network's config from the ONNX metadata (``METADATA_KEY``): number of planes, pyramid stride,
    mode ('3d' or the '2d' ablation), the working width the training frames had and whether the graph
    computes dz (``depth_flow``; without it dz comes out 0).
    """

    def __init__(self, path: str | Path, threads: int = 2) -> None:
        path = Path(path)
        self.session, info = open_network(path, threads, METADATA_KEY, "model", "flow network not found (train "
                                          "and export one: interleave train flow / interleave export flow)")
        self.path = path
        self.config: dict = info["model"]
        self.num_planes = int(self.config["num_planes"])
        self.stride = 2 ** len(self.config["encoder_channels"])
        self.working_width = int(info.get("working_width", 480))
        self.mode = str(self.config["mode"])
        self.needs_initial_flow = bool(self.config.get("initial_flow", False))
        #: whether the graph computes dz (exports with ``--no-depth-flow`` return dz = 0 uncomputed)
        self.depth_flow = bool(info.get("depth_flow", True))

    def __call__(self, mpi_n: Mpi, mpi_prev_warped: Mpi, init: Optional[np.ndarray] = None) -> np.ndarray:
        """Flow (3, Z, H, W) float32 = (du, dv) pixels, dz scene units; 0 where ``mpi_n.alpha`` is 0.

        ``init`` (H, W, 2): the 2D flow to refine (``initial_flow``), required by networks trained with one.
        """
        z = mpi_n.alpha.shape[0]
        if z != self.num_planes or mpi_prev_warped.alpha.shape != mpi_n.alpha.shape:
            raise InputError(f"MPIs of shape {mpi_n.alpha.shape} / {mpi_prev_warped.alpha.shape}: the network "
                             f"takes two MPIs of {self.num_planes} planes", field="mpi")
        feeds = {
            "color_n": mpi_n.color[None], "depth_n": mpi_n.depth[None, None], "alpha_n": mpi_n.alpha[None, None],
            "color_prev": mpi_prev_warped.color[None], "depth_prev": mpi_prev_warped.depth[None, None],
            "alpha_prev": mpi_prev_warped.alpha[None, None],
            "plane_depths": np.asarray(mpi_n.plane_depths, dtype=np.float32)[None],
        }
        if self.needs_initial_flow:
            if init is None or init.shape != mpi_n.alpha.shape[1:] + (2,):
                raise InputError(f"this network refines an initial flow of shape {mpi_n.alpha.shape[1:] + (2,)}",
                                 field="init")
            feeds["initial_flow"] = np.moveaxis(init, -1, 0)[None]
        # the exported graph takes sizes that are multiples of the pyramid stride: pad with alpha = 0 (ignored
        # by the partial convolutions, as Flow3D pads internally) and crop the flow back
        h, w = mpi_n.alpha.shape[1:]
        ph, pw = -h % self.stride, -w % self.stride
        if ph or pw:
            feeds = {k: v if k == "plane_depths" else np.pad(v, [(0, 0)] * (v.ndim - 2) + [(0, ph), (0, pw)])
                     for k, v in feeds.items()}
        feeds = {k: np.ascontiguousarray(v, dtype=np.float32) for k, v in feeds.items()}
        return self.session.run(None, feeds)[0][0][..., :h, :w]


def _crop(mpi: Mpi, box: tuple[int, int, int, int]) -> Mpi:
    y0, y1, x0, x1 = box
    return Mpi(mpi.color[..., y0:y1, x0:x1], mpi.depth[..., y0:y1, x0:x1], mpi.alpha[..., y0:y1, x0:x1],
               mpi.plane_depths)


def motion_residual(mpi_n: Mpi, mpi_prev_warped: Mpi, color_threshold: float, depth_threshold: float,
                    erode: bool = True) -> np.ndarray:
    """(H, W) bool: pixels where the camera-compensated frame n-k differs from frame n (object motion).

    Compares the composites of both MPIs where the warped n-k covers the pixel (disocclusions are not
    evidence of motion): encoded colour (max over RGB) above ``color_threshold`` or inverse depth changed by
    more than ``depth_threshold`` relative to the MPI's middle depth. With ``erode`` a 3 x 3 erosion then
    removes the one-pixel seams that resampling leaves along depth edges of a static scene.
    """
    import cv2

    color_n, depth_n, _ = geometry.composite(mpi_n)
    color_w, depth_w, acc_w = geometry.composite(mpi_prev_warped)
    planes = np.asarray(mpi_n.plane_depths, dtype=np.float64)
    finite = planes[np.isfinite(planes)]
    ref = 2.0 / (1.0 / finite[0] + 1.0 / finite[-1]) if finite.size else 1.0
    inv_n = np.where(np.isfinite(depth_n), 1.0 / np.maximum(depth_n, 1e-30), 0.0)
    inv_w = np.where(np.isfinite(depth_w), 1.0 / np.maximum(depth_w, 1e-30), 0.0)
    diff = np.abs(encode_color(color_n) - encode_color(color_w))
    d_color = np.maximum(np.maximum(diff[..., 0], diff[..., 1]), diff[..., 2])  # max over RGB (axis=-1 is slow)
    d_depth = np.abs(inv_n - inv_w) * ref
    changed = (acc_w > 0.5) & ((d_color > color_threshold) | (d_depth > depth_threshold))
    if not erode:
        return changed
    return cv2.erode(changed.astype(np.uint8), np.ones((3, 3), np.uint8)).astype(bool)


def seen_before(depth_n: np.ndarray, K_n: np.ndarray, T_n: np.ndarray, K_prev: np.ndarray, T_prev: np.ndarray,
                size_prev: tuple[int, int]) -> np.ndarray:
    """(H, W) bool: pixels of frame n whose surface, were it static, lay inside frame n-k's view (reprojected
    into camera n-k in front of it and inside its (h, w) = ``size_prev`` image; sky by the rotation alone).

    Elsewhere frame n-k never saw the surface, so the camera-compensated frame n-k (whatever the warp put
    there: a farther surface, or nothing) says nothing about object motion. ``depth_n`` (H, W) planar depth,
    +inf sky; cameras as ``geometry.reproject`` takes them (pixel centres at +0.5: inside is [0, w) x [0, h)).
    """
    uv, _, valid = geometry.reproject(depth_n, K_n, T_n, K_prev, T_prev)
    h, w = size_prev
    return valid & (uv[..., 0] >= 0) & (uv[..., 0] < w) & (uv[..., 1] >= 0) & (uv[..., 1] < h)


def motion_boxes(changed: np.ndarray, tile: int, tile_fraction: float, margin: int, stride: int,
                 full_frame_fraction: float, min_tiles: int = 1) -> list[tuple[int, int, int, int]]:
    """Boxes (y0, y1, x0, x1) the network must see: moving tiles, grown by ``margin``, snapped to ``stride``.

    A tile moves when more than ``tile_fraction`` of its pixels changed; groups of fewer than ``min_tiles``
    connected moving tiles are dropped. Connected groups of moving tiles
    (after growing by the margin) give one box each; when the boxes cover more than ``full_frame_fraction``
    of the frame the whole frame is returned instead (one network call is then cheaper than many).
    Returns [] when nothing moved.
    """
    import cv2

    h, w = changed.shape
    th, tw = math.ceil(h / tile), math.ceil(w / tile)
    padded = np.zeros((th * tile, tw * tile), dtype=np.float32)
    padded[:h, :w] = changed
    moving = padded.reshape(th, tile, tw, tile).mean(axis=(1, 3)) > tile_fraction
    if min_tiles > 1 and moving.any():  # drop isolated groups of moving tiles (resampling noise, not objects)
        count, labels, stats, _ = cv2.connectedComponentsWithStats(moving.astype(np.uint8), connectivity=8)
        moving = (stats[:, cv2.CC_STAT_AREA] >= min_tiles)[labels] & moving
    if not moving.any():
        return []
    grow = math.ceil(margin / tile)
    grown = cv2.dilate(moving.astype(np.uint8), np.ones((2 * grow + 1, 2 * grow + 1), np.uint8))
    count, _, stats, _ = cv2.connectedComponentsWithStats(grown, connectivity=8)
    boxes = []
    for label in range(1, count):
        x, y, bw, bh = (int(v) for v in stats[label, :4])
        y0, x0 = (y * tile) // stride * stride, (x * tile) // stride * stride
        y1 = min(h, -(-((y + bh) * tile) // stride) * stride)
        x1 = min(w, -(-((x + bw) * tile) // stride) * stride)
        boxes.append((y0, y1, x0, x1))
    if sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) > full_frame_fraction * h * w:
        return [(0, h, 0, w)]
    return boxes


def upsample_flow(flow: np.ndarray, alpha: np.ndarray, factor: int, full_alpha: np.ndarray) -> np.ndarray:
    """``upsample_flow_reference`` with the full-resolution sampling compiled (``engine.geometry.kernels.upsample_planes``,
    held to the reference to 1e-5 by the tests): same arguments, same (3, Z, H, W) result."""
    from engine.geometry import kernels
    num_z = flow.shape[1]
    packed = np.stack([_spread_plane(flow[:, z], alpha[z]) for z in range(num_z)])
    out = np.empty((3,) + full_alpha.shape, dtype=np.float32)
    kernels.upsample_planes(packed, int(factor), np.ascontiguousarray(full_alpha, dtype=np.float32),
                            np.array([factor, factor, 1.0], np.float32), out)
    return out


def _spread_plane(flow: np.ndarray, alpha: np.ndarray) -> np.ndarray:
    """(h, w, 4) alpha-weighted (du, dv, dz) and alpha of one plane (``flow`` (3, h, w), ``alpha`` (h, w)),
    spread two pixels into empty neighbours by normalised 3 x 3 sums; the four channels side by side, so
    every filter runs once on all of them. Both ``upsample_flow`` and its reference start from this."""
    import cv2

    a = alpha.astype(np.float32)
    packed = np.ascontiguousarray(np.concatenate([np.moveaxis(flow * a, 0, -1), a[..., None]], axis=-1),
                                  dtype=np.float32)
    for _ in range(2):
        sums = cv2.boxFilter(packed, -1, (3, 3), normalize=False, borderType=cv2.BORDER_CONSTANT)
        grow = (packed[..., 3] <= 0) & (sums[..., 3] > 0)
        packed[grow, :3] = sums[grow, :3] / sums[grow, 3:]
        packed[grow, 3] = 1.0
    return packed


def upsample_flow_reference(flow: np.ndarray, alpha: np.ndarray, factor: int, full_alpha: np.ndarray) -> np.ndarray:
    """Per-plane, alpha-normalised bilinear upsampling of a network-resolution flow to the full MPI.

    ``flow`` (3, Z, h, w) on the network grid (pixel ``i`` covers full pixels ``[f i, f (i + 1))``), alpha
    (Z, h, w); ``full_alpha`` (Z, H, W) is the full-resolution MPI on the same planes. (du, dv) are scaled by
    ``factor``, dz is kept. Each plane's flow is first spread two pixels into its empty neighbours
    (normalised 3 x 3 means), so full-resolution points whose block went to another plane still find a
    value; points with no value within reach get 0. Returns (3, Z, H, W), 0 where ``full_alpha`` is 0.
    """
    num_z = flow.shape[1]
    big_h, big_w = full_alpha.shape[1:]
    out = np.zeros((3, num_z) + full_alpha.shape[1:], dtype=np.float32)
    scale = np.array([factor, factor, 1.0], np.float32)
    for z in range(num_z):
        if not full_alpha[z].any():
            continue
        packed = _spread_plane(flow[:, z], alpha[z])
        up = upsample_blocks(packed, factor, (big_h, big_w))  # past the last whole block: the edge repeats
        where = np.flatnonzero(full_alpha[z])  # only this plane's points (a one-hot MPI: each pixel once)
        picked = up.reshape(-1, 4)[where]
        ok = picked[:, 3] > 1e-6
        values = np.where(ok[:, None], picked[:, :3] / np.where(ok, picked[:, 3], 1.0)[:, None], 0.0) * scale
        out.reshape(3, num_z, -1)[:, z, where] = values.T
    return out


def merge_planes(mpi: Mpi, flow: Optional[np.ndarray], min_fraction: float) -> tuple[Mpi, Optional[np.ndarray]]:
    """Fewer planes where the depth histogram is simple: planes of a one-hot MPI holding at most
    ``min_fraction`` of the pixels (0: empty planes) go into the nearest kept plane (in plane index).

    One-hot planes hold disjoint pixels, so merging adds them (colour, depth, alpha and the per-point flow
    travel along); the kept planes keep their depths. At least one plane is kept. The warp then re-bins
    points among fewer planes, so points of merged planes are ordered by the soft z-buffer instead of by plane.
    """
    num_z = mpi.alpha.shape[0]
    share = mpi.alpha.reshape(num_z, -1).mean(axis=1)
    keep = share > min_fraction
    if keep.all() or not keep.any():
        return mpi, flow
    kept = np.flatnonzero(keep)
    nearest = np.abs(np.arange(num_z)[:, None] - kept[None, :]).argmin(axis=1)  # position in ``kept``

    def merge(values: np.ndarray, axis: int) -> np.ndarray:
        out = np.take(values, kept, axis=axis).copy()
        for z in np.flatnonzero(~keep & (share > 0)):
            index = [slice(None)] * values.ndim
            index[axis] = int(nearest[z])
            out[tuple(index)] += np.take(values, z, axis=axis)
        return out

    merged = Mpi(merge(mpi.color, 1), merge(mpi.depth, 0), merge(mpi.alpha, 0), mpi.plane_depths[kept])
    return merged, None if flow is None else merge(flow, 1)


def config_from_options(text: str, **fixed) -> DecompConfig:
    """A ``DecompConfig`` from ``"key=value,key=value"`` (the bracket options of ``decomp[...]``), typed by
    the fields; ``fixed`` are set first and may be overridden. Unknown keys and bad values raise InputError."""
    import dataclasses
    import typing

    hints = typing.get_type_hints(DecompConfig)
    values = dict(fixed)
    for part in filter(None, (p.strip() for p in text.split(","))):
        key, sep, raw = part.partition("=")
        key = key.strip()
        if not sep or key not in hints:
            raise InputError(f"option '{part}': expected key=value with key one of "
                             f"{', '.join(f.name for f in dataclasses.fields(DecompConfig))}", field="decomp")
        kind = hints[key]
        try:
            if kind is bool:
                if raw.strip().lower() not in ("0", "1", "true", "false"):
                    raise ValueError(raw)
                values[key] = raw.strip().lower() in ("1", "true")
            else:
                values[key] = kind(raw.strip())
        except ValueError as exc:
            raise InputError(f"option '{part}': not a valid {kind.__name__}", field="decomp") from exc
    return DecompConfig(**values)


def _downsampled(frame: Frame, factor: int):
    return geometry.downsample_frame(frame.color, frame.depth, frame.camera.intrinsics, factor)


class DecompPredictor(Predictor):
    """The ``decomp`` method: DeCOMPnet's 3D object motion on MPIs, extrapolated and splatted (see module doc).

    ``state.data`` after ``prepare``: ``boxes`` (network-resolution boxes the network ran on), ``factor``
    (downsampling), ``network_fraction`` (share of the frame the network saw), ``mpi`` (full-resolution MPI
    of frame n) and ``flow`` (its u(n -> n-k), (3, Z, H, W), or None when the gate found no motion).
    """

    name = "decomp"
    history_needed = 2

    def __init__(self, config: DecompConfig = DecompConfig(), network: Optional[FlowNetwork] = None,
                 objects: Sequence[SceneObject] = (), infill: Optional["InfillNetwork"] = None) -> None:
        if not isinstance(config, DecompConfig):
            raise InputError(f"must be a DecompConfig, got {type(config).__name__}", field="config")
        self.config = config
        self.network = network if network is not None else FlowNetwork(config.model or DEFAULT_MODEL, config.threads)
        self.objects = {o.id: o for o in objects}
        if config.depth_flow and not self.network.depth_flow:
            raise InputError(f"depth_flow=1 needs the network's dz, but {self.network.path} was exported without it "
                             "(--no-depth-flow): export one with dz (interleave export flow CHECKPOINT OUT.onnx) "
                             "and pass model=OUT.onnx", field="depth_flow")
        if not config.refine and not self.network.needs_initial_flow:
            raise InputError("refine=0 keeps the initial flow alone, but this flow network takes none",
                             field="refine")
        if config.motion == "truth" and not self.objects:
            raise InputError("motion=truth needs the sequence's moving objects (object ids and transforms)",
                             field="motion")
        self.infill = None
        if config.fill == "infill":
            from engine.predict.decomp.infill import DEFAULT_INFILL_MODEL, InfillNetwork

            self.infill = infill if infill is not None else InfillNetwork(config.infill_model or DEFAULT_INFILL_MODEL,
                                                                           config.threads)

    def _prepare(self, state: PreparedState, timer) -> None:
        cfg, net = self.config, self.network
        older, newest = state.history[-2], state.history[-1]
        num_z = net.num_planes
        if cfg.motion == "truth":  # the bound: no motion estimation, the true motion is applied per target
            full = timer("mpi", geometry.build_mpi, newest.color, newest.depth, 1)
            state.data.update(boxes=[], factor=1, mpi=full, flow=None, network_fraction=0.0,
                              plane_depths=geometry.plane_depths(newest.depth, num_z))
            return
        factor = geometry.downsample_factor(newest.depth.shape[1], cfg.flow_width or net.working_width)
        factor = min(factor, *newest.depth.shape)
        low_n = timer("downsample", _downsampled, newest, factor)
        low_p = timer("downsample", _downsampled, older, factor)
        t_p, t_n = older.camera.world_to_camera, newest.camera.world_to_camera
        h, w = low_n[1].shape
        g_w = None
        if cfg.gate:  # one-plane MPIs suffice to see the residual: the network's planes cost only where it runs
            g_n = timer("gate", geometry.build_mpi, low_n[0], low_n[1], 1)
            g_p = timer("gate", geometry.build_mpi, low_p[0], low_p[1], 1)
            g_w, _ = timer("gate", geometry.forward_warp_mpi, g_p, low_p[2], t_p, low_n[2], t_n)
            changed = timer("gate", motion_residual, g_n, g_w, cfg.color_threshold, cfg.depth_threshold,
                            cfg.erode)
            if cfg.gate_unseen and changed.any():
                changed &= timer("gate", seen_before, low_n[1], low_n[2], t_n, low_p[2], t_p, low_p[1].shape)
            boxes = motion_boxes(changed, cfg.tile, cfg.tile_fraction, cfg.margin, net.stride,
                                 cfg.full_frame_fraction, cfg.min_tiles)
        else:
            boxes = [(0, h, 0, w)]
        planes = geometry.plane_depths(low_n[1], num_z)  # the network's planes: frame n's, at low resolution
        m_n = warped = None
        if boxes and (cfg.refine or not cfg.full_resolution_init):  # the network's input, or the initial flow's
            m_n = timer("mpi", geometry.build_mpi, low_n[0], low_n[1], num_z, planes)
            m_p = timer("mpi", geometry.build_mpi, low_p[0], low_p[1], num_z)
            # m_{n-k} on frame n's planes, warped into the bounding box of the boxes only (its corner: origin)
            by0, bx0 = min(b[0] for b in boxes), min(b[2] for b in boxes)
            by1, bx1 = max(b[1] for b in boxes), max(b[3] for b in boxes)
            k_box = np.array(low_n[2], dtype=np.float64)
            k_box[0, 2] -= bx0
            k_box[1, 2] -= by0
            warped, _ = timer("camera_warp", geometry.forward_warp_mpi, m_p._replace(plane_depths=planes),
                              low_p[2], t_p, k_box, t_n, out_size=(by1 - by0, bx1 - bx0))
            warped = (warped, (by0, bx0))
        flow = full = None
        # frame n at full resolution on the network's planes: the whole MPI only to splat it (render_planes=0);
        # else each box's one-hot alpha comes from the plane-index map and the flow is kept per pixel
        planes_full = None
        if cfg.render_planes == 0:
            full = timer("mpi", geometry.build_mpi, newest.color, newest.depth, num_z, planes)
            planes_full = full.alpha
        elif boxes:
            planes_full = timer("mpi", geometry.plane_index, newest.depth, planes)
        if boxes:
            flow = np.zeros((3, num_z if cfg.render_planes == 0 else 1) + newest.depth.shape, dtype=np.float32)
            regions = []  # (full-resolution region, its DIS flow): each box's initial flow is cut from one
            if net.needs_initial_flow and cfg.full_resolution_init:
                size = newest.depth.shape
                spans = merge_regions([context_region(full_box(b, factor, (h, w), size), cfg.dis_context, size)
                                       for b in boxes])
                if cfg.dis_resolution == "full":
                    full_mpi1 = timer("initial_flow", geometry.build_mpi, older.color, older.depth, 1)
                    regions = [(r, self._region_flow(r, full_mpi1, older, newest, timer)) for r in spans]
                else:
                    regions = self._finest_flows(spans, older, newest, factor, low_n, low_p, g_w, timer)
                if cfg.dis_outside:  # the boxes overwrite their part below
                    for (ry0, ry1, rx0, rx1), (region_flow, _, _) in regions:
                        part = np.moveaxis(region_flow, -1, 0)[:, None]
                        if planes_full.ndim == 3:  # per plane: each pixel's flow on its own plane
                            part = part * planes_full[None, :, ry0:ry1, rx0:rx1]
                        flow[:2, :, ry0:ry1, rx0:rx1] = part
            for box in boxes:  # everything below costs in proportion to the boxes' area
                self._box_flow(box, factor, (h, w), m_n, warped, low_n[0], planes_full, regions, flow, timer)
            if not np.isfinite(flow).all():
                raise InterleaveError(f"the flow network returned non-finite values for frame {newest.index}")
        if cfg.render_planes == 1:
            full = timer("mpi", geometry.build_mpi, newest.color, newest.depth, 1)
        elif cfg.min_plane_fraction >= 0:
            full, flow = timer("mpi", merge_planes, full, flow, cfg.min_plane_fraction)
        state.data.update(boxes=boxes, factor=factor, mpi=full, flow=flow, plane_depths=planes,
                          network_fraction=sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes) / float(h * w))

    def _region_flow(self, region: tuple[int, int, int, int], full_mpi1: Mpi, older: Frame, newest: Frame,
                     timer) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(h, w, 2) DIS flow u(n -> n-k) on a full-resolution region (y0, y1, x0, x1) of frame n: frame n-k's
        one-plane MPI (``full_mpi1``) forward-warped into frame n's view of the region only (intrinsics shifted
        to its corner), then DIS against its ``dis_target`` (holes per ``dis_holes``); also the two lumas DIS
        matched (``dis_target`` and frame n's), which ``refine_check`` scores flows with."""
        y0, y1, x0, x1 = region
        src, dst = older.camera, newest.camera
        k_region = np.array(dst.intrinsics, dtype=np.float64)
        k_region[0, 2] -= x0
        k_region[1, 2] -= y0
        moved, _ = timer("initial_flow", geometry.forward_warp_mpi, full_mpi1, src.intrinsics, src.world_to_camera,
                         k_region, dst.world_to_camera, out_size=(y1 - y0, x1 - x0))
        color_w, depth_w, acc = timer("initial_flow", geometry.composite, moved)
        color_n = newest.color[y0:y1, x0:x1]
        fill_depth = depth_w if self.config.dis_holes == "fill" else None
        luma_n = timer("initial_flow", luma8, color_n)
        target = timer("initial_flow", dis_target, color_n, color_w, acc > 0, fill_depth)
        return timer("initial_flow", dis_flow, luma_n, target, self.config.dis_preset), target, luma_n

    def _finest_flows(self, spans: list, older: Frame, newest: Frame, factor: int, low_n: tuple, low_p: tuple,
                      gate_warp: Optional[Mpi], timer) -> list:
        """``_region_flow`` of full-resolution regions (y0, y1, x0, x1) with frame n-k warped at the resolution
        of the DIS preset's finest scale (block size b = ``dis_block``) instead of full resolution: one-plane
        warp of the b-downsampled frame n-k into frame n's view (the gate's warp when ``factor`` = b), DIS with
        finest scale 0 on each region's blocks, its flow upsampled to full resolution (``upsample_blocks``,
        times b). Regions grow to whole blocks (the last block row / column takes the rows past it). The
        photometric check compares frame n's block luma with the target, both upsampled the same way (the
        blurred target against frame n's sharp luma cost 0.27 dB on training scenes).
        Returns [(region, (flow (h, w, 2), target (h, w) uint8, luma of frame n (h, w) uint8))]."""
        cfg = self.config
        size = newest.depth.shape
        block = max(1, min(dis_block(cfg.dis_preset), *size))
        if block == factor:
            small_n, small_p = low_n, low_p
        else:
            small_n = timer("initial_flow", _downsampled, newest, block)
            small_p = timer("initial_flow", _downsampled, older, block)
        moved = gate_warp if block == factor and gate_warp is not None else None
        if moved is None:
            mpi_p = timer("initial_flow", geometry.build_mpi, small_p[0], small_p[1], 1)
            moved, _ = timer("initial_flow", geometry.forward_warp_mpi, mpi_p, small_p[2],
                             older.camera.world_to_camera, small_n[2], newest.camera.world_to_camera)
        color_w, depth_w, acc = timer("initial_flow", geometry.composite, moved)
        hs, ws = small_n[1].shape
        out = []
        for y0, y1, x0, x1 in spans:
            sy0, sx0 = min(y0 // block, hs - 1), min(x0 // block, ws - 1)
            sy1, sx1 = max(sy0 + 1, min(hs, -(-y1 // block))), max(sx0 + 1, min(ws, -(-x1 // block)))
            region = full_box((sy0, sy1, sx0, sx1), block, (hs, ws), size)
            part = (slice(sy0, sy1), slice(sx0, sx1))
            color_n = small_n[0][part]
            fill_depth = depth_w[part] if cfg.dis_holes == "fill" else None
            target = timer("initial_flow", dis_target, color_n, color_w[part], acc[part] > 0, fill_depth)
            luma_small = timer("initial_flow", luma8, color_n)
            flow = timer("initial_flow", dis_flow, luma_small, target, cfg.dis_preset, 0)
            full_size = (region[1] - region[0], region[3] - region[2])
            flow = timer("initial_flow", upsample_blocks, flow, block, full_size)
            flow *= np.float32(block)
            target = timer("initial_flow", upsample_blocks, target, block, full_size)
            luma_n = timer("initial_flow", upsample_blocks, luma_small, block, full_size)
            out.append((region, (flow, target, luma_n)))
        return out

    def _box_flow(self, box, factor: int, low_size: tuple[int, int], m_n: Optional[Mpi],
                  warped: Optional[tuple[Mpi, tuple[int, int]]], low_color_n: np.ndarray, planes_full: np.ndarray,
                  regions: list, flow: np.ndarray, timer) -> None:
        """Flow of one gate box, written into ``flow`` at full resolution: (3, Z, H, W) per plane when
        ``planes_full`` is the full-resolution alpha (Z, H, W); (3, 1, H, W), each pixel its own plane's flow
        (the sum over a one-hot MPI's planes), when it is the plane-index map (H, W). ``low_size``: (h, w) of
        the working resolution; ``m_n`` and ``warped`` (the camera-compensated m_{n-k} on a part of the
        low-resolution frame and that part's corner (y, x)) are None when nothing runs at that resolution
        (``refine=0`` with the full-resolution initial flow)."""
        cfg, net = self.config, self.network
        y0, y1, x0, x1 = box
        warped_box = None
        if warped is not None:
            (oy, ox) = warped[1]
            warped_box = _crop(warped[0], (y0 - oy, y1 - oy, x0 - ox, x1 - ox))
        fy0, fy1, fx0, fx1 = full_box(box, factor, low_size, planes_full.shape[-2:])
        init = full_init = None
        if regions:
            (ry0, ry1, rx0, rx1), (region_flow, target, luma_region) = next(
                (r, f) for r, f in regions if r[0] <= fy0 and fy1 <= r[1] and r[2] <= fx0 and fx1 <= r[3])
            full_init = region_flow[fy0 - ry0:fy1 - ry0, fx0 - rx0:fx1 - rx0]
        elif net.needs_initial_flow:
            warped_color, _, acc = geometry.composite(warped_box)
            init = timer("initial_flow", initial_flow, low_color_n[y0:y1, x0:x1], warped_color, acc > 0,
                         cfg.dis_preset)
        if planes_full.ndim == 3:
            full_alpha = planes_full[:, fy0:fy1, fx0:fx1]
        else:
            index = planes_full[fy0:fy1, fx0:fx1]
            full_alpha = (index[None] == np.arange(net.num_planes)[:, None, None]).astype(np.float32)
        # the working-resolution flow to upsample: the network's (its residual over a full-resolution initial
        # flow) or, without the network at the working width, the initial flow itself; none without the
        # network at full resolution (the ablation keeps the initial flow alone)
        low_flow = None
        if cfg.refine:
            m_box = _crop(m_n, box)
            if full_init is not None:
                init = geometry.downsample_flow(full_init, factor)  # the box's rows past the last block drop out
            low_flow = timer("flow", net, m_box, warped_box, init)
            if not cfg.depth_flow:
                low_flow[2] = 0.0
            if full_init is not None:  # keep the network's residual only, the initial flow at full detail
                low_flow[:2] -= np.moveaxis(init, -1, 0)[:, None] * m_box.alpha[None]
        elif full_init is None:
            m_box = _crop(m_n, box)
            low_flow = np.zeros((3,) + m_box.alpha.shape, dtype=np.float32)
            low_flow[:2] = np.moveaxis(init, -1, 0)[:, None] * m_box.alpha[None]
        if low_flow is not None:
            part = timer("upsample", upsample_flow, low_flow, m_box.alpha, factor, full_alpha)
        else:
            part = np.zeros((3,) + full_alpha.shape, dtype=np.float32)
        dis_part = None
        if full_init is not None:
            dis_part = np.moveaxis(full_init, -1, 0)[:, None] * full_alpha[None]
            part[:2] += dis_part
        if planes_full.ndim == 2:  # one-hot: summing over planes gives each pixel its own plane's flow
            part = part.sum(axis=1, keepdims=True)
            dis_part = None if dis_part is None else dis_part.sum(axis=1, keepdims=True)
        if cfg.refine and dis_part is not None and cfg.refine_check:
            # each pixel keeps the refined flow only where it matches frame n-k better than the initial flow (by
            # more than refine_margin levels)
            luma_n, offset = luma_region[fy0 - ry0:fy1 - ry0, fx0 - rx0:fx1 - rx0], (fy0 - ry0, fx0 - rx0)
            refined = np.moveaxis(part[:2].sum(axis=1), 0, -1)  # (h, w, 2): each pixel's own plane's flow
            keep = (timer("refine_check", warp_error, luma_n, target, offset, refined) + np.float32(cfg.refine_margin)
                    < timer("refine_check", warp_error, luma_n, target, offset, full_init))
            part[:2] = np.where(keep, part[:2], dis_part)
        flow[:, :, fy0:fy1, fx0:fx1] = part

    def _render(self, state: PreparedState, target: Target, timer) -> tuple[np.ndarray, np.ndarray]:
        newest = state.history[-1]
        flow = state.data["flow"]
        motion = None if flow is None else flow * np.float32(-extrapolation_factor(state, target))
        if self.config.motion == "truth":
            truth = timer("motion", true_object_flow, newest, self.objects, target.index)  # (H, W, 3)
            motion = np.moveaxis(truth, -1, 0)[:, None] * state.data["mpi"].alpha[None]
        src, dst = newest.camera, target.camera
        if self.config.splat == "gl":
            from engine.geometry.glsplat import shared_splatter

            warp = shared_splatter().forward_warp_mpi
        else:
            warp = geometry.forward_warp_mpi
        warped, _ = timer("splat", warp, state.data["mpi"], src.intrinsics, src.world_to_camera,
                          dst.intrinsics, dst.world_to_camera, motion)
        color, depth, acc = timer("composite", geometry.composite, warped)
        holes = acc <= 0
        if self.infill is not None and holes.any():
            margin = None if self.config.infill_margin < 0 else self.config.infill_margin
            planes = state.data["plane_depths"]
            if len(planes) != self.infill.num_planes:  # a flow network on other planes: frame n's, at the infill's Z
                if "infill_planes" not in state.data:
                    state.data["infill_planes"] = geometry.plane_depths(newest.depth, self.infill.num_planes)
                planes = state.data["infill_planes"]
            color, depth = self.infill.fill(color, depth, holes, planes, newest.color,
                                            self.config.infill_iterations, timer, margin)
        else:
            color, _ = timer("fill", fill_holes, color, depth, holes, newest.color)
        return color, holes

    def object_flow(self, state: PreparedState) -> np.ndarray:
        """Per-pixel u(n -> n-k) of frame n's visible surface, (H, W, 2) pixels (0 where no motion was found)."""
        mpi, flow = state.data["mpi"], state.data["flow"]
        if flow is None:
            return np.zeros(mpi.alpha.shape[1:] + (2,), dtype=np.float32)
        weight = mpi.alpha * geometry.visibility(mpi)
        return np.moveaxis((flow[:2] * weight[None]).sum(axis=1), 0, -1)
