"""LLFF captures as shipped: ``poses_bounds.npy`` beside ``images/`` and its downscaled copies ``images_N/``.

The layout is the one LLFF's ``imgs2poses.py`` writes (Fyusion/LLFF, ``llff/poses/pose_utils.py``) and NeRF's
``nerf_llff_data`` ships (fern, flower, ...: ``images/`` at 4032x3024 with ``images_4/`` and ``images_8/``; a
capture may ship only some of them).

``poses_bounds.npy``: a float array (N, 17), one row per image, rows in the sorted file-name order of the
image folders. The first 15 numbers are a 3x5 matrix, row-major:

- columns 0-2: the camera-to-world rotation, whose columns are the camera's axes in world coordinates in
  LLFF's order **[down, right, back]** (a right-handed frame; NeRF's ``load_llff.py`` reorders them to
  [right, up, back]);
- column 3: the camera centre in world coordinates;
- column 4: ``[H, W, focal]`` of the full-size images (``images/``) in pixels; the principal point is the
  image centre and one focal serves x and y.

The last two numbers are the near and far depth bounds of what the view sees (planar depth along the
optical axis, in world units: percentiles of the COLMAP points' depths).

Conversion to the project's conventions (``engine/core/frames.py``), written once here: OpenCV axes
[right, down, forward] are the LLFF columns [1, 0, -2] (``R_opencv = R_llff @ LLFF_TO_OPENCV``; both
frames have determinant +1); ``world_to_camera`` is the rigid inverse of that camera-to-world. An image of
w x h pixels gets ``K = [[focal * w / W, 0, w / 2], [0, focal * h / H, h / 2], [0, 0, 1]]`` (the image
centre in the +0.5 pixel-centre convention), whichever folder it comes from.

Folders: ``images`` is factor 1, ``images_N`` factor N (images/ downscaled by N). :func:`choose_image_folder`
picks the folder for a requested downscale: ``images_<downscale>`` when shipped, else the coarsest shipped
folder whose factor divides it (the caller area-averages it by the rest), else an InputError listing what
is there. With no request it picks the coarsest folder shipped (``images_8``, 504x378, in LLFF's release:
the resolution of the sparse-view LLFF protocol and one a CPU trains on in minutes).

The bounds set the forward-facing normalisation downstream: the field's NDC near plane is 0.9 x the
smallest near bound and its reference camera the mean pose (``models/fields/static/model.py``), which
stands in for LLFF's recentring and ``1 / (0.75 * near)`` rescaling (NDC is invariant to both).
"""
from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from engine.core.colorspace import encode8_reference
from engine.core.errors import InputError
from engine.core.frames import Camera, validate_intrinsics, validate_pose
from engine.io.importers import read_png_linear

__all__ = ["LLFF_TO_OPENCV", "POSES_BOUNDS", "IMAGE_SUFFIXES", "LlffPoses", "LlffCapture", "llff_to_world_to_camera",
           "world_to_camera_to_llff", "read_poses_bounds", "image_folders", "choose_image_folder", "read_llff",
           "write_llff"]

#: Column selection turning LLFF camera axes [down, right, back] into OpenCV [right, down, forward]:
#: ``R_opencv = R_llff @ LLFF_TO_OPENCV`` (columns are camera axes in world coordinates). Its own inverse.
LLFF_TO_OPENCV = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])

POSES_BOUNDS = "poses_bounds.npy"
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
_FOLDER = re.compile(r"images(?:_(\d+))?")


@dataclass(eq=False)
class LlffPoses:
    """The content of a ``poses_bounds.npy``, converted: ``world_to_camera`` (N, 4, 4) OpenCV, ``hwf`` (N, 3)
    [H, W, focal] of the full-size images, ``bounds`` (N, 2) near / far planar depth; ``file`` it came from."""

    world_to_camera: np.ndarray
    hwf: np.ndarray
    bounds: np.ndarray
    file: Path

    def __len__(self) -> int:
        return int(self.world_to_camera.shape[0])


@dataclass(eq=False)
class LlffCapture:
    """Images of an LLFF capture with their cameras: ``images`` (N, H, W, 3) float32 linear RGB, ``cameras``
    (OpenCV), ``near_far`` (N, 2), ``names`` (file names), ``factor`` of the folder they came from."""

    images: np.ndarray
    cameras: list[Camera]
    near_far: np.ndarray
    names: list[str]
    factor: int


def llff_to_world_to_camera(pose: np.ndarray) -> np.ndarray:
    """OpenCV world-to-camera (4, 4) from one LLFF 3x5 pose (columns [down, right, back, centre, hwf])."""
    pose = np.asarray(pose, dtype=np.float64)
    if pose.shape != (3, 5):
        raise InputError(f"must be a 3x5 LLFF pose, got shape {pose.shape}", field="pose")
    rot = pose[:, :3] @ LLFF_TO_OPENCV
    w2c = np.eye(4)
    w2c[:3, :3] = rot.T
    w2c[:3, 3] = -rot.T @ pose[:, 3]
    return w2c


