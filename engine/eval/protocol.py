"""Speed against error: run predictors over rgbd-seq sequences and score every predicted frame.

Protocol (thesis Sec. 6.4, DeCOMPnet's evaluation): with upsampling factor k, frames 0, k, 2k, ... are
"rendered"; for every rendered frame n that has a rendered predecessor n-k, each method predicts the
frames n+1 .. n+k-1 from frames n-k and n (history; also frame n-2k, where it exists, when a method uses
three frames: ``mvec``) and the target cameras, and each prediction is
scored against the true frame (``engine.eval.metrics.score_frame``). Time per predicted frame is the render
time plus the once-per-rendered-frame preparation divided by the k-1 frames it serves (amortised).

A method name ending in ``+true_holes`` (``TRUE_HOLES``) is scored with the true frame's pixels copied into
the prediction's holes (``Prediction.holes``: its disocclusions before filling), i.e. with a perfect
infilling; it shares the predictions (and times) of the method without the suffix. ``bound_methods`` uses
it for the performance bounds of thesis Table 6.3 (``interleave eval --bounds``).
"""
from __future__ import annotations

import json
import math
import statistics
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable, Iterable, Optional, Sequence

import numpy as np
from tqdm import tqdm

from engine.core.colorspace import display_encode
from engine.core.errors import InputError
from engine.core.frames import Frame, rigid_inverse
from engine.eval.metrics import SCORE_FIELDS, Scores, crop_slices, psnr, score_frame
from engine.geometry.motion import compose_motion_vectors, rigid_motion_vectors
from engine.predict import Mvec, Target, make_predictor, method_with, option_parts, resolve_auto
from engine.runtime.stream import PredictionLoop

#: Suffix of a method name scored with the true pixels in its holes (perfect disocclusion infilling).
TRUE_HOLES = "+true_holes"


@dataclass(frozen=True)
class MethodResult(Scores):
    """Scores of one method on one sequence for one k (means over predicted frames; medians for time)."""

    sequence: str
    method: str
    k: int
    frames: int
    ms_per_frame: float
    stages_ms: dict[str, float] = field(default_factory=dict)
    per_step: dict[str, dict[str, float]] = field(default_factory=dict)
    #: mean x-y endpoint error (pixels) of the method's object flow u(n -> n+1) on frame n's moving pixels,
    #: against the true ``object_flow`` (thesis Tab. 6.2); NaN for methods that estimate no flow
    epe_moving: float = float("nan")
    #: mean fraction of the cropped frame that the method left as holes (disocclusions) before filling
    hole_fraction: float = float("nan")
    #: PSNR (dB) over the cropped hole pixels, mean over the frames that have some (NaN: none had any;
    #: +inf: every hole pixel exact, as in ``+true_holes`` rows)
    psnr_holes: float = float("nan")
    #: where the method's warps ran (``cpu`` or ``gl``: engine.geometry.backends)
    backend: str = "cpu"
    #: median GPU milliseconds per predicted frame of each stage the ``gl`` backend timed (``prepare:`` stages
    #: divided by the k-1 frames they serve, as in ``stages_ms``); empty on ``cpu``
    gpu_ms: dict[str, float] = field(default_factory=dict)


def _mean(values: Iterable[float]) -> float:
    vals = [v for v in values if not math.isnan(v)]
    return float(np.mean(vals)) if vals else float("nan")


def evaluation_pairs(num_frames: int, k: int) -> list[tuple[int, int, list[int]]]:
    """(n-k, n, [n+1 .. n+k-1]) for every rendered frame n with history and all its targets in range."""
    if k < 2:
        raise InputError(f"k must be >= 2 (k = 1 predicts nothing), got {k}", field="k")
    return [(n - k, n, list(range(n + 1, n + k))) for n in range(k, num_frames - k + 1, k)]


