"""Unsupervised training of the 3D flow network on procedural scenes (thesis Sec. 6.3.3, 6.4).

Training pairs come from ``engine.scenegen``: each scene seed is rendered once into an rgbd-seq under
``<out_dir>/data/scene_<seed>`` (its ``scenegen_config.json`` records how). A step draws, from a random
stream seeded by ``(seed, step)``, ``batch_size`` items ``(scene, k, n, crop)``: frames n and n-k are
turned into ``m_n`` and ``m^w_{n-k}`` at full size (``models.flow3d.mpi_pair``: MPIs with
``models.geometry``, camera motion cancelled by ``forward_warp_mpi``), then cropped. The loss is
``models.losses.flow_loss`` (Eq. 6.12); ground-truth flow is never used for training, only by
``endpoint_error`` for reporting.

Outputs in ``out_dir``: ``config.json`` (the ``TrainFlowConfig``), ``checkpoint.pt`` (model, optimiser,
step; written every ``checkpoint_every`` steps and at the end), ``metrics.jsonl`` (one line per logged
step, with the items drawn). ``train(config, resume=True)`` continues from ``checkpoint.pt``; because the
data of a step depend only on ``(seed, step)`` and the optimiser state is saved, the result equals an
uninterrupted run's (same thread count).

Data parallel: launched under ``torchrun`` (``WORLD_SIZE`` > 1), ranks join a gloo process group, each
takes every ``world_size``-th item of the step's batch, and DistributedDataParallel averages gradients,
so the update equals the single-process one. Only rank 0 writes files.

>>> train(TrainFlowConfig(out_dir="runs/flow3d", steps=10000))      # doctest: +SKIP
>>> # torchrun --standalone --nproc_per_node 2 -m models.train_flow --out-dir runs/flow3d --steps 10000
"""
from __future__ import annotations

import argparse
import dataclasses
import json
import os
import time
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch
import torch.distributed as dist
from torch import Tensor

from engine.config import option
from engine.errors import InputError
from engine.geometry import check_shape
from models.flow3d import Flow3D, Flow3DConfig, mpi_pair
from models.geometry import Mpi
from models.losses import FlowLossConfig, flow_loss

__all__ = ["TrainFlowConfig", "train", "load_model", "endpoint_error", "sample_items", "make_batch",
           "prepare_data", "config_from_dict"]

CHECKPOINT = "checkpoint.pt"
CONFIG = "config.json"
METRICS = "metrics.jsonl"



