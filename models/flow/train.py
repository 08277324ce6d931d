"""Unsupervised training of the 3D flow network on procedural scenes (thesis Sec. 6.3.3, 6.4).

Training pairs come from ``engine.scenegen``: each scene seed is rendered once into an rgbd-seq under
``<data_dir>/scene_<seed>`` (its ``scenegen_config.json`` records how). A step draws, from a random
stream seeded by ``(seed, step)``, ``batch_size`` items ``(scene, k, n, crop)``: frames n and n-k are
turned into ``m_n`` and ``m^w_{n-k}`` at full size (``models.flow.network.mpi_pair``: MPIs with
``models.geometry``, camera motion cancelled by ``forward_warp_mpi``), then cropped. The loss is
``models.flow.losses.flow_loss`` (Eq. 6.12), weighted by ``unsupervised_weight``. With
``supervised_weight`` > 0 a supervised term is added: the L1 error of the network's surface flow against
frame n's true object motion u(n -> n-k), computed from the scene's object transforms (``true_back_flow``):
pretraining on exact motion (``unsupervised_weight`` 0), then the thesis' losses as fine-tuning from that
checkpoint (``init_from``). ``scene_preset`` renders the scenes with a motion preset of
``engine.scenegen.presets`` (e.g. ``fast``: the speeds of path-traced game footage).

Outputs in ``out_dir``: ``config.json`` (the ``TrainFlowConfig``), ``checkpoint.pt`` (model, optimiser,
step; written every ``checkpoint_every`` steps and at the end), ``metrics.jsonl`` (one line per logged
step, with the items drawn). ``train(config, resume=True)`` continues from ``checkpoint.pt``; because the
data of a step depend only on ``(seed, step)`` and the optimiser state is saved, the result equals an
uninterrupted run's (same thread count).

Data parallel: launched under ``torchrun`` (``WORLD_SIZE`` > 1), ranks join a gloo process group, each
takes every ``world_size``-th item of the step's batch, and DistributedDataParallel averages gradients,
so the update equals the single-process one. Only rank 0 writes files.

>>> train(TrainFlowConfig(out_dir="runs/flow3d", steps=10000))      # doctest: +SKIP
>>> # torchrun --standalone --nproc_per_node 2 -m models.flow.train --out-dir runs/flow3d --steps 10000
"""
from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import os
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor
from tqdm import tqdm

from engine.core import config as core_config
from engine.core.checks import check_shape
from engine.core.config import option
from engine.core.errors import InputError
from engine.geometry import downsample_flow, downsample_frame
from engine.io.rgbd import read_sequence
from engine.predict.base import true_object_flow
from engine.predict.dis import initial_flow
from engine.scenegen import generate_sequence
from engine.scenegen.presets import PRESETS, preset_config
from models.flow.losses import FlowLossConfig, flow_loss
from models.flow.network import Flow3D, Flow3DConfig, encode_color, extrapolate, mpi_pair, surface_flow
from models.geometry import Mpi, composite
from models.trainer_cli import trainer_config, trainer_main, trainer_parser

__all__ = ["TrainFlowConfig", "train", "load_model", "endpoint_error", "sample_items", "make_batch",
           "prepare_data", "config_from_dict", "open_sequences", "StepBatches", "scene_folder", "true_back_flow",
           "supervised_loss"]

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
METRICS = "metrics.jsonl"
#: ``TrainFlowConfig.initial_estimator`` values
INITIAL_ESTIMATORS = ("dis", "corr")