def split_scoring(method: str) -> tuple[str, bool]:
    """(predictor name, true_holes) of a method name: ``"decomp[fill=simple]+true_holes"`` ->
    ``("decomp[fill=simple]", True)``; names without the ``TRUE_HOLES`` suffix give ``(method, False)``."""
    if method.endswith(TRUE_HOLES):
        return method[: -len(TRUE_HOLES)], True
    return method, False


def with_true_holes(color: np.ndarray, holes: np.ndarray, truth: np.ndarray) -> np.ndarray:
    """A copy of the predicted ``color`` (H, W, 3) with the true frame's ``truth`` (H, W, 3) where ``holes``
    (H, W) bool is set: the prediction a perfect disocclusion infilling would give (linear RGB)."""
    if color.shape != truth.shape or holes.shape != color.shape[:2]:
        raise InputError(f"color {color.shape}, truth {truth.shape} and holes {holes.shape} must be (H, W, 3), "
                         f"(H, W, 3) and (H, W)", field="holes")
    return np.where(holes[..., None], truth, color).astype(color.dtype, copy=False)


def hole_scores(truth: np.ndarray, color: np.ndarray, holes: np.ndarray) -> tuple[float, float]:
    """(fraction of the cropped frame that is holes, PSNR over those pixels or NaN if none), on sRGB-encoded
    frames with the border crop of ``engine.eval.metrics``."""
    rows, cols = crop_slices(*truth.shape[:2])
    mask = np.asarray(holes, dtype=bool)[rows, cols]
    if not mask.any():
        return 0.0, float("nan")
    return float(mask.mean()), psnr(display_encode(truth[rows, cols]), display_encode(color[rows, cols]), mask)


#: ``(older, newest, frame) -> (H, W, 2)`` motion vectors of ``frame``, the loaded frame at position ``newest``, to
#: the frame at position ``older``, from a renderer that computes them between any two of its frames (a dynamic
#: field's motion field).
VectorSource = Callable[[int, int, Frame], np.ndarray]


def history_motion_vectors(sequence, older: int, newest: int, frame: Optional[Frame] = None,
                           source: Optional[VectorSource] = None) -> np.ndarray:
    """Motion vectors (H, W, 2) of the frame at position ``newest`` pointing to the frame at position ``older``
    (the previous RENDERED frame when only every k-th frame is rendered), from a sequence whose stored
    ``motion.X/Y`` point one frame back.

    Recomputed exactly (``rigid_motion_vectors``) where the frame has its ``object_id`` channel and the
    sequence the transforms of every object it shows (none for a static scene); otherwise the stored vectors
    are chained frame by frame (``compose_motion_vectors``: exact where each intermediate frame sees the
    point, NaN where it does not).
    ``frame`` is the loaded frame at ``newest`` (read again when not given). A ``source`` gives them directly
    (as the renderer would have written them had it drawn only these frames).
    """
    frame = sequence[newest] if frame is None else frame
    if source is not None:
        return source(older, newest, frame)
    if newest - older == 1 and frame.motion_vectors is not None:
        return frame.motion_vectors
    known = {o.id for o in sequence.objects}
    if frame.object_id is not None and set(np.unique(frame.object_id).tolist()) <= known | {0}:
        motions = {o.id: o.world_from_object[older] @ rigid_inverse(o.world_from_object[newest])
                   for o in sequence.objects if o.moving}  # none listed and only id 0 seen: a static scene
        return rigid_motion_vectors(frame.depth, frame.camera, sequence.cameras[older], frame.object_id, motions)
    if frame.motion_vectors is None:
        raise InputError("has no motion vectors (channels motion.X/Y) to derive the vectors of 'mvec' from",
                         file=sequence.files[newest], frame=int(sequence.indices[newest]), field="motion.X")
    vectors = frame.motion_vectors
    for position in range(newest - 1, older, -1):
        step = sequence[position].motion_vectors
        if step is None:
            raise InputError("has no motion vectors (channels motion.X/Y) to chain", file=sequence.files[position],
                             frame=int(sequence.indices[position]), field="motion.X")
        vectors = compose_motion_vectors(vectors, step)
    return vectors


