"""Supervised training of ``models.flow.corrflow.CorrFlow`` on the scene generator's exact object motion.

``interleave train corrflow [--steps 4000] [--seed 0] [--out runs/corrflow]`` (or ``python -m
models.flow.corrflow_train``) renders the training scenes not cached yet (``TrainCorrFlowConfig.scenes``:
preset, first seed, count; 960 x 540, 12 frames, into ``runs/flow_data`` as ``models.flow.train`` does),
builds the training pairs once, then trains. A pair is, for a scene, a k of ``ks`` and a frame n >= k:
frame n and frame n-k warped into frame n's view with its holes filled (what ``flow2d`` matches:
``engine.predict.base.warp_and_fill``), both display-encoded to 8 bits, their depths as 8-bit depth codes
(``engine.predict.corrflow.network_depth``; read by a network with ``model.depth``), and the true
u(n -> n-k) (``engine.predict.base.true_object_flow``), all resized to the working width (flow
area-averaged and scaled). Training is a function of the seed only (pairs, crops, flips and gains drawn from ``numpy``
generators seeded per step).
"""
from __future__ import annotations

import argparse
import json
import multiprocessing
import sys
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Optional

import cv2
import numpy as np
import torch

from engine.core.errors import InputError
from engine.io.rgbd import read_sequence
from engine.core.config import config_to_dict
from engine.predict.base import Target, Timer, true_object_flow, warp_fill_depth
from engine.predict.corrflow import depth_reference, network_depth, network_image, working_size
from models.flow.corrflow import CorrFlow, CorrFlowConfig
from models.trainer_cli import DEVICES, resolve_device

__all__ = ["TRAIN_SCENES", "PAIR_KEYS", "build_pairs", "build_all_pairs", "extra_pairs", "prepare_pairs",
           "TrainCorrFlowConfig", "load_start_weights", "train", "main"]


#: truth larger than this (working-resolution pixels) is not supervised: points near the camera plane of
#: frame n-k project to huge (or, in float16, infinite) displacements
MAX_TRUTH = 400.0


#: arrays of a pair file; a file without one of them (an older cache) is built again
PAIR_KEYS = ("a", "b", "da", "db", "flow", "k", "n")


def build_pairs(scene: Path, out: Path, ks=(1, 2, 4), net_width: int = 512) -> Path:
    """The pairs of one scene folder as ``out/<scene>.npz`` (``a``, ``b``: (P, h, w, 3) uint8 colours of frame
    n and of the camera-compensated frame n-k; ``da``, ``db``: (P, h, w) uint8 their depth codes against
    frame n's median depth; ``flow``: (P, h, w, 2) float16 working-resolution pixels; ``k``, ``n``: (P,)),
    written once."""
    path = out / f"{scene.name}.npz"
    if path.exists():
        with np.load(path) as existing:
            if set(PAIR_KEYS) <= set(existing.files):
                return path
    seq = read_sequence(scene)
    objects = {o.id: o for o in seq.objects}
    h0, w0 = seq[0].depth.shape
    w, h = working_size(w0, h0, net_width)
    a, b, da, db, flows, kk, nn_ = [], [], [], [], [], [], []
    for k in ks:
        for n in range(k, len(seq)):
            older, newest = seq[n - k], seq[n]
            warped, depth_w, _ = warp_fill_depth(older, Target(newest.camera, newest.time, newest.index), Timer())
            reference = depth_reference(newest.depth)
            truth = true_object_flow(newest, objects, n - k)[..., :2] if objects else np.zeros((h0, w0, 2), np.float32)
            truth = np.where(np.abs(truth) < 4 * MAX_TRUTH, truth, np.nan).astype(np.float32)
            truth = cv2.resize(np.ascontiguousarray(truth), (w, h), interpolation=cv2.INTER_AREA)
            truth *= np.array([w / w0, h / h0], np.float32)
            a.append(network_image(newest.color, (w, h)))
            b.append(network_image(warped, (w, h)))
            da.append(network_depth(newest.depth, reference, (w, h)))
            db.append(network_depth(depth_w, reference, (w, h)))
            flows.append(truth.astype(np.float16))
            kk.append(k)
            nn_.append(n)
    out.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(".tmp.npz")
    np.savez(tmp, a=np.stack(a), b=np.stack(b), da=np.stack(da), db=np.stack(db), flow=np.stack(flows),
             k=np.array(kk), n=np.array(nn_))
    tmp.rename(path)
    return path


