"""Importers: turn other RGB-D layouts into :class:`Frame` streams and rgbd-seq folders.

Each layout has ``frames_from_<layout>(src, ...) -> ImportedFrames`` (metadata checked eagerly, pixels
read lazily, one frame at a time) and ``import_<layout>(src, dst, ...) -> Path`` (writes an rgbd-seq);
:func:`import_any` dispatches on a layout name for the command line.

Every importer produces the conventions of :mod:`engine.core.frames`: OpenCV camera axes, rigid
world-to-camera, pixel centres at +0.5, planar depth (+inf for sky), linear colour, flow to the next
frame in pixels (x right, y down), motion vectors to the previous frame in pixels (x right, y down, NaN
where there is none; only Blender's Vector pass gives them, see :func:`frames_from_blender`). Frame ``index`` is the file number minus the first file number and
``time = index / fps``. Depth values ``>= background_depth`` (default 1e9; Blender's renderers write 1e10
where no surface is hit) become +inf; pass ``background_depth=None`` to keep them.

A missing frame (a gap in the file numbering, or a missing depth/camera file for an existing image) is an
:class:`InputError`; with ``skip_missing=True`` it is skipped with a ``warnings.warn`` naming it.

Sections: Blender multilayer EXR, MPI-Sintel, DeCOMPnet/VEED.
"""
from __future__ import annotations

import csv
import functools
import re
import struct
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Iterator

import cv2
import numpy as np

from engine.conventions.cameras import opengl_to_opencv_world_to_camera
from engine.core.colorspace import srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, validate_depth, validate_frame, validate_intrinsics, validate_pose
from engine.io.exr import read_exr
from engine.io.meta import json_finite, json_int, load_json, require
from engine.io.rgbd import write_sequence

#: Depth at or beyond which a pixel is "no surface" (+inf). Blender (Cycles) writes 1e10 for background.
BACKGROUND_DEPTH = 1e9

@dataclass
class ImportedFrames:
    """Frames read from another layout: ``frames`` yields validated frames lazily, ``count`` of them."""

    frames: Iterator[Frame]
    fps: float
    count: int


def _background_to_inf(depth: np.ndarray, background_depth: float | None) -> np.ndarray:
    if background_depth is None:
        return depth
    return np.where(depth >= background_depth, np.float32(np.inf), depth).astype(np.float32)


def _missing(problem: str, skip: bool, **where: Any) -> None:
    """Raise InputError for a missing frame, or warn when the caller asked to skip missing frames."""
    error = InputError(problem, **where)
    if not skip:
        raise error
    warnings.warn(f"skipping: {error}", stacklevel=3)


def _numbered_files(folder: Path, suffix: str, skip_missing: bool) -> list[tuple[int, Path]]:
    """Files ``*<suffix>`` of a folder with their trailing number (``frame_0007.png`` -> 7), sorted.

    Raises InputError for an empty folder, a name without a number, duplicate numbers, or (unless
    ``skip_missing``) a gap in the numbering.
    """
    if not folder.is_dir():
        raise InputError("folder does not exist", file=folder)
    numbered = []
    for path in folder.glob(f"*{suffix}"):
        match = re.search(r"(\d+)$", path.stem)
        if match is None:
            raise InputError("file name has no frame number", file=path)
        numbered.append((int(match.group(1)), path))
    if not numbered:
        raise InputError(f"has no {suffix} files", file=folder)
    numbered.sort()
    for (a, pa), (b, pb) in zip(numbered, numbered[1:]):
        if a == b:
            raise InputError(f"two files have frame number {a}: {pa.name}, {pb.name}", file=folder)
        for gap in range(a + 1, b):
            _missing(f"file number {gap} is missing (a gap between {pa.name} and {pb.name})", skip_missing,
                     file=folder, frame=gap - numbered[0][0])
    return numbered


