"""Multi-camera rigs on procedural scenes: synchronized captures with exact depth, for the radiance fields.

``make_rig(RigConfig(...))`` samples the scene of ``config.scene`` with ``make_scene`` and places
``num_cameras`` FIXED cameras (a rig: the same pose at every frame) around it; ``generate_rig`` renders
every camera with one GL context and writes an rgbd-rig capture (``engine.io.rgbd.write_rig``): ``cam0`` ..
``cam<N-1>``, each an rgbd-seq with linear-sRGB colour, planar depth, object_id, moving, flow, object_flow
and the per-frame ``world_from_object`` of the moving objects, plus the train/test split in ``rig.json``.

Placement, derived deterministically from the scene (pure numpy, no randomness of its own):

- The rig centre ``E`` is the sampled camera path's eye at mid-sequence (``CameraPath.eye(t_mid)``), the
  common target ``T`` is the path's look-at target; every rig camera looks at ``T`` (z up, no roll) with
  the path's field of view at ``t_mid`` (square pixels, principal point at the image centre).
- ``forward-facing`` (an LLFF-like capture): a grid of ``rows`` rows in the plane through ``E``
  perpendicular to the viewing direction ``T - E``. Rows run along the camera's right axis (horizontal),
  centred on ``E``, ``baseline * |T - E|`` wide from the first to the last camera; the bottom row passes
  through ``E`` and further rows are stacked above it along the camera's up axis, one camera spacing
  (width / (columns - 1)) apart.
- ``orbit``: the cameras lie on an arc of the horizontal circle about the vertical axis through ``T`` that
  passes through ``E``; the arc spans ``baseline`` radians (arc length ``baseline`` times the horizontal
  distance), centred on ``E``; further rows are stacked above, one arc spacing apart.
- Cameras are numbered row by row (top row first), left to right as seen from the rig.
- Test cameras (``test_cameras`` of them) are interpolated between train cameras: only cameras that are
  not at either end of their row (and, with 3 or more rows, not in the first or last row) qualify, and the
  chosen ones are spread evenly over those; every other camera trains.

Clearance rule (no camera inside or right against geometry): every rig camera centre must be at least
``MIN_CAMERA_HEIGHT`` (0.4 m) above the ground and ``CAMERA_CLEARANCE`` (0.6 m) inside the walls and
ceiling of an enclosing room; while a camera is not, the whole layout is shrunk about ``E`` by ``SHRINK``
(at most ``MAX_SHRINKS`` times; ``E`` lies on the sampled path, so this converges) and ``Rig.spread``
records the factor applied (1.0 in practice: no camera is lower than ``E``). The configured baseline is
otherwise kept exactly: a static part whose bounding box comes within ``CAMERA_CLEARANCE`` of a rig
camera (a prop, pole, wire or fence bar placed clear of the sampled path but not of the rig) is removed,
as the path sampler rejects parts it cannot keep clear, and so is a moving object that comes within
``CAMERA_CLEARANCE`` plus its bounding radius of a rig camera at any frame time (or the time one frame
past the last, for flow); the other objects keep their ids. ``Rig.dropped_parts`` and
``Rig.dropped_objects`` name what was removed.

The shadow map is fitted once, to the scene's own camera path, and shared by every rig camera, so all
cameras see exactly the same lighting.

>>> rig = make_rig(RigConfig(scene=SceneConfig(seed=3, width=96, height=64), static=True))
>>> rig.names, rig.train_cameras, rig.test_cameras
(('cam0', 'cam1', 'cam2', 'cam3'), ('cam0', 'cam1', 'cam3'), ('cam2',))
>>> generate_rig(RigConfig(scene=SceneConfig(seed=3), static=True), "out/rig3")  # doctest: +SKIP
"""
from __future__ import annotations

import dataclasses
import json
import math
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Iterator

import numpy as np
from tqdm import tqdm

from engine.conventions.cameras import look_at
from engine.core.config import option
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame
from engine.io.rgbd import write_rig
from engine.scenegen.render import SceneRenderer
from engine.scenegen.sample import box_distance, make_scene
from engine.scenegen.scene import CAMERA_CLEARANCE, CameraPath, Scene, SceneConfig

