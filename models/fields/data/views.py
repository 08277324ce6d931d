"""Posed views for the static fields: NeRF-synthetic, LLFF and rgbd-rig loaders, and the train/test split.

Everything comes out in the conventions of ``engine/core/frames.py``: OpenCV cameras (x right, y down, z forward),
rigid ``world_to_camera`` 4x4, K with pixel (u, v) centred at (u + 0.5, v + 0.5), planar depth with +inf for
sky, linear RGB float32.

Conversions (each written once, here):

- **NeRF-synthetic** ``transform_matrix`` is camera-to-world with OpenGL/Blender camera axes (x right, y up,
  looking down -z): ``world_to_camera = inverse(transform_matrix @ diag(1, -1, -1, 1))``
  (``engine.io.importers.opengl_to_opencv_world_to_camera``). ``fx = fy = (W / 2) / tan(camera_angle_x / 2)``,
  ``cx = W / 2``, ``cy = H / 2`` (the image centre in the +0.5 convention). The RGBA PNGs are composited on
  white (or black) *in display-encoded sRGB values*, ``rgb * a + (1 - a)``, exactly as the NeRF-synthetic
  protocol does, then decoded to linear. ``near, far = 2, 6`` (the protocol's).
- **LLFF** captures as shipped (``poses_bounds.npy`` with ``images/``, ``images_N/``) are read by
  ``engine.io.llff`` (torch-free; LLFF's [down, right, back] axes and hwf convention are documented there);
  ``near_far`` holds the bounds as stored; the forward-facing scene starts at 0.9 x the smallest near bound
  and reaches infinity (``models/fields/static/model.py``). A capture whose cameras look around the scene
  (optical axes beyond ``FORWARD_FACING_MAX_DEG`` of their mean) is bounded-360 instead (``llff_scene_type``).
- **rgbd-rig**: already in the project's conventions (``engine.io.rgbd.read_rig``); true planar depth is kept for
  depth metrics and ``near_far`` is the finite depth range of each view (far = +inf where it sees sky).

Downscaling averages linear light over N x N pixel blocks (``cv2.INTER_AREA``) and scales K exactly
(``K' = diag(W'/W, H'/H, 1) K`` in the corner-origin convention). Depth is downscaled by taking the
nearest-sample value (no averaging across edges).
"""
from __future__ import annotations

import json
import warnings
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from engine.core.colorspace import srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera, validate_intrinsics, validate_pose
from engine.io.importers import opengl_to_opencv_world_to_camera
from engine.io.llff import read_llff
from engine.io.rgbd import read_rig

__all__ = ["SCENE_TYPES", "Views", "check_views", "split_indices", "box_from_cameras", "load_nerf_synthetic",
           "FORWARD_FACING_MAX_DEG", "optical_axis_spread", "llff_scene_type", "load_llff", "load_rig",
           "read_transforms", "check_listed_frames", "IMAGE_SUFFIXES", "read_png", "read_blender_frame", "resize_image",
           "nearest_depth", "scale_k"]

SCENE_TYPES = ("bounded-360", "forward-facing")

#: NeRF-synthetic's ray bounds (planar depth, scene units).
NERF_SYNTHETIC_NEAR_FAR = (2.0, 6.0)

IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")


