"""DeCOMPnet in the engine (thesis Ch. 6): MPI -> camera-motion cancel -> 3D flow (ONNX) -> forward splat.

Per rendered frame n (``DecompPredictor.prepare``), from frames n-k and n, one named stage after another:

1. ``downsample``: both frames are block-downsampled to the network's working width
   (``geometry.downsample_frame``, the function the training data went through);
2. ``gate``: the motion gate (``engine.predict.decomp.gate``): the network runs only on boxes around
   tiles where the camera-compensated frame n-k still differs from frame n, and not at all when none does
   (measured costs, static scene included: ``docs/flow3d.md``);
3. ``mpi`` / ``camera_warp``: for the boxes, both frames become one-hot MPIs on frame n's planes and the
   MPI of n-k is warped into frame n's view (into the boxes' bounding box only): the network's input;
4. ``initial_flow``: the 2D flow the network refines, at full resolution on the whole frame (frame n-k warped
   into frame n's view, holes filled as ``reproject`` fills them: the flow of ``flow2d``), kept outside the
   boxes too: DIS started from the correlation network (``estimator=corr``, the default:
   ``flow2d[estimator=corr]``'s flow), OpenCV DIS alone (``estimator=dis``: ``flow2d``'s), or with
   ``estimator=gl`` the GPU's flow (``flow2d[estimator=gl]``'s; on the ``gl``
   backend frame n-k's warp, the flow and its trust rules run there, only each box's block-averaged flow is
   read back for the network, and the flow stays there for the render: ``_boxes_on_gpu``);
5. ``flow`` / ``upsample`` / ``refine_check``: per box, the ONNX flow network (``FlowNetwork``) refines
   the initial flow on the MPI points (its (du, dv) only: dz is not used), the residual is upsampled to
   full resolution per plane (``upsample_flow``) and added to the initial flow, and each pixel keeps the
   refined flow only where it explains frame n better than the initial flow by more than one 8-bit level
   (``box_residual``, then ``refine_box``; with ``estimator=gl`` on the ``gl`` backend the upsampling and the
   check run on the GPU, stage ``refine``: ``GlFlowRefine``, into the flow kept there);
6. ``fallback`` (with ``fallback``): the refined flow under ``flow2d``'s trust rules, then each region whose
   motion explains frame n from n-k worse than none takes the camera-only warp
   (``engine.predict.dis.explained_motion``).

Per predicted frame n + k' (``render``): u(n -> n+k') = -(k'/k) u(n -> n-k) (thesis Eq. 6.13, k'/k from
the frame times); frame n at full resolution, one plane whose pixels carry their own plane's flow, moves by
it and by the camera (forward bilinear splat) and disocclusions are filled the way ``reproject`` fills them:
the backend's ``warp_and_fill`` (stages ``warp``, ``fill``; on ``gl`` frame n and its flow are uploaded once
in ``prepare`` and the render runs on the GPU). With ``fill=infill`` the splat (``splat``,
``geometry.forward_warp_mpi``) and ``composite`` run on the CPU and the infilling network
(``engine.predict.decomp.infill``, thesis Sec. 6.3.4) fills the holes.
``DecompTrueMotion`` replaces the predicted object motion by the true one (the bound of thesis Table 6.3).

Conventions are ``engine.geometry``'s: OpenCV cameras, pixel centres at +0.5, planar depth (+inf sky),
MPI arrays (C, Z, H, W) with planes near (0) to far (Z - 1). No torch: the network runs in onnxruntime.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Any, Literal, Optional, Sequence

import numpy as np

from engine import geometry
from engine.core.config import option
from engine.core.errors import InputError, InterleaveError
from engine.core.frames import Frame, SceneObject
from engine.geometry import Mpi
from engine.geometry.backends.gl.frame import GlFlow
from engine.geometry.backends.gl.gate import GlGate
from engine.geometry.backends.gl.refine import GlFlowRefine
from engine.geometry.camera import reprojection_matrix
from engine.geometry.holefill import fill_holes
from engine.geometry.mpi import plane_bounds
from engine.predict.backend import gl_flow_estimators
from engine.predict.base import (Predictor, PreparedState, ResidentFrame, Target, Timer, extrapolation_factor,
                                 true_object_flow)
from engine.predict.decomp.gate import Box, GateConfig, boxes_from_counts, gate_boxes
from engine.predict.decomp.infill import DEFAULT_INFILL_MODEL, InfillNetwork
from engine.predict.decomp.network import DEFAULT_MODEL, FlowNetwork
from engine.predict.decomp.upsample import spread_plane, upsample_flow
from engine.predict.corrflow import CorrFlowNetwork, corr_dis_flow
from engine.predict.dis import dis_estimator, dis_flow, drop_untrusted, fall_back, luma8, warp_error

__all__ = ["DecompConfig", "DecompState", "InitialFlow", "DecompPredictor", "DecompTrueMotion", "full_box",
           "crop_mpi", "whole_frame_initial_flow", "box_residual", "refine_box",
           "REFINE_MARGIN", "REFINE_WINDOW"]

#: The refinement check keeps the refined flow only where its photometric error is lower than the initial
#: flow's by more than this many 8-bit levels (ties and near-ties keep DIS; chosen on training scenes).
REFINE_MARGIN = 1.0
#: The side of the window (pixels) over which the refinement check averages ``warp_error``.
REFINE_WINDOW = 9


@dataclass(frozen=True)
class DecompConfig:
    """Options of the ``decomp`` predictor (``decomp[flow_width=240,gate.tile=16]``)."""

    model: str = option("", "ONNX flow network (default: the committed engine/weights/flow3d.onnx)")
    flow_width: int = option(0, "widest input in pixels the network runs at (0: the width it was trained at, "
                                "from the ONNX metadata); frames are block-downsampled by ceil(W / flow_width)")
    gate: GateConfig = option(GateConfig(), "the motion gate (engine.predict.decomp.gate)")
    threads: int = option(2, "onnxruntime intra-op threads")
    estimator: Literal["dis", "gl", "corr"] = option(
        "corr", "the initial flow's estimator: 'corr' (DIS started from the correlation network: "
                "flow2d[estimator=corr]'s flow, the best 2D estimate measured: "
                "docs/results/2026-11-28-no-vector-motion.md), 'dis' (OpenCV DIS on the CPU, flow2d's) or 'gl' (the "
                "GPU's flow of flow2d[estimator=gl]: on the gl backend the whole initial flow runs on the GPU; "
                "measured scores: docs/gpu.md)")
    corr_network: str = option("", "the correlation network of estimator=corr: an exported ONNX (default: the "
                                   "committed engine/weights/corrflow.onnx; python -m export.corrflow)")
    dis_preset: Literal["ultrafast", "fast", "medium"] = option("medium", "OpenCV DIS preset of the initial flow, for networks that refine one")
    fallback: bool = option(False, "regions whose flow explains frame n from n-k worse than no object motion take "
                                   "the camera-only warp (engine.predict.dis.explained_motion)")
    fill: Literal["simple", "infill"] = option("simple", "disocclusion fill: 'simple' (the background-biased row fill of reproject, "
                                 "engine.geometry.holefill) or 'infill' (the infilling network, "
                                 "engine.predict.decomp.infill: copies known pixels of the same MPI plane along "
                                 "predicted vectors; measured on held-out scenes: the same PSNR for about 240 ms "
                                 "more per frame, docs/infill.md, hence not the default)")
    infill_iterations: int = option(3, "passes g of the infilling network (each fills what the last left open)")
    infill_model: str = option("", "ONNX infilling network (default: the committed engine/weights/infill.onnx)")
    infill_margin: int = option(48, "hole gate of the infilling network: it runs on boxes around the holes with "
                                    "this many of its pixels as context (48 = its receptive radius: the same "
                                    "vectors as the whole frame); -1 = on the whole frame")

    def __post_init__(self) -> None:
        checks = [
            (isinstance(self.gate, GateConfig), "gate must be a GateConfig"),
            (self.flow_width >= 0, "flow_width must be >= 0"),
            (self.threads >= 1, "threads must be >= 1"),
            (self.fill in ("infill", "simple"), f"fill must be 'infill' or 'simple', got {self.fill!r}"),
            (self.estimator in ("dis", "gl", "corr"),
             f"estimator must be 'dis', 'gl' or 'corr', got {self.estimator!r}"),
            (self.infill_iterations >= 1, "infill_iterations must be >= 1"),
            (not self.corr_network or self.estimator == "corr",
             f"corr_network is read by estimator=corr only, got estimator={self.estimator}"),
            (self.infill_margin >= -1, "infill_margin must be >= 0, or -1 for the whole frame"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="DecompConfig")


@dataclass
class InitialFlow:
    """The full-resolution initial flow of frame n and what scores flows against it: ``flow`` (H, W, 2)
    u(n -> n-k) pixels, ``target`` (H, W) uint8 luma of the camera-compensated frame n-k the flow matched
    (``dis_target``), ``luma_n`` (H, W) uint8 luma of frame n, ``seen`` (H, W) bool where frame n-k saw the
    surface (``geometry.seen_before``), ``target_depth`` (H, W) and ``target_color`` (H, W, 3) that target's
    planar depth and linear RGB (filled). On the CPU path; ``_boxes_on_gpu`` keeps all of it on the GPU."""

    flow: np.ndarray
    target: np.ndarray
    luma_n: np.ndarray
    seen: np.ndarray
    target_depth: Optional[np.ndarray] = None
    target_color: Optional[np.ndarray] = None


@dataclass
class DecompState:
    """``decomp``'s per-frame state (``PreparedState.data``) after ``prepare``.

    ``boxes``: working-resolution boxes the network ran on; ``factor``: the downsampling; ``mpi``: the
    full-resolution one-plane MPI of frame n (made for ``fill=infill`` only, None otherwise); ``flow``: frame
    n's u(n -> n-k), (3, 1, H, W), or None when the gate found no motion or the flow was made on the GPU and
    stays there (``motion``); ``plane_depths``: the network's planes (frame n's, at the working resolution;
    None where the GPU's gate found no motion: frame n was not downsampled on the CPU);
    ``network_fraction``: the share of the frame the network saw; ``infill_planes``: frame n's planes at the
    infilling network's Z, made on first use when it has other planes than the flow network; ``frame`` and
    ``motion``: frame n and its flow (H, W, 3) where the backend computes (on ``gl``: uploaded once, or a
    2-channel ``GlFlow`` made there by ``estimator=gl``).
    """

    boxes: list[Box]
    factor: int
    mpi: Optional[Mpi]
    flow: Optional[np.ndarray]
    plane_depths: Optional[np.ndarray]
    network_fraction: float
    infill_planes: Optional[np.ndarray] = None
    frame: Optional[ResidentFrame] = None
    motion: Any = None


def full_box(box: Box, factor: int, low_size: tuple[int, int], size: tuple[int, int]) -> Box:
    """Full-resolution (y0, y1, x0, x1) of a working-resolution box; a box at the last block row or column
    also takes the full-resolution rows or columns past the last whole block."""
    y0, y1, x0, x1 = box
    return (y0 * factor, size[0] if y1 == low_size[0] else y1 * factor,
            x0 * factor, size[1] if x1 == low_size[1] else x1 * factor)


def crop_mpi(mpi: Mpi, box: Box) -> Mpi:
    """The part (y0, y1, x0, x1) of an MPI (views, not copies)."""
    y0, y1, x0, x1 = box
    return Mpi(mpi.color[..., y0:y1, x0:x1], mpi.depth[..., y0:y1, x0:x1], mpi.alpha[..., y0:y1, x0:x1],
               mpi.plane_depths)


def downsample(frame: Frame, factor: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(colour, depth, intrinsics) of a frame block-downsampled by ``factor`` (``geometry.downsample_frame``)."""
    return geometry.downsample_frame(frame.color, frame.depth, frame.camera.intrinsics, factor)


