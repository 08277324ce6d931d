"""Train the disocclusion infilling network (thesis Sec. 6.3.4): MSE of the infilled frame against the truth.

Data (``make_samples``; numpy, the engine's own functions): for a scene of ``engine.scenegen`` and frames
n, n + k' (k' in 1..``max_step``), frame n is splatted into frame n + k''s camera with the TRUE object
motion (``engine.predict.base.true_object_flow``; camera and objects, as the ``oracle``), so its holes are
real disocclusions and frame n + k' is the truth there. The splatted frame is block-downsampled to the
working width (``engine.predict.decomp.infill.downsample_holes``), the truth likewise (``geometry.downsample_frame``),
and crops with the most holes are kept, each with its prior vectors computed on the crop
(``engine.predict.decomp.infill.prior_vectors``) and frame n's plane depths. Samples depend on (seed, scene) only.

Training: batches of crops, one infilling pass (``models.infill.network.infill``; bilinear copies by default,
``sample_mode``), loss
``infill_loss`` on the hole pixels; Adam. ``metrics.jsonl`` logs the loss next to the loss of the prior
vectors alone (the untrained network = the simple fill) on the same batch, and on held-out scenes with
the engine's nearest-point copy. ``config.json``, an atomic ``checkpoint.pt`` (resumable) and ``best.pt``
(lowest held-out loss, the untrained network = the prior included) go to ``out_dir``. ``interleave train infill`` is this module's command line.
"""
from __future__ import annotations

import dataclasses
import json
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import numpy as np
import torch
from tqdm import tqdm

from engine import geometry
from engine.core.config import option
from engine.core.errors import InputError
from engine.io.rgbd import read_sequence
from engine.predict import true_object_flow
from engine.predict.decomp.gate import encode_color
from engine.predict.decomp.infill import candidate_vectors, downsample_holes, hole_mpi, prior_vectors
from models.flow.train import load_network, render_scenes, restore_checkpoint, save_checkpoint
from models.geometry import Mpi
from models.infill.network import (InfillConfig, InfillNet, apply_vectors, choice_loss, infill, infill_inputs,
                                   infill_loss)
from models.trainer_cli import trainer_main

__all__ = ["TrainInfillConfig", "make_samples", "batch_tensors", "choice_tensors", "candidate_errors", "train",
           "load_model", "evaluate_samples", "main"]

CHECKPOINT, CONFIG, METRICS = "checkpoint.pt", "config.json", "metrics.jsonl"
#: the checkpoint with the lowest held-out loss so far (step 0, the prior alone, included)
BEST = "best.pt"