#: (preset, first seed, count) of the training scenes: seeds 5000-5039, apart from every evaluation seed
TRAIN_SCENES = (("fast", 5000, 16), ("extreme", 5016, 8), ("medium", 5024, 8), ("gentle", 5032, 8))


@dataclass
class TrainCorrFlowConfig:
    """``net_width``: the working width of the pairs (the engine resizes frames to it); ``ks``: frame
    distances of the pairs; ``crop_candidates``: random crops drawn per sample, the one with the most moving
    pixels kept."""

    data_dir: str = "runs/flow_data"
    pairs: str = "runs/corrflow/pairs"
    out_dir: str = "runs/corrflow"
    scenes: tuple = TRAIN_SCENES
    net_width: int = 512
    ks: tuple = (1, 2, 4)
    seed: int = 0
    steps: int = 4000
    batch_size: int = 4
    crop: tuple = (224, 320)
    crop_candidates: int = 4
    lr: float = 2e-4
    weight_decay: float = 1e-5
    gamma: float = 0.8
    threads: int = 2
    log_every: int = 25
    checkpoint_every: int = 250
    model: CorrFlowConfig = field(default_factory=CorrFlowConfig)
    #: a folder of further rgbd-seq folders with object ids and transforms (e.g. imported Cycles renders,
    #: ``tools/cycles_scene.py``), their pairs cached in ``extra_pairs(config)``, drawn for a sample with
    #: probability ``extra_share``
    extra_data: str = ""
    extra_share: float = 0.0
    #: a checkpoint whose model weights start the run (fine-tuning); "" starts from a seeded initialisation
    init_from: str = ""
    #: where the model trains (``models.trainer_cli.DEVICES``: auto, cpu, cuda); batches are drawn on the CPU
    device: str = "cpu"
    #: processes that build the training pairs of the rendered scenes (one scene each)
    workers: int = 1

    def __post_init__(self) -> None:
        crop = tuple(self.crop)
        checks = [
            (self.net_width >= 8, f"net_width must be >= 8, got {self.net_width}"),
            (len(crop) == 2 and all(isinstance(v, int) and v >= 8 and v % 8 == 0 for v in crop),
             f"crop must be two positive multiples of 8 (height, width), got {self.crop}"),
            (self.threads >= 1, f"threads must be >= 1, got {self.threads}"),
            (0.0 <= self.extra_share <= 1.0, f"extra_share must be in [0, 1], got {self.extra_share}"),
            (self.batch_size >= 1, f"batch_size must be >= 1, got {self.batch_size}"),
            (self.workers >= 1, f"workers must be >= 1, got {self.workers}"),
            (self.device in DEVICES, f"device must be one of {', '.join(DEVICES)}, got {self.device!r}"),
        ]
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="TrainCorrFlowConfig")


def extra_pairs(config: TrainCorrFlowConfig) -> Path:
    """Where the pairs of ``config.extra_data`` are cached: ``<extra_data>/pairs`` at the default working width,
    ``<extra_data>/pairs_w<net_width>`` at another."""
    name = "pairs" if config.net_width == TrainCorrFlowConfig.net_width else f"pairs_w{config.net_width}"
    return Path(config.extra_data) / name


def build_all_pairs(scenes: list, out: Path, ks, net_width: int, workers: int = 1) -> list[Path]:
    """``build_pairs`` of every scene folder, by ``workers`` processes (one scene each; the files are the same)."""
    jobs = [(Path(scene), Path(out), tuple(ks), net_width) for scene in scenes]
    if workers <= 1 or len(jobs) <= 1:
        return [build_pairs(*job) for job in jobs]
    with ProcessPoolExecutor(min(workers, len(jobs)), mp_context=multiprocessing.get_context("spawn")) as pool:
        return list(pool.map(build_pairs, *zip(*jobs)))


def prepare_pairs(config: TrainCorrFlowConfig, progress: bool = True) -> Path:
    """Render the scenes of ``config.scenes`` not cached yet and build their pairs; returns the pairs folder."""
    from models.flow.train import render_scenes  # noqa: PLC0415 (the renderer is only needed here)

    scenes = [scene for preset, first, count in config.scenes
              for scene in render_scenes(config.data_dir, range(first, first + count), 960, 540, 12, preset=preset)]
    t0 = time.time()
    build_all_pairs(scenes, Path(config.pairs), config.ks, config.net_width, config.workers)
    if progress:
        print(f"pairs of {len(scenes)} scenes: {time.time() - t0:.1f} s", flush=True)
    if config.extra_data:
        extra = Path(config.extra_data)
        scenes = sorted(p for p in extra.iterdir() if (p / "sequence.json").exists()) if extra.is_dir() else []
        if not scenes:
            raise InputError("holds no rgbd-seq folders", file=extra, field="extra_data")
        build_all_pairs(scenes, extra_pairs(config), config.ks, config.net_width, config.workers)
    return Path(config.pairs)


