"""OpenCV DIS optical flow as the predictors use it: 8-bit luma, presets, any image size, the target image
frame n is matched against, and the photometric error that scores a flow.

Flows are (H, W, 2) float32 pixels (du, dv), u(n -> n-k): where frame n's pixel lies in the other image.
Pixel centres at +0.5; colours are linear RGB, display-encoded to 8 bits before DIS reads them.
"""
from __future__ import annotations

from typing import Optional

import cv2
import numpy as np

from engine.core.checks import checked_array
from engine.core.errors import InputError
from engine.geometry import kernels
from engine.geometry.encoding import encode8
from engine.geometry.holefill import fill_holes
from engine.geometry.regions import region_keeps
from engine.geometry.rigid import motion_components

__all__ = ["DIS_MIN_SIDE", "CONFIDENCE_MARGIN", "CONFIDENCE_WINDOW", "SMALL_MOTION", "DisEstimator", "dis_estimator",
           "dis_calc", "dis_block", "luma8", "encode8", "dis_flow", "dis_target", "initial_flow", "warp_error",
           "confident_motion", "trusted_motion", "drop_untrusted", "FALLBACK_RATIO", "HIDDEN_BAND", "flow_regions",
           "chroma8", "explained_motion", "fall_back"]

#: Smallest side OpenCV's DIS is given: on smaller images (e.g. 12 x 200, 3 x 200) it raises or crashes the
#: process (OpenCV 5.0, measured for every preset, finest scale 0 included); 32 px a side never did.
DIS_MIN_SIDE = 32

#: ``confident_motion``: an estimated object motion explains frame n better than no object motion (the
#: camera-only warp) where its photometric error is lower by more than this many 8-bit levels, averaged over
#: ``CONFIDENCE_WINDOW``^2 pixels
CONFIDENCE_MARGIN = 1.0
CONFIDENCE_WINDOW = 9
#: ``trusted_motion``: estimated object motion under this many pixels must be confident to be kept (what DIS
#: finds in noise and view-dependent colour is this small; larger motion is kept as estimated). Chosen on
#: validation sequences, not the benchmark's: docs/results/2026-11-25-fast-motion.md
SMALL_MOTION = 1.0
#: ``explained_motion``: a region's estimated motion is kept where its photometric error over the last interval
#: is at most this many times that of no object motion
FALLBACK_RATIO = 1.0
#: ``explained_motion``: frame n's surface was hidden at n-k where the camera-compensated frame n-k is nearer
#: than it by more than this ratio
HIDDEN_BAND = 1.1


class DisEstimator:
    """An OpenCV DIS optical flow for a preset, safe to call with and without a starting flow.

    OpenCV's ``DISOpticalFlow`` remembers that it was once given a starting flow: every later ``calc``,
    with ``None`` too, then starts from whatever its newly made output buffer holds (often the previous
    result, freed and reused), so a call without a start gave a different flow after a call with one. This
    keeps one OpenCV object for each kind of call (``calc(a, b, None)`` runs on one that never saw a start)."""

    def __init__(self, preset: int, finest_scale: Optional[int] = None) -> None:
        self._cold, self._warm = cv2.DISOpticalFlow_create(preset), cv2.DISOpticalFlow_create(preset)
        if finest_scale is not None:
            for estimator in (self._cold, self._warm):
                estimator.setFinestScale(int(finest_scale))

    def getFinestScale(self) -> int:  # noqa: N802 (OpenCV's name)
        return int(self._cold.getFinestScale())

    def calc(self, luma_a: np.ndarray, luma_b: np.ndarray, initial: Optional[np.ndarray]) -> np.ndarray:
        """OpenCV's ``calc``: (H, W, 2) float32 flow from a to b, from ``initial`` when it is given."""
        if initial is None:
            return self._cold.calc(luma_a, luma_b, None)
        return self._warm.calc(luma_a, luma_b, initial)


def dis_estimator(preset: str = "medium", finest_scale: Optional[int] = None) -> DisEstimator:
    """A DIS optical-flow estimator (``DisEstimator``) for a preset name ('ultrafast', 'fast', 'medium'; others
    raise), with its finest pyramid scale replaced by ``finest_scale`` when given (0: the input's own
    resolution)."""
    presets = {"ultrafast": cv2.DISOPTICAL_FLOW_PRESET_ULTRAFAST, "fast": cv2.DISOPTICAL_FLOW_PRESET_FAST,
               "medium": cv2.DISOPTICAL_FLOW_PRESET_MEDIUM}
    if preset not in presets:
        raise InputError(f"unknown DIS preset '{preset}', expected one of {sorted(presets)}", field="preset")
    return DisEstimator(presets[preset], finest_scale)


