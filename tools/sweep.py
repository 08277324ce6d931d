"""Speed against error of the ``decomp`` predictor's knobs: ``python -m tools.sweep SEQ_DIR...``.

Each variant is ``decomp[...]`` with one value per knob:

- ``flow_width``: the widest input the flow network runs at (frames are block-downsampled to it);
- ``fill``: disocclusion fill, ``simple`` (the row fill of ``reproject``) or ``infill`` (the network);
- ``infill_iterations`` (g): passes of the infilling network (``fill=infill`` only);
- planes Z: the flow network exported for Z MPI planes (``export.flow.with_planes``; the committed network's
  own Z needs no export, others are exported once into ``--models-dir``, which needs torch).

All variants and the baselines (``reproject``, ``flow2d``) are evaluated in one run by
``engine.eval.protocol.evaluate_sequence`` (same protocol, same frames, same machine state). Results are grouped
by frame size (the sequences' own, e.g. 960x540 and 1920x1080 scenes): per size and variant, time is the
median over sequences of the median ms per predicted frame, PSNR / FLIP the mean over sequences. A point
is on the Pareto front when no other point of its size is at least as fast and at least as good, and
strictly better in one of the two (fastest for its error); fronts are computed for PSNR and for FLIP.
"""
from __future__ import annotations

import argparse
import dataclasses
import math
import statistics
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

from engine.core.errors import InputError, InterleaveError
from engine.eval.protocol import MethodResult, evaluate_sequence, score_cell, stage_table, write_json
from engine.io.rgbd import read_sequence
from engine.predict import METHODS, make_predictor, option_parts
from engine.predict.decomp.network import DEFAULT_MODEL, FlowNetwork

__all__ = ["Variant", "SweepPoint", "pareto_front", "decomp_variants", "plane_models", "sweep_points",
           "sweep_table", "plot_sweep", "add_arguments", "run_sweep_command", "main"]

#: the knobs a variant sets; ``--decomp-options`` may not set them too
SWEPT_KEYS = ("flow_width", "fill", "infill_iterations", "model", "dis_preset")
#: where the plane-count variants of the committed flow network are exported (``flow3d_z{Z}_xy.onnx``)
DEFAULT_MODELS_DIR = Path("runs/flow3d_planes")
#: the torch checkpoint the committed ``engine/weights/flow3d.onnx`` was exported from
DEFAULT_CHECKPOINT = Path(__file__).resolve().parent.parent / "models" / "weights" / "flow3d.pt"


@dataclass(frozen=True)
class Variant:
    """One swept configuration: the method name the evaluator runs and its knob values (None: not a decomp
    knob of this method, e.g. ``infill_iterations`` with ``fill=simple`` or any knob of ``reproject``)."""

    method: str
    flow_width: Optional[int] = None
    fill: Optional[str] = None
    infill_iterations: Optional[int] = None
    planes: Optional[int] = None
    dis_preset: Optional[str] = None

    @property
    def label(self) -> str:
        """Short name for tables and plots: ``decomp w480 Z4 infill g3``, or the baseline's method name."""
        if self.fill is None:
            return self.method
        width = "native" if self.flow_width == 0 else str(self.flow_width)
        g = f" g{self.infill_iterations}" if self.infill_iterations is not None else ""
        dis = f" DIS-{self.dis_preset}" if self.dis_preset not in (None, "medium") else ""
        return f"{self.method.partition('[')[0]} w{width} Z{self.planes} {self.fill}{g}{dis}"


@dataclass
class SweepPoint:
    """One variant at one frame size: median ms per predicted frame (median over sequences) against the
    mean PSNR (dB), FLIP and PSNR over moving pixels (means over sequences), and its Pareto-front marks."""

    resolution: str
    label: str
    method: str
    flow_width: Optional[int]
    fill: Optional[str]
    infill_iterations: Optional[int]
    planes: Optional[int]
    dis_preset: Optional[str]
    sequences: int
    frames: int
    ms_per_frame: float
    psnr: float
    flip: float
    psnr_moving: float
    pareto_psnr: bool = False
    pareto_flip: bool = False