def rendered_history(sequence, older: int, newest: int, *, with_vectors: bool, three: bool,
                     vectors: Optional[VectorSource] = None) -> list[Frame]:
    """The rendered frames (oldest first) that predict after frame position ``newest``: frames ``older`` and
    ``newest``, and with ``three`` also ``2 older - newest`` where it exists. With ``with_vectors`` each
    frame but the first gets motion vectors to the frame before it in this list, as a renderer drawing only
    these frames writes them (``history_motion_vectors``, from ``vectors`` when given)."""
    history = [sequence[older], sequence[newest]]
    first = 2 * older - newest
    if with_vectors:
        history[1].motion_vectors = history_motion_vectors(sequence, older, newest, history[1], vectors)
    if three and first >= 0:
        history.insert(0, sequence[first])
        if with_vectors:
            history[1].motion_vectors = history_motion_vectors(sequence, first, older, history[1], vectors)
    return history


def make_predictors(methods: Sequence[str], objects: Sequence, *, has_vectors: bool, backend: str = "auto",
                    file=None) -> dict:
    """The predictor of each distinct method of ``methods`` (``auto`` resolved for a sequence with or without
    motion vectors, the ``TRUE_HOLES`` suffix dropped), keyed by its resolved name, built for a sequence with
    scene ``objects``: a bad name or option is an InputError naming ``file``. Cheap (tenths of a second), so
    commands that render a sequence first call it before they render."""
    predictors = {}
    for name in dict.fromkeys(resolve_auto(split_scoring(m)[0], has_vectors) for m in methods):
        try:
            predictors[name] = make_predictor(name, objects, backend=backend)
        except InputError as exc:  # name the sequence (e.g. motion=truth on a sequence without objects)
            if exc.file is not None:
                raise
            raise InputError(f"method '{name}': {exc.problem}", file=file, field=exc.field) from exc
    return predictors