def _with_companions(images: list[tuple[int, Path]], companions: dict[str, Callable[[Path], Path]],
                     skip_missing: bool) -> list[tuple[int, Path, dict[str, Path]]]:
    """Attach each image's companion files (depth, camera); a missing one is a missing frame."""
    first = images[0][0]
    out = []
    for number, image in images:
        paths = {kind: name(image) for kind, name in companions.items()}
        absent = [kind for kind, path in paths.items() if not path.is_file()]
        if absent:
            _missing(f"{absent[0]} file {paths[absent[0]]} is missing for image {image.name}", skip_missing,
                     file=paths[absent[0]], frame=number - first, field=absent[0])
            continue
        out.append((number - first, image, paths))
    if not out:
        raise InputError("no complete frames (image + depth + camera) found", file=images[0][1].parent)
    return out


def read_png_linear(path: Path) -> np.ndarray:
    """Read an 8- or 16-bit sRGB-encoded PNG as linear RGB float32 (H, W, 3); alpha is dropped."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("cannot read image (missing, not a PNG, or corrupt)", file=path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    rgb = image[..., 2::-1]  # BGR(A) -> RGB
    if np.issubdtype(image.dtype, np.unsignedinteger):  # one decode per code: the float32 of decoding each pixel
        return srgb_code_table(image.dtype)[rgb]
    scale = np.iinfo(image.dtype).max if np.issubdtype(image.dtype, np.integer) else 1.0
    return srgb_to_linear(rgb.astype(np.float32) / scale)


@functools.lru_cache(maxsize=None)
def srgb_code_table(dtype) -> np.ndarray:
    """``srgb_to_linear(code / max)`` (the division in float32) for every code of an unsigned integer dtype: what
    :func:`read_png_linear` computes per pixel, looked up."""
    top = np.iinfo(dtype).max
    table = srgb_to_linear(np.arange(top + 1).astype(np.float32) / top)
    table.flags.writeable = False
    return table


# --------------------------------------------------------------------------------------------------
# Blender multilayer EXR
# --------------------------------------------------------------------------------------------------

def _blender_intrinsics(entry: dict[str, Any], file: Path, frame: int) -> Callable[[int, int], np.ndarray]:
    """Check a camera entry's intrinsics now; the matrix is made once the image size is known."""
    if "intrinsics" in entry:
        k = validate_intrinsics(entry["intrinsics"], file=file, frame=frame)
        return lambda width, height: k
    if "focal_px" in entry:
        focal = json_finite(entry["focal_px"], file, "focal_px", frame, positive=True)
        return lambda width, height: _centered_intrinsics(focal, width, height)
    lens, sensor = (json_finite(require(entry, key, file, frame), file, key, frame, positive=True)
                    for key in ("lens_mm", "sensor_width_mm"))
    return lambda width, height: _centered_intrinsics(lens / sensor * max(width, height), width, height)


def _centered_intrinsics(focal: float, width: int, height: int) -> np.ndarray:
    """Square pixels, principal point at the image centre (W/2, H/2) (pixel centres at +0.5)."""
    return np.array([[focal, 0.0, width / 2], [0.0, focal, height / 2], [0.0, 0.0, 1.0]])


