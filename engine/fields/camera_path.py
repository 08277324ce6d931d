"""Cameras through an exported field's scene: the demo's camera path and intrinsics rescaled to another size.

Cameras follow Interleave's convention (``engine.conventions.cameras``): OpenCV axes (x right, y down,
z forward), world-to-camera matrices, pixel centres at +0.5.
"""
from __future__ import annotations

from typing import Optional

import numpy as np

from engine.conventions.cameras import look_at
from engine.core.frames import Camera

__all__ = ["scale_intrinsics", "world_up", "field_camera_path"]


def scale_intrinsics(intrinsics, width: int, height: int, to_width: int, to_height: int, *,
                     fit: str = "width") -> np.ndarray:
    """K of a ``width`` x ``height`` camera for a ``to_width`` x ``to_height`` image: the same horizontal field
    of view (``fit="width"``; the vertical extent cropped or extended about the centre) or the largest scale
    at which the whole original view fits (``fit="contain"``; the other axis extended about the centre)."""
    k = np.array(intrinsics, np.float64)
    s = to_width / width if fit == "width" else min(to_width / width, to_height / height)
    out = k.copy()
    out[:2, :3] = k[:2, :3] * s
    out[0, 2] = k[0, 2] * s + (to_width - width * s) / 2.0
    out[1, 2] = k[1, 2] * s + (to_height - height * s) / 2.0
    return out


def world_up(cameras) -> np.ndarray:
    """The world's up direction seen by cameras without roll: the direction orthogonal to every camera's x
    axis (smallest eigenvector of sum x x^T), signed like their mean up (-y) axis; that mean if ambiguous."""
    rights = np.stack([c.world_to_camera[0, :3] for c in cameras])
    ups = np.stack([-c.world_to_camera[1, :3] for c in cameras])
    mean_up = ups.sum(axis=0) / np.linalg.norm(ups.sum(axis=0))
    values, vectors = np.linalg.eigh(rights.T @ rights)
    if len(cameras) < 2 or values[1] < 1e-3 * max(values[2], 1e-12):
        return mean_up
    up = vectors[:, 0]
    return up if up @ mean_up >= 0 else -up


def _pose(rotation: np.ndarray, eye: np.ndarray) -> np.ndarray:
    """World-to-camera (4, 4) of a camera at ``eye`` with world -> camera ``rotation``."""
    pose = np.eye(4)
    pose[:3, :3], pose[:3, 3] = rotation, -rotation @ eye
    return pose


def field_camera_path(assets, train=None, count: int = 48, width: Optional[int] = None,
                      height: Optional[int] = None, *, orbit_degrees: float = 90.0):
    """A smooth camera path through a field's scene: ``(cameras, width, height)``.

    ``assets`` is a loaded export (:func:`engine.fields.render.load_field`); ``train`` is ``(cameras, width,
    height)`` of the training views or None. Bounded-360 scenes: an arc of ``orbit_degrees`` around the box
    centre at the training cameras' median radius and elevation, starting at the first training camera,
    looking at the centre, about the up direction of the training cameras (:func:`world_up`; without
    training cameras: radius (near + far) / 2, 30 degrees above the xy plane, z up). Forward-facing scenes:
    the NDC reference orientation, the camera centre swaying on a figure eight within the spread of the
    training cameras (without them: 5% of near). Intrinsics: the first training camera's (else the NDC
    camera's, else a 40-degree horizontal field of view) scaled so that its whole view fits ``width`` x
    ``height`` (default: the training size, else 640 x 360).
    """
    scene = assets.scene
    cams = list(train[0]) if train else []
    if train:
        k0, w0, h0 = cams[0].intrinsics, train[1], train[2]
    elif not assets.bounded:
        k0, (w0, h0) = np.asarray(scene["ndc_intrinsics"], np.float64), scene["ndc_size"]
    else:
        w0, h0 = 640, 360
        f = w0 / (2 * np.tan(np.radians(20.0)))
        k0 = np.array([[f, 0, w0 / 2], [0, f, h0 / 2], [0, 0, 1.0]])
    width, height = int(width or w0), int(height or h0)
    k = scale_intrinsics(k0, w0, h0, width, height, fit="contain")
    s = np.arange(count) / max(count, 1)
    poses = []
    if assets.bounded:
        center = (np.asarray(scene["box_min"]) + np.asarray(scene["box_max"])) / 2
        if cams:
            up = world_up(cams)
            offsets = np.stack([c.position - center for c in cams])
            radius = float(np.median(np.linalg.norm(offsets, axis=1)))
            elevation = float(np.median(np.arcsin(np.clip(offsets @ up / np.linalg.norm(offsets, axis=1), -1, 1))))
            first = offsets[0] - (offsets[0] @ up) * up
        else:
            up, radius, elevation = np.array([0.0, 0.0, 1.0]), (scene["near"] + scene["far"]) / 2, np.radians(30.0)
            first = np.array([1.0, 0.0, 0.0])
        e1 = first / np.linalg.norm(first)
        e2 = np.cross(up, e1)
        for a in s * np.radians(orbit_degrees):
            eye = center + radius * (np.cos(elevation) * (np.cos(a) * e1 + np.sin(a) * e2) + np.sin(elevation) * up)
            poses.append(_pose(look_at(eye, center, up), eye))
    else:
        ref = np.asarray(scene["ndc_world_to_camera"], np.float64)
        rot = ref[:3, :3]
        if cams:
            centers = np.stack([c.position for c in cams])
            mean = centers.mean(axis=0)
            local = (centers - mean) @ rot.T  # in the reference camera's axes
            amp = np.maximum((local.max(axis=0) - local.min(axis=0)) / 2, 1e-3 * scene["near"])
        else:
            mean = -rot.T @ ref[:3, 3]
            amp = np.full(3, 0.05 * scene["near"])
        for phase in 2 * np.pi * s:
            eye = mean + rot.T @ np.array([amp[0] * np.sin(phase), 0.5 * amp[1] * np.sin(2 * phase), 0.0])
            poses.append(_pose(rot, eye))
    return [Camera(k.copy(), p) for p in poses], width, height
