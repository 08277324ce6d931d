"""Does the unsupervised flow loss (Eq. 6.12) reward the true motion over the initial DIS flow, and where do
trained networks land? A diagnostic of the training objective, not of any one network.

For frame pairs (n - k, n) of rgbd-seq sequences that carry moving objects, on whole frames at the training
resolution (block-downsampled like training): ``flow_loss`` and the end-point error on moving pixels of

- ``zero``: no motion; ``dis``: the initial flow (``engine.predict.dis.initial_flow``) lifted onto every plane;
- ``truth``: the true object flow u(n -> n-k) (``engine.predict.base.true_object_flow``, block mean, dz = 0);
- ``dis+quarter``: DIS plus the truth's residual averaged over 4 x 4 blocks and upsampled (what a network
  whose output is at 1/4 resolution could reach);
- every ``NAME=CHECKPOINT`` given: that network on (m_n, m^w_{n-k}, DIS).

    python -m tools.loss_ranking heldout/seed1001 heldout/seed1002 heldout/seed1003 --every 3 \\
        --net committed=models/weights/flow3d.pt

Prints one row per candidate: mean loss, mean photometric term, mean end-point error (pixels of the
downsampled frame, k-frame flow, pixels whose true flow exceeds 0.2 px) and the share of pairs on which
the candidate's loss is below DIS's.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F

from engine.core.errors import InputError
from engine.io.rgbd import read_sequence
from engine.predict import true_object_flow
from models.flow.losses import FlowLossConfig, flow_loss
from models.flow.network import mpi_pair
from models.flow.train import dis_initial_flow, frame_tensors, load_model


def _lift(flow_2d: torch.Tensor, alpha: torch.Tensor) -> torch.Tensor:
    """(1, 2 or 3, H, W) -> (1, 3, Z, H, W): the same flow on every plane where the MPI holds a point."""
    z, h, w = alpha.shape[-3:]
    out = torch.zeros(1, 3, z, h, w)
    out[:, :flow_2d.shape[1]] = flow_2d[:, :, None]
    return out * alpha


def rank_pairs(sequences: list[str], factor: int = 2, num_planes: int = 4, every: int = 3,
               ks=(1, 2, 4), nets: dict | None = None, min_moving: int = 50) -> list[dict]:
    """One record per pair: {"sequence", "n", "k", "moving", candidate: (loss, photometric, epe)}."""

    nets = nets or {}
    config = FlowLossConfig()
    rows = []
    for path in sequences:
        seq = read_sequence(path)
        if not seq.objects:
            raise InputError("has no moving objects (needs object ids and transforms)", file=Path(path))
        objects = {o.id: o for o in seq.objects}
        for n in range(max(ks), len(seq), every):
            for k in ks:
                frame_n, frame_p = seq[n], seq[n - k]
                t_n, t_p = frame_tensors(frame_n, factor), frame_tensors(frame_p, factor)
                with torch.no_grad():
                    m_n, m_p = mpi_pair(*t_n, *t_p, num_planes)
                    dis = dis_initial_flow(t_n[0], m_p)
                    h, w = m_n.alpha.shape[-2:]
                    truth = torch.from_numpy(true_object_flow(frame_n, objects, frame_p.index)).permute(2, 0, 1)[None]
                    truth = F.avg_pool2d(truth, factor)[..., :h, :w]
                    truth[:, :2] /= factor
                    moving = truth[:, :2].norm(dim=1) > 0.2
                    if int(moving.sum()) < min_moving:
                        continue
                    residual = F.interpolate(F.avg_pool2d(truth[:, :2] - dis, 4), size=(h, w), mode="bilinear",
                                             align_corners=False)
                    candidates = {"zero": torch.zeros(1, 3, *m_n.alpha.shape[-3:]), "dis": _lift(dis, m_n.alpha),
                                  "truth": _lift(truth[:, :2], m_n.alpha),
                                  "dis+quarter": _lift(dis + residual, m_n.alpha)}
                    for name, net in nets.items():
                        candidates[name] = net(m_n, m_p, dis)
                    record = {"sequence": str(path), "n": n, "k": k, "moving": int(moving.sum())}
                    for name, flow in candidates.items():
                        loss, terms = flow_loss(m_n, m_p, flow, config)
                        # each pixel's flow: the alpha-weighted mean over planes (one-hot MPIs: its own plane's)
                        pixel = flow[:, :2].sum(2) / m_n.alpha.sum(2).clamp(min=1)
                        epe = (pixel - truth[:, :2]).norm(dim=1)[moving].mean()
                        record[name] = (float(loss), float(terms["photometric"]), float(epe))
                    rows.append(record)
    return rows


def summary(rows: list[dict]) -> list[dict]:
    names = [key for key in rows[0] if key not in ("sequence", "n", "k", "moving")] if rows else []
    dis = np.array([r["dis"][0] for r in rows])
    out = []
    for name in names:
        values = np.array([r[name] for r in rows])
        out.append({"candidate": name, "loss": float(values[:, 0].mean()), "photometric": float(values[:, 1].mean()),
                    "epe": float(values[:, 2].mean()), "below_dis": float(np.mean(values[:, 0] < dis)),
                    "pairs": len(rows)})
    return out


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(prog="python -m tools.loss_ranking", description=__doc__.split("\n\n")[0])
    parser.add_argument("sequences", nargs="+")
    parser.add_argument("--every", type=int, default=3, help="every this many frames n")
    parser.add_argument("--net", action="append", default=[], help="NAME=CHECKPOINT of a trained flow network")
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--json", help="write the per-pair records and the summary here")
    args = parser.parse_args(argv)
    torch.set_num_threads(args.threads)
    nets = {}
    for spec in args.net:
        name, sep, path = spec.partition("=")
        if not sep:
            raise InputError(f"expected NAME=CHECKPOINT, got {spec!r}", field="--net")
        nets[name] = load_model(path)
    rows = rank_pairs(args.sequences, every=args.every, nets=nets)
    table = summary(rows)
    print(f"{'candidate':14s} {'loss':>8s} {'photometric':>11s} {'EPE (px)':>9s} {'below DIS':>9s}  ({len(rows)} pairs)")
    for t in table:
        print(f"{t['candidate']:14s} {t['loss']:8.5f} {t['photometric']:11.5f} {t['epe']:9.3f} {t['below_dis']:9.2f}")
    if args.json:
        Path(args.json).write_text(json.dumps({"summary": table, "pairs": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