def network_input(low_n: tuple, low_p: tuple, t_n: np.ndarray, t_p: np.ndarray, planes: np.ndarray,
                  boxes: Sequence[Box], timer: Timer) -> tuple[Mpi, Mpi, tuple[int, int]]:
    """Stages ``mpi`` and ``camera_warp``: m_n (one-hot MPI of frame n on ``planes``, working resolution),
    m_{n-k} on frame n's planes warped into frame n's view over the bounding box of the boxes only, and that
    box's corner (y, x). ``low_n`` / ``low_p``: (colour, depth, intrinsics) of frames n and n-k."""
    num_z = len(planes)
    with timer("mpi"):
        m_n = geometry.build_mpi(low_n[0], low_n[1], num_z, planes)
        m_p = geometry.build_mpi(low_p[0], low_p[1], num_z)
    by0, bx0 = min(b[0] for b in boxes), min(b[2] for b in boxes)
    by1, bx1 = max(b[1] for b in boxes), max(b[3] for b in boxes)
    k_box = np.array(low_n[2], dtype=np.float64)
    k_box[0, 2] -= bx0
    k_box[1, 2] -= by0
    with timer("camera_warp"):
        warped, _ = geometry.forward_warp_mpi(m_p._replace(plane_depths=planes), low_p[2], t_p, k_box, t_n,
                                              out_size=(by1 - by0, bx1 - bx0))
    return m_n, warped, (by0, bx0)