def pareto_front(times: Sequence[float], errors: Sequence[float]) -> list[bool]:
    """Which points are on the Pareto front of time against error, both lower-is-better.

    Point i is on the front when no other point j has ``times[j] <= times[i]`` and ``errors[j] <= errors[i]``
    with at least one strict (nothing is faster for the same error or better for the same time). Points with
    a NaN time or error are never on it and dominate nothing; identical points are both on it. For a
    higher-is-better metric pass its negation (``-psnr``).

    >>> pareto_front([1.0, 2.0, 3.0], [5.0, 6.0, 4.0])
    [True, False, True]
    """
    if len(times) != len(errors):
        raise InputError(f"{len(times)} times but {len(errors)} errors", field="errors")
    valid = [not (math.isnan(t) or math.isnan(e)) for t, e in zip(times, errors)]
    out = []
    for i, (t, e) in enumerate(zip(times, errors)):
        dominated = any(valid[j] and times[j] <= t and errors[j] <= e and (times[j] < t or errors[j] < e)
                        for j in range(len(times)) if j != i)
        out.append(valid[i] and not dominated)
    return out


def decomp_variants(flow_widths: Sequence[int], fills: Sequence[str], infill_iterations: Sequence[int],
                    planes: Sequence[int], models: dict[int, str], options: str = "",
                    base: str = "decomp", dis_presets: Sequence[str] = ("medium",)) -> list[Variant]:
    """Every combination of the knobs as ``decomp[...]`` variants (``infill_iterations`` only with ``fill=infill``;
    ``dis_presets``: OpenCV DIS presets of the initial flow, 'medium' being the default and left unwritten).

    ``models`` maps each Z in ``planes`` to its ONNX flow network ('' for the committed one, see
    ``plane_models``); ``options`` ("key=value,...") are added to every variant and may not set a swept knob.
    """
    extra = option_parts(options)
    clash = [p for p in extra if p.partition("=")[0].strip() in SWEPT_KEYS]
    if clash:
        raise InputError(f"{', '.join(clash)}: swept by the sweep itself (use its own option)", field="decomp_options")
    for name, values in (("flow_width", flow_widths), ("fill", fills), ("planes", planes),
                         ("dis_preset", dis_presets)):
        if not values:
            raise InputError("needs at least one value", field=name)
    if any(w < 0 for w in flow_widths) or any(z < 1 for z in planes) or any(g < 1 for g in infill_iterations):
        raise InputError("flow widths must be >= 0 (0: the network's own), planes and infill iterations >= 1",
                         field="sweep")
    unknown = sorted(set(fills) - {"simple", "infill"})
    if unknown:
        raise InputError(f"unknown fill {', '.join(unknown)}, expected simple or infill", field="fill")
    bad = sorted(set(dis_presets) - {"ultrafast", "fast", "medium"})
    if bad:
        raise InputError(f"unknown DIS preset {', '.join(bad)}, expected ultrafast, fast or medium",
                         field="dis_preset")
    if "infill" in fills and not infill_iterations:
        raise InputError("fill=infill needs at least one infill iteration count", field="infill_iterations")
    missing = [z for z in planes if z not in models]
    if missing:
        raise InputError(f"no flow network for Z = {missing}", field="planes")
    variants = []
    for preset in dict.fromkeys(dis_presets):
        for z in dict.fromkeys(planes):
            for width in dict.fromkeys(flow_widths):
                for fill in dict.fromkeys(fills):
                    for g in (dict.fromkeys(infill_iterations) if fill == "infill" else [None]):
                        opts = extra + [f"flow_width={width}", f"fill={fill}"]
                        opts += [f"infill_iterations={g}"] if g is not None else []
                        opts += [f"model={models[z]}"] if models[z] else []
                        opts += [f"dis_preset={preset}"] if preset != "medium" else []
                        variants.append(Variant(f"{base}[{','.join(opts)}]", width, fill, g, z, preset))
    return variants