def frames_from_blender(cameras_json: str | Path, *, layer: str = "ViewLayer",
                        background_depth: float | None = BACKGROUND_DEPTH,
                        skip_missing: bool = False) -> ImportedFrames:
    """Frames from Blender multilayer EXRs plus a camera JSON (pass conventions as written by Cycles).

    EXR channels used (``<layer>`` is the view layer name, default ``ViewLayer``):

    - ``<layer>.Combined.R/G/B`` (``.A`` ignored): scene-linear colour (assumed Rec.709 primaries, Blender's
      default working space).
    - ``<layer>.Depth.Z``: for perspective and orthographic cameras this is planar depth, the camera-space
      distance along the optical axis (Cycles ``camera_z_depth``), not the distance along the ray.
      Values ``>= background_depth`` (Cycles writes 1e10 for background) become +inf. Panoramic cameras
      (where Blender writes ray distance) are not supported.
    - ``<layer>.Vector.X/Y/Z/W`` (optional, the Vector pass; Cycles writes it only with motion blur off).
      Blender's manual (Render > View Layers > Passes, "Vector"): "the four components consist of 2D
      vectors giving the motion towards the next and previous frame position in pixel space". Cycles
      computes it in ``primitive_motion_vector`` (``intern/cycles/kernel/geom/primitive.h``): the
      surface point P at the scene's frame - 1 and frame + 1 (object, deformation and camera motion
      included) is projected with the previous / next camera's world-to-raster transform, then
      ``motion_pre = raster_pre - raster(P)`` and ``motion_post = raster(P) - raster_post`` are returned
      as ``(X, Y, Z, W) = (motion_pre.xy, motion_post.xy)``; raster y points UP (row 0 of Blender's
      buffers is the bottom one). So ``XY = p_prev - p`` and ``ZW = p - p_next``, in pixels, y up.
      Measured on a Cycles render (Blender 5.0.1, ``tools/blender_vector_check.py``, fixture
      ``tests/io/data/blender_vectors``): a surface seen moving DOWN the image (rows increasing) towards
      the current frame has ``Y > 0``, i.e. y up as the source says; ``(X, -Y)`` matches the exact
      current -> previous vectors within 0.12 px (mean 0.001 px) on pixels away from object edges, and
      ``(-Z, W)`` the exact vectors to the next frame as closely.

      * ``motion_vectors`` (current -> previous, y down) ``= (X, -Y)``.
      * ``flow`` (to the next frame, y down) ``= (-Z, +W)`` (negate ``ZW``, then negate y).
      * Background: Cycles writes no vector where a camera ray hits the world (the pass is divided by
        its per-pixel weight and is 0 where no sample hit a surface), and the Depth pass (one sample,
        not anti-aliased) marks the pixel with 1e10 even where some anti-aliased samples hit a surface
        (those pixels get the mean vector of the samples that did). The sky's real motion (the camera's
        rotation) is therefore missing: ``motion_vectors`` are NaN wherever the depth is background
        (``>= background_depth``, or 1e10 with ``background_depth=None``). ``flow`` keeps Cycles'
        values there (0 for pure sky pixels), as before: it must be finite.
      * The vectors point to the Blender frame ``number - 1``: a frame whose previous imported frame is
        another one (a gap in the frame numbers, a frame step, a skipped render) gets no
        ``motion_vectors`` (a warning names it). The first frame keeps its vectors (they point to the
        frame before the sequence, as the scene generator's frame 0 does).

      Blender 5 writes multilayer EXRs as one part per pass; every part is read.

    Camera JSON (this project's own, written by the script below)::

        {"fps": 24.0,
         "frames": [{"frame": 1, "file": "render/0001.exr",
                     "camera_to_world": [[...], [...], [...], [0, 0, 0, 1]],
                     "lens_mm": 50.0, "sensor_width_mm": 36.0}, ...]}

    - ``file``: the EXR, relative to the JSON's folder.
    - ``camera_to_world``: the camera object's ``matrix_world`` (Blender camera convention: x right, y up,
      looking down -z; rigid, so the camera object must not be scaled). Converted to an OpenCV
      world-to-camera with :func:`opengl_to_opencv_world_to_camera`.
    - intrinsics, one of: ``"intrinsics"`` (3x3, OpenCV pixel convention, centres at +0.5);
      ``"focal_px"`` (square pixels, principal point at the image centre (W/2, H/2)); or ``"lens_mm"`` and
      ``"sensor_width_mm"`` with sensor fit AUTO and no lens shift: ``f = lens / sensor_width * max(W, H)``.
    - ``frame`` numbers must strictly increase; ``index = frame - first frame``, ``time = index / fps``.

    Script (run in Blender; writes the JSON next to the renders)::

        import bpy, json
        s, cam = bpy.context.scene, bpy.context.scene.camera
        out = {"fps": s.render.fps / s.render.fps_base, "frames": []}
        for f in range(s.frame_start, s.frame_end + 1):
            s.frame_set(f)
            out["frames"].append({"frame": f, "file": f"{f:04d}.exr",
                                  "camera_to_world": [list(r) for r in cam.matrix_world],
                                  "lens_mm": cam.data.lens, "sensor_width_mm": cam.data.sensor_width})
        json.dump(out, open(bpy.path.abspath("//render/cameras.json"), "w"))
    """
    cameras_json = Path(cameras_json)
    meta = load_json(cameras_json)
    fps = json_finite(require(meta, "fps", cameras_json), cameras_json, "fps", positive=True)
    entries = require(meta, "frames", cameras_json)
    if not isinstance(entries, list) or not entries:
        raise InputError("must be a non-empty list", file=cameras_json, field="frames")
    parsed, numbers = [], []
    for k, entry in enumerate(entries):
        if not isinstance(entry, dict):
            raise InputError("must be an object", file=cameras_json, field=f"frames[{k}]")
        number = json_int(require(entry, "frame", cameras_json, frame=k), cameras_json, "frame", frame=k)
        if numbers and number <= numbers[-1]:
            raise InputError(f"frame {number} follows {numbers[-1]}: frame numbers must strictly increase",
                             file=cameras_json, frame=k, field="frame")
        numbers.append(number)
        camera_to_world = validate_pose(require(entry, "camera_to_world", cameras_json, frame=k),
                                        file=cameras_json, frame=k, field_name="camera_to_world")
        world_to_camera = opengl_to_opencv_world_to_camera(camera_to_world)
        exr = cameras_json.parent / str(require(entry, "file", cameras_json, frame=k))
        if not exr.is_file():
            _missing(f"render {exr} is missing", skip_missing, file=exr, frame=number - numbers[0])
            continue
        intrinsics = _blender_intrinsics(entry, cameras_json, k)
        parsed.append((number - numbers[0], exr, world_to_camera, intrinsics))
    if not parsed:
        raise InputError("none of the listed renders exist", file=cameras_json, field="frames")

    def frames() -> Iterator[Frame]:
        names = {c: f"{layer}.{c}" for c in ("Combined.R", "Combined.G", "Combined.B", "Depth.Z")}
        vector = [f"{layer}.Vector.{c}" for c in "XYZW"]
        previous_number = None
        for index, exr, world_to_camera, intrinsics in parsed:
            number = numbers[0] + index
            ch = read_exr(exr, all_parts=True)
            absent = [n for n in names.values() if n not in ch]
            if absent:
                raise InputError(f"missing Blender pass channel(s) {absent}; channels present: {sorted(ch)} "
                                 f"(enable the Combined and Z passes; is the view layer named '{layer}'?)",
                                 file=exr, frame=index, field=absent[0])
            raw_depth = ch[names["Depth.Z"]]
            depth = _background_to_inf(raw_depth, background_depth)
            height, width = depth.shape
            flow = motion = None
            if all(v in ch for v in vector):
                flow = np.stack([-ch[vector[2]], ch[vector[3]]], axis=-1)
                if previous_number is None and index != 0 or previous_number not in (None, number - 1):
                    warnings.warn(f"{exr.name} (frame {number}): no motion vectors: Blender's point to frame "
                                  f"{number - 1}, which is not the previous imported frame", stacklevel=2)
                else:
                    no_surface = raw_depth >= (BACKGROUND_DEPTH if background_depth is None else background_depth)
                    motion = np.stack([ch[vector[0]], -ch[vector[1]]], axis=-1)
                    motion[no_surface] = np.nan
            color = np.stack([ch[names[f"Combined.{c}"]] for c in "RGB"], axis=-1)
            frame = Frame(index=index, time=index / fps, color=color, depth=depth,
                          camera=Camera(intrinsics(width, height), world_to_camera), flow=flow,
                          motion_vectors=motion)
            previous_number = number
            yield validate_frame(frame, file=exr)

    return ImportedFrames(frames=frames(), fps=fps, count=len(parsed))