@dataclass(frozen=True)
class TrainFlowConfig:
    """What and how to train. Defaults follow the thesis (256x256 crops, batch 4, Adam 1e-4 (0.9, 0.999))."""

    out_dir: str = option("runs/flow3d", "folder for config.json, checkpoint.pt, metrics.jsonl and data/")
    seed: int = option(0, "seed of the weights and of the data drawn at every step")
    steps: int = option(10000, "optimiser steps")
    batch_size: int = option(4, "pairs per step, over all processes (divisible by the number of processes)")
    crop: int = option(256, "square crop size in pixels (a multiple of 16 avoids internal padding)")
    lr: float = option(1e-4, "Adam learning rate")
    betas: tuple[float, float] = option((0.9, 0.999), "Adam betas")
    k_values: tuple[int, ...] = option((1, 2, 4), "frame gaps k of the pairs (m_n, m_{n-k}), drawn uniformly")
    scene_seeds: tuple[int, ...] = option(tuple(range(1000, 1032)), "engine.scenegen seeds of the training scenes")
    scene_width: int = option(640, "rendered scene width")
    scene_height: int = option(360, "rendered scene height")
    scene_frames: int = option(12, "frames rendered per scene (the thesis' sequences have 12)")
    threads: int = option(2, "torch intra-op threads per process")
    checkpoint_every: int = option(500, "save checkpoint.pt every this many steps (and at the end)")
    log_every: int = option(10, "append to metrics.jsonl every this many steps")
    model: Flow3DConfig = field(default_factory=Flow3DConfig,
                                metadata={"help": "network hyper-parameters (num_planes, mode, channels, ranges)"})
    loss: FlowLossConfig = field(default_factory=FlowLossConfig, metadata={"help": "loss weights (Eq. 6.8-6.12)"})

    def __post_init__(self) -> None:
        checks = [
            (self.steps >= 0 and self.batch_size >= 1, "steps must be >= 0 and batch_size >= 1"),
            (self.crop >= 1, "crop must be >= 1"),
            (self.crop <= min(self.scene_width, self.scene_height), "crop must fit in the scene size"),
            (self.lr > 0 and all(0.0 <= b < 1.0 for b in self.betas), "lr must be > 0, betas in [0, 1)"),
            (len(self.k_values) >= 1 and all(k >= 1 for k in self.k_values), "k_values must be >= 1"),
            (max(self.k_values) < self.scene_frames, "scene_frames must exceed the largest k"),
            (len(self.scene_seeds) >= 1, "scene_seeds must not be empty"),
            (self.threads >= 1 and self.checkpoint_every >= 1 and self.log_every >= 1,
             "threads, checkpoint_every and log_every must be >= 1"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="TrainFlowConfig")


def config_from_dict(data: dict) -> TrainFlowConfig:
    """Inverse of ``dataclasses.asdict`` for ``TrainFlowConfig`` (lists back to tuples, nested configs)."""
    return _from_dict(TrainFlowConfig, data)


def _from_dict(cls, data: dict):
    hints = typing.get_type_hints(cls)
    kwargs = {}
    for f in dataclasses.fields(cls):
        if f.name not in data:
            continue
        value, hint = data[f.name], hints[f.name]
        if dataclasses.is_dataclass(hint):
            value = _from_dict(hint, value)
        elif typing.get_origin(hint) is tuple:
            value = tuple(value)
        kwargs[f.name] = value
    return cls(**kwargs)


# ----------------------------------------------------------------------------------------------------
# Data


def prepare_data(config: TrainFlowConfig, *, progress: bool = False) -> list[Path]:
    """Render every scene seed that is not cached yet; returns the rgbd-seq folders, one per seed."""
    from engine.scenegen import SceneConfig, generate_sequence

    root = Path(config.out_dir) / "data"
    paths = []
    for seed in config.scene_seeds:
        path = root / f"scene_{seed:06d}"
        if not (path / "sequence.json").exists():
            scene = SceneConfig(seed=seed, width=config.scene_width, height=config.scene_height,
                                num_frames=config.scene_frames)
            generate_sequence(scene, path.with_name(path.name + ".tmp"), progress=progress)
            path.with_name(path.name + ".tmp").rename(path)
        paths.append(path)
    return paths


def sample_items(config: TrainFlowConfig, step: int) -> list[dict]:
    """The ``batch_size`` items of a step: ``{"scene", "k", "n", "y", "x"}``, a function of (seed, step) only."""
    rng = np.random.default_rng([config.seed, step])
    items = []
    for _ in range(config.batch_size):
        k = int(rng.choice(config.k_values))
        items.append({"scene": int(rng.choice(config.scene_seeds)), "k": k,
                      "n": int(rng.integers(k, config.scene_frames)),
                      "y": int(rng.integers(0, config.scene_height - config.crop + 1)),
                      "x": int(rng.integers(0, config.scene_width - config.crop + 1))})
    return items


def _frame_tensors(frame) -> tuple[Tensor, ...]:
    color = torch.from_numpy(np.ascontiguousarray(frame.color))[None]
    depth = torch.from_numpy(np.ascontiguousarray(frame.depth))[None]
    k = torch.from_numpy(frame.camera.intrinsics)[None].float()
    t = torch.from_numpy(frame.camera.world_to_camera)[None].float()
    return color, depth, k, t


def _crop_mpi(mpi: Mpi, y: int, x: int, size: int) -> Mpi:
    def crop(t: Tensor) -> Tensor:
        return t[..., y:y + size, x:x + size]
    return Mpi(crop(mpi.color), crop(mpi.depth), crop(mpi.alpha), mpi.plane_depths)


def make_batch(config: TrainFlowConfig, items: list[dict], sequences: dict) -> tuple[Mpi, Mpi, Tensor]:
    """Crops of ``(m_n, m^w_{n-k})`` for ``items`` and the ground-truth object flow of frame n, (B, c, c, 2).

    ``sequences`` maps scene seed -> ``engine.io.RgbdSequence``. The object flow (frame n -> n+1, pixels)
    is only for evaluation (zeros when the sequence has none).
    """
    firsts, seconds, flows = [], [], []
    for item in items:
        seq = sequences[item["scene"]]
        frame_n, frame_p = seq[item["n"]], seq[item["n"] - item["k"]]
        with torch.no_grad():
            m_n, m_p = mpi_pair(*_frame_tensors(frame_n), *_frame_tensors(frame_p), config.model.num_planes)
        y, x, c = item["y"], item["x"], config.crop
        firsts.append(_crop_mpi(m_n, y, x, c))
        seconds.append(_crop_mpi(m_p, y, x, c))
        gt = frame_n.object_flow if frame_n.object_flow is not None else np.zeros(frame_n.depth.shape + (2,))
        flows.append(torch.from_numpy(np.ascontiguousarray(gt[y:y + c, x:x + c], dtype=np.float32)))

    def stack(mpis: list[Mpi]) -> Mpi:
        return Mpi(*(torch.cat(parts, dim=0) for parts in zip(*mpis)))

    return stack(firsts), stack(seconds), torch.stack(flows)


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


# ----------------------------------------------------------------------------------------------------
# Training


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


def load_model(path: str | Path) -> Flow3D:
    """The ``Flow3D`` saved in a checkpoint (eval mode)."""
    state = torch.load(Path(path), map_location="cpu", weights_only=False)
    config = _from_dict(Flow3DConfig, state["model_config"])
    model = Flow3D(config)
    model.load_state_dict(state["model"])
    return model.eval()


def _save_checkpoint(path: Path, model: Flow3D, optimizer, step: int, config: TrainFlowConfig) -> None:
    tmp = path.with_name(path.name + ".tmp")
    torch.save({"step": step, "model": model.state_dict(), "optimizer": optimizer.state_dict(),
                "model_config": dataclasses.asdict(config.model), "config": dataclasses.asdict(config)}, tmp)
    tmp.replace(path)


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
    if config.batch_size % world:
        raise InputError(f"batch_size {config.batch_size} is not divisible by {world} processes", field="batch_size")
    torch.set_num_threads(config.threads)
    out = Path(config.out_dir)
    ckpt_path = out / CHECKPOINT
    if rank == 0:
        out.mkdir(parents=True, exist_ok=True)
        (out / CONFIG).write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
        prepare_data(config, progress=progress)
    if world > 1:
        dist.barrier()

    from engine.io import read_sequence
    sequences = {seed: read_sequence(out / "data" / f"scene_{seed:06d}") for seed in config.scene_seeds}

    torch.manual_seed(config.seed)
    model = Flow3D(config.model)
    optimizer = torch.optim.Adam(model.parameters(), lr=config.lr, betas=tuple(config.betas))
    start = 0
    if resume and ckpt_path.exists():
        state = torch.load(ckpt_path, map_location="cpu", weights_only=False)
        if state["model_config"] != dataclasses.asdict(config.model):
            raise InputError("was trained with another network config; use a new out_dir", file=ckpt_path,
                             field="model_config")
        model.load_state_dict(state["model"])
        optimizer.load_state_dict(state["optimizer"])
        start = int(state["step"])
    net = model
    if world > 1:
        net = torch.nn.parallel.DistributedDataParallel(model)
    model.train()

    bar = None
    if progress and rank == 0:
        from tqdm import tqdm
        bar = tqdm(total=config.steps, initial=start, desc="flow3d", unit="step")
    metrics = (out / METRICS).open("a") if rank == 0 else None
    try:
        for step in range(start, config.steps):
            t0 = time.perf_counter()
            items = sample_items(config, step)
            mine = items[rank::world]
            mpi_n, mpi_p, _ = make_batch(config, mine, sequences)
            t1 = time.perf_counter()
            flow = net(mpi_n, mpi_p)
            loss, terms = flow_loss(mpi_n, mpi_p, flow, config.loss)
            optimizer.zero_grad(set_to_none=True)
            loss.mean().backward()
            optimizer.step()
            done = step + 1
            if rank == 0:
                if done % config.log_every == 0 or done == config.steps:
                    record = {"step": done, "loss": float(loss.detach().mean()),
                              **{name: float(value.detach().mean()) for name, value in terms.items()},
                              "data_s": round(t1 - t0, 4), "step_s": round(time.perf_counter() - t0, 4),
                              "items": items}
                    metrics.write(json.dumps(record) + "\n")
                    metrics.flush()
                if done % config.checkpoint_every == 0 or done == config.steps:
                    _save_checkpoint(ckpt_path, model, optimizer, done, config)
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
        _save_checkpoint(ckpt_path, model, optimizer, start, config)
    return ckpt_path


def main(argv: Optional[list[str]] = None) -> None:
    """``python -m models.train_flow`` (or under ``torchrun``): one ``--option`` per field of
    ``TrainFlowConfig``, ``Flow3DConfig`` and ``FlowLossConfig`` (``engine.cli.add_dataclass_options``;
    tuples comma-separated, e.g. ``--scene-seeds 1,2,3 --num-planes 4 --beta 0.15``)."""
    from engine.cli import add_dataclass_options

    parser = argparse.ArgumentParser(prog="python -m models.train_flow",
                                     description="Train the DeCOMPnet 3D flow network (unsupervised).")
    add_dataclass_options(parser, TrainFlowConfig, skip=("model", "loss"))
    add_dataclass_options(parser, Flow3DConfig)
    add_dataclass_options(parser, FlowLossConfig)
    parser.add_argument("--resume", action="store_true", help="continue from out_dir/checkpoint.pt")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = vars(parser.parse_args(argv))

    def pick(cls) -> dict:
        return {f.name: args[f.name] for f in dataclasses.fields(cls) if f.name in args}

    config = TrainFlowConfig(**{k: v for k, v in pick(TrainFlowConfig).items() if k not in ("model", "loss")},
                             model=Flow3DConfig(**pick(Flow3DConfig)), loss=FlowLossConfig(**pick(FlowLossConfig)))
    train(config, progress=not args["no_progress"], resume=args["resume"])


if __name__ == "__main__":
    main()
