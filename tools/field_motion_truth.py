"""What a trained dynamic field's motion gets right: its motion against a capture's true object motion.

``python -m tools.field_motion_truth EXPORT CAMERA [--depth truth|field] [--json FILE]`` reads a dynamic-field
export (``interleave export dynamic``) and one camera of the capture it was trained on, an rgbd-seq folder with
ground-truth ``object_flow`` (e.g. the held-out camera of an rgbd-rig: ``RIG/cam2``). For every pair of
consecutive frames (n, n+1) whose times lie in the field's trained range it moves each pixel's surface point
by the field's own motion from t_n to t_{n+1} (``engine.fields.dynamic.field_object_flow``, what the field's
vectors and ``oracle`` are made of) and compares that screen motion with frame n's true ``object_flow``
(pixels, to the next frame, object motion alone):

- over the moving objects (``object_id`` > 0; without object ids, where the true motion exceeds 0.25 px): the
  end-point error beside zero motion's (a field that learned no motion), and the share of the pixels where
  the field's motion halves zero motion's error;
- over the static background (where the field should move nothing): the end-point error and the share of its
  pixels the field moves by more than 0.25 px;
- the flow MLP's hidden units that no point of the cube at any trained time switches on (ReLU input <= 0 at
  :data:`UNIT_SAMPLES` uniform random points and times, seeded): a unit off for every input passes no gradient
  from the flow, so neither the photometric loss nor the prior can switch it back on, and a field whose units are
  all off moves nothing (``docs/results/2026-11-30-dynamic-motion-pairs.md``).

A static camera's vectors are this object motion; a moving camera's add the camera's own, which the field does
not learn. Means over the pairs. The surface point lies at frame n's TRUE depth (``--depth truth``, the
default: the motion alone, the field's geometry errors left out) or at the depth the field renders
(``--depth field``, the numpy renderer: what the field's vectors are made of, geometry errors included).
"""
from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Optional

import numpy as np

from engine.core.errors import InputError
from engine.fields.dynamic import (DynamicAssets, field_object_flow, hex_plane_features_np, load_dynamic_field,
                                   normalize_time, render_dynamic_field)
from engine.io.rgbd import read_sequence
from tools.field_vectors_check import report

__all__ = ["MOVING_PX", "DEPTHS", "UNIT_SAMPLES", "flow_units", "check", "main"]

#: screen motion (pixels) above which a background pixel counts as moved, and (without object ids) a pixel
#: as part of a moving object
MOVING_PX = 0.25
#: where the surface point of a pixel lies: at the capture's depth or at the field's rendered depth
DEPTHS = ("truth", "field")
#: random (point, time) samples over which a flow MLP unit must stay off to count as never active
UNIT_SAMPLES = 1 << 16


def flow_units(assets: DynamicAssets, samples: int = UNIT_SAMPLES, seed: int = 0) -> tuple[int, int]:
    """(hidden units of the flow MLP, those never active): a unit is active at a sample where its ReLU input is
    positive; the samples are uniform in the contracted cube [-1, 1]^3 and in normalised time [-1, 1]. (0, 0)
    for an export whose motion is motion slots (no flow MLP)."""
    if assets.slots is not None:
        return 0, 0
    rng = np.random.default_rng(seed)
    coords = rng.uniform(-1.0, 1.0, (samples, 3)).astype(np.float32)
    taus = rng.uniform(-1.0, 1.0, samples).astype(np.float32)
    x = hex_plane_features_np(assets.planes["motion_spatial"], assets.planes["motion_temporal"], coords, taus)
    total = dead = 0
    for w, b in assets.flow_layers[:-1]:
        x = x @ w.T + b
        total += x.shape[1]
        dead += int((~(x > 0).any(axis=0)).sum())
        x = np.maximum(x, 0.0)
    return total, dead


def _length(a: np.ndarray) -> np.ndarray:
    return np.hypot(a[..., 0], a[..., 1])


def _trained(time: float, time_range: tuple[float, float]) -> bool:
    """Whether the field renders ``time``: the renderers' own rule (``normalize_time``, which refuses a time
    outside the trained range by more than its tolerance and clamps the rest)."""
    try:
        normalize_time(time, time_range)
    except InputError:
        return False
    return True


def check(export: Path, camera: Path, depth: str = "truth") -> dict:
    """The figures of the module doc as a flat dict (means over the frame pairs; pixels).

    Raises:
        InputError: not an export or an rgbd-seq folder, a frame without ``object_flow``, no pair of
            consecutive frames inside the field's trained range, or ``depth`` not one of :data:`DEPTHS`.
    """
    if depth not in DEPTHS:
        raise InputError(f"must be one of {list(DEPTHS)}, got {depth!r}", field="depth")
    assets = load_dynamic_field(export)
    seq = read_sequence(camera)
    inside = [_trained(t, assets.time_range) for t in seq.times]
    pairs = [n for n in range(len(seq) - 1) if inside[n] and inside[n + 1]]
    if not pairs:
        t0, t1 = assets.time_range
        raise InputError(f"no two consecutive frames inside the field's trained times [{t0}, {t1}]",
                         file=Path(camera))
    sums: dict[str, list[float]] = {}

    def add(key: str, value) -> None:
        sums.setdefault(key, []).append(float(value))

    for n in pairs:
        frame = seq[n]
        if frame.object_flow is None:
            raise InputError("has no ground-truth object flow", file=Path(camera), frame=frame.index,
                             field="object_flow")
        t, t_next = frame.time, float(seq.times[n + 1])
        truth = frame.object_flow[..., :2]
        fg = np.isfinite(frame.depth)
        objects = (frame.object_id > 0) & fg if frame.object_id is not None else (_length(truth) > MOVING_PX) & fg
        background = fg & ~objects
        k_mat, pose = frame.camera.intrinsics, frame.camera.world_to_camera
        at = frame.depth if depth == "truth" else render_dynamic_field(assets, k_mat, pose, *frame.depth.shape,
                                                                       t)["depth"]
        moved = field_object_flow(assets, k_mat, pose, at, t, t_next)[..., :2]
        err = _length(moved - truth)
        add("object pixel share", objects.mean())
        if objects.any():
            add("objects: true motion, px", _length(truth)[objects].mean())
            add("objects: EPE of the field's motion, px", err[objects].mean())
            add("objects: EPE of zero motion, px", _length(truth)[objects].mean())
            halved = err < 0.5 * _length(truth)
            add("objects: share where the field halves zero motion's error", halved[objects].mean())
        if background.any():
            add("background: EPE of the field's motion, px", err[background].mean())
            add(f"background: share the field moves > {MOVING_PX} px", (_length(moved) > MOVING_PX)[background].mean())
    out = {key: round(float(np.mean(values)), 4) for key, values in sums.items()}
    out["pairs"] = len(pairs)
    out["flow MLP: hidden units"], out["flow MLP: hidden units never active"] = flow_units(assets)
    return out


def main(argv: Optional[list[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tools.field_motion_truth", description=__doc__.splitlines()[0])
    parser.add_argument("export", type=Path, help="a dynamic field's export folder ('interleave export dynamic')")
    parser.add_argument("camera", type=Path, help="an rgbd-seq folder with object_flow, e.g. RIG/cam2")
    parser.add_argument("--depth", choices=DEPTHS, default="truth",
                        help="surface points at the capture's depth (the motion alone) or the field's rendered depth")
    parser.add_argument("--json", type=Path, default=None, help="also write the figures here")
    args = parser.parse_args(argv)
    return report(lambda: check(args.export, args.camera, args.depth), args.json,
                  "python -m tools.field_motion_truth", argv)


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