def _load_pairs(folder: Path) -> dict:
    files = sorted(folder.glob("*.npz"))
    if not files:
        raise InputError("holds no pair files (.npz)", file=folder, field="pairs")
    parts = [np.load(f) for f in files]
    return {key: np.concatenate([p[key] for p in parts]) for key in ("a", "b", "da", "db", "flow")}


def _batch(sets: list, rng: np.random.Generator, config: TrainCorrFlowConfig) -> tuple[torch.Tensor, ...]:
    """A batch from ``sets`` ([main pairs] or [main, extra]): a sample is from the extra set with probability
    ``config.extra_share`` (no draw without one, so a run without extra data draws as before it existed)."""
    ch, cw = config.crop
    a, b, f = [], [], []
    for _ in range(config.batch_size):
        data = sets[1] if len(sets) > 1 and rng.random() < config.extra_share else sets[0]
        total, h, w = data["a"].shape[:3]
        i = int(rng.integers(total))
        corners = [(int(rng.integers(0, h - ch + 1)), int(rng.integers(0, w - cw + 1)))
                   for _ in range(config.crop_candidates)]
        motion = np.linalg.norm(np.nan_to_num(data["flow"][i].astype(np.float32)), axis=-1) > 0.5
        y, x = max(corners, key=lambda c: int(motion[c[0]:c[0] + ch, c[1]:c[1] + cw].sum()))
        ia = data["a"][i, y:y + ch, x:x + cw].astype(np.float32) / 255
        ib = data["b"][i, y:y + ch, x:x + cw].astype(np.float32) / 255
        if config.model.depth:  # the depth codes as a fourth channel (flipped with the colours, no gain)
            ia = np.dstack([ia, data["da"][i, y:y + ch, x:x + cw].astype(np.float32) / 255])
            ib = np.dstack([ib, data["db"][i, y:y + ch, x:x + cw].astype(np.float32) / 255])
        fl = data["flow"][i, y:y + ch, x:x + cw].astype(np.float32)
        if rng.random() < 0.5:
            ia, ib, fl = ia[:, ::-1], ib[:, ::-1], fl[:, ::-1] * np.array([-1, 1], np.float32)
        if rng.random() < 0.5:
            ia, ib, fl = ia[::-1], ib[::-1], fl[::-1] * np.array([1, -1], np.float32)
        gain = np.ones(ia.shape[-1], np.float32)
        gain[:3] = rng.uniform(0.8, 1.2, size=3)
        ia, ib = np.clip(ia * gain, 0, 1), np.clip(ib * gain, 0, 1)
        a.append(ia.transpose(2, 0, 1))
        b.append(ib.transpose(2, 0, 1))
        f.append(fl.transpose(2, 0, 1))
    return tuple(torch.from_numpy(np.ascontiguousarray(np.stack(x))) for x in (a, b, f))


def valid_truth(target: torch.Tensor) -> torch.Tensor:
    """(B, 1, H, W) bool: where the (B, 2, H, W) truth is finite and within ``MAX_TRUTH``."""
    return (torch.isfinite(target) & (target.abs() < MAX_TRUTH)).all(dim=1, keepdim=True)


def sequence_loss(flows: list, target: torch.Tensor, gamma: float) -> torch.Tensor:
    """RAFT's loss, balanced: every iteration's L1 distance to ``target`` (mean over the two components),
    averaged over the valid static pixels and over the valid moving ones (truth over 0.5 px) separately and
    the two means averaged (a set without pixels left out), weighted gamma^(N-1-i). Moving pixels are a
    tenth of a frame: unbalanced, predicting no motion is the easy minimum."""
    valid = valid_truth(target)
    target = torch.where(valid, target, torch.zeros_like(target))
    moving = valid & (target.norm(dim=1, keepdim=True) > 0.5)
    groups = [g for g in (valid & ~moving, moving) if bool(g.any())]
    weight = sum(g / g.sum() for g in groups) / max(1, len(groups))
    n = len(flows)
    return sum(gamma ** (n - 1 - i) * ((flow - target).abs().mean(dim=1, keepdim=True) * weight).sum()
               for i, flow in enumerate(flows))