def whole_frame_initial_flow(older: Frame, newest: Frame, preset: str, gl_flow: Any = None,
                             corr: Optional[CorrFlowNetwork] = None) -> InitialFlow:
    """Flow u(n -> n-k) of the whole frame at full resolution: frame n-k forward-warped into frame n's view, its
    holes filled as ``reproject`` fills them, the flow from frame n to that target (DIS with ``preset``, or
    ``gl_flow.estimate``: a ``GlOpticalFlow``, or DIS started from the correlation network ``corr``:
    ``corrflow.corr_dis_flow``), kept where ``dis.trusted_motion`` trusts it (so the flow equals ``flow2d``'s
    with that estimator)."""
    src, dst = older.camera, newest.camera
    color_w, depth_w, holes = geometry.forward_warp_frame(older.color, older.depth, src.intrinsics,
                                                          src.world_to_camera, dst.intrinsics, dst.world_to_camera)
    luma_n = luma8(newest.color)
    filled, filled_depth = fill_holes(color_w, depth_w, holes, newest.color)[:2]
    target = luma8(filled)  # engine.predict.dis.dis_target
    seen = geometry.seen_before(newest.depth, dst.intrinsics, dst.world_to_camera, src.intrinsics, src.world_to_camera,
                                older.depth.shape)
    if corr is not None:
        flow = corr_dis_flow(corr, dis_estimator(preset), newest.color, filled, luma_n, target, newest.depth,
                             filled_depth)
    else:
        flow = dis_flow(luma_n, target, preset) if gl_flow is None else gl_flow.estimate(newest.color, filled)
    drop_untrusted(flow, luma_n, target, seen)
    return InitialFlow(flow, target, luma_n, seen, filled_depth, filled)


