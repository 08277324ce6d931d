"""An analytic two-layer scene for tests: exact frames with no renderer involved.

A textured background plane at z = 6 (world) and a textured square at z = 3 that moves right by
``object_speed`` world units per frame; the camera translates along x by ``camera_speed`` per frame
(OpenCV axes, looking down +z). Every channel (colour, planar depth, object id, moving, flow,
object_flow) is computed in closed form, so predictors and the evaluation can be checked exactly.
"""
from __future__ import annotations

import dataclasses

import cv2
import numpy as np

from engine.core.frames import Camera, Frame, SceneObject, rigid_inverse
from engine.geometry.motion import rigid_motion_vectors

BACKGROUND_Z = 6.0
SQUARE_Z = 3.0
SQUARE_HALF = 0.5


def _texture(x: np.ndarray, y: np.ndarray, phase: float) -> np.ndarray:
    r = 0.5 + 0.4 * np.sin(3.1 * x + phase) * np.cos(2.3 * y)
    g = 0.5 + 0.4 * np.sin(1.7 * x - 2.9 * y + phase)
    b = 0.5 + 0.4 * np.cos(4.3 * y + 0.5 * x)
    return np.stack([r, g, b], axis=-1).astype(np.float32)


def two_layer_sequence(num_frames: int = 8, width: int = 64, height: int = 48, camera_speed: float = 0.05,
                       object_speed: float = 0.08, fps: float = 30.0,
                       square_half: float = SQUARE_HALF,
                       object_path=None) -> tuple[list[Frame], list[SceneObject]]:
    """``object_path(i)``, when given, is the square's x at frame i instead of ``object_speed * i`` (its
    ``flow`` / ``object_flow`` channels still assume ``object_speed``: use the object transforms)."""
    fx = fy = 0.9 * width
    k = np.array([[fx, 0, width / 2], [0, fy, height / 2], [0, 0, 1]], dtype=np.float64)
    u, v = np.meshgrid(np.arange(width) + 0.5, np.arange(height) + 0.5)
    rx, ry = (u - k[0, 2]) / fx, (v - k[1, 2]) / fy
    frames, transforms = [], []
    for i in range(num_frames + 1):
        cam_x = camera_speed * i
        obj_x = object_speed * i if object_path is None else float(object_path(i))
        w2c = np.eye(4)
        w2c[0, 3] = -cam_x
        world_from_object = np.eye(4)
        world_from_object[0, 3] = obj_x
        world_from_object[2, 3] = SQUARE_Z
        transforms.append(world_from_object)
        if i == num_frames:
            break
        # square: world x in [obj_x - h, obj_x + h], y in [-h, h] at z = 3
        sx, sy = cam_x + rx * SQUARE_Z, ry * SQUARE_Z
        on_square = (np.abs(sx - obj_x) <= square_half) & (np.abs(sy) <= square_half)
        bx, by = cam_x + rx * BACKGROUND_Z, ry * BACKGROUND_Z
        color = np.where(on_square[..., None], _texture(sx - obj_x, sy, 1.0), _texture(bx, by, 0.0))
        depth = np.where(on_square, SQUARE_Z, BACKGROUND_Z).astype(np.float32)
        # flow to the next frame: camera moves +camera_speed, the square +object_speed
        bg_flow = -camera_speed * fx / BACKGROUND_Z
        sq_flow = (object_speed - camera_speed) * fx / SQUARE_Z
        flow = np.zeros((height, width, 2), np.float32)
        flow[..., 0] = np.where(on_square, sq_flow, bg_flow)
        object_flow = np.zeros((height, width, 2), np.float32)
        object_flow[..., 0] = np.where(on_square, object_speed * fx / SQUARE_Z, 0.0)
        frames.append(Frame(index=i, time=i / fps, color=color, depth=depth, camera=Camera(k, w2c),
                            object_id=on_square.astype(np.int32), moving=on_square.copy(), flow=flow,
                            object_flow=object_flow))
    objects = [SceneObject(id=1, name="square", moving=True, world_from_object=np.stack(transforms[:num_frames]))]
    return frames, objects


def rotation(axis, angle: float) -> np.ndarray:
    """Rodrigues rotation matrix about ``axis`` by ``angle`` radians."""
    a = np.asarray(axis, dtype=np.float64) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k


def rigid(axis, angle: float, t) -> np.ndarray:
    """A rigid 4x4 transform: rotation about ``axis`` by ``angle``, then translation ``t``."""
    m = np.eye(4)
    m[:3, :3], m[:3, 3] = rotation(axis, angle), t
    return m


def with_vectors(frames: list[Frame], objects: list[SceneObject], older: int, newest: int) -> Frame:
    """Frame ``newest`` carrying the exact vectors an engine rendering ``older`` then ``newest`` writes."""
    frame = frames[newest]
    motions = {o.id: o.world_from_object[older] @ rigid_inverse(o.world_from_object[newest]) for o in objects}
    vectors = rigid_motion_vectors(frame.depth, frame.camera, frames[older].camera, frame.object_id, motions)
    return dataclasses.replace(frame, motion_vectors=vectors)


def smooth_noise(rng: np.random.Generator, shape: tuple, scale: float, cell: int = 6) -> np.ndarray:
    """float32 noise of ``shape`` (H, W, ...) smooth over about ``cell`` pixels, standard deviation about
    ``scale``: bicubic upsampling of a coarse normal grid."""
    noise = rng.normal(0, 1, (shape[0] // cell + 3, shape[1] // cell + 3) + tuple(shape[2:])).astype(np.float32)
    big = cv2.resize(noise, (shape[1] + 3 * cell, shape[0] + 3 * cell), interpolation=cv2.INTER_CUBIC)
    return scale * big[:shape[0], :shape[1]]


def turned_pose(tx: float, yaw: float) -> np.ndarray:
    """World-to-camera (4, 4): a camera turned by ``yaw`` radians about y and moved by ``tx`` along x."""
    c, s = np.cos(yaw), np.sin(yaw)
    t = np.eye(4)
    t[:3, :3] = [[c, 0, s], [0, 1, 0], [-s, 0, c]]
    t[0, 3] = tx
    return t