def dis_calc(estimator, luma_a: np.ndarray, luma_b: np.ndarray, initial: Optional[np.ndarray] = None) -> np.ndarray:
    """``estimator.calc(luma_a, luma_b)``, (H, W, 2) float32 flow from a to b, for any size: images with a
    side under ``DIS_MIN_SIDE`` are padded by repeating their edge pixels (no motion there) and the flow is
    cropped back. Same-size uint8 (H, W) images; ``initial`` (H, W, 2) float32, optional: the flow DIS
    starts from (OpenCV uses a same-size float32 flow passed to ``calc`` as its coarsest scale's estimate)."""
    h, w = luma_a.shape
    if luma_b.shape != (h, w):
        raise InputError(f"DIS images of shapes {luma_a.shape} and {luma_b.shape}: expected the same", field="luma")
    if initial is not None:
        initial = np.array(checked_array(initial, "initial", ("H", "W", 2), {"H": h, "W": w}), dtype=np.float32)
    pad_h, pad_w = max(0, DIS_MIN_SIDE - h), max(0, DIS_MIN_SIDE - w)
    if not (pad_h or pad_w):
        return estimator.calc(luma_a, luma_b, initial)
    a, b = (cv2.copyMakeBorder(x, 0, pad_h, 0, pad_w, cv2.BORDER_REPLICATE) for x in (luma_a, luma_b))
    if initial is not None:
        initial = cv2.copyMakeBorder(initial, 0, pad_h, 0, pad_w, cv2.BORDER_CONSTANT, value=0)
    return np.ascontiguousarray(estimator.calc(a, b, initial)[:h, :w])


def dis_block(preset: str = "medium") -> int:
    """Block size 2^s of a DIS preset's finest pyramid scale s (medium: 2, fast and ultrafast: 4). DIS
    computes nothing finer: its flow on a full-size image is its flow on the image's ``cv2.INTER_AREA``
    block means (finest scale 0), bilinearly upsampled and scaled by the block size."""
    return 2 ** int(dis_estimator(preset).getFinestScale())


def luma8(color: np.ndarray) -> np.ndarray:
    """(H, W) uint8 luma of display-encoded linear RGB (H, W, 3): what DIS optical flow reads."""
    return cv2.cvtColor(encode8(color), cv2.COLOR_RGB2GRAY)


def dis_flow(luma_n: np.ndarray, target: np.ndarray, preset: str = "medium",
             finest_scale: Optional[int] = None) -> np.ndarray:
    """``initial_flow`` on lumas already made: ``luma8`` of frame n and its ``dis_target``, (H, W, 2) float32
    (``finest_scale``: see ``dis_estimator``)."""
    return np.ascontiguousarray(dis_calc(dis_estimator(preset, finest_scale), luma_n, target), dtype=np.float32)


def dis_target(color_n: np.ndarray, warped_color: np.ndarray, covered: np.ndarray,
               warped_depth: Optional[np.ndarray] = None) -> np.ndarray:
    """(H, W) uint8 luma of the camera-compensated frame n-k that ``initial_flow`` matches frame n against:
    the warp's colour where it landed; elsewhere frame n's own colour, or, given the warp's depth (H, W),
    the background-biased row fill of ``reproject`` (``engine.geometry.holefill``, frame n's colour where a hole's row
    and column hold no known pixel), which is what ``flow2d`` matches against."""
    if warped_depth is None:
        return luma8(np.where(covered[..., None], warped_color, color_n))
    return luma8(fill_holes(warped_color, warped_depth, ~covered, color_n)[0])