def box_residual(network: FlowNetwork, box: Box, m_n: Mpi, warped: tuple[Mpi, tuple[int, int]],
                 init: Optional[np.ndarray], timer: Timer) -> tuple[np.ndarray, np.ndarray]:
    """Stage ``flow`` of one gate box (working-resolution pixels): the network's flow on the box (3, Z, h, w)
    and the box's alpha (Z, h, w). ``warped``: the camera-compensated m_{n-k} on a part of the working-resolution
    frame and that part's corner (y, x); ``init``: the initial flow block-averaged onto the box (h, w, 2)
    (``geometry.downsample_flow`` of its full-resolution box), None for a network that refines none. With an
    initial flow only the network's residual is kept: the initial flow is added back at full detail
    (``refine_box``). The network's dz is not used (0): the committed network's plane offsets cost 0.9 dB.
    """
    y0, y1, x0, x1 = box
    oy, ox = warped[1]
    warped_box = crop_mpi(warped[0], (y0 - oy, y1 - oy, x0 - ox, x1 - ox))
    m_box = crop_mpi(m_n, box)
    with timer("flow"):
        low_flow = network(m_box, warped_box, init)
    low_flow[2] = 0.0
    if init is not None:  # keep the network's residual only
        low_flow[:2] -= np.moveaxis(init, -1, 0)[:, None] * m_box.alpha[None]
    return low_flow, m_box.alpha