# --------------------------------------------------------------------------------------------------
# MPI-Sintel
# --------------------------------------------------------------------------------------------------

#: Tag at the start of Sintel's .dpt, .cam (and .flo) files.
SINTEL_TAG = 202021.25


def _read_sintel(path: Path, size: Callable[[bytes], int]) -> bytes:
    """The bytes of a Sintel file, after checking its tag and that it has ``size(data)`` bytes."""
    if not path.is_file():
        raise InputError("file does not exist", file=path)
    data = path.read_bytes()
    tag = struct.unpack("<f", data[:4])[0] if len(data) >= 4 else None
    if tag != SINTEL_TAG:
        raise InputError(f"bad tag {tag!r}, expected {SINTEL_TAG} (not a Sintel file, or wrong byte order)", file=path)
    if len(data) != size(data):
        raise InputError(f"has {len(data)} bytes, expected {size(data)} (truncated or corrupt)", file=path)
    return data


def read_dpt(path: str | Path) -> np.ndarray:
    """Read a Sintel ``.dpt`` depth map: float32 tag 202021.25, int32 width, int32 height, float32 depth
    row-major (little-endian). Sintel depth is planar (camera-space z). Returns (H, W) float32.
    """
    def size(data: bytes) -> int:
        if len(data) < 12:
            return 12
        width, height = struct.unpack("<ii", data[4:12])
        return 12 + 4 * max(width, 0) * max(height, 0)

    data = _read_sintel(Path(path), size)
    width, height = struct.unpack("<ii", data[4:12])
    if width <= 0 or height <= 0:
        raise InputError(f"bad size {width}x{height} in header", file=path)
    return np.frombuffer(data, dtype="<f4", offset=12).reshape(height, width).astype(np.float32)


