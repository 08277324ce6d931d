"""Time-stamped posed views for the dynamic fields: D-NeRF scenes and rgbd-rig videos, split by camera.

:class:`TimedViews` is a :class:`~models.fields.data.views.Views` (same conventions: OpenCV cameras, rigid
``world_to_camera``, pixel centres at +0.5, planar depth with +inf for sky, linear RGB) whose every view
also carries its time, its physical camera and its frame number.

- **D-NeRF** (:func:`load_dnerf`): NeRF-synthetic's layout and camera convention (``load_nerf_synthetic``:
  Blender camera-to-world ``transform_matrix``, ``camera_angle_x``, RGBA composited on white in
  display-encoded values, near/far 2 and 6) plus a ``time`` per frame in [0, 1]. Monocular: every frame is
  its own camera. Frames listed in the JSON whose image is missing are skipped with one warning naming them.
  A listed ``file_path`` whose folder does not exist is looked up in the split's own folder
  (``<split>/<name>.png``): the shared lego's train JSON names ``./train_low/`` (darkened copies that were
  not kept) for the original ``./train/`` renders.
- **rgbd-rig video** (:func:`load_rig_video`): every frame of every camera of a synchronized capture, with
  the frames' times (seconds) and true planar depth; ``near_far`` per view is its finite depth range.

Images are downscaled while loading (area average of linear light, exact K; depth takes each block's
centre sample), exactly as ``Views.downscaled``.
"""
from __future__ import annotations

from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Optional, Sequence

import cv2
import numpy as np

from engine.core.colorspace import display_encode, srgb_to_linear
from engine.core.errors import InputError
from engine.core.frames import Camera
from engine.io.rgbd import read_rig
from models.fields.data.views import (IMAGE_SUFFIXES, NERF_SYNTHETIC_NEAR_FAR, Views, box_from_cameras,
                                      check_listed_frames, check_views, nearest_depth, read_blender_frame,
                                      read_transforms, resize_image, scale_k)

__all__ = ["TimedViews", "check_timed_views", "load_dnerf", "load_rig_video", "split_by_camera", "frame_step",
           "border_crossings"]


@dataclass(eq=False)
class TimedViews(Views):
    """Posed, time-stamped images of a dynamic scene (a :class:`Views` with per-view time and camera).

    Attributes (beyond :class:`Views`'):
        times: (N,) float64 time of each view in the data's units (seconds for rigs, [0, 1] for D-NeRF).
        camera_ids: (N,) int64 index into ``camera_names`` of the physical camera of each view.
        frame_ids: (N,) int64 frame number of each view in its camera's sequence.
        camera_names: the physical cameras (for monocular D-NeRF, one per frame).
        objects: (N, H, W) bool, True where the view sees one of the scene's objects (rgbd ``object_id`` > 0:
            the content a motion model has to move), or None where the data has no object ids (D-NeRF).
    """

    times: np.ndarray = field(default_factory=lambda: np.zeros(0))
    camera_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    frame_ids: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    camera_names: list[str] = field(default_factory=list)
    objects: Optional[np.ndarray] = None

    @property
    def time_range(self) -> tuple[float, float]:
        """(earliest, latest) time of these views."""
        return float(np.min(self.times)), float(np.max(self.times))

    def subset(self, indices: Sequence[int]) -> "TimedViews":
        """The views at ``indices`` (copies), with their times, cameras and frame numbers."""
        idx = [int(i) for i in indices]
        base = Views.subset(self, idx)
        return replace(base, times=self.times[idx].copy(), camera_ids=self.camera_ids[idx].copy(),
                       frame_ids=self.frame_ids[idx].copy(),
                       objects=None if self.objects is None else self.objects[idx].copy())

    def downscaled(self, factor: int) -> "TimedViews":
        """:meth:`Views.downscaled`, the object masks sampled as the depth is (block centres)."""
        out = Views.downscaled(self, factor)
        if out is self or self.objects is None:
            return out
        return replace(out, objects=np.stack([nearest_depth(m, int(factor), out.width, out.height)
                                              for m in self.objects]))

    def of_cameras(self, names: Sequence[str]) -> "TimedViews":
        """Every view of the named cameras, camera by camera in the order given, then by time."""
        unknown = [n for n in names if n not in self.camera_names]
        if unknown:
            raise InputError(f"unknown camera(s) {unknown}; cameras: {self.camera_names}", field="cameras")
        idx = []
        for name in names:
            k = self.camera_names.index(name)
            mine = np.flatnonzero(self.camera_ids == k)
            idx += mine[np.argsort(self.times[mine], kind="stable")].tolist()
        return self.subset(idx)