def initial_flow(color_n: np.ndarray, warped_color: np.ndarray, covered: np.ndarray,
                 preset: str = "medium") -> np.ndarray:
    """2D flow u(n -> n-k) a flow network refines: OpenCV DIS from frame n to the camera-compensated frame n-k.

    Both images are display-encoded 8-bit luma; pixels the warp left uncovered (disocclusions) take frame
    n's own colour, so they read as "no motion" instead of as edges. Training (``models.flow.train``)
    calls this function.

    Args:
        color_n: (H, W, 3) linear RGB of frame n; warped_color: (H, W, 3) composite of m^w_{n-k};
        covered: (H, W) bool, where the warp landed; preset: DIS preset 'ultrafast', 'fast' or 'medium'.

    Returns:
        (H, W, 2) float32 pixels.
    """
    return dis_flow(luma8(color_n), dis_target(color_n, warped_color, covered), preset)


def warp_error(luma_n: np.ndarray, target: np.ndarray, offset: tuple[int, int], flow: np.ndarray,
               window: int = 9) -> np.ndarray:
    """(h, w) photometric error of a flow u(n -> n-k): |luma of frame n - ``target`` sampled at x + u| (8-bit
    levels, bilinear; a sample outside ``target`` costs 255), averaged over ``window`` x ``window`` pixels.

    ``luma_n`` (h, w) is a part of frame n whose top-left pixel is pixel ``offset`` (y, x) of ``target``
    (``dis_target`` of a larger region); ``flow`` (h, w, 2) pixels.
    """
    h, w = luma_n.shape
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32) + np.float32(offset[1]),
                         np.arange(h, dtype=np.float32) + np.float32(offset[0]))
    sampled = cv2.remap(target.astype(np.float32), gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR,
                        borderMode=cv2.BORDER_CONSTANT, borderValue=-1.0)
    error = np.where(sampled < 0, np.float32(255.0), np.abs(luma_n.astype(np.float32) - sampled))
    return cv2.blur(error, (window, window), borderType=cv2.BORDER_REFLECT)


def confident_motion(luma_n: np.ndarray, target: np.ndarray, flow: np.ndarray, margin: float = CONFIDENCE_MARGIN,
                     window: int = CONFIDENCE_WINDOW) -> np.ndarray:
    """(H, W) bool: where the object motion ``flow`` u(n -> n-k) (H, W, 2 or more; its first two channels,
    pixels) explains frame n better than no object motion, by more than ``margin`` 8-bit levels of
    ``warp_error`` (``window`` x ``window`` means).

    ``target`` is the camera-compensated frame n-k (``dis_target``), so zero flow is the camera-only warp:
    where an estimate does not beat it (a textureless object, noise, view-dependent colour of a static scene)
    a predictor can fall back to that warp (``trusted_motion`` does, for motion under a pixel).
    ``luma_n`` / ``target``: (H, W) uint8 of the same size.
    """
    h, w = luma_n.shape
    if target.shape != (h, w) or flow.shape[:2] != (h, w) or flow.ndim != 3 or flow.shape[2] < 2:
        raise InputError(f"confidence of a flow of shape {flow.shape} for lumas {luma_n.shape} and {target.shape}",
                         field="flow")
    still = cv2.blur(cv2.absdiff(luma_n, target).astype(np.float32), (window, window), borderType=cv2.BORDER_REFLECT)
    moved = warp_error(luma_n, target, (0, 0), np.ascontiguousarray(flow[..., :2], dtype=np.float32), window)
    return moved < still - np.float32(margin)


def trusted_motion(luma_n: np.ndarray, target: np.ndarray, flow: np.ndarray, seen: np.ndarray,
                   small: float = SMALL_MOTION) -> np.ndarray:
    """(H, W) bool: where a predictor keeps an estimated object motion u(n -> n-k) (``flow`` (H, W, >= 2)
    pixels), elsewhere it uses none (the camera-only warp):

    - only where frame n-k saw the surface (``seen``, ``engine.geometry.seen_before``): content entering at
      the border as the camera turns has no past to be matched with, whatever DIS returns there;
    - motion under ``small`` pixels only where it explains frame n better than none (``confident_motion``):
      DIS's sub-pixel answers to noise, aliasing and view-dependent colour are not object motion.

    Measured on validation sequences, gentle to extreme (docs/results/2026-11-25-fast-motion.md): together
    they raise whole-frame PSNR on every set and k, moving pixels within 0.05 dB; a confidence test on all
    motion instead tears objects apart (-1 dB over moving pixels on gentle scenes).
    """
    if seen.shape != luma_n.shape:
        raise InputError(f"seen mask of shape {seen.shape} for lumas of shape {luma_n.shape}", field="seen")
    small_motion = np.hypot(flow[..., 0], flow[..., 1]) < small
    keep = seen.copy()
    if small_motion.any():
        keep &= ~small_motion | confident_motion(luma_n, target, flow)
    return keep