__all__ = ["ARRANGEMENTS", "MIN_CAMERA_HEIGHT", "Rig", "RigConfig", "camera_split", "generate_rig", "make_rig",
           "render_rig"]

#: Camera arrangements ``RigConfig.arrangement`` may name.
ARRANGEMENTS = ("forward-facing", "orbit")
#: Lowest a rig camera centre may be above the ground, metres (the path sampler's lowest eye is 0.4-0.5 m).
MIN_CAMERA_HEIGHT = 0.4
#: Factor the layout is scaled by, about the rig centre, while a camera is not clear of the scene.
SHRINK = 0.8
#: Most shrink steps before giving up (0.8 ** 20 is about 1 %).
MAX_SHRINKS = 20


@dataclass(frozen=True)
class RigConfig:
    """What to capture: a procedural scene and a rig of fixed, synchronized cameras looking at it."""

    scene: SceneConfig = option(SceneConfig(), "the scene (every SceneConfig option; its camera path only "
                                               "places the rig)")
    num_cameras: int = option(4, "number of rig cameras")
    test_cameras: int = option(1, "cameras held out for testing, each between train cameras (never at the end "
                                  "of a row)")
    arrangement: str = option("forward-facing", "camera layout: " + ", ".join(ARRANGEMENTS)
                              + " (a grid facing the target, or an arc around it)")
    baseline: float = option(0.2, "spread of the cameras: forward-facing, the rig's width as a fraction of the "
                                  "distance to the target; orbit, the arc's angle in radians")
    rows: int = option(1, "rows of cameras, stacked upwards one camera spacing apart (num_cameras must be a "
                          "multiple)")
    static: bool = option(False, "static capture: sets the scene's num_objects to 0,0 and num_frames to 1")

    def __post_init__(self) -> None:
        if not isinstance(self.scene, SceneConfig):
            raise InputError(f"must be a SceneConfig, got {type(self.scene).__name__}", field="scene")
        if self.static:  # applied here, so that the saved config says what was rendered
            object.__setattr__(self, "scene", replace(self.scene, num_objects=(0, 0), num_frames=1))
        n, rows = self.num_cameras, self.rows
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise InputError(f"num_cameras must be an integer >= 2, got {n!r}", field="num_cameras")
        if isinstance(rows, bool) or not isinstance(rows, int) or rows < 1 or n % rows or n // rows < 2:
            raise InputError(f"rows must divide num_cameras into rows of at least 2 cameras, got rows={rows!r} "
                             f"for {n} cameras", field="rows")
        if self.arrangement not in ARRANGEMENTS:
            raise InputError(f"arrangement must be one of {', '.join(ARRANGEMENTS)}, got {self.arrangement!r}",
                             field="arrangement")
        limit = 2.0 if self.arrangement == "forward-facing" else 2.0 * math.pi
        if not (isinstance(self.baseline, (int, float)) and 0.0 < self.baseline <= limit):
            raise InputError(f"baseline must be in (0, {limit:.4g}] for a {self.arrangement} rig, got "
                             f"{self.baseline!r}", field="baseline")
        m, candidates = self.test_cameras, len(_test_candidates(n // rows, rows))
        if isinstance(m, bool) or not isinstance(m, int) or not 0 <= m <= candidates:
            raise InputError(f"test_cameras must be in 0..{candidates} ({n} cameras in {rows} row(s) have "
                             f"{candidates} not at the end of a row or in an outer row), got {m!r}",
                             field="test_cameras")


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Rig:
    """A scene and the fixed cameras of a rig (see the module docstring for the placement rules)."""

    config: RigConfig
    scene: Scene
    """the sampled scene less any dropped part or object; its camera is the sampled path (it fits the shadow map)"""
    cameras: tuple[CameraPath, ...]
    """one motionless path per rig camera"""
    names: tuple[str, ...]
    train_cameras: tuple[str, ...]
    test_cameras: tuple[str, ...]
    centre: np.ndarray = field(repr=False)
    """(3,) the rig centre E (the path's eye at mid-sequence), world"""
    target: np.ndarray = field(repr=False)
    """(3,) the point every camera looks at, world"""
    spread: float
    """scale applied to the configured layout for clearance (1.0: not shrunk)"""
    dropped_parts: tuple[str, ...]
    """names of static parts removed because they came too close to a rig camera"""
    dropped_objects: tuple[int, ...]
    """ids of moving objects removed because they came too close to a rig camera"""

    @property
    def num_frames(self) -> int:
        return self.scene.num_frames

    def camera_scene(self, camera: int | str) -> Scene:
        """The scene seen from one rig camera (index or name): ``scene`` with that camera's path."""
        k = self.names.index(camera) if isinstance(camera, str) else int(camera)
        return replace(self.scene, camera=self.cameras[k])

    def camera_at(self, camera: int | str, index: int = 0) -> Camera:
        """The Camera (intrinsics, world_to_camera) of one rig camera at frame ``index`` (the same at every frame)."""
        return self.camera_scene(camera).camera_at(index)


def _test_candidates(cols: int, rows: int) -> list[int]:
    """Camera numbers (row-major) that may be test cameras: not at the end of a row nor in an outer row (3+ rows)."""
    inner_rows = range(1, rows - 1) if rows >= 3 else range(rows)
    return [r * cols + c for r in inner_rows for c in range(1, cols - 1)]


def camera_split(config: RigConfig) -> tuple[list[int], list[int]]:
    """(train, test) camera numbers (row-major) of a rig: ``test_cameras`` inner cameras spread evenly."""
    cols = config.num_cameras // config.rows
    candidates = _test_candidates(cols, config.rows)
    m = config.test_cameras
    test = [candidates[int(math.floor((i + 0.5) * len(candidates) / m))] for i in range(m)]
    return [k for k in range(config.num_cameras) if k not in test], test


def _layout(config: RigConfig, centre: np.ndarray, target: np.ndarray, scale: float) -> np.ndarray:
    """Camera centres (num_cameras, 3), row-major, for the layout scaled by ``scale`` about ``centre``."""
    rows, cols = config.rows, config.num_cameras // config.rows
    col = np.tile(np.arange(cols) - (cols - 1) / 2.0, rows)  # left to right
    row = np.repeat(rows - 1.0 - np.arange(rows), cols)  # top row first (+ up); the bottom row passes through E
    distance = float(np.linalg.norm(target - centre))
    if config.arrangement == "forward-facing":
        rotation = look_at(centre, target)  # the rig's own view: rows right, down, forward
        right, up = rotation[0], -rotation[1]
        spacing = scale * config.baseline * distance / (cols - 1)
        return centre + spacing * (col[:, None] * right + row[:, None] * up)
    offset = centre[:2] - target[:2]
    radius = float(np.linalg.norm(offset))
    if radius < 1e-6:
        raise InputError("the rig centre is straight above the target: no orbit about it", field="arrangement")
    step = scale * config.baseline / (cols - 1)  # radians; increasing angle moves the camera to its right
    angle = math.atan2(offset[1], offset[0]) + step * col
    height = centre[2] + step * radius * row
    return np.stack([target[0] + radius * np.cos(angle), target[1] + radius * np.sin(angle), height], -1)


def _bounds_clear(scene: Scene, eyes: np.ndarray) -> bool:
    """Whether every eye (N, 3) is high enough above the ground and inside the enclosing room, if any."""
    if eyes[:, 2].min() < MIN_CAMERA_HEIGHT:
        return False
    for part in scene.static_parts:
        if part.shape == "room":  # keep off the walls and the ceiling
            inv = np.linalg.inv(part.transform)
            local = eyes @ inv[:3, :3].T + inv[:3, 3]
            hx, hy, hz = part.size
            if (np.abs(local[:, :2]) > np.array([hx, hy]) - CAMERA_CLEARANCE).any() \
                    or (local[:, 2] > 2 * hz - CAMERA_CLEARANCE).any():
                return False
    return True


def make_rig(config: RigConfig) -> Rig:
    """Sample the scene of ``config`` and place the rig's cameras (deterministic; pure numpy, no GL).

    See the module docstring for the layout and the clearance rule.

    Raises:
        InputError: a bad config, or no shrink of the layout keeps the cameras above the ground and inside
            an enclosing room (not seen in practice: another seed or a smaller baseline will do).
    """
    scene = make_scene(config.scene)
    path = scene.camera
    t_mid = path.t_mid
    centre = np.asarray(path.eye(t_mid), np.float64)
    target = np.asarray(path.target, np.float64)
    scale = 1.0
    for _ in range(MAX_SHRINKS + 1):
        eyes = _layout(config, centre, target, scale)
        if _bounds_clear(scene, eyes):
            break
        scale *= SHRINK
    else:
        raise InputError(f"no rig layout down to {scale / SHRINK:.3g} x the baseline keeps every camera "
                         f"{MIN_CAMERA_HEIGHT} m above the ground and inside the scene (seed {config.scene.seed}); "
                         f"try another seed or a smaller baseline", field="baseline")

    kept_parts = [p for p in scene.static_parts
                  if p.shape in ("plane", "room") or box_distance(eyes, p).min() > CAMERA_CLEARANCE]
    times = np.arange(scene.num_frames + 1) / scene.config.fps  # every frame and the one past the last
    objects = [o for o in scene.objects
               if np.linalg.norm(o.motion.position(times)[:, None] - eyes[None], axis=-1).min()
               > o.bounding_radius() + CAMERA_CLEARANCE]
    dropped_parts = tuple(p.name for p in scene.static_parts if p not in kept_parts)
    dropped_objects = tuple(o.id for o in scene.objects if o not in objects)
    scene = replace(scene, static_parts=tuple(kept_parts), objects=tuple(objects))

    cameras = tuple(CameraPath(kind="static", centre=eye, t_mid=t_mid, look_mode="target", target=target.copy(),
                               fov_deg=path.fov_deg) for eye in eyes)
    names = tuple(f"cam{k}" for k in range(config.num_cameras))
    train, test = camera_split(config)
    return Rig(config=config, scene=scene, cameras=cameras, names=names,
               train_cameras=tuple(names[k] for k in train), test_cameras=tuple(names[k] for k in test),
               centre=centre, target=target, spread=scale, dropped_parts=dropped_parts,
               dropped_objects=dropped_objects)


def render_rig(rig: Rig, *, progress: bool = False) -> Iterator[tuple[str, Frame]]:
    """Yield ``(camera name, frame)`` for every frame of every camera, camera by camera, with one GL context.

    Frames are those of ``render_scene`` (linear RGB, planar depth with +inf sky, OpenCV camera, object_id,
    moving, flow and object_flow); the cameras do not move, so flow is object motion alone. The shadow map
    is the scene's own (fitted to the sampled path), the same for every camera.
    """

    renderer = SceneRenderer(rig.scene)  # builds the geometry and the shadow map set-up once
    bar = tqdm(total=len(rig.names) * rig.num_frames, desc="render rig", unit="frame", disable=not progress)
    try:
        for k, name in enumerate(rig.names):
            view = rig.camera_scene(k)
            for index in range(rig.num_frames):
                renderer.scene = view  # render_frame reads the camera (only) from the scene it holds
                frame = renderer.render_frame(index, camera=k)
                bar.update()
                yield name, frame
    finally:
        bar.close()
        renderer.release()


def generate_rig(config: RigConfig, out_dir: str | Path, *, progress: bool = True) -> Path:
    """Make the rig of ``config``, render it and write it as an rgbd-rig capture to ``out_dir``; returns the path.

    One rgbd-seq per camera (``cam0`` ...; see ``engine.io.rgbd.write_rig``) with every ground-truth channel of
    ``generate_sequence`` and the objects' per-frame transforms, ``rig.json`` with the default split, and the
    config beside it as ``rigscene_config.json``.
    """

    rig = make_rig(config)
    stream = render_rig(rig, progress=progress)

    def frames_of(name: str) -> Iterator[Frame]:  # write_rig consumes the cameras in order, each to its end
        for _ in range(rig.num_frames):
            got, frame = next(stream)
            assert got == name, (got, name)
            yield frame

    out = Path(out_dir)
    try:
        write_rig(out, {name: frames_of(name) for name in rig.names}, list(rig.train_cameras),
                  list(rig.test_cameras), fps=rig.scene.config.fps, objects=rig.scene.scene_objects(),
                  color_space="linear-srgb")
    finally:
        stream.close()
    (out / "rigscene_config.json").write_text(json.dumps(dataclasses.asdict(config), indent=2) + "\n")
    return out