@dataclass(eq=False)
class Views:
    """Posed images of one static scene.

    Attributes:
        images: (N, H, W, 3) float32 linear RGB (already composited on ``background`` where the source had
            alpha).
        cameras: N cameras (OpenCV conventions).
        near_far: (N, 2) float64 planar-depth bounds per view, 0 < near < far (far may be +inf).
        scene_type: ``bounded-360`` or ``forward-facing``.
        depth: (N, H, W) float32 planar depth (+inf = sky), or None.
        bounds: (2, 3) float64 [box_min, box_max] of a bounded scene, or None (fitted to the cameras).
        background: (3,) float32 linear RGB the images are composited on (white for NeRF-synthetic).
        names: N labels (file names) for messages.
        downscale: resolution factor relative to the dataset's own images.
        default_split: (train indices, test indices) the dataset defines, or None.
    """

    images: np.ndarray
    cameras: list[Camera]
    near_far: np.ndarray
    scene_type: str
    depth: Optional[np.ndarray] = None
    bounds: Optional[np.ndarray] = None
    background: np.ndarray = field(default_factory=lambda: np.zeros(3, np.float32))
    names: list[str] = field(default_factory=list)
    downscale: int = 1
    default_split: Optional[tuple[list[int], list[int]]] = None

    def __len__(self) -> int:
        return int(self.images.shape[0])

    @property
    def height(self) -> int:
        return int(self.images.shape[1])

    @property
    def width(self) -> int:
        return int(self.images.shape[2])

    def subset(self, indices: Sequence[int]) -> "Views":
        """The views at ``indices`` (copies of the arrays; no default split)."""
        idx = [int(i) for i in indices]
        for i in idx:
            if not 0 <= i < len(self):
                raise InputError(f"view index {i} out of range for {len(self)} views", field="indices")
        names = [self.names[i] for i in idx] if self.names else []
        return replace(self, images=self.images[idx].copy(), cameras=[self.cameras[i] for i in idx],
                       near_far=self.near_far[idx].copy(), names=names, default_split=None,
                       depth=None if self.depth is None else self.depth[idx].copy())

    def downscaled(self, factor: int) -> "Views":
        """Views at 1/``factor`` of this resolution (area-averaged colour, exact K, nearest depth)."""
        if isinstance(factor, bool) or not isinstance(factor, (int, np.integer)) or factor < 1:
            raise InputError(f"must be a positive integer, got {factor!r}", field="downscale")
        if factor == 1:
            return self
        w, h = max(1, self.width // factor), max(1, self.height // factor)
        images = np.stack([resize_image(im, w, h) for im in self.images])
        cameras = [Camera(scale_k(c.intrinsics, w / self.width, h / self.height), c.world_to_camera)
                   for c in self.cameras]
        depth = None
        if self.depth is not None:
            depth = np.stack([nearest_depth(d, factor, w, h) for d in self.depth])
        return replace(self, images=images, cameras=cameras, depth=depth, downscale=self.downscale * int(factor))


def check_views(views: Views) -> Views:
    """Validate a :class:`Views` once at a public entry point; raises InputError naming the field."""
    if not isinstance(views, Views):
        raise InputError(f"must be a Views, got {type(views).__name__}", field="views")
    im = views.images
    if not isinstance(im, np.ndarray) or im.ndim != 4 or im.shape[-1] != 3 or im.shape[0] < 1:
        raise InputError(f"must have shape (N >= 1, H, W, 3), got {getattr(im, 'shape', None)}", field="images")
    if not np.issubdtype(im.dtype, np.floating) or not np.all(np.isfinite(im)) or np.any(im < 0):
        raise InputError("must be finite, non-negative floats (linear RGB)", field="images")
    n = im.shape[0]
    if len(views.cameras) != n:
        raise InputError(f"has {len(views.cameras)} cameras for {n} images", field="cameras")
    for i, cam in enumerate(views.cameras):
        validate_intrinsics(cam.intrinsics, frame=i)
        validate_pose(cam.world_to_camera, frame=i)
    nf = np.asarray(views.near_far, dtype=np.float64)
    if nf.shape != (n, 2) or np.any(np.isnan(nf)) or np.any(nf[:, 0] <= 0) or np.any(~np.isfinite(nf[:, 0])) \
            or np.any(nf[:, 1] <= nf[:, 0]):
        raise InputError(f"must be (N, 2) with 0 < near < far (far may be inf), got {nf.tolist()[:4]}...",
                         field="near_far")
    if views.scene_type not in SCENE_TYPES:
        raise InputError(f"must be one of {SCENE_TYPES}, got {views.scene_type!r}", field="scene_type")
    if views.depth is not None:
        d = views.depth
        if d.shape != im.shape[:3] or np.any(np.isnan(d)) or np.any(d <= 0):
            raise InputError(f"must be (N, H, W) planar depth > 0 (+inf = sky), got shape {d.shape}", field="depth")
    if views.bounds is not None:
        b = np.asarray(views.bounds, dtype=np.float64)
        if b.shape != (2, 3) or not np.all(np.isfinite(b)) or np.any(b[1] <= b[0]):
            raise InputError(f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] with min < max, got {b.tolist()}",
                             field="bounds")
    bg = np.asarray(views.background, dtype=np.float32)
    if bg.shape != (3,) or not np.all(np.isfinite(bg)):
        raise InputError(f"must be 3 finite numbers (linear RGB), got {views.background!r}", field="background")
    return views