def check_timed_views(views: TimedViews) -> TimedViews:
    """:func:`~models.fields.data.views.check_views` plus the time, camera and frame arrays."""
    check_views(views)
    if not isinstance(views, TimedViews):
        raise InputError(f"must be TimedViews (time-stamped views), got {type(views).__name__}", field="views")
    n = len(views)
    times = np.asarray(views.times, np.float64)
    if times.shape != (n,) or not np.all(np.isfinite(times)):
        raise InputError(f"must be (N,) finite times for {n} views, got shape {times.shape}", field="times")
    for name in ("camera_ids", "frame_ids"):
        value = np.asarray(getattr(views, name))
        if value.shape != (n,) or not np.issubdtype(value.dtype, np.integer):
            raise InputError(f"must be (N,) integers for {n} views, got {value.shape} {value.dtype}", field=name)
    if n and (views.camera_ids.min() < 0 or views.camera_ids.max() >= len(views.camera_names)):
        raise InputError(f"must index camera_names ({len(views.camera_names)} cameras)", field="camera_ids")
    if views.objects is not None and (views.objects.shape != views.images.shape[:3] or views.objects.dtype != bool):
        raise InputError(f"must be (N, H, W) bool masks {views.images.shape[:3]}, got {views.objects.shape} "
                         f"{views.objects.dtype}", field="objects")
    return views


def frame_step(times: np.ndarray) -> float:
    """The sequence's frame interval: the median gap between consecutive distinct times (0 for one time)."""
    unique = np.unique(np.asarray(times, np.float64))
    return float(np.median(np.diff(unique))) if unique.size > 1 else 0.0


# --------------------------------------------------------------------------------------------------
# D-NeRF


def _dnerf_image(root: Path, split: str, rel: str) -> Optional[Path]:
    path = root / rel
    if path.suffix.lower() not in IMAGE_SUFFIXES:
        path = path.with_name(path.name + ".png")
    if path.is_file():
        return path
    if not path.parent.is_dir():  # a folder the copy does not have: look in the split's own folder
        alt = root / split / path.name
        if alt.is_file():
            return alt
    return None


