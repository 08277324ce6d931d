"""`interleave`: the command-line entry point.

Subcommands: ``demo`` (the frame-upsampling demo on the built-in scene), ``eval`` (speed against error
on rgbd-seq sequences; ``eval --bounds`` the performance bounds of thesis Table 6.3; ``eval field RUN_DIR``
scores a trained radiance field), ``render-scene`` (write a
procedural dynamic scene as rgbd-seq), ``render-rig`` (the same scene seen by a rig of fixed cameras, as
rgbd-rig), ``import`` (convert Blender, MPI-Sintel or DeCOMPnet/VEED layouts to rgbd-seq), ``train`` /
``export`` (``flow`` network, static ``field``; need torch), ``play`` (a live window, or a video, of a renderer
drawing every k-th frame and Interleave generating the rest) and ``serve`` (prediction sessions for game
engines over a local socket). Bad input ends with one line naming the problem and exit status 2, never a
traceback.
"""
from __future__ import annotations

import argparse
import importlib
import sys
from pathlib import Path
from typing import Optional, Sequence

from engine.core.config import add_options, config_from_args
from engine.core.errors import InputError, InterleaveError
from engine.geometry.backends import BACKEND_CHOICES

METHOD_HELP = ("comma-separated predictors: repeat (last rendered frame), reproject (camera-only depth "
               "reprojection, background hole fill), flow2d (camera warp + OpenCV DIS optical flow, linear "
               "extrapolation), decomp (DeCOMPnet: 3D object flow on MPIs, ONNX network), decomp2d (its 2D "
               "ablation network), mvec (the renderer's motion vectors, motion.X/Y, extrapolated in 3D; "
               "mvec[undilate=true] for dilated vectors), auto (mvec where a sequence has motion vectors, else "
               "flow2d), oracle (true object motion; needs object_id and objects). decomp and "
               "decomp2d take options in brackets, e.g. decomp[gate.enabled=false,flow_width=240] "
               "(engine/predict/decomp/predictor.py); a name "
               "ending in +true_holes is scored with the true pixels in its holes (perfect infilling)")

BACKEND_HELP = ("where the warps run: cpu (numpy + numba), gl (OpenGL 4.5 compute, frames kept on the GPU; "
                "decomp prepares on the CPU but for decomp[estimator=gl]'s initial flow) or auto (gl on a hardware "
                "GPU, else cpu) (default: auto)")

#: The torch-side entry points that ``train`` and ``export`` dispatch to: each module's ``main(argv, prog)``.
#: Imported only when asked for, so every other command runs without torch.
TORCH_COMMANDS = {
    "train": {"flow": "models.flow.train", "corrflow": "models.flow.corrflow_train", "infill": "models.infill.train",
              "field": "models.fields.train_static", "dynamic": "models.fields.train_dynamic"},
    "export": {"flow": "export.flow", "corrflow": "export.corrflow", "infill": "export.infill",
               "field": "export.field", "dynamic": "export.dynamic"},
}