def split_indices(num_frames: int, *, views: Optional[int] = None, train_views: Optional[Sequence[int]] = None,
                  test_views: Optional[Sequence[int]] = None, test_every: int = 8) -> tuple[list[int], list[int]]:
    """Train and test frame indices for sparse-view training.

    Default (the LLFF protocol of the thesis): every ``test_every``-th frame (0, 8, 16, ...) is a test view;
    the ``views`` train frames are spread uniformly over the rest, as the interior points of ``views + 2``
    evenly spaced positions (so neither end is used): with 20 frames and 3 views, train 5, 10, 14 and test
    0, 8, 16. ``views=None`` trains on all the rest; ``test_every=0`` holds nothing out. Explicit
    ``train_views`` / ``test_views`` override either rule and must not overlap.

    >>> split_indices(20, views=3)
    ([5, 10, 14], [0, 8, 16])
    """
    if isinstance(num_frames, bool) or not isinstance(num_frames, (int, np.integer)) or num_frames < 1:
        raise InputError(f"must be a positive integer, got {num_frames!r}", field="num_frames")
    n = int(num_frames)

    def _indices(values, name):
        out = [int(i) for i in values]
        bad = [i for i in out if not 0 <= i < n]
        if bad:
            raise InputError(f"indices {bad} out of range for {n} frames", field=name)
        if len(set(out)) != len(out):
            raise InputError(f"has duplicates: {out}", field=name)
        return out

    if test_views is not None:
        test = _indices(test_views, "test_views")
    else:
        if isinstance(test_every, bool) or not isinstance(test_every, (int, np.integer)) or test_every < 0:
            raise InputError(f"must be an integer >= 0, got {test_every!r}", field="test_every")
        test = list(range(0, n, int(test_every))) if test_every else []
    if train_views is not None:
        train = _indices(train_views, "train_views")
        overlap = sorted(set(train) & set(test))
        if overlap:
            raise InputError(f"frames {overlap} are both train and test views", field="train_views")
        return train, test
    rest = [i for i in range(n) if i not in set(test)]
    if views is None:
        return rest, test
    if isinstance(views, bool) or not isinstance(views, (int, np.integer)) or not 1 <= views <= len(rest):
        raise InputError(f"must be an integer in 1..{len(rest)} (frames left after the test views), got {views!r}",
                         field="views")
    positions = np.floor(np.linspace(0, len(rest) - 1, int(views) + 2)[1:-1] + 0.5).astype(int)
    if len(set(positions.tolist())) < views:  # too few frames for distinct interior points: include the ends
        positions = np.floor(np.linspace(0, len(rest) - 1, int(views)) + 0.5).astype(int)
    return [rest[p] for p in positions], test