@dataclass(frozen=True)
class TrainInfillConfig:
    """Everything that defines an infilling training run (saved as ``config.json`` beside the checkpoint)."""

    out_dir: str = option("runs/infill", "output folder (config.json, checkpoint.pt, metrics.jsonl)")
    data_dir: str = option("runs/flow_data", "rgbd-seq scenes, rendered there if missing (shared with the "
                                             "flow network's training data)")
    seed: int = option(0, "seed of the torch initialisation and of the sample draw")
    steps: int = option(2000, "optimiser steps")
    batch_size: int = option(16, "crops per step")
    crop: int = option(64, "crop size in working-resolution pixels (a multiple of the U-Net stride)")
    downsample: int = option(4, "block size from the scene resolution to the working resolution (960 -> 240: "
                                   "the network runs at 240 px wide in the engine too)")
    lr: float = option(1e-3, "Adam learning rate")
    scene_seeds: tuple[int, ...] = option(tuple(range(5000, 5030)), "training scenes (engine.scenegen seeds)")
    val_seeds: tuple[int, ...] = option((5030, 5031), "held-out scenes for the logged validation loss")
    scene_width: int = option(960, "scene width (pixels) when rendering missing scenes")
    scene_height: int = option(540, "scene height")
    scene_frames: int = option(12, "frames per scene")
    samples_per_scene: int = option(16, "frame pairs (n, n + k') drawn per scene")
    max_step: int = option(4, "largest k' (frames past n)")
    crop_candidates: int = option(6, "random crops per pair, of which those with the most holes are kept")
    crops_per_sample: int = option(2, "crops kept per pair")
    sample_mode: str = option("bilinear", "how training copies along the vectors: 'bilinear' (blends four "
                                          "points) or 'straight_through' (the nearest point, as the engine, with "
                                          "bilinear gradients; diverged here: held-out loss 25-40x the prior's)")
    choice_objective: str = option("weighted_ce", "loss of a choice head (models.infill.network.choice_loss): "
                                                  "'weighted_ce' or 'expected' (collapsed onto the prior here)")
    threads: int = option(1, "torch threads (1: with 2, backward ran 20x slower here when another process "
                                "shared the machine)")
    log_every: int = option(25, "steps between metrics.jsonl records")
    val_every: int = option(200, "steps between held-out evaluations")
    checkpoint_every: int = option(200, "steps between checkpoints")
    model: InfillConfig = field(default_factory=InfillConfig, metadata={"help": "network config"})

    def __post_init__(self) -> None:
        stride = self.model.stride
        checks = [
            (self.steps >= 1 and self.batch_size >= 1 and self.lr > 0, "steps, batch_size >= 1 and lr > 0"),
            (self.crop >= stride and self.crop % stride == 0, f"crop must be a positive multiple of {stride}"),
            (self.downsample >= 1 and self.max_step >= 1, "downsample and max_step must be >= 1"),
            (self.scene_frames > self.max_step, "scene_frames must exceed max_step"),
            (self.crop * self.downsample <= min(self.scene_width, self.scene_height), "crop larger than the scenes"),
            (self.crops_per_sample <= self.crop_candidates, "crops_per_sample must be <= crop_candidates"),
            (len(self.scene_seeds) >= 1, "needs at least one scene seed"),
            (self.sample_mode in ("bilinear", "straight_through"), "sample_mode: 'bilinear' or 'straight_through'"),
            (self.choice_objective in ("weighted_ce", "expected"), "choice_objective: 'weighted_ce' or 'expected'"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="TrainInfillConfig")


# ----------------------------------------------------------------------------------------------------
# Data


def make_samples(config: TrainInfillConfig, seeds, *, progress: bool = False) -> list[dict]:
    """Training crops of the scenes ``seeds`` (see the module docstring), each a dict of numpy arrays:
    ``color`` (h, w, 3), ``depth`` (h, w) (+inf in holes), ``holes`` (h, w), ``prior`` (2, h, w), ``truth``
    (h, w, 3), ``planes`` (Z,), plus ``scene``, ``n``, ``step`` and the crop corner."""

    paths = render_scenes(config.data_dir, seeds, config.scene_width, config.scene_height, config.scene_frames,
                          progress=progress)
    f, size, z = config.downsample, config.crop, config.model.num_planes
    out = []
    for seed, path in tqdm(list(zip(seeds, paths)), desc="infill data", disable=not progress, unit="scene"):
        seq = read_sequence(path)
        objects = {o.id: o for o in seq.objects}
        rng = np.random.default_rng([config.seed, int(seed)])
        for _ in range(config.samples_per_scene):
            step = int(rng.integers(1, config.max_step + 1))
            n = int(rng.integers(0, len(seq) - step))
            frame, target = seq[n], seq[n + step]
            flow = true_object_flow(frame, objects, n + step) if objects else None
            src, dst = frame.camera, target.camera
            color, depth, holes = geometry.forward_warp_frame(frame.color, frame.depth, src.intrinsics,
                                                              src.world_to_camera, dst.intrinsics,
                                                              dst.world_to_camera, flow)
            low_c, low_d, low_h = downsample_holes(color, depth, holes, f)
            truth = geometry.downsample_frame(target.color, target.depth, dst.intrinsics, f)[0]
            planes = geometry.plane_depths(geometry.downsample_frame(frame.color, frame.depth, src.intrinsics,
                                                                     f)[1], z)
            h, w = low_h.shape
            corners = [(int(rng.integers(0, h - size + 1)), int(rng.integers(0, w - size + 1)))
                       for _ in range(config.crop_candidates)]
            counts = [int(low_h[y:y + size, x:x + size].sum()) for y, x in corners]
            for i in np.argsort(counts)[::-1][:config.crops_per_sample]:
                y, x = corners[i]
                if counts[i] == 0 or counts[i] == size * size:
                    continue  # nothing to learn from: no hole, or nothing known to copy from
                crop = (slice(y, y + size), slice(x, x + size))
                hc, dc = low_h[crop], low_d[crop]
                sample = {"color": low_c[crop], "depth": dc, "holes": hc, "prior": prior_vectors(dc, hc),
                          "truth": truth[crop], "planes": planes, "scene": int(seed), "n": n, "step": step,
                          "corner": (y, x)}
                if config.model.head == "choice":
                    sample["candidates"] = candidate_vectors(dc, hc)
                    sample["errors"] = candidate_errors(low_c[crop], hc, sample["candidates"], truth[crop])
                out.append(sample)
    return out


def candidate_errors(color: np.ndarray, holes: np.ndarray, candidates: np.ndarray,
                     truth: np.ndarray) -> np.ndarray:
    """(K, h, w) float32 squared error (encoded colour, channel mean, as ``infill_loss``) of copying each
    candidate's source pixel into each hole pixel; 0 at known pixels. ``candidates`` (2 K, h, w)."""

    rows, cols = np.indices(holes.shape)
    enc, target = encode_color(color), encode_color(truth)
    h, w = holes.shape
    out = []
    for dx, dy in candidates.reshape(-1, 2, h, w):
        sy = np.clip(np.rint(rows + dy).astype(np.int64), 0, h - 1)
        sx = np.clip(np.rint(cols + dx).astype(np.int64), 0, w - 1)
        src = np.where(holes[sy, sx][..., None], np.float32(0.0), enc[sy, sx])  # a hole source copies nothing
        out.append(np.where(holes, ((src - target) ** 2).mean(axis=-1), np.float32(0.0)))
    return np.stack(out).astype(np.float32)


def choice_tensors(samples: list[dict]) -> tuple[Mpi, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(MPI, holes, candidate vectors (B, 2 K, h, w), candidate errors (B, K, h, w)) for the choice head."""
    mpi, holes, _, _ = batch_tensors(samples)
    cand = torch.from_numpy(np.stack([s["candidates"] for s in samples]))
    errors = torch.from_numpy(np.stack([s["errors"] for s in samples]))
    return mpi, holes, cand, errors


def _masked_mean(err: torch.Tensor, holes: torch.Tensor) -> torch.Tensor:
    mask = holes.to(err.dtype)
    return (err * mask).sum(dim=(1, 2)) / mask.sum(dim=(1, 2)).clamp(min=1.0)


def batch_tensors(samples: list[dict]) -> tuple[Mpi, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(MPI (B, ...), holes (B, h, w) bool, prior (B, 2, h, w), truth (B, h, w, 3)) of a list of crops; the
    MPIs are built by ``engine.predict.decomp.infill.hole_mpi``, the function the engine uses."""

    mpis = [hole_mpi(s["color"], s["depth"], s["holes"], s["planes"]) for s in samples]
    mpi = Mpi(torch.from_numpy(np.stack([m.color for m in mpis])),
              torch.from_numpy(np.stack([m.depth for m in mpis]))[:, None],
              torch.from_numpy(np.stack([m.alpha for m in mpis]))[:, None],
              torch.from_numpy(np.stack([np.asarray(m.plane_depths, np.float32) for m in mpis])))
    holes = torch.from_numpy(np.stack([s["holes"] for s in samples]))
    prior = torch.from_numpy(np.stack([s["prior"] for s in samples]))
    truth = torch.from_numpy(np.stack([s["truth"] for s in samples]).astype(np.float32))
    return mpi, holes, prior, truth


def evaluate_samples(net: Optional[InfillNet], samples: list[dict], mode: str = "nearest",
                     batch: int = 16) -> float:
    """Mean ``infill_loss`` over ``samples`` after one pass (``net=None``: the prior vectors alone); for a
    choice head (samples with ``errors``): the mean error of the arg-max candidate, as the engine copies."""
    losses = []
    with torch.no_grad():
        for i in range(0, len(samples), batch):
            if "errors" in samples[i] and (net is None or net.config.head == "choice"):
                mpi, holes, cand, errors = choice_tensors(samples[i:i + batch])
                pick = (torch.zeros_like(errors[:, :1], dtype=torch.long) if net is None else
                        net(infill_inputs(mpi, holes, cand)).argmax(dim=1, keepdim=True))
                losses.append(_masked_mean(errors.gather(1, pick)[:, 0], holes))
                continue
            mpi, holes, prior, truth = batch_tensors(samples[i:i + batch])
            if net is None:
                filled, _ = apply_vectors(mpi, holes, prior[:, :, None].expand(-1, -1, mpi.alpha.shape[2], -1, -1),
                                          mode)
            else:
                filled, _ = infill(net, mpi, holes, prior, mode)
            losses.append(infill_loss(filled, holes, truth))
    return float(torch.cat(losses).mean()) if losses else float("nan")


# ----------------------------------------------------------------------------------------------------
# Training


def load_model(path: str | Path) -> InfillNet:
    """The ``InfillNet`` saved in a checkpoint (eval mode)."""

    return load_network(path, InfillNet, InfillConfig)


def train(config: TrainInfillConfig, progress: bool = True, resume: bool = False) -> Path:
    """Train ``InfillNet`` and return the path of ``checkpoint.pt`` (see the module docstring)."""

    if not isinstance(config, TrainInfillConfig):
        raise InputError(f"must be a TrainInfillConfig, got {type(config).__name__}", field="config")
    torch.set_num_threads(config.threads)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    (out / CONFIG).write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
    ckpt = out / CHECKPOINT
    train_samples = make_samples(config, config.scene_seeds, progress=progress)
    val_samples = make_samples(config, config.val_seeds, progress=progress) if config.val_seeds else []
    if not train_samples:
        raise InputError("the scenes gave no crop with holes to learn from", field="scene_seeds")
    torch.manual_seed(config.seed)
    net = InfillNet(config.model)
    optimizer = torch.optim.Adam(net.parameters(), lr=config.lr)
    start = 0
    if resume and ckpt.exists():
        start = restore_checkpoint(ckpt, net, optimizer, config.model)
    metrics = (out / METRICS).open("a")
    bar = None
    if progress:
        bar = tqdm(total=config.steps, initial=start, desc="infill", unit="step")
    val_prior = evaluate_samples(None, val_samples) if val_samples else float("nan")
    best_val = float("inf")
    if val_samples and not (out / BEST).exists():  # step 0 (the prior alone) is the first candidate
        best_val = val_prior
        save_checkpoint(out / BEST, net, optimizer, start, config)
    elif (out / BEST).exists():
        best_val = min((json.loads(line).get("val_loss", float("inf"))
                        for line in (out / METRICS).read_text().splitlines() if line.strip()), default=float("inf"))
    try:
        for step in range(start, config.steps):
            t0 = time.perf_counter()
            rng = np.random.default_rng([config.seed, 7, step])
            picked = rng.choice(len(train_samples), size=min(config.batch_size, len(train_samples)), replace=False)
            chosen = [train_samples[i] for i in picked]
            net.train()
            if config.model.head == "choice":
                mpi, holes, cand, errors = choice_tensors(chosen)
                loss = choice_loss(net(infill_inputs(mpi, holes, cand)), errors, holes, config.choice_objective).mean()
            else:
                mpi, holes, prior, truth = batch_tensors(chosen)
                filled, _ = infill(net, mpi, holes, prior, config.sample_mode)
                loss = infill_loss(filled, holes, truth).mean()
            optimizer.zero_grad(set_to_none=True)
            loss.backward()
            optimizer.step()
            done = step + 1
            if done % config.log_every == 0 or done == config.steps:
                with torch.no_grad():
                    if config.model.head == "choice":
                        base_loss = float(_masked_mean(errors[:, 0], holes).mean())
                    else:
                        z = mpi.alpha.shape[2]
                        base, _ = apply_vectors(mpi, holes, prior[:, :, None].expand(-1, -1, z, -1, -1), "nearest")
                        base_loss = float(infill_loss(base, holes, truth).mean())
                record = {"step": done, "loss": float(loss.detach()), "loss_prior_only": base_loss,
                          "step_s": round(time.perf_counter() - t0, 4), "samples": [int(i) for i in picked]}
                if val_samples and (done % config.val_every == 0 or done == config.steps):
                    net.eval()
                    record.update(val_loss=evaluate_samples(net, val_samples), val_loss_prior_only=val_prior)
                    if record["val_loss"] < best_val:  # the export takes best.pt: the lowest held-out loss
                        best_val = record["val_loss"]
                        save_checkpoint(out / BEST, net, optimizer, done, config)
                metrics.write(json.dumps(record) + "\n")
                metrics.flush()
            if done % config.checkpoint_every == 0 or done == config.steps:
                save_checkpoint(ckpt, net, optimizer, done, config)
            if bar is not None:
                bar.update(1)
                bar.set_postfix(loss=f"{float(loss.detach()):.5f}")
    finally:
        metrics.close()
        if bar is not None:
            bar.close()
    if start >= config.steps and not ckpt.exists():
        save_checkpoint(ckpt, net, optimizer, start, config)
    return ckpt


def main(argv: Optional[list[str]] = None, prog: str = "python -m models.infill.train") -> None:
    """Command line of ``train`` (``interleave train infill`` calls this): one ``--option`` per field of
    ``TrainInfillConfig`` (the network's as ``--model.name``), ``--config FILE``, ``--resume``, ``--no-progress``."""
    trainer_main(argv, prog, "Train the DeCOMPnet disocclusion infilling network (thesis Sec. 6.3.4) on "
                             "procedural scenes.", TrainInfillConfig, train)


if __name__ == "__main__":
    main()