def _int_list(text: str) -> list[int]:
    try:
        return [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected comma-separated integers, got '{text}'") from None


def build_parser() -> argparse.ArgumentParser:
    from engine.scenegen import SceneConfig

    parser = argparse.ArgumentParser(
        prog="interleave",
        description="Interleave: predict the frames a renderer skips (interleaved reprojection) from past RGB-D "
                    "frames and camera poses.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    demo = sub.add_parser("demo", help="render the built-in scene, predict every in-between frame, write a "
                                       "side-by-side video and the speed/error table",
                          description="Renders the built-in procedural scene, keeps every k-th frame as "
                                      "'rendered', predicts the rest with every method, prints the eval table and "
                                      "writes side_by_side.mp4 (truth | prediction | FLIP error) for the best "
                                      "non-oracle method, results.json, table.md and speed_vs_error.png.")
    demo.add_argument("--out", type=Path, default=Path("out/demo"), help="output folder (default: out/demo)")
    demo.add_argument("--k", type=int, default=2, help="upsampling factor: one rendered frame every k (default: 2)")
    demo.add_argument("--seed", type=int, default=7, help="seed of the built-in scene (default: 7)")
    demo.add_argument("--frames", type=int, default=48, help="frames to render (default: 48)")
    demo.add_argument("--width", type=int, default=640, help="frame width in pixels (default: 640)")
    demo.add_argument("--height", type=int, default=360, help="frame height in pixels (default: 360)")
    demo.add_argument("--methods", default="repeat,reproject,flow2d,decomp,mvec,oracle", help=METHOD_HELP)
    demo.add_argument("--backend", choices=BACKEND_CHOICES, default="auto", help=BACKEND_HELP)
    demo.add_argument("--field", type=Path, default=None, metavar="RUN_OR_EXPORT_DIR",
                      help="render a trained radiance field (the folder 'interleave export field|dynamic' wrote, or "
                           "its run folder) with the GL field renderer along a camera path through its scene instead "
                           "of the built-in scene (a dynamic field over its trained times, with its own motion "
                           "vectors for mvec); the truth of a predicted frame is the field's render at its pose and "
                           "time (oracle is skipped)")

    ev = sub.add_parser("eval", help="score predictors on rgbd-seq sequences: PSNR, SSIM, FLIP, time per frame "
                                     "('interleave eval field RUN_DIR' scores a trained radiance field)",
                        description="For every rendered frame n (every k-th) with history, each method predicts "
                                    "n+1..n+k-1 from frames n-k and n; predictions are scored on sRGB-encoded "
                                    "frames with DeCOMPnet's proportional border crop, over the whole crop and over "
                                    "moving pixels. Time per predicted frame is the median, preparation amortised.")
    ev.add_argument("sequences", nargs="+", type=Path, metavar="SEQ_DIR", help="rgbd-seq folders")
    ev.add_argument("--k", type=_int_list, default=[2], help="upsampling factor(s), comma-separated (default: 2)")
    ev.add_argument("--methods", default="repeat,reproject,flow2d,decomp,mvec,oracle", help=METHOD_HELP)
    ev.add_argument("--backend", choices=BACKEND_CHOICES, default="auto", help=BACKEND_HELP)
    ev.add_argument("--json", type=Path, default=None, help="write records and summary to this JSON file")
    ev.add_argument("--plot", type=Path, default=None, help="write the time-against-error plot to this PNG")
    ev.add_argument("--no-flip", action="store_true", help="skip FLIP (about 0.4 s per 960x540 frame)")
    ev.add_argument("--max-groups", type=_positive_int, default=None,
                    help="use at most this many rendered frames n per sequence, spread evenly (default: all)")
    ev.add_argument("--bounds", nargs="?", const="decomp", default=None, metavar="DECOMP_VARIANT",
                    help="instead of --methods, the performance bounds of thesis Table 6.3 for this decomp variant "
                         "(default: decomp; e.g. 'decomp[fill=simple]'): local motion prediction and disocclusion "
                         "infilling each predicted or true (motion=truth; true pixels in the holes); needs the "
                         "sequences' objects")

    rs = sub.add_parser("render-scene", help="render a procedural dynamic scene to an rgbd-seq folder",
                        description="Deterministic by --seed: camera path, moving rigid objects, textures, thin "
                                    "structures, sky at infinite depth, lighting, and ground truth (depth, poses, "
                                    "object ids, moving mask, total and object-only flow). Headless (EGL).")
    rs.add_argument("out", type=Path, metavar="OUT_DIR", help="folder to write (sequence.json + frames/)")
    from engine.scenegen.presets import PRESETS

    rs.add_argument("--preset", choices=list(PRESETS), default="gentle",
                    help="motion preset the options below start from (engine/scenegen/presets.py): gentle (the "
                         "defaults), medium, fast (the 10-35 px a frame of path-traced game footage: fast objects "
                         "and spins, fast camera yaw, thin structures, Monte Carlo-like noise), extreme")
    add_options(rs, SceneConfig)

    from engine.scenegen import RigConfig

    rr = sub.add_parser("render-rig", help="render a procedural scene from a rig of fixed cameras to an rgbd-rig "
                                           "capture (radiance-field training data with true depth)",
                        description="Samples the scene of --seed like render-scene, places --num-cameras fixed, "
                                    "synchronized cameras around its camera path's mid-sequence eye, all looking at "
                                    "its target (docs/scenegen.md, Rigs), and writes cam0..camN-1 as rgbd-seq with "
                                    "every ground-truth channel plus rig.json with the train/test split. "
                                    "--static: no moving objects, one frame. Headless (EGL).")
    rr.add_argument("out", type=Path, metavar="OUT_DIR", help="folder to write (rig.json + cam0/ ...)")
    add_options(rr, SceneConfig)
    add_options(rr, RigConfig, skip=("scene",))

    imp = sub.add_parser("import", help="convert Blender multilayer EXR, MPI-Sintel or DeCOMPnet/VEED data to rgbd-seq",
                         description="See engine/io/importers.py for each layout's expected files.")
    imp.add_argument("layout", choices=["blender", "sintel", "veed"], help="the source layout")
    imp.add_argument("src", type=Path, help="source folder (for sintel: the dataset root, with --scene)")
    imp.add_argument("dst", type=Path, help="rgbd-seq folder to write")
    imp.add_argument("--scene", default=None, help="MPI-Sintel scene name, e.g. alley_1")
    imp.add_argument("--fps", type=float, default=None,
                     help="frame rate to record, sintel and veed (default: 24 for sintel, 30 for veed; blender "
                          "reads it from cameras.json)")
    imp.add_argument("--depth-channel", default=None,
                     help="veed: the EXR channel holding planar depth (default: B, as in the authors' data)")
    imp.add_argument("--skip-missing", action="store_true", help="skip frames with missing files (warn) "
                                                                 "instead of stopping with an error")
    descriptions = {
        "train": ("train a network (needs the 'train' extra: torch)",
                  "'interleave train flow --config configs/flow3d.json' trains the 3D flow network; 'interleave train "
                  "corrflow' the correlation flow network of flow2d[estimator=corr]; 'interleave "
                  "train infill' the disocclusion infilling network; 'interleave train field --scene DIR --views 3' "
                  "a static radiance field; 'interleave train dynamic --scene DIR' a dynamic one (rgbd-rig video or "
                  "D-NeRF); 'interleave train flow|field|dynamic --help' lists every option."),
        "export": ("export a trained network to ONNX (needs the 'train' extra: torch)",
                   "'interleave export flow CHECKPOINT OUT.onnx' writes the flow network's ONNX graph and checks it "
                   "against torch ('export infill CHECKPOINT OUT.onnx': the infilling network's, 'export corrflow "
                   "CHECKPOINT OUT.onnx' the correlation flow network's); 'interleave export "
                   "field RUN_DIR' a trained field's ONNX query and renderer assets ('export dynamic RUN_DIR': a "
                   "dynamic field's (p, t, d) query); '... --help' for options."),
    }
    for command, (help_text, description) in descriptions.items():
        sp = sub.add_parser(command, help=help_text, description=description)
        sp.add_argument("what", choices=list(TORCH_COMMANDS[command]), help=f"what to {command}")
        sp.add_argument("options", nargs=argparse.REMAINDER, help=f"options of that {command}er (see its --help)")
    from demos.play import PlayConfig

    pl = sub.add_parser("play", help="a live window where the renderer draws every k-th frame and Interleave "
                                     "generates the rest (headless: a video)",
                        description="The built-in scene (or an exported field, --field) renders every k-th frame and "
                                    "the predictor generates the others, with an overlay of rendered and generated "
                                    "fps and per-stage ms. Keys: M method, K k, S split view (truth | generated | "
                                    "error), Q or Esc quit. --record OUT.mp4 records headless; without a display "
                                    "(or pyglet) it says so in one line and records to out/play/play.mp4. Prints a "
                                    "one-line summary (docs/play.md).")
    add_options(pl, PlayConfig)
    sv = sub.add_parser("serve", help="serve prediction sessions to game engines over a local socket",
                        description="Binary protocol over a Unix socket or TCP on 127.0.0.1, frames in shared memory "
                                    "(docs/server.md, engine/runtime/include/interleave_protocol.h). Runs until SIGINT or "
                                    "SIGTERM, then unlinks every shared-memory segment and the socket file.")
    sv.add_argument("--listen", default="default",
                    help="unix:/path/to.sock or tcp:PORT (127.0.0.1 only; tcp:0 picks a free port) (default: "
                         "$XDG_RUNTIME_DIR/interleave.sock, else /tmp/interleave-UID/interleave.sock in a folder "
                         "only this user can enter)")
    sv.add_argument("--models", type=Path, default=None,
                    help="folder of the networks decomp sessions use (flow3d.onnx, flow2d.onnx, infill.onnx; "
                         "default: the committed engine/weights); clients cannot name files")
    sv.add_argument("--backend", choices=BACKEND_CHOICES, default="auto", help=BACKEND_HELP)
    from engine.runtime.server import ServerLimits

    add_options(sv, ServerLimits)
    return parser


def _needs_torch(command: str):
    try:
        import torch  # noqa: F401
    except ImportError as exc:
        raise InterleaveError(f"'interleave {command}' needs torch: pip install -e '.[train]'") from exc


def _methods(text: str) -> list[str]:
    from engine.predict import split_methods

    methods = split_methods(text)
    if not methods:
        raise InputError("names no method", field="--methods")
    return methods


def main(argv: Optional[Sequence[str]] = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    # 'interleave eval field|dynamic RUN_DIR': radiance-field runs, not rgbd-seq sequences
    field_evals = {"field": TORCH_COMMANDS["train"]["field"], "dynamic": TORCH_COMMANDS["train"]["dynamic"]}
    if argv[:1] == ["eval"] and argv[1:2] and argv[1] in field_evals:
        command = f"eval {argv[1]}"
        try:
            _needs_torch(command)
        except InterleaveError as exc:
            print(f"interleave {command}: error: {exc}", file=sys.stderr)
            return 2
        return importlib.import_module(field_evals[argv[1]]).eval_main(argv[2:], prog=f"interleave {command}")
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.command == "demo" and args.field is not None:
            from demos.upsample import run_field_demo

            run_field_demo(args.field, args.out, k=args.k, frames=args.frames, width=args.width, height=args.height,
                           methods=_methods(args.methods), backend=args.backend)
        elif args.command == "demo":
            from demos.upsample import run_demo

            run_demo(args.out, k=args.k, seed=args.seed, frames=args.frames, width=args.width, height=args.height,
                     methods=_methods(args.methods), backend=args.backend)
        elif args.command == "play":
            from demos.play import PlayConfig, play

            print(play(config_from_args(PlayConfig, args)).line())
        elif args.command == "eval":
            return _run_eval(args)
        elif args.command == "render-scene":
            from engine.scenegen import SceneConfig, generate_sequence
            from engine.scenegen.presets import preset_config

            config = config_from_args(SceneConfig, args, preset_config(args.preset))
            path = generate_sequence(config, args.out, progress=True)
            print(f"wrote {path}")
        elif args.command == "render-rig":
            from engine.scenegen import RigConfig, SceneConfig, generate_rig

            config = config_from_args(RigConfig, args, RigConfig(scene=config_from_args(SceneConfig, args)))
            path = generate_rig(config, args.out, progress=True)
            print(f"wrote {path}")
        elif args.command == "import":
            from engine.io.importers import import_any

            kwargs = {k: v for k, v in (("scene", args.scene), ("fps", args.fps),
                                        ("depth_channel", args.depth_channel)) if v is not None}
            allowed = {"blender": set(), "sintel": {"scene", "fps"}, "veed": {"fps", "depth_channel"}}[args.layout]
            if args.layout == "sintel" and "scene" not in kwargs:
                raise InputError("layout sintel needs --scene NAME (one of the folders under SRC/final)",
                                 field="--scene")
            if set(kwargs) - allowed:
                raise InterleaveError(f"layout {args.layout} does not take "
                                      f"{', '.join('--' + k.replace('_', '-') for k in sorted(set(kwargs) - allowed))}")
            path = import_any(args.src, args.dst, args.layout, skip_missing=args.skip_missing, progress=True, **kwargs)
            print(f"wrote {path}")
        elif args.command in TORCH_COMMANDS:
            _needs_torch(args.command)
            module = importlib.import_module(TORCH_COMMANDS[args.command][args.what])
            result = module.main(args.options, prog=f"interleave {args.command} {args.what}")
            return result if isinstance(result, int) else 0
        elif args.command == "serve":
            from engine.runtime.server import ServerLimits, parse_address, serve

            serve(parse_address(args.listen), config_from_args(ServerLimits, args), args.models, backend=args.backend)
    except InterleaveError as exc:
        print(f"interleave {args.command}: error: {exc}", file=sys.stderr)
        return 2
    return 0


def _check_output_file(path: Path, name: str) -> None:
    """An output file the command will write at the end: its folder must be creatable and writable and the
    path must not be a folder."""
    path = Path(path)
    if path.is_dir():
        raise InputError("is a folder, not a file", file=path, field=name)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create its folder ({exc.strerror})", file=path, field=name) from None
    existed = path.exists()
    try:
        with open(path, "a"):
            pass
    except OSError as exc:
        raise InputError(f"cannot be written ({exc.strerror})", file=path, field=name) from None
    if not existed:
        path.unlink()


def _positive_int(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if value < 1:
        raise argparse.ArgumentTypeError(f"must be >= 1, got {value}")
    return value


def _run_eval(args: argparse.Namespace) -> int:
    from engine.eval.protocol import (bound_methods, bounds_summary, bounds_table, evaluate_sequence, markdown_table,
                                      per_step_table, plot, split_scoring, stage_table, summarize, write_json)
    from engine.io.rgbd import read_sequence
    from engine.predict import METHODS

    bounds = None if args.bounds is None else bound_methods(args.bounds)
    methods = _methods(args.methods) if bounds is None else [row.method for row in bounds]
    unknown = [m for m in methods if split_scoring(m)[0].partition("[")[0] not in METHODS]
    if unknown:  # fail before any work
        raise InterleaveError(f"unknown method(s) {', '.join(unknown)}; expected some of {', '.join(METHODS)}")
    for name, path in (("--json", args.json), ("--plot", args.plot)):
        if path is not None:
            _check_output_file(path, name)  # before any work, not after it
    sequences = [read_sequence(path) for path in args.sequences]  # every sequence's metadata before any work
    results = []
    for sequence in sequences:
        for k in args.k:
            results.extend(evaluate_sequence(sequence, methods, k, with_flip=not args.no_flip,
                                             max_groups=args.max_groups, progress=True, backend=args.backend))
    if bounds is None:
        print(markdown_table(results))
    else:
        print(f"Performance bounds of {args.bounds} (thesis Table 6.3; LMP: local motion prediction, DI: "
              "disocclusion infilling; pred: the method's own, GT: true motion / true pixels in the holes):\n")
        print(bounds_table(results, bounds))
    if any(k > 2 for k in args.k):
        print("\nPer future step k' (frame n + k' from frames n-k and n), means over sequences:\n")
        print(per_step_table(results))
    print("\nStage breakdown, median ms per predicted frame:\n")
    print(stage_table([r for r in results if not split_scoring(r.method)[1]]))  # +true_holes: same times
    if args.json:
        extra = {"command": " ".join(sys.argv)}
        if bounds is not None:
            extra.update(bounds_variant=args.bounds, bounds=bounds_summary(results, bounds))
        write_json(results, args.json, extra)
        print(f"wrote {args.json}")
    if args.plot:
        plot(results, args.plot)
        print(f"wrote {args.plot}")
    summary = summarize(results)
    for k in args.k:
        rep = [r for r in results if r.method == "reproject" and r.k == k]
        rpt = [r for r in results if r.method == "repeat" and r.k == k]
        if rep and rpt:
            wins = sum(a.psnr > b.psnr for a, b in zip(rep, rpt))
            print(f"k={k}: reproject beats repeat (PSNR) on {wins} of {len(rep)} sequences")
    return 0 if summary else 1


if __name__ == "__main__":
    sys.exit(main())