def drop_untrusted(flow: np.ndarray, luma_n: np.ndarray, target: np.ndarray, seen: np.ndarray,
                   small: float = SMALL_MOTION) -> np.ndarray:
    """Zero, in place, the motion of ``flow`` (H, W, 2) float32 (C-contiguous, as DIS returns it) that
    ``trusted_motion`` does not keep, and return it: ``flow[~trusted_motion(...)] = 0`` (the test oracle) in
    one compiled pass over the rows (``kernels.zero_untrusted``), ~3x cheaper at 960x540."""
    h, w = luma_n.shape
    if seen.shape != (h, w):
        raise InputError(f"seen mask of shape {seen.shape} for lumas of shape {luma_n.shape}", field="seen")
    if flow.shape != (h, w, 2) or flow.dtype != np.float32 or not flow.flags.c_contiguous:
        raise InputError(f"expected a C-contiguous float32 flow of shape {(h, w, 2)}, got {flow.dtype} {flow.shape}",
                         field="flow")
    confident = confident_motion(luma_n, target, flow)
    seen = np.ascontiguousarray(seen, dtype=np.bool_)
    kernels.run_ranges(lambda r0, r1: kernels.zero_untrusted(flow, seen, confident, np.float32(small), r0, r1),
                       kernels.split_rows(h, w))
    return flow