def read_cam(path: str | Path) -> tuple[np.ndarray, np.ndarray]:
    """Read a Sintel ``.cam`` file: float32 tag, 9 float64 (K, row-major), 12 float64 (3x4 world-to-camera,
    row-major), little-endian; 172 bytes. Returns (K (3, 3), world_to_camera (4, 4)) float64, K unchanged.
    """
    data = _read_sintel(Path(path), lambda _: 4 + 8 * 21)
    values = np.frombuffer(data, dtype="<f8", offset=4)
    world_to_camera = np.vstack([values[9:].reshape(3, 4), [0.0, 0.0, 0.0, 1.0]])
    return values[:9].reshape(3, 3).copy(), world_to_camera


def frames_from_sintel(root: str | Path, scene: str, *, image_pass: str = "final", image_dir: str | Path | None = None,
                       fps: float = 24.0, principal_point_offset: float = 0.5,
                       background_depth: float | None = BACKGROUND_DEPTH, skip_missing: bool = False) -> ImportedFrames:
    """Frames from MPI-Sintel: ``<root>/<image_pass>/<scene>/frame_XXXX.png``, ``<root>/depth/<scene>/frame_XXXX.dpt``,
    ``<root>/camdata_left/<scene>/frame_XXXX.cam``.

    ``image_dir`` replaces the image folder with any folder of numbered PNGs (depth and camera files are
    matched by file stem). PNG colour is sRGB-encoded and is decoded to linear. The extrinsics are
    already OpenCV world-to-camera. Sintel's K places the image centre at ((W-1)/2, (H-1)/2) (pixel
    centres on integers, e.g. cx = 511.5 at 1024 wide); the format puts centres at +0.5, so
    ``principal_point_offset`` (0.5) is added to cx and cy; pass 0.0 to keep K as stored.
    Sintel numbers frames from 1 (frame_0001 becomes index 0); the film runs at 24 fps.
    """
    root = Path(root)
    images = Path(image_dir) if image_dir is not None else root / image_pass / scene
    fps = json_finite(fps, None, "fps", positive=True)
    entries = _with_companions(
        _numbered_files(images, ".png", skip_missing),
        {"depth": lambda p: root / "depth" / scene / f"{p.stem}.dpt",
         "camera": lambda p: root / "camdata_left" / scene / f"{p.stem}.cam"}, skip_missing)

    def frames() -> Iterator[Frame]:
        for index, image, paths in entries:
            intrinsics, world_to_camera = read_cam(paths["camera"])
            intrinsics[:2, 2] += principal_point_offset
            camera = Camera(validate_intrinsics(intrinsics, file=paths["camera"], frame=index),
                            validate_pose(world_to_camera, file=paths["camera"], frame=index))
            depth = validate_depth(_background_to_inf(read_dpt(paths["depth"]), background_depth),
                                   file=paths["depth"], frame=index)
            color = read_png_linear(image)
            if color.shape[:2] != depth.shape:
                raise InputError(f"depth is {depth.shape[1]}x{depth.shape[0]}, image {image.name} is "
                                 f"{color.shape[1]}x{color.shape[0]}", file=paths["depth"], frame=index)
            frame = Frame(index=index, time=index / fps, color=color, depth=depth, camera=camera)
            yield validate_frame(frame, file=image)

    return ImportedFrames(frames=frames(), fps=fps, count=len(entries))


