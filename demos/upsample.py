"""The frame-upsampling demo: render the built-in scene, keep every k-th frame, predict the rest.

``upsample_stream`` is the loop a renderer would run: rendered frames go in, and for every tick a frame
comes out, either the rendered one or one predicted from the last two rendered frames and the camera of
that tick. ``run_demo`` renders the built-in procedural scene, evaluates every method on it, and writes a
side-by-side video (truth | prediction | error) of the best method, the table, the JSON and the plot.
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterator, Sequence

import cv2
import numpy as np

from engine.frames import Frame
from engine.colorspace import display_encode
from engine.metrics import flip_map
from engine.predictors import Predictor, Reproject, Target


@dataclass
class OutputFrame:
    """One displayed tick: its index, linear colour, whether it was predicted, and the true frame of the tick."""

    index: int
    color: np.ndarray
    predicted: bool
    truth: Frame


def upsample_stream(frames: Sequence[Frame], k: int, predictor: Predictor) -> Iterator[OutputFrame]:
    """Show frames 0, k, 2k, ... as rendered and predict the others from the last rendered frames.

    Only each predicted tick's camera and time are read from the frames in between (what a game knows
    before rendering). Until two frames are rendered, a two-frame method falls back to `reproject`.
    """
    fallback = Reproject()
    rendered: list[Frame] = []
    state = None
    for frame in frames:
        if frame.index % k == 0:
            rendered = (rendered + [frame])[-2:]
            method = predictor if len(rendered) >= predictor.history_needed else fallback
            state = method.prepare(rendered)
            yield OutputFrame(frame.index, frame.color, False, frame)
        elif state is not None:
            pred = method.render(state, Target(frame.camera, frame.time, frame.index))
            yield OutputFrame(frame.index, pred.color, True, frame)


def _label(image: np.ndarray, text: str) -> np.ndarray:
    cv2.putText(image, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (0, 0, 0), 3, cv2.LINE_AA)
    cv2.putText(image, text, (8, 22), cv2.FONT_HERSHEY_SIMPLEX, 0.6, (255, 255, 255), 1, cv2.LINE_AA)
    return image


def side_by_side(truth: np.ndarray, shown: np.ndarray, predicted: bool, index: int, method: str) -> np.ndarray:
    """truth | shown frame | FLIP error (magma), as one 8-bit BGR image with labels."""
    import matplotlib

    a, b = display_encode(truth), display_encode(shown)
    err = flip_map(a, b) if predicted else np.zeros(a.shape[:2], np.float32)
    err_rgb = matplotlib.colormaps["magma"](err)[..., :3]
    tiles = [(a, f"truth {index}"), (b, f"{method} (predicted)" if predicted else "rendered"),
             (err_rgb, f"FLIP error {err.mean():.3f}")]
    out = [_label(cv2.cvtColor((t * 255 + 0.5).astype(np.uint8), cv2.COLOR_RGB2BGR), s) for t, s in tiles]
    return np.concatenate(out, axis=1)


def run_demo(out_dir: Path, *, k: int = 2, seed: int = 7, frames: int = 48, width: int = 640,
             height: int = 360, methods: Sequence[str] = ("repeat", "reproject", "flow2d", "decomp", "oracle"),
             progress: bool = True) -> dict:
    """Render the built-in scene into ``out_dir/scene``, evaluate ``methods``, write video and reports.

    Returns the evaluation summary; prints the table.
    """
    from tqdm import tqdm

    from engine.evaluate import evaluate_sequence, markdown_table, plot, stage_table, summarize, write_json
    from engine.io import read_sequence
    from engine.predictors import make_predictor
    from engine.scenegen import SceneConfig, generate_sequence

    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    scene_dir = generate_sequence(SceneConfig(width=width, height=height, num_frames=frames, seed=seed),
                                  out_dir / "scene", progress=progress)
    sequence = read_sequence(scene_dir)
    results = evaluate_sequence(sequence, list(methods), k, progress=progress)
    table = markdown_table(results) + "\n\nStage breakdown, median ms per predicted frame:\n\n" + stage_table(results)
    (out_dir / "table.md").write_text(table + "\n")
    write_json(results, out_dir / "results.json", {"command": f"interleave demo --k {k} --seed {seed}"})
    plot(results, out_dir / "speed_vs_error.png")
    print(table)

    candidates = [r for r in results if r.method != "oracle"]
    best = max(candidates, key=lambda r: r.psnr).method
    predictor = make_predictor(best, sequence.objects)
    writer = cv2.VideoWriter(str(out_dir / "side_by_side.mp4"), cv2.VideoWriter_fourcc(*"mp4v"),
                             float(sequence.fps), (3 * sequence.width, sequence.height))
    stills = 0
    for shown in tqdm(upsample_stream(sequence, k, predictor), total=len(sequence), desc="video",
                      disable=not progress, unit="frame"):
        image = side_by_side(shown.truth.color, shown.color, shown.predicted, shown.index, best)
        writer.write(image)
        if shown.predicted and stills < 3 and shown.index >= len(sequence) // 2:
            cv2.imwrite(str(out_dir / f"still_{shown.index:04d}.png"), image)
            stills += 1
    writer.release()
    print(f"best non-oracle method: {best}; wrote {out_dir / 'side_by_side.mp4'}, {out_dir / 'table.md'}, "
          f"{out_dir / 'results.json'}, {out_dir / 'speed_vs_error.png'}")
    return summarize(results)