def plane_models(planes: Sequence[int], models_dir: Path = DEFAULT_MODELS_DIR,
                 checkpoint: Path = DEFAULT_CHECKPOINT) -> dict[int, str]:
    """Z -> ONNX flow network for each plane count: '' (the committed ``engine/weights/flow3d.onnx``) for its
    own Z, else ``models_dir/flow3d_z{Z}_xy.onnx``, exported from ``checkpoint`` with ``export.flow --num-planes``
    when missing (needs torch; about 2 minutes per Z on 2 CPU cores), with ``--no-depth-flow`` like the
    committed one, so every Z is timed with the same graph (a sweep cannot ask for dz: ``depth_flow=1`` fails
    on the committed graph)."""

    own = FlowNetwork(DEFAULT_MODEL, threads=1).num_planes
    out: dict[int, str] = {}
    for z in dict.fromkeys(planes):
        if z == own:
            out[z] = ""
            continue
        path = Path(models_dir) / f"flow3d_z{z}_xy.onnx"
        if not path.is_file():
            export_args = [str(checkpoint), str(path), "--num-planes", str(z), "--no-depth-flow"]
            command = "interleave export flow " + " ".join(export_args)
            try:
                from export.flow import main as export_flow_main
            except ImportError as exc:
                raise InputError(f"Z = {z} needs the flow network exported for {z} planes; with torch installed "
                                 f"run: {command}", file=path, field="planes") from exc
            if not Path(checkpoint).is_file():
                raise InputError("checkpoint to export the plane variants from not found", file=checkpoint)
            print(f"exporting the flow network for Z = {z} planes: {command}", flush=True)
            export_flow_main(export_args, prog="interleave export flow")
        got = FlowNetwork(path, threads=1).num_planes
        if got != z:
            raise InputError(f"holds a network for {got} planes, expected {z}", file=path, field="planes")
        out[z] = str(path)
    return out


def sweep_points(results: Sequence[tuple[str, MethodResult]], variants: Sequence[Variant]) -> list[SweepPoint]:
    """Aggregate (resolution, result) pairs into one ``SweepPoint`` per (resolution, variant), in variant
    order within each resolution, and mark the Pareto fronts per resolution."""
    points = []
    for resolution in dict.fromkeys(res for res, _ in results):
        group = []
        for v in variants:
            rows = [r for res, r in results if res == resolution and r.method == v.method]
            if not rows:
                continue

            def mean(name: str) -> float:
                vals = [getattr(r, name) for r in rows if not math.isnan(getattr(r, name))]
                return float(sum(vals) / len(vals)) if vals else float("nan")

            group.append(SweepPoint(resolution=resolution, label=v.label, method=v.method, flow_width=v.flow_width,
                                    fill=v.fill, infill_iterations=v.infill_iterations, planes=v.planes,
                                    dis_preset=v.dis_preset,
                                    sequences=len(rows), frames=sum(r.frames for r in rows),
                                    ms_per_frame=float(statistics.median(r.ms_per_frame for r in rows)),
                                    psnr=mean("psnr"), flip=mean("flip"), psnr_moving=mean("psnr_moving")))
        times = [p.ms_per_frame for p in group]
        for p, on in zip(group, pareto_front(times, [-p.psnr for p in group])):
            p.pareto_psnr = on
        for p, on in zip(group, pareto_front(times, [p.flip for p in group])):
            p.pareto_flip = on
        points.extend(group)
    return points