def load_start_weights(model: CorrFlow, checkpoint: Path) -> None:
    """``model``'s weights from ``checkpoint`` (fine-tuning). An RGB checkpoint starts an RGB-D model too: the
    first convolution's depth-channel weights start at 0, so the model starts as the RGB network."""
    state = torch.load(checkpoint, map_location="cpu", weights_only=False)["model"]
    first = "encoder.trunk.0.weight"
    want = model.state_dict()[first].shape
    if state[first].shape != want:
        if state[first].shape[0] != want[0] or state[first].shape[1] > want[1]:
            raise InputError(f"its first convolution is {tuple(state[first].shape)}, the model's {tuple(want)}",
                             file=checkpoint, field="init_from")
        grown = torch.zeros(want, dtype=state[first].dtype)
        grown[:, :state[first].shape[1]] = state[first]
        state = {**state, first: grown}
    try:
        model.load_state_dict(state)
    except RuntimeError as exc:
        raise InputError(f"does not fit the model ({str(exc).splitlines()[0]})", file=checkpoint,
                         field="init_from") from None


def train(config: TrainCorrFlowConfig, resume: bool = False) -> Path:
    torch.manual_seed(config.seed)
    torch.set_num_threads(config.threads)
    out = Path(config.out_dir)
    out.mkdir(parents=True, exist_ok=True)
    folders = [Path(config.pairs)] + ([extra_pairs(config)] if config.extra_data and config.extra_share > 0 else [])
    sets = [_load_pairs(folder) for folder in folders]
    for folder, data in zip(folders, sets):
        if any(c > side for c, side in zip(config.crop, data["a"].shape[1:3])):
            raise InputError(f"pairs of {data['a'].shape[1]} x {data['a'].shape[2]} px are smaller than the crop "
                             f"{config.crop[0]} x {config.crop[1]}", file=folder, field="crop")
    device = resolve_device(config.device)
    model = CorrFlow(config.model)
    if config.init_from:
        load_start_weights(model, Path(config.init_from))
    model.to(device)
    opt = torch.optim.AdamW(model.parameters(), lr=config.lr, weight_decay=config.weight_decay)
    sched = torch.optim.lr_scheduler.OneCycleLR(opt, config.lr, total_steps=config.steps + 100, pct_start=0.05,
                                                anneal_strategy="linear", cycle_momentum=False)
    start, ckpt = 0, out / "checkpoint.pt"
    if resume and ckpt.exists():
        state = torch.load(ckpt, map_location=device, weights_only=False)
        model.load_state_dict(state["model"])
        opt.load_state_dict(state["optimizer"])
        sched.load_state_dict(state["scheduler"])
        start = state["step"]
    cfg = config_to_dict(config)
    (out / "config.json").write_text(json.dumps(cfg, indent=2))
    log = open(out / "metrics.jsonl", "a")
    t0 = time.time()
    for step in range(start, config.steps):
        rng = np.random.default_rng([config.seed, step])
        a, b, target = (x.to(device) for x in _batch(sets, rng, config))
        flows = model(a, b)
        loss = sequence_loss(flows, target, config.gamma)
        opt.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        sched.step()
        if (step + 1) % config.log_every == 0:
            with torch.no_grad():
                valid = valid_truth(target)[:, 0]
                target = torch.where(valid[:, None], target, torch.zeros_like(target))
                epe = (flows[-1] - target).norm(dim=1)[valid]
                moving = target.norm(dim=1)[valid] > 0.5
                row = {"step": step + 1, "loss": float(loss), "epe": float(epe.mean()),
                       "epe_moving": float(epe[moving].mean()) if moving.any() else None,
                       "lr": sched.get_last_lr()[0], "s": round(time.time() - t0, 1)}
            log.write(json.dumps(row) + "\n")
            log.flush()
            print(row, flush=True)
        if (step + 1) % config.checkpoint_every == 0 or step + 1 == config.steps:
            torch.save({"model": model.state_dict(), "optimizer": opt.state_dict(), "scheduler": sched.state_dict(),
                        "step": step + 1, "config": cfg}, ckpt)
    return ckpt