def box_from_cameras(cameras: Sequence[Camera], height: int, width: int) -> np.ndarray:
    """An axis-aligned box (2, 3) for cameras looking inwards (bounded-360).

    Centre: the point nearest (least squares) to every optical axis. Half size: the median camera distance
    to it times tan(half the wider field of view), i.e. the cube that fills the median view (1.45 for
    NeRF-synthetic, whose objects fit in [-1.5, 1.5]^3). Cameras with (nearly) parallel axes have no such
    point: the box is then centred one unit in front of the mean camera, with distance 1.
    """
    a = np.zeros((3, 3))
    b = np.zeros(3)
    centers, axes = [], []
    for cam in cameras:
        c2w = cam.camera_to_world
        axis = c2w[:3, 2] / np.linalg.norm(c2w[:3, 2])
        m = np.eye(3) - np.outer(axis, axis)
        a += m
        b += m @ c2w[:3, 3]
        centers.append(c2w[:3, 3])
        axes.append(axis)
    centers, axes = np.array(centers), np.array(axes)
    if np.linalg.cond(a) < 1e8:
        focus = np.linalg.solve(a, b)
        distance = float(np.median(np.linalg.norm(centers - focus, axis=1)))
    else:
        distance = 1.0
        focus = centers.mean(axis=0) + axes.mean(axis=0) * distance
    k = cameras[0].intrinsics
    tan_half = max(width / (2.0 * k[0, 0]), height / (2.0 * k[1, 1]))
    half = max(distance * tan_half, 1e-6)
    return np.stack([focus - half, focus + half])


# --------------------------------------------------------------------------------------------------
# Image helpers


def resize_image(image: np.ndarray, w: int, h: int) -> np.ndarray:
    """``image`` resized to w x h (area filter, float32); itself when it already has that size."""
    if image.shape[1] == w and image.shape[0] == h:
        return image
    return cv2.resize(image, (w, h), interpolation=cv2.INTER_AREA).astype(np.float32)


def nearest_depth(depth: np.ndarray, factor: int, w: int, h: int) -> np.ndarray:
    """Depth at the block-centre sample of each factor x factor block."""
    o = factor // 2
    return np.ascontiguousarray(depth[o::factor, o::factor][:h, :w])


def scale_k(k: np.ndarray, sx: float, sy: float) -> np.ndarray:
    """Intrinsics scaled by sx along x and sy along y (a resized image; float64)."""
    return np.diag([sx, sy, 1.0]) @ np.asarray(k, dtype=np.float64)


def read_blender_frame(path: Path, matrix: np.ndarray, background: np.ndarray, meta_file: Path, index: int
                       ) -> tuple[np.ndarray, np.ndarray]:
    """One frame of a Blender-style ``transforms_*.json`` (NeRF-synthetic, D-NeRF): the OpenCV world-to-camera
    of its OpenGL camera-to-world ``matrix`` and its display-encoded RGB, an RGBA image composited on
    ``background`` in display-encoded values (as the NeRF-synthetic protocol does). InputError names the
    file and frame of a bad matrix."""
    if matrix.shape != (4, 4):
        raise InputError(f"must be 4x4, got {matrix.shape}", file=meta_file, frame=index, field="transform_matrix")
    w2c = validate_pose(opengl_to_opencv_world_to_camera(matrix), file=meta_file, frame=index,
                        field_name="transform_matrix")
    rgb, alpha = read_png(path)
    if alpha is not None:
        rgb = rgb * alpha[..., None] + (1.0 - alpha[..., None]) * background
    return w2c, rgb


def read_png(path: Path) -> tuple[np.ndarray, Optional[np.ndarray]]:
    """Display-encoded RGB in [0, 1] (H, W, 3) float64 and alpha (H, W) or None."""
    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if image is None:
        raise InputError("cannot read image (not an image file, or corrupt)", file=path)
    if image.ndim == 2:
        image = np.repeat(image[..., None], 3, axis=-1)
    scale = float(np.iinfo(image.dtype).max) if np.issubdtype(image.dtype, np.integer) else 1.0
    image = image.astype(np.float64) / scale
    rgb = image[..., 2::-1] if image.shape[2] >= 3 else np.repeat(image[..., :1], 3, axis=-1)
    alpha = image[..., 3] if image.shape[2] == 4 else None
    return rgb, alpha


# --------------------------------------------------------------------------------------------------
# NeRF-synthetic