def world_to_camera_to_llff(world_to_camera: np.ndarray, hwf: Sequence[float]) -> np.ndarray:
    """The LLFF 3x5 pose of an OpenCV world-to-camera (4, 4) and the full-size ``[H, W, focal]``: the inverse of
    :func:`llff_to_world_to_camera`."""
    w2c = validate_pose(world_to_camera)
    hwf = np.asarray(hwf, dtype=np.float64)
    if hwf.shape != (3,):
        raise InputError(f"must be [H, W, focal], got shape {hwf.shape}", field="hwf")
    rot = w2c[:3, :3].T  # camera-to-world rotation, OpenCV columns
    return np.concatenate([rot @ LLFF_TO_OPENCV, (-rot @ w2c[:3, 3])[:, None], hwf[:, None]], axis=1)


def read_poses_bounds(root: str | Path) -> LlffPoses:
    """Read and check ``poses_bounds.npy`` (``root`` is the capture folder or the file itself).

    Raises:
        InputError: naming the file, the row (``frame``) and the field (``pose``, ``hwf``, ``bounds``) of a
            missing or unreadable file, a shape other than (N >= 1, 17), a non-finite number, a rotation that
            is not one, a non-positive size or focal, or bounds without 0 < near < far.
    """
    path = Path(root)
    file = path if path.suffix == ".npy" else path / POSES_BOUNDS
    if not file.is_file():
        raise InputError("file does not exist (an LLFF capture holds poses_bounds.npy beside its image folders)",
                         file=file)
    try:
        data = np.load(file, allow_pickle=False)
    except (ValueError, OSError, EOFError) as exc:
        raise InputError(f"cannot be read as .npy ({exc})", file=file) from None
    if data.ndim != 2 or data.shape[1] != 17 or data.shape[0] < 1 or not np.issubdtype(data.dtype, np.number):
        raise InputError(f"must be a numeric (N, 17) array (a 3x5 pose and near, far per image), got shape "
                         f"{data.shape} of {data.dtype}", file=file, field="shape")
    data = data.astype(np.float64)
    for row, values in enumerate(data):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            column = int(bad[0])
            name = "bounds" if column >= 15 else "hwf" if column % 5 == 4 else "pose"
            raise InputError(f"has a non-finite value ({values[column]}) at column {column}", file=file, frame=row,
                             field=name)
    poses = data[:, :15].reshape(-1, 3, 5)
    hwf, bounds = poses[:, :, 4].copy(), data[:, 15:].copy()
    w2c = []
    for row, pose in enumerate(poses):
        if np.any(hwf[row] <= 0):
            raise InputError(f"must be positive [H, W, focal], got {hwf[row].tolist()}", file=file, frame=row,
                             field="hwf")
        if not 0 < bounds[row, 0] < bounds[row, 1]:
            raise InputError(f"must satisfy 0 < near < far, got {bounds[row].tolist()}", file=file, frame=row,
                             field="bounds")
        w2c.append(validate_pose(llff_to_world_to_camera(pose), file=file, frame=row, field_name="pose"))
    return LlffPoses(world_to_camera=np.stack(w2c), hwf=hwf, bounds=bounds, file=file)


def image_folders(root: str | Path) -> dict[int, Path]:
    """The image folders of a capture by factor: ``images`` -> 1, ``images_N`` -> N (sorted by factor)."""
    root = Path(root)
    found = {}
    for path in root.iterdir() if root.is_dir() else ():
        match = _FOLDER.fullmatch(path.name)
        if match and path.is_dir() and (match.group(1) is None or int(match.group(1)) >= 1):
            found[1 if match.group(1) is None else int(match.group(1))] = path
    return dict(sorted(found.items()))


def choose_image_folder(root: str | Path, downscale: Optional[int] = None) -> tuple[Path, int]:
    """(folder, its factor) to read for ``downscale`` (relative to ``images/``; None: the coarsest shipped).

    ``images_<downscale>`` when present, else the coarsest folder whose factor divides ``downscale`` (the
    caller downscales it by ``downscale // factor``: it holds the fewest pixels that still reach the
    requested resolution exactly); InputError naming the missing folder and listing the shipped ones otherwise.
    """
    root = Path(root)
    folders = image_folders(root)
    if not folders:
        raise InputError("holds no image folder (images/ or images_N/ beside poses_bounds.npy)", file=root)
    if downscale is None:
        factor = max(folders)
        return folders[factor], factor
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise InputError(f"must be a positive integer, got {downscale!r}", field="downscale")
    usable = [f for f in folders if downscale % f == 0]
    if not usable:
        wanted = "images" if downscale == 1 else f"images_{downscale}"
        shipped = ", ".join(p.name for p in folders.values())
        raise InputError(f"folder does not exist and no finer folder divides downscale {downscale} (shipped: "
                         f"{shipped}; pass --downscale with one of {sorted(folders)} or a multiple)",
                         file=root / wanted, field="downscale")
    factor = max(usable)
    return folders[factor], factor