def _scenes(text: str) -> tuple:
    """``--scenes``: "PRESET:FIRST:COUNT,..." -> ((preset, first seed, count), ...)."""
    try:
        scenes = tuple((p, int(first), int(count)) for p, first, count in (part.split(":") for part in text.split(",")))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected PRESET:FIRST:COUNT,..., e.g. fast:5000:16, got {text!r}") from None
    return scenes


def _ints(text: str) -> tuple[int, ...]:
    """``--ks``: "1,2,4" -> (1, 2, 4)."""
    try:
        return tuple(int(v) for v in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, e.g. 1,2,4, got {text!r}") from None


def _crop_size(text: str) -> tuple[int, int]:
    """``--crop``: "HxW" -> (H, W)."""
    try:
        h, w = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected HxW in pixels, e.g. 224x320, got {text!r}") from None
    return h, w


def main(argv: Optional[list] = None, prog: str = "python -m models.flow.corrflow_train") -> int:
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", default="runs/flow_data", help="where the rendered training scenes are cached")
    parser.add_argument("--pairs", default="runs/corrflow/pairs", help="where the training pairs are cached")
    parser.add_argument("--out", default="runs/corrflow", help="checkpoint, config.json and metrics.jsonl")
    parser.add_argument("--steps", type=int, default=4000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--resume", action="store_true", help="continue the checkpoint in --out")
    parser.add_argument("--pairs-only", action="store_true", help="render the scenes and build the pairs, no training")
    parser.add_argument("--lr", type=float, default=TrainCorrFlowConfig.lr)
    parser.add_argument("--init-from", default="", help="a checkpoint whose model weights start the run")
    parser.add_argument("--extra-data", default="",
                        help="a folder of rgbd-seq folders (with object ids and transforms) to train on too")
    parser.add_argument("--extra-share", type=float, default=0.0, help="share of samples from --extra-data")
    parser.add_argument("--threads", type=int, default=TrainCorrFlowConfig.threads, help="torch threads")
    parser.add_argument("--net-width", type=int, default=TrainCorrFlowConfig.net_width,
                        help="working width of the pairs (and of the exported network)")
    parser.add_argument("--crop", type=_crop_size, default=TrainCorrFlowConfig.crop,
                        help="training crop HxW at the working resolution (default: %(default)s)")
    parser.add_argument("--depth", action="store_true",
                        help="an RGB-D network: both images carry their depth code as a fourth channel")
    parser.add_argument("--scenes", type=_scenes, default=TRAIN_SCENES,
                        help="training scenes as PRESET:FIRST:COUNT,... (default: the seeds 5000-5039 of TRAIN_SCENES)")
    parser.add_argument("--ks", type=_ints, default=TrainCorrFlowConfig.ks, help="frame distances of the pairs")
    parser.add_argument("--iterations", type=int, default=CorrFlowConfig.iterations,
                        help="update iterations in training (each supervised)")
    parser.add_argument("--batch-size", type=int, default=TrainCorrFlowConfig.batch_size)
    parser.add_argument("--device", default="auto", metavar="|".join(DEVICES),
                        help="where the model trains (auto: cuda when torch sees a GPU)")
    parser.add_argument("--workers", type=int, default=1, help="processes building the pairs (one scene each)")
    parser.add_argument("--channels", type=_ints, default=None,
                        help="the network's widths: the encoder's three stages, features, context, GRU hidden, "
                             "e.g. 16,32,64,64,32,48 (the committed network's)")
    args = parser.parse_args(argv)
    widths = {}
    if args.channels is not None:
        if len(args.channels) != 6 or min(args.channels) < 1:
            parser.error(f"--channels takes six positive widths, got {args.channels}")
        widths = dict(zip(("feature_channels", "context_channels", "hidden_channels"), args.channels[3:]),
                      encoder_channels=tuple(args.channels[:3]))
    try:
        config = TrainCorrFlowConfig(data_dir=args.data, pairs=args.pairs, out_dir=args.out, steps=args.steps,
                                     seed=args.seed, lr=args.lr, init_from=args.init_from,
                                     extra_data=args.extra_data, extra_share=args.extra_share, threads=args.threads,
                                     net_width=args.net_width, crop=args.crop, scenes=args.scenes, ks=args.ks,
                                     batch_size=args.batch_size, device=args.device, workers=args.workers,
                                     model=CorrFlowConfig(depth=args.depth, iterations=args.iterations, **widths))
        resolve_device(config.device)  # a device this machine lacks is an error before any rendering
        prepare_pairs(config)
        if not args.pairs_only:
            print(f"wrote {train(config, resume=args.resume)}")
    except InputError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