def flow_regions(depth: np.ndarray, flow: np.ndarray, intrinsics: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
    """The pixels with an object motion in ``flow`` (H, W, 2) and a finite, positive depth (``depth`` (H, W),
    planar) in the groups ``engine.geometry.rigid.motion_components`` makes of 3D motion: (moving flat indices
    (M,), labels (M,), count).

    Each pixel's 3D displacement is read from the flow at its own depth (frame n's: a 2D flow does not give
    the depth at n-k), so neighbours join where their depths are alike and they move alike: a region never
    spans a depth edge nor two differently moving objects."""
    h, w = depth.shape
    flow = checked_array(flow, "flow", ("H", "W", 2), {"H": h, "W": w})
    k_inv = np.linalg.inv(np.asarray(intrinsics, np.float64))
    moving = np.flatnonzero(((flow[..., 0] != 0) | (flow[..., 1] != 0)) & np.isfinite(depth) & (depth > 0))
    if not moving.size:
        return moving, np.zeros(0, np.int64), 0
    y, x = np.divmod(moving, w)
    z = depth.reshape(-1)[moving].astype(np.float64)
    du = flow.reshape(-1, 2)[moving].astype(np.float64)

    def lifted(u: np.ndarray, v: np.ndarray) -> np.ndarray:  # z K^-1 (u, v, 1)
        return np.stack([(k_inv[c, 0] * u + k_inv[c, 1] * v + k_inv[c, 2]) * z for c in range(3)], axis=-1)

    now = lifted(x + 0.5, y + 0.5)
    velocity = now - lifted(x + 0.5 + du[:, 0], y + 0.5 + du[:, 1])
    labels, count = motion_components((h, w), moving, now, velocity)
    return moving, labels, count


def chroma8(color: np.ndarray) -> np.ndarray:
    """(H, W, 2) float32: the red and blue shares of display-encoded ``color`` (H, W, 3) linear RGB, scaled to
    0-255: what a change of brightness (noise that scales a pixel, a sheen, a shadow) leaves alone."""
    c = encode8(color).astype(np.float32)
    return np.float32(255.0) * c[..., ::2] / (c.sum(axis=-1, keepdims=True) + np.float32(3.0))


def _sampled(image: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """``image`` (H, W[, C]) float32 sampled bilinearly at x + ``flow`` (edge pixels repeated outside)."""
    h, w = flow.shape[:2]
    gx, gy = np.meshgrid(np.arange(w, dtype=np.float32), np.arange(h, dtype=np.float32))
    return cv2.remap(image, gx + flow[..., 0], gy + flow[..., 1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)


def explained_motion(flow: np.ndarray, luma_n: np.ndarray, target: np.ndarray, depth: np.ndarray,
                     intrinsics: np.ndarray, colors: Optional[tuple[np.ndarray, np.ndarray]] = None,
                     target_depth: Optional[np.ndarray] = None, ratio: float = FALLBACK_RATIO) -> np.ndarray:
    """(H, W) bool: False on the regions (``flow_regions``) whose estimated object motion ``flow`` u(n -> n-k)
    does not explain frame n from frame n-k, True elsewhere.

    A pixel's error under the motion is |``luma_n`` - ``target`` sampled at x + u| (8-bit levels; ``target``
    the camera-compensated frame n-k, ``dis_target``), under no object motion (the camera-only warp)
    |``luma_n`` - ``target``|. Given ``colors`` (frame n's and the target's linear RGB, (H, W, 3)), the same
    errors of their ``chroma8`` are added: the estimators match luma only, so chroma is evidence they did not
    fit (a flow read into noise or a sheen matches their luma, not the chroma of the surface it drags). A region
    keeps its motion unless its error, summed over the pixels whose source x + u lies inside frame n-k,
    exceeds ``ratio`` times that of no motion (``engine.geometry.regions.region_keeps``, the check of
    ``mvec``'s fall-back; content that entered from outside the frame is no evidence either way).

    Given ``target_depth`` (H, W), the planar depth of the target, a pixel whose surface frame n-k hid
    (the target nearer by more than ``HIDDEN_BAND``: the wall a moving object uncovers) has no error of its own
    under no motion (the target shows the occluder): it counts the median error of the still pixels frame
    n-k showed (the frame's noise), so a surface dragged along into what the object uncovers falls back.

    A whole region falls back or none of it, so an object is not torn apart where its inside is flat. Motion
    that does match the frames in luma and chroma (DIS following a white highlight over a static wall) is
    kept."""
    h, w = luma_n.shape
    if target.shape != (h, w) or depth.shape != (h, w):
        raise InputError(f"lumas {luma_n.shape} / {target.shape} and depth {depth.shape}: expected one size",
                         field="depth")
    moving, labels, count = flow_regions(depth, flow, intrinsics)
    keep = np.ones(h * w, bool)
    if not count:
        return keep.reshape(h, w)
    flow = np.ascontiguousarray(flow, dtype=np.float32)
    model = np.abs(luma_n.astype(np.float32) - _sampled(target.astype(np.float32), flow))
    difference = cv2.absdiff(luma_n, target).astype(np.float32)
    if colors is not None:
        chroma_n, chroma_t = (chroma8(checked_array(c, "colors", ("H", "W", 3), {"H": h, "W": w})) for c in colors)
        model += np.abs(chroma_n - _sampled(chroma_t, flow)).sum(axis=-1)
        difference += np.abs(chroma_n - chroma_t).sum(axis=-1)
    model, difference = model.reshape(-1)[moving], difference.reshape(-1)
    still = difference[moving]
    if target_depth is not None:
        hidden = (target_depth * np.float32(HIDDEN_BAND) < depth).reshape(-1)
        judged = ~hidden
        judged[moving] = False
        floor = np.float32(np.median(difference[judged])) if judged.any() else np.float32(0.0)
        still = np.where(hidden[moving], floor, still)
    y, x = np.divmod(moving, w)
    source = flow.reshape(-1, 2)[moving]
    sx, sy = x + 0.5 + source[:, 0], y + 0.5 + source[:, 1]
    inside = (sx >= 0) & (sx < w) & (sy >= 0) & (sy < h)
    keep[moving] = region_keeps(labels, count, model, still, inside, ratio=ratio)[labels]
    return keep.reshape(h, w)


def fall_back(flow: np.ndarray, luma_n: np.ndarray, target: np.ndarray, depth: np.ndarray, intrinsics: np.ndarray,
              colors: Optional[tuple[np.ndarray, np.ndarray]] = None, target_depth: Optional[np.ndarray] = None,
              ratio: float = FALLBACK_RATIO) -> int:
    """Zero, in place, the motion of ``flow`` (H, W, 2) that ``explained_motion`` does not keep (same arguments):
    those regions take the camera-only warp. Returns the number of pixels held."""
    held = ~explained_motion(flow, luma_n, target, depth, intrinsics, colors, target_depth, ratio)
    flow[held] = 0.0
    return int(held.sum())