def refine_box(full: Box, low_flow: np.ndarray, alpha: np.ndarray, factor: int, plane_index: np.ndarray,
               initial: Optional[InitialFlow], timer: Timer) -> np.ndarray:
    """Stages ``upsample`` and ``refine_check`` of one gate box on the CPU (``GlFlowRefine`` on the GPU): its
    flow (3, 1, h, w), each pixel its own plane's (the sum over a one-hot MPI's planes). The network's
    ``low_flow`` (3, Z, h_low, w_low) with its ``alpha`` (``box_residual``) is upsampled per plane onto the
    pixels of that plane (``plane_index`` (H, W): frame n's plane of every pixel) and added to the initial
    flow; each pixel keeps the sum only where it explains frame n better than the initial flow alone by more
    than ``REFINE_MARGIN`` levels (``warp_error``)."""
    fy0, fy1, fx0, fx1 = full
    index = plane_index[fy0:fy1, fx0:fx1]
    full_alpha = (index[None] == np.arange(alpha.shape[0])[:, None, None]).astype(np.float32)
    with timer("upsample"):
        part = upsample_flow(low_flow, alpha, factor, full_alpha)
    if initial is None:
        return part.sum(axis=1, keepdims=True)
    full_init = initial.flow[fy0:fy1, fx0:fx1]
    dis_part = np.moveaxis(full_init, -1, 0)[:, None] * full_alpha[None]
    part[:2] += dis_part
    part = part.sum(axis=1, keepdims=True)  # one-hot: summing over planes gives each pixel its own plane's flow
    dis_part = dis_part.sum(axis=1, keepdims=True)
    luma_n, offset = initial.luma_n[fy0:fy1, fx0:fx1], (fy0, fx0)
    refined = np.moveaxis(part[:2].sum(axis=1), 0, -1)  # (h, w, 2): each pixel's own plane's flow
    with timer("refine_check"):
        keep = (warp_error(luma_n, initial.target, offset, refined, REFINE_WINDOW) + np.float32(REFINE_MARGIN)
                < warp_error(luma_n, initial.target, offset, full_init, REFINE_WINDOW))
    part[:2] = np.where(keep, part[:2], dis_part)
    return part