def sweep_table(points: Sequence[SweepPoint]) -> str:
    """One row per (resolution, variant), fastest first within a resolution; the last column names the
    fronts the point is on (PSNR, FLIP)."""
    def knob(value) -> str:
        return "-" if value is None else "native" if value == 0 else str(value)

    lines = ["| size | method | flow_width | fill | g | Z | DIS | frames | ms/frame | PSNR | FLIP | PSNR moving | Pareto |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    order = {res: i for i, res in enumerate(dict.fromkeys(p.resolution for p in points))}
    for p in sorted(points, key=lambda p: (order[p.resolution], p.ms_per_frame)):
        front = ", ".join(name for name, on in (("PSNR", p.pareto_psnr), ("FLIP", p.pareto_flip)) if on) or ""
        method = p.label if p.fill is None else p.method.partition("[")[0]  # baselines keep their options
        lines.append(f"| {p.resolution} | {method} | {knob(p.flow_width)} | {knob(p.fill)} | "
                     f"{knob(p.infill_iterations)} | {knob(p.planes)} | {knob(p.dis_preset)} | {p.frames} | "
                     f"{p.ms_per_frame:.1f} | "
                     f"{p.psnr:.2f} | {score_cell(p.flip, 4)} | {score_cell(p.psnr_moving, 2)} | {front} |")
    return "\n".join(lines)


def plot_sweep(points: Sequence[SweepPoint], path: Path) -> bool:
    """Time against PSNR and FLIP (FLIP only if measured), one row of panels per frame size, front points
    joined by a line; returns False (writes nothing) when matplotlib is not installed."""
    try:
        import matplotlib
    except ImportError:
        return False
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.ticker import FuncFormatter, LogLocator, NullFormatter

    sizes = list(dict.fromkeys(p.resolution for p in points))
    panels = [(metric, on_front, label) for metric, on_front, label in
              (("psnr", "pareto_psnr", "PSNR (dB, higher is better)"),
               ("flip", "pareto_flip", "FLIP (lower is better)"))
              if any(math.isfinite(getattr(p, metric)) for p in points)]
    if not panels:
        return False
    fig, axes = plt.subplots(len(sizes), len(panels), figsize=(6 * len(panels), 4.5 * len(sizes)), squeeze=False)
    colors = {None: "tab:gray", "simple": "tab:blue", "infill": "tab:orange"}
    for row, size in zip(axes, sizes):
        group = [p for p in points if p.resolution == size and p.ms_per_frame > 0]
        for ax, (metric, on_front, label) in zip(row, panels):
            for p in (p for p in group if math.isfinite(getattr(p, metric))):
                ax.scatter([max(p.ms_per_frame, 1e-2)], [getattr(p, metric)], color=colors.get(p.fill, "tab:green"),
                           marker="*" if getattr(p, on_front) else "o", s=110 if getattr(p, on_front) else 35,
                           edgecolor="black" if getattr(p, on_front) else "none", zorder=3)
                ax.annotate(p.label, (max(p.ms_per_frame, 1e-2), getattr(p, metric)), fontsize=6,
                            xytext=(3, 3), textcoords="offset points")
            front = sorted((p for p in group if getattr(p, on_front)), key=lambda p: p.ms_per_frame)
            if len(front) > 1:
                ax.plot([max(p.ms_per_frame, 1e-2) for p in front], [getattr(p, metric) for p in front],
                        color="black", lw=0.8, drawstyle="steps-post", zorder=2)
            ax.set_xscale("log")
            ax.xaxis.set_major_locator(LogLocator(subs=(1.0, 2.0, 5.0)))
            ax.xaxis.set_major_formatter(FuncFormatter(lambda value, _: f"{value:g}"))
            ax.xaxis.set_minor_formatter(NullFormatter())
            ax.set_xlabel("ms per predicted frame (median, log scale)")
            ax.set_ylabel(label)
            ax.set_title(f"{size} (stars: Pareto front; grey: baselines, blue: simple fill, orange: infill)",
                         fontsize=8)
            ax.grid(True, alpha=0.3)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return True


def _ints(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None


def _words(text: str) -> list[str]:
    return [v.strip() for v in text.split(",") if v.strip()]


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """The sweep's options."""
    parser.add_argument("sequences", nargs="+", type=Path, metavar="SEQ_DIR",
                        help="rgbd-seq folders; their frame size is the resolution swept (results are grouped by it)")
    parser.add_argument("--k", type=int, default=2, help="upsampling factor: one rendered frame every k (default: 2)")
    parser.add_argument("--flow-width", type=_ints, default=[480, 240], metavar="W,...",
                        help="flow network input widths in pixels (0: the network's own) (default: 480,240)")
    parser.add_argument("--fill", type=_words, default=["simple", "infill"], metavar="FILL,...",
                        help="disocclusion fills: simple (row fill of reproject) and/or infill (the infilling "
                             "network) (default: simple,infill)")
    parser.add_argument("--infill-iterations", type=_ints, default=[1, 2, 3], metavar="G,...",
                        help="passes g of the infilling network, swept with fill=infill only (default: 1,2,3)")
    parser.add_argument("--planes", type=_ints, default=[4], metavar="Z,...",
                        help="MPI planes of the flow network, e.g. 2,4,8; Z other than the committed network's (4) "
                             "is exported once into --models-dir from --checkpoint, needs torch (default: 4)")
    parser.add_argument("--dis-presets", type=_words, default=["medium"], metavar="PRESET,...",
                        help="OpenCV DIS presets of decomp's initial flow: ultrafast, fast, medium (default: medium)")
    parser.add_argument("--decomp-options", default="", metavar="KEY=VALUE,...",
                        help="DecompConfig options added to every variant, e.g. 'gate.enabled=false' (not the swept knobs)")
    parser.add_argument("--baselines", type=_words, default=["reproject", "flow2d"], metavar="METHOD,...",
                        help="methods measured in the same run (default: reproject,flow2d)")
    parser.add_argument("--models-dir", type=Path, default=DEFAULT_MODELS_DIR,
                        help=f"where the plane-count variants of the flow network live (default: {DEFAULT_MODELS_DIR})")
    parser.add_argument("--checkpoint", type=Path, default=DEFAULT_CHECKPOINT,
                        help="torch checkpoint the plane variants are exported from "
                             "(default: models/weights/flow3d.pt)")
    parser.add_argument("--out", type=Path, default=Path("out/sweep"),
                        help="folder for sweep.json, sweep.md and sweep.png (default: out/sweep)")
    parser.add_argument("--no-flip", action="store_true", help="skip FLIP (about 0.4 s per 960x540 frame); "
                                                               "then only the PSNR front is marked")
    parser.add_argument("--max-groups", type=int, default=None,
                        help="use at most this many rendered frames n per sequence, spread evenly (default: all)")


def run_sweep_command(args: argparse.Namespace) -> int:
    """Run the sweep described by ``add_arguments``' options: print the tables, write sweep.json / .md / .png."""

    unknown = [m for m in args.baselines if m.partition("[")[0] not in METHODS]
    if unknown:
        raise InputError(f"unknown baseline(s) {', '.join(unknown)}; expected some of {', '.join(METHODS)}",
                         field="baselines")
    if args.max_groups is not None and args.max_groups < 1:
        raise InputError(f"must be >= 1, got {args.max_groups}", field="max_groups")
    sequences = [read_sequence(path) for path in args.sequences]  # fail on a bad folder before any export
    # the grid, its options and its networks (e.g. the infilling one) fail now too, not after an export
    trial = decomp_variants(args.flow_width, args.fill, args.infill_iterations, args.planes,
                            dict.fromkeys(args.planes, ""), args.decomp_options, dis_presets=args.dis_presets)
    for fill in dict.fromkeys(args.fill):
        make_predictor(next(v.method for v in trial if v.fill == fill))
    models = plane_models(args.planes, args.models_dir, args.checkpoint)
    variants = [Variant(m) for m in args.baselines] + decomp_variants(
        args.flow_width, args.fill, args.infill_iterations, args.planes, models, args.decomp_options,
        dis_presets=args.dis_presets)
    methods = [v.method for v in variants]
    results: list[tuple[str, MethodResult]] = []
    for sequence in sequences:
        size = f"{sequence.width}x{sequence.height}"
        for r in evaluate_sequence(sequence, methods, args.k, with_flip=not args.no_flip,
                                   max_groups=args.max_groups, progress=True):
            results.append((size, r))
    points = sweep_points(results, variants)
    labels = {v.method: v.label for v in variants}
    parts = [f"Speed against error, k = {args.k} (median ms per predicted frame; means over sequences):\n",
             sweep_table(points)]
    for size in dict.fromkeys(res for res, _ in results):
        relabelled = [dataclasses.replace(r, method=labels[r.method]) for res, r in results if res == size]
        parts += [f"\nStage breakdown at {size}, median ms per predicted frame:\n", stage_table(relabelled)]
    text = "\n".join(parts)
    print(text)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "sweep.md").write_text(text + "\n")
    command = " ".join(sys.argv)
    write_json([r for _, r in results], out / "sweep.json",
               {"command": command, "k": args.k, "resolutions": [res for res, _ in results],
                "points": [dataclasses.asdict(p) for p in points]})
    print(f"wrote {out / 'sweep.md'} and {out / 'sweep.json'}")
    if plot_sweep(points, out / "sweep.png"):
        print(f"wrote {out / 'sweep.png'}")
    else:
        print("no plot: matplotlib is not installed (pip install matplotlib) or no score was finite")
    return 0


def main(argv: Optional[Sequence[str]] = None, prog: str = "python -m tools.sweep") -> int:
    """``python -m tools.sweep SEQ_DIR... [options]`` (run from the repository root)."""
    parser = argparse.ArgumentParser(prog=prog, description=__doc__.split("\n\n")[0])
    add_arguments(parser)
    args = parser.parse_args(None if argv is None else list(argv))
    try:
        return run_sweep_command(args)
    except InterleaveError as exc:
        print(f"{prog}: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
