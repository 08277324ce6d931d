"""Read and write rgbd-seq (versions 1 and 2) sequences and rgbd-rig captures.

The on-disk format is specified in ``docs/formats/rgbd-seq.md``; in short::

    <sequence>/sequence.json           metadata, cameras, object transforms
    <sequence>/frames/000000.exr       R, G, B, Z (+ motion.X/Y; object_id, moving, flow.X/Y, object_flow.X/Y)

Conventions (the same as :mod:`engine.core.frames`): OpenCV camera axes (x right, y down, z forward),
``world_to_camera`` rigid 4x4, pixel (u, v) centred at (u + 0.5, v + 0.5), planar depth > 0 with +inf for
sky, flow in pixels from this frame to the next (x right, y down). In memory colour is always linear
Rec.709 (``linear-srgb``); ``srgb`` files are decoded with the exact sRGB EOTF on load.

All metadata is validated eagerly by :func:`read_sequence` (a bad pose in frame 9 000 fails at open
time); pixel data is decoded and validated lazily, one frame per ``seq[i]``.

>>> seq = read_sequence("capture/cam0")            # doctest: +SKIP
>>> frame = seq[0]; frame.depth.shape == (seq.height, seq.width)  # doctest: +SKIP
True
>>> seq.has_channel("object_flow")                 # doctest: +SKIP
False
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from functools import cached_property
from pathlib import Path
from typing import Any, Iterable, Iterator, Mapping

import numpy as np
from tqdm import tqdm

from engine.core.checks import numeric_array
from engine.core.colorspace import linear_to_srgb, srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, SceneObject, validate_frame, validate_intrinsics, validate_pose
from engine.geometry.motion import camera_motion_vectors
from engine.io.exr import read_exr, read_exr_info, write_exr
from engine.io.meta import json_choice, json_finite, json_int, load_json, require

FORMAT = "rgbd-seq"
RIG_FORMAT = "rgbd-rig"
#: The version written when no frame carries motion vectors (what every version-1 reader reads) ...
VERSION = 1
#: ... and when some do (version 2 adds the ``motion.X/Y`` channels and the ``motion_vectors`` entry).
MOTION_VERSION = 2
VERSIONS = (VERSION, MOTION_VERSION)
#: ``motion_vectors.camera`` of sequence.json: the vectors include the camera's motion, or only the objects'.
MOTION_CAMERA = ("included", "excluded")
COLOR_SPACES = ("linear-srgb", "srgb")
REQUIRED_CHANNELS = ("R", "G", "B", "Z")
#: EXR channels of each Frame field. ``has_channel`` accepts a field name or a channel name.
FIELD_CHANNELS: dict[str, tuple[str, ...]] = {
    "color": ("R", "G", "B"),
    "depth": ("Z",),
    "object_id": ("object_id",),
    "moving": ("moving",),
    "flow": ("flow.X", "flow.Y"),
    "object_flow": ("object_flow.X", "object_flow.Y"),
    "motion_vectors": ("motion.X", "motion.Y"),
}
#: Largest difference (seconds) between the times of frame i of two cameras of a rig.
RIG_TIME_TOLERANCE = 1e-6


# --------------------------------------------------------------------------------------------------
# sRGB transfer function (IEC 61966-2-1)
# --------------------------------------------------------------------------------------------------

def _load_header(path: Path, expected_format: str, versions: tuple[int, ...] = (VERSION,)) -> dict[str, Any]:
    """Load a metadata JSON and check its ``format`` and ``version`` fields."""
    meta = load_json(path)
    if meta.get("format") != expected_format:
        raise InputError(f"must be '{expected_format}', got {meta.get('format')!r}", file=path, field="format")
    version = meta.get("version")
    if isinstance(version, bool) or version not in versions:
        known = " and ".join(str(v) for v in versions)
        raise InputError(f"unsupported version {version!r} (this reader knows version {known})",
                         file=path, field="version")
    return meta



def _parse_objects(raw: Any, indices: list[int] | None, file: Path | None) -> list[SceneObject]:
    """Validate the ``objects`` list; with ``indices`` also check one transform per frame."""
    if not isinstance(raw, list):
        raise InputError(f"must be a list, got {type(raw).__name__}", file=file, field="objects")
    objects: list[SceneObject] = []
    for k, entry in enumerate(raw):
        if not isinstance(entry, dict):
            raise InputError("must be an object", file=file, field=f"objects[{k}]")
        oid = json_int(require(entry, "id", file, name=f"objects[{k}].id"), file, f"objects[{k}].id", minimum=1)
        where = f"objects[id={oid}]"
        if any(o.id == oid for o in objects):
            raise InputError(f"duplicate object id {oid}", file=file, field=f"{where}.id")
        name = require(entry, "name", file, name=f"{where}.name")
        moving = require(entry, "moving", file, name=f"{where}.moving")
        if not isinstance(name, str):
            raise InputError(f"must be a string, got {name!r}", file=file, field=f"{where}.name")
        if not isinstance(moving, bool):
            raise InputError(f"must be true or false, got {moving!r}", file=file, field=f"{where}.moving")
        transforms = require(entry, "world_from_object", file, name=f"{where}.world_from_object")
        transforms = numeric_array(transforms, file=file, field=f"{where}.world_from_object")
        n = len(transforms) if indices is None else len(indices)
        if transforms.shape != (n, 4, 4):
            raise InputError(f"must have shape ({n}, 4, 4) (one transform per frame), got {transforms.shape}",
                             file=file, field=f"{where}.world_from_object")
        for f, transform in enumerate(transforms):
            validate_pose(transform, file=file, frame=f if indices is None else indices[f],
                          field_name=f"{where}.world_from_object")
        objects.append(SceneObject(id=oid, name=name, moving=moving, world_from_object=transforms))
    return objects


# --------------------------------------------------------------------------------------------------
# Reading
# --------------------------------------------------------------------------------------------------

@dataclass(eq=False)
class RgbdSequence:
    """An rgbd-seq on disk with validated metadata; frames are decoded on access.

    ``seq[i]`` is the i-th listed frame (position, not ``index``; negative positions count from the end);
    ``seq.indices[i]`` is its frame number. Each access reads, validates and returns a fresh
    :class:`Frame` (colour linear, depth planar, OpenCV camera).

    Attributes:
        path: the sequence folder.
        width, height: frame size in pixels.
        fps: nominal frame rate.
        color_space: ``linear-srgb`` or ``srgb`` (how the EXR colour is stored; frames are always linear).
        cameras: per-frame :class:`Camera`.
        times: (N,) float64 seconds.
        indices: (N,) int64 frame numbers, strictly increasing.
        files: per-frame EXR paths.
        objects: scene objects with one world-from-object transform per frame.
        version: the file's rgbd-seq version (1, or 2 with motion vectors).
        motion_camera: ``included`` or ``excluded``: whether the stored ``motion.X/Y`` vectors include the
            camera's motion. Frames always hold vectors with it included: ``excluded`` vectors get the
            camera's own motion added on load (from the frame's depth and the previous frame's camera;
            the first frame, which has no previous frame, loads without vectors).
    """

    path: Path
    width: int
    height: int
    fps: float
    color_space: str
    cameras: list[Camera] = field(repr=False)
    times: np.ndarray = field(repr=False)
    indices: np.ndarray = field(repr=False)
    files: list[Path] = field(repr=False)
    objects: list[SceneObject] = field(repr=False)
    version: int = VERSION
    motion_camera: str = "included"

    def __len__(self) -> int:
        return len(self.files)

    def __getitem__(self, position: int) -> Frame:
        if not -len(self) <= position < len(self):
            raise IndexError(f"frame position {position} out of range for {len(self)} frames")
        return self._load(position % len(self))

    def __iter__(self) -> Iterator[Frame]:
        return (self._load(k) for k in range(len(self)))

    @cached_property
    def channels(self) -> tuple[str, ...]:
        """EXR channel names of the first frame (read from its header only)."""
        return read_exr_info(self.files[0]).channels

    def has_channel(self, name: str) -> bool:
        """Whether the first frame carries ``name``.

        ``name`` is a Frame field (``"flow"``, ``"object_flow"``, ``"motion_vectors"``, ``"object_id"``,
        ``"moving"``: true when
        all its EXR channels are present) or an EXR channel name (``"flow.X"``). Later frames are assumed
        to carry the same channels; a frame that does not simply loads with that field set to None.
        """
        return all(c in self.channels for c in FIELD_CHANNELS.get(name, (name,)))

    def _load(self, k: int) -> Frame:
        file, index = self.files[k], int(self.indices[k])
        info = read_exr_info(file)  # the size from the header, before any pixel is decoded
        if (info.height, info.width) != (self.height, self.width):
            raise InputError(f"image is {info.width}x{info.height}, sequence.json says {self.width}x{self.height}",
                             file=file, frame=index, field="Z")
        ch = read_exr(file)
        missing = [c for c in REQUIRED_CHANNELS if c not in ch]
        if missing:
            raise InputError(
                f"missing required channel(s) {missing}; channels present: {sorted(ch)}. rgbd-seq needs "
                f"R, G, B and Z (planar depth); other layouts can be converted with engine.io.importers",
                file=file, frame=index, field=missing[0])
        if ch["Z"].shape != (self.height, self.width):
            h, w = ch["Z"].shape
            raise InputError(f"image is {w}x{h}, sequence.json says {self.width}x{self.height}",
                             file=file, frame=index, field="Z")
        optional: dict[str, np.ndarray | None] = {}
        for name in ("object_id", "moving", "flow", "object_flow", "motion_vectors"):
            names = FIELD_CHANNELS[name]
            present = [c for c in names if c in ch]
            if present and len(present) < len(names):
                absent = [c for c in names if c not in ch]
                raise InputError(f"has {present} without {absent}: both components are needed",
                                 file=file, frame=index, field=present[0])
            optional[name] = np.stack([ch[c] for c in names], axis=-1) if present else None
        color = np.stack([ch["R"], ch["G"], ch["B"]], axis=-1)
        if self.color_space == "srgb":
            outside = int(np.count_nonzero((color < 0) | (color > 1)))
            if outside:
                raise InputError(f"has {outside} values outside [0, 1] (color_space is srgb)",
                                 file=file, frame=index, field="RGB")
            color = srgb_to_linear(color)
        frame = Frame(index=index, time=float(self.times[k]), color=color, depth=ch["Z"], camera=self.cameras[k],
                      object_id=None if optional["object_id"] is None else optional["object_id"][..., 0],
                      moving=None if optional["moving"] is None else optional["moving"][..., 0],
                      flow=optional["flow"], object_flow=optional["object_flow"],
                      motion_vectors=optional["motion_vectors"])
        frame = validate_frame(frame, file=file)
        if frame.motion_vectors is not None and self.motion_camera == "excluded":
            frame.motion_vectors = (None if k == 0 else frame.motion_vectors + camera_motion_vectors(
                frame.depth, frame.camera, self.cameras[k - 1]))
        return frame


def read_sequence(path: str | Path) -> RgbdSequence:
    """Open an rgbd-seq folder (or its ``sequence.json``) and validate all of its metadata.

    Checks: format/version, positive integer width/height, fps > 0, color_space, depth == planar-z,
    camera_convention == opencv, each frame's index/time/file/intrinsics/world_to_camera, strictly
    increasing indices, non-decreasing finite times, that every frame file exists, and the objects.
    Pixel data is not read (see :class:`RgbdSequence`).

    Raises:
        InputError: naming the file, frame and field of the first problem found.
    """
    root = Path(path)
    if root.name == "sequence.json":
        root = root.parent
    meta_file = root / "sequence.json"
    if root.is_dir() and not meta_file.exists():
        raise InputError("is a folder without sequence.json: not an rgbd-seq sequence", file=root)
    if root.is_file():
        raise InputError("is a file; an rgbd-seq sequence is a folder holding sequence.json", file=root)
    meta = _load_header(meta_file, FORMAT, VERSIONS)
    version = int(meta["version"])
    motion_camera = "included"
    if version >= MOTION_VERSION and "motion_vectors" in meta:
        entry = meta["motion_vectors"]
        if not isinstance(entry, dict):
            raise InputError("must be an object such as {\"camera\": \"included\"}", file=meta_file,
                             field="motion_vectors")
        motion_camera = json_choice(entry.get("camera", "included"), MOTION_CAMERA, meta_file,
                                    "motion_vectors.camera")
    width = json_int(require(meta, "width", meta_file), meta_file, "width", minimum=1)
    height = json_int(require(meta, "height", meta_file), meta_file, "height", minimum=1)
    fps = json_finite(require(meta, "fps", meta_file), meta_file, "fps", positive=True)
    color_space = json_choice(require(meta, "color_space", meta_file), COLOR_SPACES, meta_file, "color_space")
    json_choice(require(meta, "depth", meta_file), ("planar-z",), meta_file, "depth")
    json_choice(require(meta, "camera_convention", meta_file), ("opencv",), meta_file, "camera_convention")
    entries = require(meta, "frames", meta_file)
    if not isinstance(entries, list) or not entries:
        raise InputError("must be a non-empty list", file=meta_file, field="frames")

    cameras, times, indices, files = [], [], [], []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise InputError("must be an object", file=meta_file, field=f"frames[{k}]")
        index = json_int(require(entry, "index", meta_file, frame=k), meta_file, "index", frame=k, minimum=0)
        time = json_finite(require(entry, "time", meta_file, frame=index), meta_file, "time", frame=index)
        if indices and index <= indices[-1]:
            raise InputError(f"index {index} follows {indices[-1]}: indices must be strictly increasing",
                             file=meta_file, frame=index, field="index")
        if times and time < times[-1]:
            raise InputError(f"time {time} is before the previous frame's {times[-1]}: times must not decrease",
                             file=meta_file, frame=index, field="time")
        rel = require(entry, "file", meta_file, frame=index)
        if not isinstance(rel, str) or not rel:
            raise InputError(f"must be a relative path string, got {rel!r}", file=meta_file, frame=index, field="file")
        if not _inside(root, rel):  # checked before the file system is asked anything about it
            raise InputError(f"must name a file inside the sequence folder, got {rel!r}", file=meta_file,
                             frame=index, field="file")
        intrinsics = validate_intrinsics(require(entry, "intrinsics", meta_file, frame=index), file=meta_file, frame=index)
        pose = validate_pose(require(entry, "world_to_camera", meta_file, frame=index), file=meta_file, frame=index)
        if not (root / rel).is_file():
            raise InputError(f"frame file {rel} does not exist (listed in {meta_file})",
                             file=root / rel, frame=index, field="file")
        cameras.append(Camera(intrinsics, pose))
        times.append(time)
        indices.append(index)
        files.append(root / rel)
    objects = _parse_objects(meta.get("objects", []), indices, meta_file)
    return RgbdSequence(path=root, width=width, height=height, fps=fps, color_space=color_space,
                        cameras=cameras, times=np.asarray(times, dtype=np.float64),
                        indices=np.asarray(indices, dtype=np.int64), files=files, objects=objects,
                        version=version, motion_camera=motion_camera)


def _output_folder(path: str | Path) -> Path:
    """The folder a writer will fill: absent or a folder, never a file."""
    root = Path(path)
    if root.exists() and not root.is_dir():
        raise InputError("exists and is not a folder", file=root)
    return root


def _inside(root: Path, rel: str) -> bool:
    """``rel`` is a relative path that stays inside ``root`` (no absolute path, no ``..`` out of it, no
    symbolic link out of it)."""
    path = Path(rel)
    if path.is_absolute() or ".." in path.parts or "\\" in rel:
        return False
    base = root.resolve()
    return (base / path).resolve().is_relative_to(base)


# --------------------------------------------------------------------------------------------------
# Writing
# --------------------------------------------------------------------------------------------------

def _frame_channels(frame: Frame, color_space: str, file: Path) -> dict[str, np.ndarray]:
    color = frame.color
    if color_space == "srgb":
        over = int(np.count_nonzero(color > 1))
        if over:
            raise InputError(f"has {over} values > 1, which srgb cannot store; write linear-srgb instead",
                             file=file, frame=frame.index, field="RGB")
        color = linear_to_srgb(color)
    channels = {"R": color[..., 0], "G": color[..., 1], "B": color[..., 2], "Z": frame.depth}
    for name in ("object_id", "moving"):
        if getattr(frame, name) is not None:
            channels[name] = getattr(frame, name)
    for name in ("flow", "object_flow", "motion_vectors"):
        value = getattr(frame, name)
        if value is not None:
            if value.shape[:2] != frame.depth.shape:
                raise InputError(f"are {value.shape[1]}x{value.shape[0]}: rgbd-seq stores motion vectors at the "
                                 f"frame's size {frame.width}x{frame.height}", file=file, frame=frame.index,
                                 field=name)
            x, y = FIELD_CHANNELS[name]
            channels[x], channels[y] = value[..., 0], value[..., 1]
    return channels


def _objects_json(objects: list[SceneObject]) -> list[dict[str, Any]]:
    return [{"id": o.id, "name": o.name, "moving": o.moving,
             "world_from_object": np.asarray(o.world_from_object, dtype=np.float64).tolist()} for o in objects]


def _write_json(path: Path, data: dict[str, Any]) -> None:
    """Write JSON atomically, one line per top-level key and per entry of a list of objects (frames)."""
    lines = []
    for key, value in data.items():
        if isinstance(value, list) and value and isinstance(value[0], dict):
            items = ",\n    ".join(json.dumps(v) for v in value)
            lines.append(f"  {json.dumps(key)}: [\n    {items}\n  ]")
        else:
            lines.append(f"  {json.dumps(key)}: {json.dumps(value)}")
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text("{\n" + ",\n".join(lines) + "\n}\n")
    os.replace(tmp, path)


def write_sequence(path: str | Path, frames: Iterable[Frame], *, fps: float,
                   objects: list[SceneObject] | None = None, color_space: str = "linear-srgb",
                   half_color: bool = False, progress: bool = False) -> Path:
    """Write frames as an rgbd-seq folder: ``frames/<index:06d>.exr`` per frame, then ``sequence.json``.

    Frames are consumed one at a time (a generator is never held in memory), each validated with
    :func:`validate_frame` before it is written. Their indices must strictly increase, times must not
    decrease, and all must have the same size. Optional channels are written for the frames that carry
    them. Colour is stored as FLOAT (bit-exact round trip) or, with ``half_color``, as HALF; Z, flow and
    the other channels are always FLOAT. With ``color_space="srgb"`` the (linear) colour is encoded with
    the sRGB transfer function and must lie in [0, 1]. An existing ``sequence.json`` is removed first and
    the new one written last, atomically, so a folder without it is an interrupted write. Existing frame
    files of the same names are replaced.

    Args:
        path: the sequence folder (created if needed).
        frames: the frames, in order.
        fps: nominal frame rate, > 0.
        objects: scene objects, each with one world-from-object transform per written frame.
        color_space: ``linear-srgb`` or ``srgb``.
        half_color: store R, G, B as 16-bit floats.
        progress: show a progress bar (tqdm).

    Returns:
        The sequence folder.
    """
    root = _output_folder(path)
    meta_file = root / "sequence.json"
    fps = json_finite(fps, None, "fps", positive=True)
    if color_space not in COLOR_SPACES:
        raise InputError(f"must be one of {list(COLOR_SPACES)}, got {color_space!r}", field="color_space")
    objects_raw = _objects_json(objects or [])
    _parse_objects(objects_raw, None, None)  # ids and rigidity now; the per-frame count once all are written
    if progress:
        frames = tqdm(frames, desc=f"writing {root.name}", unit="frame")
    (root / "frames").mkdir(parents=True, exist_ok=True)
    meta_file.unlink(missing_ok=True)  # until the new one is written, the folder reads as incomplete
    entries: list[dict[str, Any]] = []
    for frame in frames:
        if isinstance(frame.index, bool) or not isinstance(frame.index, (int, np.integer)) or frame.index < 0:
            raise InputError(f"must be a non-negative integer, got {frame.index!r}", field="index")
        rel = f"frames/{int(frame.index):06d}.exr"
        frame = validate_frame(frame, file=root / rel)
        where = dict(file=root / rel, frame=frame.index)
        if entries:
            first = entries[0]
            if (frame.width, frame.height) != (first["_w"], first["_h"]):
                raise InputError(f"is {frame.width}x{frame.height}, the first frame is {first['_w']}x{first['_h']}",
                                 **where, field="Z")
            if frame.index <= entries[-1]["index"]:
                raise InputError(f"index {frame.index} follows {entries[-1]['index']}: indices must strictly increase",
                                 **where, field="index")
            if frame.time < entries[-1]["time"]:
                raise InputError(f"time {frame.time} is before the previous frame's {entries[-1]['time']}",
                                 **where, field="time")
        write_exr(root / rel, _frame_channels(frame, color_space, root / rel),
                  half={"R", "G", "B"} if half_color else frozenset())
        entries.append({"index": int(frame.index), "time": float(frame.time), "file": rel,
                        "intrinsics": frame.camera.intrinsics.tolist(),
                        "world_to_camera": frame.camera.world_to_camera.tolist(),
                        "_w": frame.width, "_h": frame.height, "_mv": frame.motion_vectors is not None})
    if not entries:
        raise InputError("no frames to write", file=meta_file, field="frames")
    _parse_objects(objects_raw, [e["index"] for e in entries], meta_file)
    with_motion = any(e["_mv"] for e in entries)
    meta = {"format": FORMAT, "version": MOTION_VERSION if with_motion else VERSION, "width": entries[0]["_w"],
            "height": entries[0]["_h"],
            "fps": fps, "color_space": color_space, "depth": "planar-z", "camera_convention": "opencv",
            "frames": [{k: v for k, v in e.items() if not k.startswith("_")} for e in entries]}
    if with_motion:
        meta["motion_vectors"] = {"camera": "included"}
    if objects_raw:
        meta["objects"] = objects_raw
    _write_json(meta_file, meta)
    return root


# --------------------------------------------------------------------------------------------------
# Multi-camera rigs
# --------------------------------------------------------------------------------------------------

@dataclass(eq=False)
class RgbdRig:
    """A synchronized multi-camera capture: one :class:`RgbdSequence` per camera, same frame count and times.

    Attributes:
        path: the capture folder (holding ``rig.json``).
        cameras: camera name -> its sequence, in ``rig.json`` order.
        train_cameras, test_cameras: the default split (tools may override it).
    """

    path: Path
    cameras: dict[str, RgbdSequence] = field(repr=False)
    train_cameras: list[str]
    test_cameras: list[str]

    def __len__(self) -> int:
        """Number of frames (time steps), the same for every camera."""
        return len(next(iter(self.cameras.values())))

    @property
    def times(self) -> np.ndarray:
        """(N,) float64 seconds, shared by all cameras (those of the first camera)."""
        return next(iter(self.cameras.values())).times


def _check_rig_names(cameras: Any, train: Any, test: Any, file: Path) -> tuple[list[str], list[str], list[str]]:
    if not isinstance(cameras, list) or not cameras:
        raise InputError("must be a non-empty list of camera folder names", file=file, field="cameras")
    for name in cameras:
        if not isinstance(name, str) or not name or name in (".", "..") or "/" in name or "\\" in name:
            raise InputError(f"{name!r} is not a plain folder name", file=file, field="cameras")
    if len(set(cameras)) != len(cameras):
        raise InputError(f"has duplicate names: {cameras}", file=file, field="cameras")
    for key, names in (("train_cameras", train), ("test_cameras", test)):
        if not isinstance(names, list):
            raise InputError("must be a list of camera names", file=file, field=key)
        unknown = [n for n in names if n not in cameras]
        if unknown:
            raise InputError(f"names cameras not in 'cameras' {cameras}: {unknown}", file=file, field=key)
    return list(cameras), list(train), list(test)


def _check_synchronized(sequences: Mapping[str, RgbdSequence]) -> None:
    (first_name, first), *others = sequences.items()
    for name, seq in others:
        meta_file = seq.path / "sequence.json"
        if len(seq) != len(first):
            raise InputError(f"camera '{name}' has {len(seq)} frames, camera '{first_name}' has {len(first)}",
                             file=meta_file, field="frames")
        off = np.flatnonzero(np.abs(seq.times - first.times) > RIG_TIME_TOLERANCE)
        if off.size:
            k = int(off[0])
            raise InputError(f"camera '{name}' has time {seq.times[k]} at position {k}, camera '{first_name}' "
                             f"has {first.times[k]}: frame i of every camera must share its time",
                             file=meta_file, frame=int(seq.indices[k]), field="time")


def read_rig(path: str | Path) -> RgbdRig:
    """Open an rgbd-rig capture (folder or its ``rig.json``) and validate it and every camera's sequence.

    Raises InputError for a bad ``rig.json`` (format, version, camera names, split naming unknown cameras)
    or cameras that differ in frame count or times (beyond ``RIG_TIME_TOLERANCE``).
    """
    root = Path(path)
    if root.name == "rig.json":
        root = root.parent
    rig_file = root / "rig.json"
    meta = _load_header(rig_file, RIG_FORMAT)
    cameras, train, test = _check_rig_names(require(meta, "cameras", rig_file), meta.get("train_cameras", []),
                                            meta.get("test_cameras", []), rig_file)
    sequences = {name: read_sequence(root / name) for name in cameras}
    _check_synchronized(sequences)
    return RgbdRig(path=root, cameras=sequences, train_cameras=train, test_cameras=test)


def write_rig(path: str | Path, camera_sequences: Mapping[str, Iterable[Frame]], train: list[str],
              test: list[str], *, fps: float, objects: list[SceneObject] | None = None,
              color_space: str = "linear-srgb", half_color: bool = False, progress: bool = False) -> Path:
    """Write an rgbd-rig: one rgbd-seq per camera (``<path>/<name>/``, see :func:`write_sequence`), then ``rig.json``.

    ``camera_sequences`` maps camera folder names to their frames (any iterable, e.g. an
    :class:`RgbdSequence` or a generator); frame i of every camera must share its time. ``rig.json`` is
    written only after every sequence is written and the cameras are checked to be synchronized.

    Returns:
        The capture folder.
    """
    root = _output_folder(path)
    rig_file = root / "rig.json"
    cameras, train, test = _check_rig_names(list(camera_sequences), list(train), list(test), rig_file)
    for name in cameras:
        write_sequence(root / name, camera_sequences[name], fps=fps, objects=objects, color_space=color_space,
                       half_color=half_color, progress=progress)
    _check_synchronized({name: read_sequence(root / name) for name in cameras})
    _write_json(rig_file, {"format": RIG_FORMAT, "version": VERSION, "cameras": cameras,
                           "train_cameras": train, "test_cameras": test})
    return root