@dataclass(frozen=True)
class TrainFlowConfig:
    """What and how to train. Defaults follow the thesis (256x256 crops, batch 4, Adam 1e-4 (0.9, 0.999))."""

    out_dir: str = option("runs/flow3d", "folder for config.json, checkpoint.pt and metrics.jsonl")
    data_dir: str = option("runs/flow_data", "folder the training scenes are rendered to (shared between runs)")
    seed: int = option(0, "seed of the weights and of the data drawn at every step")
    steps: int = option(10000, "optimiser steps")
    batch_size: int = option(4, "pairs per step, over all processes (divisible by the number of processes)")
    crop: int = option(128, "square crop size in pixels of the downsampled frames (a multiple of 16 avoids "
                            "internal padding)")
    downsample: int = option(2, "block size the frames are downsampled by before the MPIs are built "
                                "(engine.geometry.downsample_frame; the engine's decomp predictor runs the "
                                "network at the same working width, 480 px)")
    lr: float = option(1e-4, "Adam learning rate")
    betas: tuple[float, float] = option((0.9, 0.999), "Adam betas")
    k_values: tuple[int, ...] = option((1, 2, 4), "frame gaps k of the pairs (m_n, m_{n-k}), drawn uniformly")
    scene_seeds: tuple[int, ...] = option(tuple(range(5000, 5032)),
                                          "engine.scenegen seeds of the training scenes (held-out: 1001-1003)")
    scene_width: int = option(960, "rendered scene width")
    scene_height: int = option(540, "rendered scene height")
    scene_frames: int = option(12, "frames rendered per scene (the thesis' sequences have 12)")
    scene_preset: str = option("gentle", "motion preset of the training scenes (engine.scenegen.presets: gentle, "
                                         "medium, fast, extreme); other than gentle, scenes are cached as "
                                         "<preset>_<seed>")
    supervised_weight: float = option(0.0, "weight of the supervised term: mean |du, dv| error of the network's "
                                           "surface flow against frame n's true object motion u(n -> n-k) (from "
                                           "the scene's object transforms), in working-resolution pixels; 0: the "
                                           "thesis' unsupervised training only")
    unsupervised_weight: float = option(1.0, "weight of the unsupervised loss (Eq. 6.8-6.12); 0 with a "
                                             "supervised_weight > 0: supervised pretraining")
    init_from: str = option("", "checkpoint.pt whose network weights start the run (e.g. supervised pretraining "
                                "before unsupervised fine-tuning); the optimiser starts afresh")
    initial_estimator: str = option("dis", "the initial flow a network with model.initial_flow refines: dis (OpenCV "
                                           "DIS on the downsampled MPIs' composite) or corr (the engine's decomp "
                                           "start: whole_frame_initial_flow with the committed correlation network "
                                           "at full resolution, its trust rules, block-meaned to the working size)")
    crop_candidates: int = option(4, "random crop positions drawn per frame pair; the crops_per_pair with the "
                                     "largest camera-compensated colour residual (m_n vs m^w_{n-k}) are trained on")
    crops_per_pair: int = option(2, "crops taken from each frame pair (building a pair costs more than a "
                                    "network step on a crop); batch_size / crops_per_pair pairs per step")
    threads: int = option(2, "torch intra-op threads per process")
    workers: int = option(0, "processes that build the batches of the coming steps while the network trains "
                             "(torch DataLoader, each with its own frame cache); 0: built in the training "
                             "process. The batches are the same either way")
    device: str = option("cpu", "torch device the network trains on (e.g. cuda); batches are built on the CPU")
    checkpoint_every: int = option(500, "save checkpoint.pt every this many steps (and at the end)")
    log_every: int = option(10, "append to metrics.jsonl every this many steps")
    model: Flow3DConfig = field(default_factory=Flow3DConfig,
                                metadata={"help": "network hyper-parameters (num_planes, mode, channels, ranges)"})
    loss: FlowLossConfig = field(default_factory=FlowLossConfig, metadata={"help": "loss weights (Eq. 6.8-6.12)"})

    def __post_init__(self) -> None:
        checks = [
            (self.steps >= 0 and self.batch_size >= 1, "steps must be >= 0 and batch_size >= 1"),
            (self.crop >= 1, "crop must be >= 1"),
            (self.downsample >= 1 and 1 <= self.crops_per_pair <= self.crop_candidates,
             "downsample must be >= 1 and 1 <= crops_per_pair <= crop_candidates"),
            (self.batch_size % self.crops_per_pair == 0, "batch_size must be a multiple of crops_per_pair"),
            (self.crop <= min(self.scene_width, self.scene_height) // self.downsample,
             "crop must fit in the downsampled scene size"),
            (self.lr > 0 and all(0.0 <= b < 1.0 for b in self.betas), "lr must be > 0, betas in [0, 1)"),
            (len(self.k_values) >= 1 and all(k >= 1 for k in self.k_values), "k_values must be >= 1"),
            (self.initial_estimator in INITIAL_ESTIMATORS,
             f"initial_estimator must be one of {', '.join(INITIAL_ESTIMATORS)}"),
            (max(self.k_values) < self.scene_frames, "scene_frames must exceed the largest k"),
            (len(self.scene_seeds) >= 1, "scene_seeds must not be empty"),
            (self.threads >= 1 and self.checkpoint_every >= 1 and self.log_every >= 1,
             "threads, checkpoint_every and log_every must be >= 1"),
            (self.workers >= 0, "workers must be >= 0"),
            (self.supervised_weight >= 0 and self.unsupervised_weight >= 0
             and self.supervised_weight + self.unsupervised_weight > 0,
             "supervised_weight and unsupervised_weight must be >= 0, not both 0"),
            (self.scene_preset in PRESETS, f"scene_preset must be one of {', '.join(PRESETS)}"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="TrainFlowConfig")


def config_from_dict(data: dict) -> TrainFlowConfig:
    """Inverse of ``dataclasses.asdict`` for ``TrainFlowConfig`` (lists back to tuples, nested configs)."""
    return core_config.config_from_dict(TrainFlowConfig, data)


# ----------------------------------------------------------------------------------------------------
# Data


def prepare_data(config: TrainFlowConfig, *, progress: bool = False) -> list[Path]:
    """Render every scene seed that is not cached yet; returns the rgbd-seq folders, one per seed."""
    return render_scenes(config.data_dir, config.scene_seeds, config.scene_width, config.scene_height,
                         config.scene_frames, progress=progress, preset=config.scene_preset)


def scene_folder(data_dir: str | Path, seed: int, preset: str = "gentle") -> Path:
    """``<data_dir>/scene_<seed>`` (gentle, the generator's defaults) or ``<data_dir>/<preset>_<seed>``."""
    return Path(data_dir) / (f"scene_{seed:06d}" if preset == "gentle" else f"{preset}_{seed:06d}")


def render_scenes(data_dir: str | Path, seeds, width: int, height: int, frames: int, *,
                  progress: bool = False, preset: str = "gentle") -> list[Path]:
    """``scene_folder`` rgbd-seq folders from ``engine.scenegen`` (motion ``preset``), rendering those not
    cached yet (written to a ``.tmp`` folder, then renamed: an interrupted render is never taken for a
    finished one)."""

    paths = []
    for seed in seeds:
        path = scene_folder(data_dir, seed, preset)
        if not (path / "sequence.json").exists():
            scene = preset_config(preset, seed=seed, width=width, height=height, num_frames=frames)
            generate_sequence(scene, path.with_name(path.name + ".tmp"), progress=progress)
            path.with_name(path.name + ".tmp").rename(path)
        paths.append(path)
    return paths


def sample_items(config: TrainFlowConfig, step: int) -> list[dict]:
    """The frame pairs of a step, a function of (seed, step) only: ``batch_size / crops_per_pair`` items
    ``{"scene", "k", "n", "crops"}`` with ``crops`` the ``crop_candidates`` (y, x) corners ``make_batch``
    chooses ``crops_per_pair`` from."""
    rng = np.random.default_rng([config.seed, step])
    items = []
    for _ in range(config.batch_size // config.crops_per_pair):
        k = int(rng.choice(config.k_values))
        items.append({"scene": int(rng.choice(config.scene_seeds)), "k": k,
                      "n": int(rng.integers(k, config.scene_frames)),
                      "crops": [[int(rng.integers(0, config.scene_height // config.downsample - config.crop + 1)),
                                 int(rng.integers(0, config.scene_width // config.downsample - config.crop + 1))]
                                for _ in range(config.crop_candidates)]})
    return items


def _residual(m_n: Mpi, m_p: Mpi) -> Tensor:
    """(H, W) camera-compensated colour residual: |encoded colour difference| where both MPIs hold a point."""
    both = m_n.alpha * m_p.alpha
    diff = (encode_color(m_n.color) - encode_color(m_p.color)).abs().sum(dim=1, keepdim=True)
    return (diff * both).sum(dim=(1, 2))[0]


def choose_crops(residual: Tensor, crops: list, size: int, count: int) -> list[list[int]]:
    """The ``count`` candidate [y, x] corners whose ``size`` crops hold the largest residual sums (stable order)."""
    sums = np.array([float(residual[y:y + size, x:x + size].sum()) for y, x in crops])
    order = np.argsort(-sums, kind="stable")[:count]
    return [list(crops[i]) for i in sorted(order.tolist())]


def frame_tensors(frame, factor: int) -> tuple[Tensor, ...]:
    """(color, depth, K, T) batched tensors of a frame block-downsampled by ``factor`` (as the engine does)."""
    color, depth, k = downsample_frame(frame.color, frame.depth, frame.camera.intrinsics, factor)
    t = torch.from_numpy(frame.camera.world_to_camera)[None].float()
    return torch.from_numpy(color)[None], torch.from_numpy(depth)[None], torch.from_numpy(k)[None].float(), t


def _object_flow(frame, factor: int) -> np.ndarray:
    """Frame n's ground-truth object flow (n -> n+1) at the downsampled size, in downsampled pixels."""
    if frame.object_flow is None:
        return np.zeros((frame.depth.shape[0] // factor, frame.depth.shape[1] // factor, 2), dtype=np.float32)
    return downsample_flow(frame.object_flow, factor)


def _crop_mpi(mpi: Mpi, y: int, x: int, size: int) -> Mpi:
    def crop(t: Tensor) -> Tensor:
        return t[..., y:y + size, x:x + size]
    return Mpi(crop(mpi.color), crop(mpi.depth), crop(mpi.alpha), mpi.plane_depths)


def _low_res_frame(config: TrainFlowConfig, sequences: dict, scene: int, n: int, cache: Optional[dict]):
    """(color, depth, K, T tensors, object flow array) of frame n of a scene at the downsampled size."""
    key = (scene, n)
    if cache is not None and key in cache:
        return cache[key]
    frame = sequences[scene][n]
    value = (frame_tensors(frame, config.downsample), _object_flow(frame, config.downsample))
    if cache is not None:
        cache[key] = value
    return value


def dis_initial_flow(color_n: Tensor, m_p: Mpi) -> Tensor:
    """``engine.predict.decomp.predictor.initial_flow`` (OpenCV DIS, the engine's function) for one pair, (1, 2, H, W)."""

    warped_color, _, acc = composite(m_p)
    flow = initial_flow(color_n[0].numpy(), warped_color[0].numpy(), acc[0].numpy() > 0)
    return torch.from_numpy(flow).permute(2, 0, 1)[None]


def corr_initial_flow(sequence, n: int, k: int, factor: int, cache: Optional[dict]) -> Tensor:
    """The engine's ``decomp`` start for frame n from n-k (``whole_frame_initial_flow`` with the committed
    correlation network, DIS preset medium, the trust rules), block-meaned by ``factor``: (1, 2, h, w) in
    downsampled pixels. Kept in ``cache`` (per scene folder, n, k) with the network (one per process)."""
    key = ("corr", str(getattr(sequence, "path", id(sequence))), n, k)
    if cache is not None and key in cache:
        return cache[key]
    from engine.predict.corrflow import CorrFlowNetwork
    from engine.predict.decomp.predictor import whole_frame_initial_flow

    network = cache.get("corr_network") if cache is not None else None
    if network is None:
        network = CorrFlowNetwork(threads=1)
        if cache is not None:
            cache["corr_network"] = network
    flow = whole_frame_initial_flow(sequence[n - k], sequence[n], "medium", None, network).flow
    value = torch.from_numpy(downsample_flow(np.ascontiguousarray(flow), factor)).permute(2, 0, 1)[None]
    if cache is not None:
        cache[key] = value
    return value


def true_back_flow(sequence, n: int, k: int, factor: int) -> np.ndarray:
    """Frame n's true object motion u(n -> n-k) (``engine.predict.base.true_object_flow``, (du, dv) only),
    block-meaned to the downsampled grid, in downsampled pixels (h // factor, w // factor, 2); zeros for a
    sequence without moving objects."""
    frame = sequence[n]
    objects = {o.id: o for o in sequence.objects}
    if frame.object_id is None or not objects:
        return np.zeros((frame.depth.shape[0] // factor, frame.depth.shape[1] // factor, 2), np.float32)
    return downsample_flow(np.ascontiguousarray(true_object_flow(frame, objects, n - k)[..., :2]), factor)


def make_batch(config: TrainFlowConfig, items: list[dict], sequences: dict,
               cache: Optional[dict] = None) -> tuple[Mpi, Mpi, Tensor, Optional[Tensor], Optional[Tensor]]:
    """Crops of ``(m_n, m^w_{n-k})`` for ``items``, the ground-truth object flow of frame n (B, c, c, 2),
    for networks that refine one (``Flow3DConfig.initial_flow``) the initial flow (B, 2, c, c), else None,
    and with ``supervised_weight`` > 0 the supervised target u(n -> n-k) (B, c, c, 2, ``true_back_flow``),
    else None.

    An item with ``crops`` candidates yields ``crops_per_pair`` crops (``choose_crops``, recorded in the
    item as ``picked``); an item with ``y``, ``x`` yields that one crop.

    Frames are block-downsampled by ``config.downsample`` first (``engine.geometry.downsample_frame``).
    ``sequences`` maps scene seed -> ``engine.io.rgbd.RgbdSequence`` (or anything indexable the same way);
    ``cache`` (a dict, optional) keeps the downsampled frames between calls (training passes one). The
    object flow (frame n -> n+1, block mean, in downsampled pixels) is only for evaluation (zeros when the
    sequence has none).
    """
    firsts, seconds, flows, inits, targets = [], [], [], [], []
    for item in items:
        tensors_n, flow_n = _low_res_frame(config, sequences, item["scene"], item["n"], cache)
        tensors_p, _ = _low_res_frame(config, sequences, item["scene"], item["n"] - item["k"], cache)
        with torch.no_grad():
            m_n, m_p = mpi_pair(*tensors_n, *tensors_p, config.model.num_planes)
        init = None
        if config.model.initial_flow and config.initial_estimator == "corr":
            init = corr_initial_flow(sequences[item["scene"]], item["n"], item["k"], config.downsample, cache)
        elif config.model.initial_flow:
            init = dis_initial_flow(tensors_n[0], m_p)
        back = None
        if config.supervised_weight > 0:
            back = true_back_flow(sequences[item["scene"]], item["n"], item["k"], config.downsample)
        c = config.crop
        if "crops" in item:
            item["picked"] = choose_crops(_residual(m_n, m_p), item["crops"], c, config.crops_per_pair)
        for y, x in item.get("picked", [[item.get("y", 0), item.get("x", 0)]]):
            firsts.append(_crop_mpi(m_n, y, x, c))
            seconds.append(_crop_mpi(m_p, y, x, c))
            flows.append(torch.from_numpy(np.ascontiguousarray(flow_n[y:y + c, x:x + c])))
            if init is not None:
                inits.append(init[..., y:y + c, x:x + c])
            if back is not None:
                targets.append(torch.from_numpy(np.ascontiguousarray(back[y:y + c, x:x + c])))

    def stack(mpis: list[Mpi]) -> Mpi:
        return Mpi(*(torch.cat(parts, dim=0) for parts in zip(*mpis)))

    return (stack(firsts), stack(seconds), torch.stack(flows), (torch.cat(inits) if inits else None),
            (torch.stack(targets) if targets else None))


def supervised_loss(flow: Tensor, mpi_n: Mpi, target: Tensor) -> Tensor:
    """Per-item mean |(du, dv) - target| (L1 over both components) of the network's surface flow (B, 3, Z, H, W)
    against the true u(n -> n-k) (B, H, W, 2) over the pixels frame n covers, (B,)."""
    pred = surface_flow(flow, mpi_n)[..., :2]
    covered = mpi_n.alpha.sum(dim=2)[:, 0].clamp_max(1.0)  # (B, H, W): 1 where frame n has a surface
    error = (pred - target).abs().sum(dim=-1) * covered
    return error.sum(dim=(1, 2)) / covered.sum(dim=(1, 2)).clamp_min(1.0)


# ----------------------------------------------------------------------------------------------------
# Evaluation


def endpoint_error(pred_flow: Tensor, gt_object_flow: Tensor, mask: Optional[Tensor] = None) -> Tensor:
    """Average endpoint error in x-y (thesis Tab. 6.2), a scalar tensor: mean of ||pred_xy - gt|| over ``mask``.

    Both flows must mean the same motion, e.g. the predicted ``u(n -> n+1)`` (``extrapolate(flow, 1 / k)``
    collapsed to pixels with ``surface_flow``) against frame n's ``object_flow`` (n -> n+1, pixels).

    Args:
        pred_flow: (B, H, W, 2 or 3) pixels (a third component, dz, is ignored).
        gt_object_flow: (B, H, W, 2) pixels.
        mask: optional (B, H, W) bool, the pixels to score (e.g. moving pixels); default all.

    Returns:
        The mean EPE in pixels; NaN when the mask selects nothing.
    """
    sizes: dict = {}
    check_shape(pred_flow, "pred_flow", ("B", "H", "W", "C"), sizes)
    check_shape(gt_object_flow, "gt_object_flow", ("B", "H", "W", 2), sizes)
    if sizes["C"] not in (2, 3):
        raise InputError(f"must have 2 or 3 components, got {sizes['C']}", field="pred_flow")
    epe = torch.linalg.vector_norm(pred_flow[..., :2] - gt_object_flow, dim=-1)
    if mask is None:
        return epe.mean()
    check_shape(mask, "mask", ("B", "H", "W"), sizes, floating=False)
    mask = mask.to(torch.bool)
    return epe[mask].mean() if bool(mask.any()) else torch.tensor(float("nan"), dtype=epe.dtype)


def _moving_epe(flow: Tensor, mpi_n: Mpi, gt_flow: Tensor, ks: list[int]) -> tuple[float, float]:
    """Monitoring only: EPE of the predicted u(n -> n+1) = -u(n -> n-k) / k on pixels whose true object
    flow exceeds 0.1 px, and the EPE of zero flow on the same pixels (NaN when none moves)."""
    steps = torch.tensor([1.0 / k for k in ks], dtype=flow.dtype).reshape(-1, 1, 1, 1, 1)
    pred = surface_flow(extrapolate(flow, 1.0) * steps, mpi_n)
    moving = torch.linalg.vector_norm(gt_flow, dim=-1) > 0.1
    return (float(endpoint_error(pred, gt_flow, moving)),
            float(endpoint_error(torch.zeros_like(gt_flow), gt_flow, moving)))


# ----------------------------------------------------------------------------------------------------
# Training


def open_sequences(config: TrainFlowConfig) -> dict:
    """Scene seed -> ``engine.io.rgbd.RgbdSequence`` of the rendered training scenes (``prepare_data``)."""

    return {seed: read_sequence(scene_folder(config.data_dir, seed, config.scene_preset))
            for seed in config.scene_seeds}


class StepBatches(torch.utils.data.Dataset):
    """Item i: ``(items, make_batch(...))`` of step ``start + i`` for process ``rank`` of ``world``, with
    ``items`` = ``sample_items(config, step)`` (this rank's share marked with the crops it picked).

    A function of (seed, step) only, so the batches are the same whether they are built in the training
    process or in DataLoader workers (each keeps its own cache of downsampled frames, about 3 MB a frame).
    """

    def __init__(self, config: TrainFlowConfig, start: int, rank: int = 0, world: int = 1) -> None:
        self.config, self.start, self.rank, self.world = config, start, rank, world
        self.sequences: Optional[dict] = None
        self.cache: dict = {}

    def __len__(self) -> int:
        return max(self.config.steps - self.start, 0)

    def __getitem__(self, index: int):
        if self.sequences is None:
            self.sequences = open_sequences(self.config)
        items = sample_items(self.config, self.start + index)
        return items, make_batch(self.config, items[self.rank::self.world], self.sequences, self.cache)


def _as_is(batch):
    return batch


def _distributed() -> tuple[int, int, bool]:
    """(rank, world size, whether this call created the process group)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    created = False
    if world > 1 and not dist.is_initialized():
        dist.init_process_group("gloo")
        created = True
    if dist.is_initialized():
        return dist.get_rank(), dist.get_world_size(), created
    return 0, 1, False


def load_network(path: str | Path, network_class, config_class):
    """The network a checkpoint holds (``network_class(config_class(**model_config))``, eval mode); shared
    with the infilling trainer."""
    state = torch.load(Path(path), map_location="cpu", weights_only=False)
    model = network_class(core_config.config_from_dict(config_class, state["model_config"]))
    model.load_state_dict(state["model"])
    return model.eval()


def load_model(path: str | Path) -> Flow3D:
    """The ``Flow3D`` saved in a checkpoint (eval mode)."""
    return load_network(path, Flow3D, Flow3DConfig)


def save_checkpoint(path: Path, model: torch.nn.Module, optimizer, step: int, config) -> None:
    """Atomic ``checkpoint.pt``: model and optimiser state, step, ``config.model`` and ``config`` as dicts
    (any training config with a nested ``model`` dataclass; the infilling trainer uses it too)."""
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "model_config": dataclasses.asdict(config.model), "config": dataclasses.asdict(config)}, tmp)
    tmp.replace(path)


def restore_checkpoint(path: Path, model: torch.nn.Module, optimizer, model_config) -> int:
    """Load a ``save_checkpoint`` file into ``model`` and ``optimizer`` and return its step; InputError when
    it was trained with another network config than ``model_config`` (a dataclass)."""
    state = torch.load(path, map_location="cpu", weights_only=False)
    if state["model_config"] != dataclasses.asdict(model_config):
        raise InputError("was trained with another network config; use a new out_dir", file=path,
                         field="model_config")
    model.load_state_dict(state["model"])
    optimizer.load_state_dict(state["optimizer"])
    return int(state["step"])


def train(config: TrainFlowConfig, progress: bool = True, resume: bool = False) -> Path:
    """Train ``Flow3D`` unsupervised (Eq. 6.12) and return the path of ``checkpoint.pt``.

    Args:
        config: everything that defines the run; saved as ``config.json`` in ``config.out_dir``.
        progress: show a tqdm bar (rank 0).
        resume: continue from ``checkpoint.pt`` if present (its network config must match).
    """
    if not isinstance(config, TrainFlowConfig):
        raise InputError(f"must be a TrainFlowConfig, got {type(config).__name__}", field="config")
    rank, world, created = _distributed()
    try:
        return _train(config, progress, resume, rank, world)
    finally:
        if created:
            dist.destroy_process_group()


def _train(config: TrainFlowConfig, progress: bool, resume: bool, rank: int, world: int) -> Path:
    if (config.batch_size // config.crops_per_pair) % world:
        raise InputError(f"the {config.batch_size // config.crops_per_pair} frame pairs per step (batch_size / "
                         f"crops_per_pair) do not divide among {world} processes", field="batch_size")
    torch.set_num_threads(config.threads)
    out = Path(config.out_dir)
    ckpt_path = out / CHECKPOINT
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / CONFIG).write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
        prepare_data(config, progress=progress)
    if world > 1:
        dist.barrier()

    torch.manual_seed(config.seed)
    device = torch.device(config.device)
    model = Flow3D(config.model).to(device)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr, betas=tuple(config.betas))
    start = 0
    if resume and ckpt_path.exists():
        start = restore_checkpoint(ckpt_path, model, optimizer, config.model)
    elif config.init_from:
        source = load_model(config.init_from)
        if source.config != model.config:
            raise InputError(f"holds a network of config {source.config}, this run trains {model.config}",
                             file=config.init_from, field="init_from")
        model.load_state_dict(source.state_dict())
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model)
    model.train()

    bar = None
    if progress and rank == 0:
        bar = tqdm(total=config.steps, initial=start, desc="flow3d", unit="step")
    metrics = (out / METRICS).open("a") if rank == 0 else None
    batches = StepBatches(config, start, rank, world)
    if config.workers:
        loader = iter(torch.utils.data.DataLoader(batches, batch_size=None, shuffle=False,
                                                  num_workers=config.workers, collate_fn=_as_is))
    else:
        loader = (batches[i] for i in range(len(batches)))
    try:
        for step in range(start, config.steps):
            t0 = time.perf_counter()
            items, (mpi_n, mpi_p, gt_flow, init, target) = next(loader)
            mine = items[rank::world]
            t1 = time.perf_counter()
            on_device = [Mpi(*(t.to(device) for t in mpi)) for mpi in (mpi_n, mpi_p)]
            flow = net(*on_device, None if init is None else init.to(device))
            loss, terms = flow_loss(*on_device, flow, config.loss)
            loss = loss * config.unsupervised_weight
            if target is not None:
                terms["supervised"] = supervised_loss(flow, on_device[0], target.to(device))
                loss = loss + config.supervised_weight * terms["supervised"]
            optimizer.zero_grad(set_to_none=True)
            loss.mean().backward()
            optimizer.step()
            done = step + 1
            if rank == 0:
                if done % config.log_every == 0 or done == config.steps:
                    ks = [item["k"] for item in mine for _ in item.get("picked", [None])]
                    epe, epe_zero = _moving_epe(flow.detach().cpu(), mpi_n, gt_flow, ks)
                    record = {"step": done, "loss": float(loss.detach().mean()), "epe_moving": epe,
                              "epe_moving_zero_flow": epe_zero,
                              **{name: float(value.detach().mean()) for name, value in terms.items()},
                              "data_s": round(t1 - t0, 4), "step_s": round(time.perf_counter() - t0, 4),
                              "items": items}
                    metrics.write(json.dumps(record) + "\n")
                    metrics.flush()
                if done % config.checkpoint_every == 0 or done == config.steps:
                    save_checkpoint(ckpt_path, model, optimizer, done, config)
                if bar is not None:
                    bar.update(1)
                    bar.set_postfix(loss=f"{float(loss.detach().mean()):.4f}")
            if world > 1 and (done % config.checkpoint_every == 0 or done == config.steps):
                dist.barrier()
    finally:
        if bar is not None:
            bar.close()
        if metrics is not None:
            metrics.close()
    if rank == 0 and start >= config.steps and not ckpt_path.exists():
        save_checkpoint(ckpt_path, model, optimizer, start, config)
    if world > 1:
        # Drop the DDP reducer (it holds the process group and gloo work objects) before the group is
        # destroyed, and let every rank get here first: a rank whose peer has already hung up while gloo
        # still owns pending work aborts with "terminate called without an active exception".
        del net
        gc.collect()
        dist.barrier()
    return ckpt_path


DESCRIPTION = "Train the DeCOMPnet 3D flow network (unsupervised, thesis Eq. 6.8-6.12) on procedural scenes."


def build_parser(prog: str = "python -m models.flow.train") -> argparse.ArgumentParser:
    """One ``--option`` per field of ``TrainFlowConfig`` (the network's fields as ``--model.name``, the loss's
    as ``--loss.name``; tuples comma-separated, e.g. ``--scene-seeds 1,2,3``), plus ``--config FILE`` (a
    ``config.json`` as ``train`` writes it; options given on the command line override it), ``--resume`` and
    ``--no-progress`` (``models.trainer_cli``)."""
    return trainer_parser(TrainFlowConfig, prog, DESCRIPTION)


def config_from_args(args: argparse.Namespace) -> TrainFlowConfig:
    """The run's config: ``args.config``'s file (if any; else the defaults) with the options given on the
    command line set."""
    return trainer_config(TrainFlowConfig, args)


def main(argv: Optional[list[str]] = None, prog: str = "python -m models.flow.train") -> None:
    """Command line of ``train`` (``interleave train flow`` calls this); see ``build_parser``."""
    trainer_main(argv, prog, DESCRIPTION, TrainFlowConfig, train)


if __name__ == "__main__":
    main()