def evaluate_sequence(sequence, methods: Sequence[str], k: int, *, with_flip: bool = True,
                      max_groups: Optional[int] = None, progress: bool = False,
                      backend: str = "auto", vectors: Optional[VectorSource] = None,
                      predictors: Optional[dict] = None) -> list[MethodResult]:
    """Evaluate ``methods`` on one loaded ``RgbdSequence`` with upsampling factor ``k``.

    ``max_groups`` limits how many rendered frames n are used (evenly spread over the sequence). Methods
    that differ only by the ``TRUE_HOLES`` suffix share one predictor, its predictions and its times.
    ``backend`` is where the methods' warps run (``engine.predict.use_backend``). ``vectors``: the motion
    vectors of the rendered frames to the previous rendered ones, where the renderer gives them directly
    (default: derived from the sequence, ``history_motion_vectors``). ``predictors``: predictors by method
    name made by the caller, used for those names of ``methods`` (e.g. an ``oracle`` that knows a field
    renderer's own motion).
    """

    groups = evaluation_pairs(len(sequence), k)
    if not groups:
        raise InputError(f"sequence has {len(sequence)} frames: too few for k = {k} (needs at least {2 * k})",
                         file=sequence.path)
    if max_groups is not None and len(groups) > max_groups:
        pick = np.linspace(0, len(groups) - 1, max_groups).round().astype(int)
        groups = [groups[i] for i in sorted(set(pick.tolist()))]
    has_vectors = sequence.has_channel("motion_vectors")
    sources = {m: resolve_auto(split_scoring(m)[0], has_vectors) for m in methods}
    given = dict(predictors or {})
    predictors = {**make_predictors([m for m in methods if m not in given], sequence.objects,
                                    has_vectors=has_vectors, backend=backend, file=sequence.path), **given}
    if "oracle" in predictors and "oracle" not in given and not sequence.objects:
        raise InputError("method 'oracle' needs the sequence's objects and object_id channel", file=sequence.path)
    with_vectors = any(isinstance(p, Mvec) for p in predictors.values())
    wants_three = any(p.history_wanted >= 3 for p in predictors.values())
    if with_vectors and not has_vectors and not sequence.has_channel("object_id"):
        raise InputError("method 'mvec' needs motion vectors (channels motion.X/Y), or object_id and the objects' "
                         "transforms to derive them", file=sequence.path, field="motion_vectors")
    loops = {name: PredictionLoop(predictor) for name, predictor in predictors.items()}
    scores: dict[str, list] = {m: [] for m in methods}
    times: dict[str, list[float]] = {p: [] for p in predictors}
    stages: dict[str, list[dict[str, float]]] = {p: [] for p in predictors}
    gpu: dict[str, list[dict[str, float]]] = {p: [] for p in predictors}
    epes: dict[str, list[float]] = {p: [] for p in predictors}
    with tqdm(total=len(groups) * (k - 1) * len(methods), desc=f"{Path(str(sequence.path)).name} k={k}",
              disable=not progress, unit="frame") as bar:  # closed (its line ended) on an error too
        for older_i, newest_i, target_is in groups:
            # the renderer's vectors of frame n point to the previous rendered frame, n-k (and n-k's to n-2k)
            history = rendered_history(sequence, older_i, newest_i, with_vectors=with_vectors, three=wants_three,
                                       vectors=vectors)
            truths = [sequence[i] for i in target_is]
            for name, loop in loops.items():
                start = time.perf_counter()
                state = loop.load(history).state
                prep_ms = 1e3 * (time.perf_counter() - start)
                if hasattr(loop.predictor, "object_flow"):
                    epes[name].append(flow_epe(loop.predictor.object_flow(state), history[-2], history[-1],
                                               truths[0]))
                for step, truth in enumerate(truths, start=1):
                    target = Target(truth.camera, truth.time, truth.index)
                    start = time.perf_counter()
                    pred = loop.predict(target)
                    render_ms = 1e3 * (time.perf_counter() - start)
                    per_frame = {s: v for s, v in pred.stages_ms.items()}
                    for s, v in state.stages_ms.items():
                        per_frame[f"prepare:{s}"] = v / (k - 1)
                    times[name].append(render_ms + prep_ms / (k - 1))
                    stages[name].append(per_frame)
                    gpu[name].append({**pred.gpu_ms,
                                      **{f"prepare:{s}": v / (k - 1) for s, v in state.gpu_ms.items()}})
                    for method in (m for m in methods if sources[m] == name):
                        color = pred.color
                        if split_scoring(method)[1]:
                            color = with_true_holes(pred.color, pred.holes, truth.color)
                        frame_score = score_frame(truth.color, color, truth.moving, with_flip=with_flip)
                        scores[method].append((step, frame_score, hole_scores(truth.color, color, pred.holes)))
                        bar.update(1)
    results = []
    for name in methods:
        source = sources[name]
        frame_scores = [s for _, s, _ in scores[name]]
        stage_names = sorted({s for d in stages[source] for s in d})
        per_step = {}
        for step in range(1, k):
            at = [s for st, s, _ in scores[name] if st == step]
            per_step[str(step)] = {"frames": len(at), "psnr": _mean(s.psnr for s in at),
                                   "ssim": _mean(s.ssim for s in at), "flip": _mean(s.flip for s in at),
                                   "psnr_moving": _mean(s.psnr_moving for s in at)}
        results.append(MethodResult(
            sequence=Path(str(sequence.path)).name, method=name, k=k, frames=len(frame_scores),
            **{f: _mean(getattr(s, f) for s in frame_scores) for f in SCORE_FIELDS},
            ms_per_frame=float(statistics.median(times[source])),
            stages_ms={s: float(statistics.median(d.get(s, 0.0) for d in stages[source])) for s in stage_names},
            per_step=per_step, epe_moving=_mean(epes[source]),
            hole_fraction=_mean(h[0] for _, _, h in scores[name]),
            psnr_holes=_mean(h[1] for _, _, h in scores[name]), backend=predictors[source].backend,
            gpu_ms={s: float(statistics.median(d.get(s, 0.0) for d in gpu[source]))
                    for s in sorted({s for d in gpu[source] for s in d})}))
    return results