# --------------------------------------------------------------------------------------------------
# DeCOMPnet / VEED
# --------------------------------------------------------------------------------------------------

#: VEED intrinsics: fx = fy = 2100 px at 1920x1080, principal point at the image centre.
VEED_FOCAL_PX = 2100.0
VEED_SIZE = (1920, 1080)


def veed_intrinsics(width: int, height: int) -> np.ndarray:
    """VEED's fixed intrinsics scaled to ``width`` x ``height``: fx = 2100 W / 1920, fy = 2100 H / 1080,
    cx = W / 2, cy = H / 2 (the image centre in the +0.5 pixel-centre convention)."""
    return np.array([[VEED_FOCAL_PX * width / VEED_SIZE[0], 0.0, width / 2],
                     [0.0, VEED_FOCAL_PX * height / VEED_SIZE[1], height / 2],
                     [0.0, 0.0, 1.0]])


def read_transformation_csv(path: str | Path) -> np.ndarray:
    """Read ``TransformationMatrices.csv``: one row of 16 comma-separated numbers per frame, a 4x4
    world-to-camera matrix, row-major (OpenCV axes). Blank lines are ignored. Returns (N, 4, 4) float64;
    each matrix is checked to be rigid. Errors name the file and the 1-based row.
    """
    path = Path(path)
    if not path.is_file():
        raise InputError("file does not exist", file=path)
    matrices = []
    with open(path, newline="") as f:
        for row, cells in enumerate(csv.reader(f), start=1):
            if not any(c.strip() for c in cells):
                continue
            try:
                values = [float(c) for c in cells]
            except ValueError:
                raise InputError(f"row {row} is not numeric: {cells}", file=path, field=f"row {row}") from None
            if len(values) != 16:
                raise InputError(f"row {row} has {len(values)} numbers, expected 16 (a row-major 4x4 matrix)",
                                 file=path, field=f"row {row}")
            matrices.append(validate_pose(np.reshape(values, (4, 4)), file=path, field_name=f"row {row}"))
    if not matrices:
        raise InputError("has no rows", file=path)
    return np.stack(matrices)