class DecompPredictor(Predictor):
    """The ``decomp`` method: DeCOMPnet's 3D object motion on MPIs, extrapolated and splatted (see module doc).

    ``state.data`` after ``prepare`` is a ``DecompState``.
    """

    name = "decomp"
    history_needed = 2
    backends = ("cpu", "gl")  # the render with the simple fill and estimator=gl's initial flow; fill=infill: CPU

    def __init__(self, config: DecompConfig = DecompConfig(), network: Optional[FlowNetwork] = None,
                 objects: Sequence[SceneObject] = (), infill: Optional[InfillNetwork] = None) -> None:
        if not isinstance(config, DecompConfig):
            raise InputError(f"must be a DecompConfig, got {type(config).__name__}", field="config")
        self.config = config
        self.network = network if network is not None else FlowNetwork(config.model or DEFAULT_MODEL, config.threads)
        self.objects = {o.id: o for o in objects}
        self._gl: Optional[tuple] = None  # (GlOpticalFlow, GlTrust) of estimator=gl
        # estimator=corr's network: the committed one opened on first use, a given one now (a bad file fails here)
        self._corr: Optional[CorrFlowNetwork] = (CorrFlowNetwork(config.corr_network, threads=config.threads)
                                                 if config.corr_network else None)
        self._refine: Optional[GlFlowRefine] = None
        self._gate: Optional[GlGate] = None
        self.infill = None
        if config.fill == "infill":
            self.infill = infill if infill is not None else InfillNetwork(config.infill_model or DEFAULT_INFILL_MODEL,
                                                                           config.threads)
            self.backends = ("cpu",)  # the infilling network's render (splat, composite, network) runs on the CPU

    def _prepare(self, state: PreparedState, timer: Timer) -> DecompState:
        cfg, net = self.config, self.network
        older, newest = state.history[-2], state.history[-1]
        size = newest.depth.shape
        factor = geometry.downsample_factor(size[1], cfg.flow_width or net.working_width)
        factor = min(factor, *size)
        t_p, t_n = older.camera.world_to_camera, newest.camera.world_to_camera
        low_size = (size[0] // factor, size[1] // factor)  # downsample_frame's
        boxes = None  # the gate's boxes: on the GPU first where frames are there
        if cfg.gate.enabled and self._on_gpu():
            boxes = self._gate_on_gpu(older, newest, factor, low_size, timer)
        if boxes is None or boxes:  # for the CPU's gate or the network (not where the GPU's gate found no motion)
            with timer("downsample"):
                low_n, low_p = downsample(newest, factor), downsample(older, factor)
        if boxes is None and cfg.gate.enabled:
            with timer("gate"):
                boxes = gate_boxes(cfg.gate, low_n, low_p, t_n, t_p, net.stride)
        elif boxes is None:
            boxes = [(0, low_size[0], 0, low_size[1])]
        planes, flow, on_gpu = None, None, None
        if boxes:
            planes = geometry.plane_depths(low_n[1], net.num_planes)  # the network's planes: frame n's, low resolution
            m_n, warped, corner = network_input(low_n, low_p, t_n, t_p, planes, boxes, timer)
            fulls = [full_box(box, factor, low_size, size) for box in boxes]
            net_input = (net, m_n, (warped, corner))
            if net.needs_initial_flow and cfg.estimator == "gl" and self._on_gpu() and not cfg.fallback:
                on_gpu = self._boxes_on_gpu(state, boxes, fulls, factor, planes, net_input, timer)
            else:
                flow = self._boxes_on_cpu(state, boxes, fulls, factor, planes, net_input, timer)
        data = DecompState(boxes=boxes, factor=factor, mpi=None, flow=flow, plane_depths=planes,
                           network_fraction=sum((b[1] - b[0]) * (b[3] - b[2]) for b in boxes)
                           / float(low_size[0] * low_size[1]))
        self._resident(state, data, timer, on_gpu)
        return data

    def _on_gpu(self) -> bool:
        """Whether frames n and n-k are on the GPU for the preparation (the ``gl`` backend, the simple fill)."""
        return self.frames.name == "gl" and self.infill is None

    def _gate_on_gpu(self, older: Frame, newest: Frame, factor: int, low_size: tuple[int, int],
                     timer: Timer) -> list[Box]:
        """``gate_boxes`` with the changed pixels counted per tile on the GPU (``GlGate``, stage ``gate``): only
        the counts come back; the boxes are made from them as from the CPU's (``boxes_from_counts``)."""
        gate = self.config.gate
        if self._gate is None:
            self._gate = GlGate(gate.color_threshold, gate.depth_threshold, gate.erode, gate.unseen, gate.tile)
        frame_p, frame_n = self.frames.resident(older, timer), self.frames.resident(newest, timer)
        with timer("gate"):
            counts = self._gate.tile_counts(frame_n.image, frame_p.image, newest.camera.intrinsics,
                                            newest.camera.world_to_camera, older.camera.intrinsics,
                                            older.camera.world_to_camera, factor, gpu_ms=timer.gpu)
            return boxes_from_counts(counts, low_size, gate.tile, gate.tile_fraction, gate.margin,
                                     self.network.stride, gate.full_frame_fraction, gate.min_tiles)

    def _boxes_on_cpu(self, state: PreparedState, boxes: list, fulls: list, factor: int, planes: np.ndarray,
                      net_input: tuple, timer: Timer) -> np.ndarray:
        """The flow (3, 1, H, W) of frame n on the CPU: the initial flow (DIS, or the GPU's estimator between
        the CPU's warp and trust rules), the network on every box, ``refine_box``, and no motion where frame
        n-k did not see the surface."""
        older, newest = state.history[-2], state.history[-1]
        net = net_input[0]
        with timer("mpi"):
            plane_index = geometry.plane_index(newest.depth, planes)
        initial = None
        if net.needs_initial_flow:
            gl_flow = None
            if self.config.estimator == "gl":
                gl_flow = self._gl_estimators()[0]
            if self.config.estimator == "corr" and self._corr is None:
                self._corr = CorrFlowNetwork(threads=self.config.threads)
            with timer("initial_flow"):
                initial = whole_frame_initial_flow(older, newest, self.config.dis_preset, gl_flow, self._corr)
        residuals = []
        for box, (fy0, fy1, fx0, fx1) in zip(boxes, fulls):  # from here on, costs follow the boxes' area
            init = None if initial is None else geometry.downsample_flow(initial.flow[fy0:fy1, fx0:fx1], factor)
            residuals.append(box_residual(net, box, net_input[1], net_input[2], init, timer))
        self._check_finite(residuals, newest)
        flow = np.zeros((3, 1) + newest.depth.shape, dtype=np.float32)
        if initial is not None:  # outside the boxes; they overwrite their part
            flow[:2, 0] = np.moveaxis(initial.flow, -1, 0)
        for full, (low_flow, alpha) in zip(fulls, residuals):
            fy0, fy1, fx0, fx1 = full
            flow[:, :, fy0:fy1, fx0:fx1] = refine_box(full, low_flow, alpha, factor, plane_index, initial, timer)
        if initial is not None:  # no motion where frame n-k did not see the surface (nor in the boxes)
            flow[:, 0, ~initial.seen] = 0.0
            if self.config.fallback:
                with timer("fallback"):
                    # the refined flow under flow2d's trust rules first (the network leaves sub-pixel motion
                    # everywhere, which would join all into one region), then whole regions fall back
                    planar = np.ascontiguousarray(np.moveaxis(flow[:2, 0], 0, -1))
                    drop_untrusted(planar, initial.luma_n, initial.target, initial.seen)
                    fall_back(planar, initial.luma_n, initial.target, newest.depth, newest.camera.intrinsics,
                              (newest.color, initial.target_color), initial.target_depth)
                    flow[:2, 0] = np.moveaxis(planar, -1, 0)
        return flow

    def _boxes_on_gpu(self, state: PreparedState, boxes: list, fulls: list, factor: int, planes: np.ndarray,
                      net_input: tuple, timer: Timer) -> tuple:
        """``_boxes_on_cpu`` with the GPU's estimator on the ``gl`` backend: frame n-k's warp, the flow and its
        trust rules run on the GPU (``GlFrames.estimate_flow_back``, stage ``initial_flow``); only each box's
        block-averaged initial flow comes back, for the network; the refinement check runs there too
        (``GlFlowRefine``, stage ``refine``; overlapping boxes each start from a copy of the initial flow, as
        on the CPU). Returns (frame n, its flow) as they are on the GPU."""
        older, newest = state.history[-2], state.history[-1]
        estimator, trust = self._gl_estimators()
        if self._refine is None:
            self._refine = GlFlowRefine(REFINE_MARGIN, REFINE_WINDOW)
        frame_p, frame_n = self.frames.resident(older, timer), self.frames.resident(newest, timer)
        with timer("initial_flow"):
            flow = self.frames.estimate_flow_back(frame_p, frame_n, estimator, trust, Timer(gpu=timer.gpu))
            initial = flow if len(boxes) == 1 else flow.copy()
            inits = [self._refine.initial_low(initial, full, factor) for full in fulls]
        residuals = [box_residual(net_input[0], box, net_input[1], net_input[2], init, timer)
                     for box, init in zip(boxes, inits)]
        self._check_finite(residuals, newest)
        src, dst = older.camera, newest.camera
        matrix = reprojection_matrix(dst.intrinsics, dst.world_to_camera, src.intrinsics, src.world_to_camera)
        bounds = plane_bounds(planes)
        for full, (low_flow, alpha) in zip(fulls, residuals):
            with timer("refine"):
                packed = np.stack([spread_plane(low_flow[:, z], alpha[z]) for z in range(alpha.shape[0])])
                self._refine.apply(flow, initial, estimator.lumas, frame_n.image, matrix, older.depth.shape, bounds,
                                   full, packed, factor, gpu_ms=timer.gpu)
        return frame_n, flow

    @staticmethod
    def _check_finite(residuals: list, newest: Frame) -> None:
        if not all(np.isfinite(low_flow).all() for low_flow, _ in residuals):
            raise InterleaveError(f"the flow network returned non-finite values for frame {newest.index}")

    def _gl_estimators(self) -> tuple:
        """(GlOpticalFlow, GlTrust) of ``estimator=gl``, made on first use."""
        if self._gl is None:
            self._gl = gl_flow_estimators()
        return self._gl

    def _resident(self, state: PreparedState, data: DecompState, timer: Timer, on_gpu: Optional[tuple] = None) -> None:
        """Frame n and its flow where the backend computes (the simple fill), or frame n's one-plane MPI (the
        infilling network's path). ``on_gpu``: (frame n, its flow) already on the GPU (``_boxes_on_gpu``)."""
        newest = state.history[-1]
        flow = None if data.flow is None else np.ascontiguousarray(np.moveaxis(data.flow[:, 0], 0, -1))
        if self.infill is not None:
            with timer("mpi"):
                data.mpi = geometry.build_mpi(newest.color, newest.depth, 1)
            data.motion = flow
            return
        if on_gpu is None:
            data.frame = self.frames.resident(newest, timer)
            if flow is not None:
                data.motion = self.frames.resident_flow(flow, timer)
            return
        data.frame, data.motion = on_gpu

    def _object_motion(self, state: PreparedState, target: Target, timer: Timer) -> tuple[Any, float]:
        """(flow, scale): the object motion u(n -> target) of frame n's pixels is scale * flow (flow: (H, W, 3)
        or the backend's resident copy; None for none)."""
        return state.data.motion, -extrapolation_factor(state, target)

    def _render(self, state: PreparedState, target: Target, timer: Timer) -> tuple[np.ndarray, np.ndarray]:
        data: DecompState = state.data
        flow, scale = self._object_motion(state, target, timer)
        if self.infill is None:
            return self.frames.warp_and_fill(data.frame, target, timer, flow, scale)
        newest = state.history[-1]
        motion = None if flow is None else np.moveaxis(flow * np.float32(scale), -1, 0)[:, None]
        src, dst = newest.camera, target.camera
        with timer("splat"):
            warped, _ = geometry.forward_warp_mpi(data.mpi, src.intrinsics, src.world_to_camera, dst.intrinsics,
                                                  dst.world_to_camera, motion)
        with timer("composite"):
            color, depth, acc = geometry.composite(warped)
        holes = acc <= 0
        if self.infill is not None and holes.any():
            margin = None if self.config.infill_margin < 0 else self.config.infill_margin
            planes = data.plane_depths
            if len(planes) != self.infill.num_planes:  # a flow network on other planes: frame n's, at the infill's Z
                if data.infill_planes is None:
                    data.infill_planes = geometry.plane_depths(newest.depth, self.infill.num_planes)
                planes = data.infill_planes
            color, depth = self.infill.fill(color, depth, holes, planes, newest.color,
                                            self.config.infill_iterations, timer, margin)
        else:
            with timer("fill"):
                color, _ = fill_holes(color, depth, holes, newest.color)
        return color, holes

    def object_flow(self, state: PreparedState) -> np.ndarray:
        """Per-pixel u(n -> n-k) of frame n's visible surface, (H, W, 2) pixels (0 where no motion was found)."""
        flow = state.data.flow
        if flow is None and isinstance(state.data.motion, GlFlow):  # made on the GPU and kept there
            return state.data.motion.read()
        if flow is None:  # frame n's one-plane MPI covers every pixel: the flow is its plane's
            return np.zeros(state.history[-1].depth.shape + (2,), dtype=np.float32)
        return np.moveaxis(flow[:2, 0], 0, -1).copy()


class DecompTrueMotion(DecompPredictor):
    """``decomp`` given the sequence's TRUE object motion instead of estimating it (as the ``oracle``): the
    bound of thesis Table 6.3 (``decomp[motion=truth]``; ``engine.eval.protocol.bound_methods``). Frame n's
    one-plane MPI moves by each pixel's true object motion to the target frame (``true_object_flow``; the
    target must be a frame of the sequence), then by the camera; holes are filled as ``decomp`` fills them."""

    def __init__(self, config: DecompConfig = DecompConfig(), network: Optional[FlowNetwork] = None,
                 objects: Sequence[SceneObject] = (), infill: Optional[InfillNetwork] = None) -> None:
        super().__init__(config, network, objects, infill)
        if not self.objects:
            raise InputError("motion=truth needs the sequence's moving objects (object ids and transforms)",
                             field="motion")

    def _prepare(self, state: PreparedState, timer: Timer) -> DecompState:
        newest = state.history[-1]
        data = DecompState(boxes=[], factor=1, mpi=None, flow=None, network_fraction=0.0,
                           plane_depths=geometry.plane_depths(newest.depth, self.network.num_planes))
        self._resident(state, data, timer)
        return data

    def _object_motion(self, state: PreparedState, target: Target, timer: Timer) -> tuple[Any, float]:
        with timer("motion"):
            return true_object_flow(state.history[-1], self.objects, target.index), 1.0  # (H, W, 3)