def flow_epe(flow_back: np.ndarray, older, newest, following) -> float:
    """EPE of an estimated u(n -> n-k) (H, W, 2), extrapolated to u(n -> n+1) (Eq. 6.13 with the frame
    times), against frame n's true object flow (n -> n+1) on its moving pixels; NaN if it has neither."""
    if newest.object_flow is None or newest.moving is None or not newest.moving.any():
        return float("nan")
    step = (following.time - newest.time) / (newest.time - older.time)
    error = np.linalg.norm(-step * flow_back[..., :2] - newest.object_flow, axis=-1)
    return float(error[newest.moving].mean())


def summarize(results: Sequence[MethodResult]) -> dict:
    """Per (method, k): means over sequences, and each method's time relative to `reproject` in the same run."""
    out: dict = {}
    for method in dict.fromkeys(r.method for r in results):
        for k in sorted({r.k for r in results}):
            rows = [r for r in results if r.method == method and r.k == k]
            if not rows:
                continue
            out[f"{method}/k={k}"] = {
                "method": method, "k": k, "sequences": len(rows), "frames": sum(r.frames for r in rows),
                "psnr": _mean(r.psnr for r in rows), "ssim": _mean(r.ssim for r in rows),
                "flip": _mean(r.flip for r in rows), "psnr_moving": _mean(r.psnr_moving for r in rows),
                "ssim_moving": _mean(r.ssim_moving for r in rows), "flip_moving": _mean(r.flip_moving for r in rows),
                "ms_per_frame": float(statistics.median(r.ms_per_frame for r in rows)),
                "epe_moving": _mean(r.epe_moving for r in rows),
                "hole_fraction": _mean(r.hole_fraction for r in rows),
                "psnr_holes": _mean(r.psnr_holes for r in rows),
            }
    for key, row in out.items():
        base = out.get(f"reproject/k={row['k']}")
        row["time_vs_reproject"] = row["ms_per_frame"] / base["ms_per_frame"] if base else float("nan")
    return out


def score_cell(value: Optional[float], digits: int) -> str:
    """A table cell of a score: ``-`` for one that was not computed or has no pixels (NaN, or None as read
    back from JSON), e.g. the moving-pixel columns of a static scene; the one formatter of every eval table
    (JSON stores the same scores as null: :func:`json_safe`).

    >>> score_cell(float("nan"), 2), score_cell(None, 2), score_cell(21.184, 2)
    ('-', '-', '21.18')
    """
    return "-" if value is None or math.isnan(value) else f"{value:.{digits}f}"


def markdown_table(results: Sequence[MethodResult]) -> str:
    """One row per (sequence, method, k), then the per-method means; ``-`` where a score is NaN (no FLIP after
    ``--no-flip``, no moving pixels, no flow)."""
    head = ("| sequence | k | method | frames | PSNR | SSIM | FLIP | PSNR moving | FLIP moving | EPE moving (px) "
            "| ms/frame |\n|---|---|---|---|---|---|---|---|---|---|---|")
    lines = [head]

    def scores(row) -> str:
        return " | ".join(score_cell(row[name], digits) for name, digits in (
            ("psnr", 2), ("ssim", 4), ("flip", 4), ("psnr_moving", 2), ("flip_moving", 4), ("epe_moving", 2)))

    for r in results:
        lines.append(f"| {r.sequence} | {r.k} | {r.method} | {r.frames} | {scores(asdict(r))} | "
                     f"{r.ms_per_frame:.1f} |")
    for row in summarize(results).values():
        lines.append(f"| **mean** | {row['k']} | {row['method']} | {row['frames']} | {scores(row)} | "
                     f"{row['ms_per_frame']:.1f} (x{row['time_vs_reproject']:.2f}) |")
    return "\n".join(lines)