def load_dnerf(root: str | Path, split: str = "train", *, downscale: int = 1, white_background: bool = True,
               bounds: Optional[np.ndarray] = None) -> TimedViews:
    """Load one split of a D-NeRF scene (NeRF-synthetic layout + a ``time`` per frame).

    Args:
        root: the scene folder holding ``transforms_<split>.json``.
        split: ``train``, ``val`` or ``test``.
        downscale: integer factor (8: 800x800 -> 100x100), applied image by image while loading.
        white_background: composite RGBA on white (the protocol), else black.
        bounds: (2, 3) box; default fitted to the cameras of this split (``box_from_cameras``).

    Views are sorted by time. Listed frames whose image is missing are skipped with one ``warnings.warn``
    naming them all (see the module doc for ``file_path`` folders that do not exist).

    Raises:
        InputError: missing or malformed JSON (a frame without a finite ``time``), no readable frame, images of
            different sizes.
    """
    root = Path(root)
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise InputError(f"must be a positive integer, got {downscale!r}", field="downscale")
    meta_file = root / f"transforms_{split}.json"
    angle, entries = read_transforms(meta_file, "D-NeRF")
    background = np.ones(3) if white_background else np.zeros(3)
    images, poses, names, times, missing = [], [], [], [], []
    size = None
    for i, entry in enumerate(entries):
        try:
            rel = str(entry["file_path"])
            matrix = np.asarray(entry["transform_matrix"], dtype=np.float64)
            time = float(entry["time"])
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"malformed frame entry ({type(exc).__name__}: {exc}); D-NeRF frames need file_path, "
                             "transform_matrix and time", file=meta_file, frame=i) from None
        if not np.isfinite(time):
            raise InputError(f"must be finite, got {time}", file=meta_file, frame=i, field="time")
        path = _dnerf_image(root, split, rel)
        if path is None:
            missing.append(rel)
            continue
        w2c, rgb = read_blender_frame(path, matrix, background, meta_file, i)
        if size is None:
            size = rgb.shape[:2]
        elif rgb.shape[:2] != size:
            raise InputError(f"image is {rgb.shape[1]}x{rgb.shape[0]}, the first was {size[1]}x{size[0]}", file=path)
        linear = srgb_to_linear(rgb).astype(np.float32)
        h, w = size
        images.append(resize_image(linear, max(1, w // downscale), max(1, h // downscale)))
        poses.append(w2c)
        names.append(Path(rel).name)
        times.append(time)
    check_listed_frames(meta_file, missing, len(images))
    h, w = size
    focal = 0.5 * w / np.tan(0.5 * angle)
    k = scale_k(np.array([[focal, 0.0, w / 2.0], [0.0, focal, h / 2.0], [0.0, 0.0, 1.0]]),
                 images[0].shape[1] / w, images[0].shape[0] / h)
    order = np.argsort(np.asarray(times), kind="stable")
    n = len(images)
    views = TimedViews(images=np.stack([images[i] for i in order]), cameras=[Camera(k.copy(), poses[i]) for i in order],
                       near_far=np.tile(np.array(NERF_SYNTHETIC_NEAR_FAR), (n, 1)), scene_type="bounded-360",
                       background=background.astype(np.float32), names=[names[i] for i in order],
                       downscale=int(downscale), times=np.asarray(times, np.float64)[order],
                       camera_ids=np.arange(n, dtype=np.int64), frame_ids=np.arange(n, dtype=np.int64),
                       camera_names=[names[i] for i in order])
    views.bounds = (np.asarray(bounds, dtype=np.float64) if bounds is not None
                    else box_from_cameras(views.cameras, views.height, views.width))
    return check_timed_views(views)


# --------------------------------------------------------------------------------------------------
# rgbd-rig video


def load_rig_video(path: str | Path, *, downscale: int = 1, frames: Optional[Sequence[int]] = None,
                   scene_type: str = "forward-facing") -> TimedViews:
    """Every frame of every camera of an rgbd-rig capture, with times and true planar depth.

    Args:
        path: the capture folder (``rig.json``).
        downscale: integer factor applied frame by frame.
        frames: positions of the frames to load (default: all), the same for every camera.
        scene_type: ``forward-facing`` (NDC of the mean camera) or ``bounded-360``.

    Views are ordered camera by camera (``rig.json`` order), then by time; ``default_split`` holds the view
    indices of the rig's train and test cameras.
    """
    if isinstance(downscale, bool) or not isinstance(downscale, (int, np.integer)) or downscale < 1:
        raise InputError(f"must be a positive integer, got {downscale!r}", field="downscale")
    rig = read_rig(path)
    names = list(rig.cameras)
    positions = list(range(len(rig))) if frames is None else [int(f) for f in frames]
    bad = [p for p in positions if not 0 <= p < len(rig)]
    if bad or not positions:
        raise InputError(f"frame positions {bad or positions} out of range for {len(rig)} frames", file=rig.path,
                         field="frames")
    images, depths, cams, near_far, times, cam_ids, frame_ids, labels, objects = [], [], [], [], [], [], [], [], []
    for c, name in enumerate(names):
        seq = rig.cameras[name]
        for pos in positions:
            f = seq[pos]
            finite = f.depth[np.isfinite(f.depth)]
            if finite.size == 0:
                raise InputError("every pixel is sky: no depth range", file=seq.path, frame=f.index, field="Z")
            near = float(finite.min())
            far = float(finite.max()) if finite.size == f.depth.size else float("inf")
            if not far > near:
                far = near * 1.01
            h, w = f.depth.shape
            w2, h2 = max(1, w // downscale), max(1, h // downscale)
            images.append(resize_image(f.color.astype(np.float32), w2, h2))
            depths.append(nearest_depth(f.depth, downscale, w2, h2) if downscale > 1 else f.depth)
            if f.object_id is not None:
                objects.append(nearest_depth(f.object_id, downscale, w2, h2) > 0)
            cams.append(Camera(scale_k(f.camera.intrinsics, w2 / w, h2 / h), f.camera.world_to_camera))
            near_far.append((near, far))
            times.append(float(f.time))
            cam_ids.append(c)
            frame_ids.append(int(f.index))
            labels.append(f"{name}@{int(f.index)}")
    sizes = {im.shape for im in images}
    if len(sizes) != 1:
        raise InputError(f"cameras have different image sizes {sorted(sizes)}", file=rig.path)
    cam_ids_a = np.asarray(cam_ids, np.int64)
    split = ([int(i) for i in np.flatnonzero(np.isin(cam_ids_a, [names.index(n) for n in rig.train_cameras]))],
             [int(i) for i in np.flatnonzero(np.isin(cam_ids_a, [names.index(n) for n in rig.test_cameras]))])
    views = TimedViews(images=np.stack(images), cameras=cams, near_far=np.asarray(near_far, np.float64),
                       scene_type=scene_type, depth=np.stack(depths).astype(np.float32), names=labels,
                       downscale=int(downscale), default_split=split if split[0] or split[1] else None,
                       times=np.asarray(times, np.float64), camera_ids=cam_ids_a,
                       frame_ids=np.asarray(frame_ids, np.int64), camera_names=names,
                       objects=np.stack(objects) if len(objects) == len(images) else None)
    return check_timed_views(views)


def split_by_camera(views: TimedViews, train_cameras: Sequence[str], test_cameras: Sequence[str]
                    ) -> tuple[TimedViews, TimedViews]:
    """(every view of the train cameras, every view of the test cameras); the two lists must not overlap."""
    overlap = sorted(set(train_cameras) & set(test_cameras))
    if overlap:
        raise InputError(f"cameras {overlap} are both train and test cameras", field="train_cameras")
    if not train_cameras:
        raise InputError("no train camera selected", field="train_cameras")
    return views.of_cameras(list(train_cameras)), views.of_cameras(list(test_cameras))


# --------------------------------------------------------------------------------------------------
# Objects entering or leaving the views (the canonical-volume limitation, thesis Sec. 5.3.4)


def border_crossings(views: TimedViews, *, threshold: float = 0.1, ring: int = 2, min_fraction: float = 0.02,
                     shadow_ratio: tuple[float, float] = (0.1, 0.95), shadow_chroma: float = 0.15) -> dict[str, object]:
    """Find moving content crossing the image border of fixed cameras: objects entering or leaving the views.

    For every camera that does not move and has at least 3 frames, the background is the per-pixel temporal
    median of its display-encoded frames; a pixel of frame t is *moving content* where any channel differs
    from the background by more than ``threshold``, except where it is a shadow: a darker copy of the
    background (linear ratio to the background within ``shadow_ratio`` in every channel, the channels' ratios
    within ``shadow_chroma`` of each other: moving shadows are appearance, which the canonical colour's time
    input models, not geometry). A 3 x 3 opening removes isolated pixels. Frame t of the
    camera *crosses the border* when more than ``min_fraction`` of the ``ring`` pixels nearest the image
    edge are moving content: something is (partly) outside the view, entering or leaving it. Cameras that
    move (monocular D-NeRF) cannot be tested this way and are listed in ``skipped_cameras``.

    Returns:
        ``{"times": [...] (sorted times at which some camera crosses), "events": [{"camera", "time",
        "border_fraction"}], "tested_cameras": [...], "skipped_cameras": [...], "threshold", "ring",
        "min_fraction"}``.
    """
    events, tested, skipped = [], [], []
    kernel = np.ones((3, 3), np.uint8)
    for c, name in enumerate(views.camera_names):
        idx = np.flatnonzero(views.camera_ids == c)
        if idx.size == 0:
            continue
        poses = np.stack([views.cameras[i].world_to_camera for i in idx])
        if idx.size < 3 or np.abs(poses - poses[0]).max() > 1e-6:
            skipped.append(name)
            continue
        tested.append(name)
        idx = idx[np.argsort(views.times[idx], kind="stable")]
        linear = views.images[idx]
        frames = display_encode(linear)
        background = np.median(frames, axis=0)
        background_linear = np.median(linear, axis=0)
        h, w = frames.shape[1:3]
        edge = np.zeros((h, w), bool)
        r = max(1, min(int(ring), h // 2, w // 2))
        edge[:r], edge[-r:], edge[:, :r], edge[:, -r:] = True, True, True, True
        for i, frame, lin in zip(idx, frames, linear):
            changed = np.abs(frame - background).max(axis=-1) > threshold
            ratio = lin / np.maximum(background_linear, 1e-4)
            shadow = (ratio.max(axis=-1) < shadow_ratio[1]) & (ratio.min(axis=-1) > shadow_ratio[0]) \
                & (ratio.max(axis=-1) - ratio.min(axis=-1) < shadow_chroma)
            moving = (changed & ~shadow).astype(np.uint8)
            moving = cv2.morphologyEx(moving, cv2.MORPH_OPEN, kernel).astype(bool)
            fraction = float(moving[edge].mean())
            if fraction > min_fraction:
                events.append({"camera": name, "time": float(views.times[i]), "border_fraction": fraction})
    return {"times": sorted({e["time"] for e in events}), "events": events, "tested_cameras": tested,
            "skipped_cameras": skipped, "threshold": threshold, "ring": ring, "min_fraction": min_fraction}