def frames_from_veed(seq_dir: str | Path, *, color_dir: str | Path = "rgb", depth_dir: str | Path = "depth",
                     matrices: str | Path = "TransformationMatrices.csv", depth_channel: str = "B",
                     intrinsics: np.ndarray | None = None, fps: float = 30.0,
                     background_depth: float | None = BACKGROUND_DEPTH, skip_missing: bool = False) -> ImportedFrames:
    """Frames from a DeCOMPnet/VEED-Dynamic sequence folder: ``rgb/0000.png``..., ``depth/0000.exr``...,
    ``TransformationMatrices.csv``.

    ``color_dir``, ``depth_dir`` and ``matrices`` are relative to ``seq_dir`` (or absolute). Colour: any
    folder of numbered PNGs, sRGB-encoded, decoded to linear. Depth: planar z in EXR channel
    ``depth_channel`` (``B`` in the authors' code), matched to the PNG by file stem. Poses: CSV row r
    (0-based) is the frame numbered ``first + r``, so the CSV must have exactly one row per number from
    the first PNG to the last. Intrinsics: :func:`veed_intrinsics` at the PNG size unless ``intrinsics``
    (3x3, centres at +0.5) is given. VEED does not record a frame rate; ``fps`` defaults to 30.
    """
    seq_dir = Path(seq_dir)
    csv_path = seq_dir / matrices
    fps = json_finite(fps, None, "fps", positive=True)
    fixed_intrinsics = None if intrinsics is None else validate_intrinsics(intrinsics, field_name="intrinsics")
    images = _numbered_files(seq_dir / color_dir, ".png", skip_missing)
    poses = read_transformation_csv(csv_path)
    expected = images[-1][0] - images[0][0] + 1
    if len(poses) != expected:
        row = min(len(poses), expected) + 1
        raise InputError(f"has {len(poses)} rows, but the PNGs {images[0][1].name}..{images[-1][1].name} need "
                         f"{expected} (one per frame number); row {row} "
                         f"{'is missing' if len(poses) < expected else 'has no frame'}",
                         file=csv_path, field=f"row {row}")
    entries = _with_companions(images, {"depth": lambda p: seq_dir / depth_dir / f"{p.stem}.exr"}, skip_missing)

    def frames() -> Iterator[Frame]:
        for index, image, paths in entries:
            ch = read_exr(paths["depth"])
            if depth_channel not in ch:
                raise InputError(f"has no channel '{depth_channel}'; channels present: {sorted(ch)} "
                                 f"(choose one with depth_channel=)", file=paths["depth"], frame=index,
                                 field=depth_channel)
            depth = validate_depth(_background_to_inf(ch[depth_channel], background_depth),
                                   file=paths["depth"], frame=index, field_name=depth_channel)
            color = read_png_linear(image)
            if color.shape[:2] != depth.shape:
                raise InputError(f"depth is {depth.shape[1]}x{depth.shape[0]}, image {image.name} is "
                                 f"{color.shape[1]}x{color.shape[0]}", file=paths["depth"], frame=index)
            height, width = depth.shape
            k = veed_intrinsics(width, height) if fixed_intrinsics is None else fixed_intrinsics
            frame = Frame(index=index, time=index / fps, color=color, depth=depth, camera=Camera(k, poses[index]))
            yield validate_frame(frame, file=image)

    return ImportedFrames(frames=frames(), fps=fps, count=len(entries))


# --------------------------------------------------------------------------------------------------
# Writing an rgbd-seq from any layout
# --------------------------------------------------------------------------------------------------

def import_blender(src: str | Path, dst: str | Path, *, progress: bool = False, **options: Any) -> Path:
    """Convert Blender renders (``src`` = the camera JSON, or a folder holding ``cameras.json``) to an rgbd-seq."""
    src = Path(src)
    imported = frames_from_blender(src / "cameras.json" if src.is_dir() else src, **options)
    return write_sequence(dst, imported.frames, fps=imported.fps, progress=progress)


def import_sintel(src: str | Path, dst: str | Path, *, scene: str, progress: bool = False, **options: Any) -> Path:
    """Convert one MPI-Sintel scene (``src`` = the folder holding ``final/``, ``depth/``, ``camdata_left/``)."""
    imported = frames_from_sintel(src, scene, **options)
    return write_sequence(dst, imported.frames, fps=imported.fps, progress=progress)


def import_veed(src: str | Path, dst: str | Path, *, progress: bool = False, **options: Any) -> Path:
    """Convert one VEED sequence folder (``rgb/``, ``depth/``, ``TransformationMatrices.csv``) to an rgbd-seq."""
    imported = frames_from_veed(src, **options)
    return write_sequence(dst, imported.frames, fps=imported.fps, progress=progress)


IMPORTERS: dict[str, Callable[..., Path]] = {"blender": import_blender, "sintel": import_sintel, "veed": import_veed}


def import_any(src: str | Path, dst: str | Path, layout: str, **options: Any) -> Path:
    """Convert ``src`` in ``layout`` (``blender``, ``sintel``, ``veed``) to an rgbd-seq at ``dst``.

    ``options`` go to the layout's ``import_<layout>`` / ``frames_from_<layout>`` (e.g. ``scene=`` for
    sintel, ``depth_channel=`` for veed, ``skip_missing=``, ``progress=``). Returns ``dst``.
    """
    if layout not in IMPORTERS:
        raise InputError(f"unknown layout {layout!r}; expected one of {sorted(IMPORTERS)}", field="layout")
    return IMPORTERS[layout](src, dst, **options)