def read_transforms(meta_file: Path, what: str) -> tuple[float, list]:
    """``camera_angle_x`` (radians, checked in (0, pi)) and the frame entries of a Blender-style
    ``transforms_<split>.json`` (NeRF-synthetic, D-NeRF); InputError naming the file otherwise."""
    if not meta_file.is_file():
        raise InputError("file does not exist", file=meta_file)
    try:
        meta = json.loads(meta_file.read_text())
        angle = float(meta["camera_angle_x"])
        entries = list(meta["frames"])
    except (json.JSONDecodeError, KeyError, TypeError, ValueError) as exc:
        raise InputError(f"is not a {what} transforms file ({type(exc).__name__}: {exc})", file=meta_file) from None
    if not 0 < angle < np.pi:
        raise InputError(f"must be in (0, pi) radians, got {angle}", file=meta_file, field="camera_angle_x")
    return angle, entries


def check_listed_frames(meta_file: Path, missing: list[str], loaded: int) -> None:
    """Warn once, naming them, about listed frames whose image is missing; InputError when none loaded."""
    if missing:
        shown = ", ".join(missing[:8]) + (f" and {len(missing) - 8} more" if len(missing) > 8 else "")
        warnings.warn(f"{meta_file}: skipping {len(missing)} listed frame(s) whose image is missing: {shown}",
                      stacklevel=3)
    if not loaded:
        raise InputError("no listed frame has an image file", file=meta_file, field="frames")


def load_nerf_synthetic(root: str | Path, split: str = "train", *, downscale: int = 1, white_background: bool = True,
                        bounds: Optional[np.ndarray] = None) -> Views:
    """Load one split of a NeRF-synthetic (Blender) scene.

    Args:
        root: the scene folder holding ``transforms_<split>.json``.
        split: ``train``, ``val`` or ``test``.
        downscale: integer factor (8: 800x800 -> 100x100).
        white_background: composite RGBA on white (the protocol), else on black.
        bounds: (2, 3) box; default fitted to the cameras (:func:`box_from_cameras`).

    Frames listed in the JSON whose image file does not exist are skipped with one ``warnings.warn`` that
    names them (the shared subset of lego deliberately lacks most frames).

    Raises:
        InputError: missing or malformed JSON, no readable frame, images of different sizes.
    """
    root = Path(root)
    meta_file = root / f"transforms_{split}.json"
    angle, entries = read_transforms(meta_file, "NeRF-synthetic")
    background = np.ones(3) if white_background else np.zeros(3)
    images, poses, names, missing = [], [], [], []
    for i, entry in enumerate(entries):
        try:
            rel = str(entry["file_path"])
            matrix = np.asarray(entry["transform_matrix"], dtype=np.float64)
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed frame entry ({exc})", file=meta_file, frame=i) from None
        path = root / rel
        if path.suffix.lower() not in IMAGE_SUFFIXES:
            path = path.with_name(path.name + ".png")
        if not path.is_file():
            missing.append(rel)
            continue
        w2c, rgb = read_blender_frame(path, matrix, background, meta_file, i)
        images.append(srgb_to_linear(rgb))
        poses.append(w2c)
        names.append(rel)
    check_listed_frames(meta_file, missing, len(images))
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        raise InputError(f"images have different sizes {sorted(sizes)}", file=meta_file)
    h, w = images[0].shape[:2]
    focal = 0.5 * w / np.tan(0.5 * angle)
    k = np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]])
    cams = [Camera(k.copy(), p) for p in poses]
    views = Views(images=np.stack(images).astype(np.float32), cameras=cams,
                  near_far=np.tile(np.array(NERF_SYNTHETIC_NEAR_FAR), (len(images), 1)), scene_type="bounded-360",
                  background=background.astype(np.float32), names=names)
    views = views.downscaled(downscale)
    views.bounds = (np.asarray(bounds, dtype=np.float64) if bounds is not None
                    else box_from_cameras(views.cameras, views.height, views.width))
    return check_views(views)


# --------------------------------------------------------------------------------------------------
# LLFF


#: An LLFF capture is forward-facing (NDC of the mean camera) when every optical axis lies within this many
#: degrees of the mean axis; otherwise its cameras look around the scene and it is bounded-360.
FORWARD_FACING_MAX_DEG = 30.0