def read_llff(root: str | Path, downscale: Optional[int] = None) -> LlffCapture:
    """Read an LLFF capture from the folder :func:`choose_image_folder` picks for ``downscale``: images
    (linear RGB), OpenCV cameras with K for their size, the bounds as ``near_far``; ``factor`` is the folder's
    (the caller downscales by ``downscale // factor``). Images match the rows of ``poses_bounds.npy`` in sorted
    file-name order and must all have one size.

    Raises:
        InputError: a bad ``poses_bounds.npy`` (:func:`read_poses_bounds`), no usable folder, a count of images
            other than the number of rows, an unreadable image or images of different sizes.
    """
    root = Path(root)
    poses = read_poses_bounds(root)
    folder, factor = choose_image_folder(root, downscale)
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in IMAGE_SUFFIXES)
    if len(files) != len(poses):
        raise InputError(f"has {len(poses)} rows but {folder.name}/ holds {len(files)} images (one row per image, "
                         "in sorted file-name order)", file=poses.file, field="rows")
    images, cameras = [], []
    for i, path in enumerate(files):
        rgb = read_png_linear(path)
        if images and rgb.shape != images[0].shape:
            raise InputError(f"is {rgb.shape[1]}x{rgb.shape[0]}, {files[0].name} is {images[0].shape[1]}x"
                             f"{images[0].shape[0]}: the images of a folder must have one size", file=path)
        h, w = rgb.shape[:2]
        h0, w0, focal = poses.hwf[i]
        k = np.array([[focal * w / w0, 0.0, w / 2.0], [0.0, focal * h / h0, h / 2.0], [0.0, 0.0, 1.0]])
        images.append(rgb)
        cameras.append(Camera(validate_intrinsics(k, file=poses.file, frame=i, field_name="hwf"),
                              poses.world_to_camera[i]))
    return LlffCapture(images=np.stack(images).astype(np.float32, copy=False), cameras=cameras, near_far=poses.bounds,
                       names=[p.name for p in files], factor=factor)


def write_llff(root: str | Path, images: np.ndarray, cameras: Sequence[Camera], near_far: np.ndarray,
               factors: Sequence[int] = (1,)) -> Path:
    """Write views as an LLFF capture: ``poses_bounds.npy`` and, per factor, ``images`` / ``images_N`` (8-bit
    sRGB PNGs ``image_0000.png`` ..., area-averaged in linear light, sizes ``W // N`` x ``H // N``).

    Args:
        root: the capture folder (created).
        images: (N, H, W, 3) linear RGB of the full-size images (factor 1).
        cameras: N OpenCV cameras of those images, square pixels and the principal point at the image
            centre (LLFF stores one focal and no principal point).
        near_far: (N, 2) planar-depth bounds, 0 < near < far < inf.
        factors: the folders to write (1 for ``images/``).

    Returns ``root``. Raises InputError for cameras LLFF cannot hold or bad shapes.
    """
    images = np.asarray(images)
    if images.ndim != 4 or images.shape[-1] != 3 or images.shape[0] < 1:
        raise InputError(f"must have shape (N >= 1, H, W, 3), got {images.shape}", field="images")
    n, h, w = images.shape[:3]
    near_far = np.asarray(near_far, dtype=np.float64)
    if len(cameras) != n or near_far.shape != (n, 2):
        raise InputError(f"need {n} cameras and (N, 2) bounds, got {len(cameras)} and {near_far.shape}",
                         field="cameras")
    if not np.all(np.isfinite(near_far)) or np.any(near_far[:, 0] <= 0) or np.any(near_far[:, 1] <= near_far[:, 0]):
        raise InputError("must be finite with 0 < near < far", field="near_far")
    rows = []
    for i, cam in enumerate(cameras):
        k = validate_intrinsics(cam.intrinsics, frame=i)
        if k[0, 0] != k[1, 1] or k[0, 1] != 0 or k[0, 2] != w / 2 or k[1, 2] != h / 2:
            raise InputError("LLFF holds one focal and a centred principal point: fx == fy, cx = W/2, cy = H/2, "
                             f"got {k.tolist()}", frame=i, field="intrinsics")
        pose = world_to_camera_to_llff(cam.world_to_camera, [h, w, k[0, 0]])
        rows.append(np.concatenate([pose.reshape(-1), near_far[i]]))
    root = Path(root)
    root.mkdir(parents=True, exist_ok=True)
    for factor in factors:
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise InputError(f"must be positive integers, got {factor!r}", field="factors")
        folder = root / ("images" if factor == 1 else f"images_{factor}")
        folder.mkdir(exist_ok=True)
        size = (max(1, w // factor), max(1, h // factor))
        for i, image in enumerate(images):
            small = image if factor == 1 else cv2.resize(image.astype(np.float32), size, interpolation=cv2.INTER_AREA)
            cv2.imwrite(str(folder / f"image_{i:04d}.png"), encode8_reference(small)[..., ::-1])
    np.save(root / POSES_BOUNDS, np.stack(rows))
    return root