def stage_table(results: Sequence[MethodResult]) -> str:
    """Median milliseconds per predicted frame of each stage, per (method, k), medians over sequences: wall
    time, then (for methods on the ``gl`` backend) ``gpu total``, the GPU time its GL timer queries measured.

    ``prepare:`` stages run once per rendered frame and are shown divided by the k-1 frames they serve.
    """
    keys = list(dict.fromkeys((r.method, r.k) for r in results))
    stages = sorted({s for r in results for s in r.stages_ms})
    gpu = any(r.gpu_ms for r in results)
    head = ["method", "k", "backend"] + stages + ["total"] + (["gpu total"] if gpu else [])
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for method, k in keys:
        rows = [r for r in results if r.method == method and r.k == k]
        cells = [f"{statistics.median(r.stages_ms.get(s, 0.0) for r in rows):.1f}" for s in stages]
        cells.append(f"{statistics.median(r.ms_per_frame for r in rows):.1f}")
        if gpu:
            cells.append(f"{statistics.median(sum(r.gpu_ms.values()) for r in rows):.2f}" if rows[0].gpu_ms else "-")
        lines.append(f"| {method} | {k} | {rows[0].backend} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def per_step_table(results: Sequence[MethodResult]) -> str:
    """Scores per future step k' = 1 .. k-1 (the frame n + k' predicted from frames n-k and n), per (method, k):
    means over sequences of each sequence's per-step means; frames summed."""
    lines = ["| method | k | k' | frames | PSNR | SSIM | FLIP | PSNR moving |", "|---|---|---|---|---|---|---|---|"]
    for method, k in dict.fromkeys((r.method, r.k) for r in results):
        rows = [r for r in results if r.method == method and r.k == k]
        for step in range(1, k):
            at = [r.per_step[str(step)] for r in rows if str(step) in r.per_step]
            if not at:
                continue
            frames = sum(int(a.get("frames", 0)) for a in at)
            cells = " | ".join(score_cell(_mean(a[name] for a in at), digits)
                               for name, digits in (("psnr", 2), ("ssim", 4), ("flip", 4), ("psnr_moving", 2)))
            lines.append(f"| {method} | {k} | {step} | {frames} | {cells} |")
    return "\n".join(lines)


@dataclass(frozen=True)
class BoundRow:
    """One row of the performance-bound analysis (thesis Table 6.3).

    ``motion`` (LMP, local motion prediction): 'pred' = the variant's flow network, 'GT' = the sequence's
    true object motion (``motion=truth``); ``infill`` (DI, disocclusion infilling): 'pred' = the variant's
    own fill, 'GT' = the true frame's pixels in its holes (``TRUE_HOLES``). ``method`` is what the evaluator runs.
    """

    motion: str
    infill: str
    method: str


def bound_methods(variant: str = "decomp") -> list[BoundRow]:
    """The four rows of thesis Table 6.3 for a ``decomp`` / ``decomp2d`` variant (e.g. ``decomp[fill=simple]``):
    (pred, pred) the variant itself, (GT, pred) with ``motion=truth``, (pred, GT) and (GT, GT) the same two
    scored with the true pixels in the holes. The variant must not set ``motion`` itself."""
    base, bracket, rest = variant.strip().partition("[")
    if base not in ("decomp", "decomp2d") or (bracket and not rest.endswith("]")) or TRUE_HOLES in variant:
        raise InputError(f"the bound analysis takes a decomp variant such as decomp or decomp[fill=simple], "
                         f"got '{variant}'", field="bounds")
    options = option_parts(rest[:-1]) if bracket else []
    if any(p.partition("=")[0].strip() == "motion" for p in options):
        raise InputError(f"'{variant}': the bound analysis sets motion=truth itself; leave motion out",
                         field="bounds")
    own, truth = method_with(base, options), method_with(base, options + ["motion=truth"])
    return [BoundRow("pred", "pred", own), BoundRow("GT", "pred", truth),
            BoundRow("pred", "GT", own + TRUE_HOLES), BoundRow("GT", "GT", truth + TRUE_HOLES)]


def bounds_summary(results: Sequence[MethodResult], rows: Sequence[BoundRow]) -> list[dict]:
    """Per (k, bound row): ``summarize``'s means over sequences, with the row's ``motion`` and ``infill``."""
    summary = summarize(results)
    out = []
    for k in sorted({r.k for r in results}):
        for row in rows:
            entry = summary.get(f"{row.method}/k={k}")
            if entry is not None:
                out.append({"motion": row.motion, "infill": row.infill, **entry})
    return out


def bounds_table(results: Sequence[MethodResult], rows: Sequence[BoundRow]) -> str:
    """Thesis Table 6.3: LMP / DI as pred or GT against PSNR, SSIM, FLIP and PSNR over moving pixels, means
    over sequences per k; also the share of the frame that was holes and the PSNR over those pixels."""
    def holes_psnr(value: float) -> str:
        return "exact" if value == math.inf else score_cell(value, 2)

    lines = ["| k | LMP | DI | method | frames | PSNR | SSIM | FLIP | PSNR moving | holes (%) | PSNR holes |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for e in bounds_summary(results, rows):
        lines.append(f"| {e['k']} | {e['motion']} | {e['infill']} | {e['method']} | {e['frames']} | "
                     f"{score_cell(e['psnr'], 2)} | {score_cell(e['ssim'], 4)} | {score_cell(e['flip'], 4)} | "
                     f"{score_cell(e['psnr_moving'], 2)} | {score_cell(100 * e['hole_fraction'], 2)} | "
                     f"{holes_psnr(e['psnr_holes'])} |")
    return "\n".join(lines)


def json_safe(x):
    """``x`` (nested dicts and lists) with NaN and +-inf floats replaced by None (JSON's null)."""
    if isinstance(x, float) and not math.isfinite(x):
        return None
    if isinstance(x, dict):
        return {k: json_safe(v) for k, v in x.items()}
    if isinstance(x, list):
        return [json_safe(v) for v in x]
    return x


def write_json(results: Sequence[MethodResult], path: Path, extra: Optional[dict] = None) -> None:
    """Records (one per sequence, method, k) plus the summary; NaN and inf written as null."""
    doc = {"records": [asdict(r) for r in results], "summary": summarize(results), **(extra or {})}
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    Path(path).write_text(json.dumps(json_safe(doc), indent=2))


def plot(results: Sequence[MethodResult], path: Path) -> None:
    """Time per predicted frame against PSNR and FLIP, one colour per method, one marker per k."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(metric, label) for metric, label in (("psnr", "PSNR (dB, higher is better)"),
                                                     ("flip", "FLIP (lower is better)"))
              if any(math.isfinite(getattr(r, metric)) for r in results)]  # no FLIP panel after --no-flip
    if not panels:
        raise InputError("no finite score to plot", file=path, field="--plot")
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.2), squeeze=False)
    axes = axes[0]
    methods = list(dict.fromkeys(r.method for r in results))
    markers = {k: m for k, m in zip(sorted({r.k for r in results}), "os^Dv")}
    colors = plt.get_cmap("tab10")
    for ax, (metric, label) in zip(axes, panels):
        for mi, method in enumerate(methods):
            for k, marker in markers.items():
                rows = [r for r in results if r.method == method and r.k == k and math.isfinite(getattr(r, metric))]
                xs = [max(r.ms_per_frame, 1e-2) for r in rows]
                ys = [getattr(r, metric) for r in rows]
                ax.scatter(xs, ys, color=colors(mi), marker=marker, alpha=0.45, s=22)
                if rows:
                    ax.scatter([statistics.median(xs)], [_mean(ys)], color=colors(mi), marker=marker, s=90,
                               edgecolor="black", label=f"{method} k={k}")
        ax.set_xscale("log")
        ax.set_xlabel("ms per predicted frame (median, log scale)")
        ax.set_ylabel(label)
        ax.grid(True, alpha=0.3)
    axes[0].legend(fontsize=7, loc="best")
    fig.suptitle("Speed against error (small: one sequence; large: mean over sequences)")
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