def optical_axis_spread(cameras: Sequence[Camera]) -> float:
    """The largest angle, in degrees, between a camera's optical axis (its camera-to-world +z, normalised) and the
    cameras' mean axis; 180 when the axes cancel out (no mean direction, e.g. two opposite cameras)."""
    axes = np.array([cam.camera_to_world[:3, 2] / np.linalg.norm(cam.camera_to_world[:3, 2]) for cam in cameras])
    mean = axes.mean(axis=0)
    norm = np.linalg.norm(mean)
    if norm < 1e-6:
        return 180.0
    return float(np.degrees(np.arccos(np.clip(axes @ (mean / norm), -1.0, 1.0))).max())


def llff_scene_type(cameras: Sequence[Camera]) -> str:
    """``forward-facing`` when every camera's optical axis is within ``FORWARD_FACING_MAX_DEG`` of the mean axis
    (:func:`optical_axis_spread`; LLFF's own scenes: a few degrees), else ``bounded-360`` (a capture walked
    around its object, such as ``llff_beer``, 84 degrees: the NDC of the mean camera cannot hold the views far
    from it)."""
    return "forward-facing" if optical_axis_spread(cameras) <= FORWARD_FACING_MAX_DEG else "bounded-360"


def load_llff(root: str | Path, *, downscale: Optional[int] = None, scene_type: str = "auto") -> Views:
    """Load an LLFF capture as shipped (``engine.io.llff``: ``poses_bounds.npy`` and ``images/``, ``images_N/``).

    ``downscale`` is relative to ``images/`` (the size ``poses_bounds.npy`` describes): ``images_<downscale>``
    when shipped, else the coarsest shipped folder that divides it, area-averaged to it; None picks the
    coarsest folder shipped. ``Views.downscale`` is the resolution reached; ``near_far`` the file's bounds.
    ``scene_type`` ``auto`` is :func:`llff_scene_type` of all the capture's cameras.

    Raises:
        InputError: a bad poses_bounds.npy, no usable image folder, count or size mismatches.
    """
    capture = read_llff(root, downscale)
    if scene_type == "auto":
        scene_type = llff_scene_type(capture.cameras)
    views = Views(images=capture.images, cameras=capture.cameras, near_far=capture.near_far, scene_type=scene_type,
                  names=capture.names, downscale=capture.factor)
    if downscale is not None and downscale != capture.factor:
        views = views.downscaled(int(downscale) // capture.factor)
    return check_views(views)


# --------------------------------------------------------------------------------------------------
# rgbd-rig


def load_rig(path: str | Path, *, frame: int = 0, scene_type: str = "forward-facing") -> Views:
    """Load frame ``frame`` of every camera of an rgbd-rig capture (a static scene) as views.

    Colour and planar depth come straight from the rgbd-seq frames; ``near_far`` is each view's finite depth
    range (far = +inf where the view sees sky); ``default_split`` is the rig's train/test cameras.
    """
    rig = read_rig(path)
    names = list(rig.cameras)
    images, depths, cams, near_far = [], [], [], []
    for name in names:
        seq = rig.cameras[name]
        if not -len(seq) <= frame < len(seq):
            raise InputError(f"frame position {frame} out of range for {len(seq)} frames", file=seq.path, field="frame")
        f = seq[frame]
        finite = f.depth[np.isfinite(f.depth)]
        if finite.size == 0:
            raise InputError("every pixel is sky: no depth range", file=seq.path, frame=f.index, field="Z")
        far = float(finite.max()) if finite.size == f.depth.size else float("inf")
        near = float(finite.min())
        if not far > near:
            far = near * 1.01
        images.append(f.color)
        depths.append(f.depth)
        cams.append(f.camera)
        near_far.append((near, far))
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        raise InputError(f"cameras have different image sizes {sorted(sizes)}", file=rig.path)
    split = ([names.index(n) for n in rig.train_cameras], [names.index(n) for n in rig.test_cameras])
    return check_views(Views(images=np.stack(images).astype(np.float32), cameras=cams,
                             near_far=np.array(near_far, dtype=np.float64), scene_type=scene_type,
                             depth=np.stack(depths).astype(np.float32), names=names,
                             default_split=split if split[0] or split[1] else None))
