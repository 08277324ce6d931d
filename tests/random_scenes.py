"""Random scenes and camera motions for the geometry tests (numpy only, so torch-free test modules share them)."""
from __future__ import annotations

import numpy as np


def rotation(rotvec) -> np.ndarray:
    """Rodrigues: rotation matrix of an axis-angle vector (radians)."""
    rotvec = np.asarray(rotvec, dtype=np.float64)
    angle = float(np.linalg.norm(rotvec))
    if angle == 0.0:
        return np.eye(3)
    k = rotvec / angle
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(angle) * kx + (1 - np.cos(angle)) * kx @ kx


def pose(rotvec=(0.0, 0.0, 0.0), translation=(0.0, 0.0, 0.0)) -> np.ndarray:
    """A rigid world-to-camera matrix."""
    t = np.eye(4)
    t[:3, :3] = rotation(rotvec)
    t[:3, 3] = translation
    return t


def intrinsics(height: int, width: int, focal: float = 1.0) -> np.ndarray:
    f = focal * width
    return np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])


def random_scene(rng: np.random.Generator, height: int = 12, width: int = 16, sky: float = 0.15,
                 near: float = 1.0, far: float = 20.0, boxes: int = 3):
    """A smooth log-depth background with nearer boxes, a sky band on top, random colours."""
    yy, xx = np.mgrid[0:height, 0:width] / max(height, width)
    phase = rng.uniform(0, 2 * np.pi, 2)
    t = 0.5 + 0.25 * np.sin(3 * xx + phase[0]) * np.cos(2 * yy + phase[1])
    depth = np.exp(np.log(near) + (np.log(far) - np.log(near)) * t)
    for _ in range(boxes):
        y0, x0 = rng.integers(0, height - 2), rng.integers(0, width - 2)
        depth[y0:y0 + rng.integers(2, 6), x0:x0 + rng.integers(2, 6)] = rng.uniform(near, np.sqrt(near * far))
    depth[:int(round(sky * height))] = np.inf
    color = rng.uniform(0, 1, (height, width, 3))
    return color.astype(np.float32), depth.astype(np.float32)


def moving_cameras(rng: np.random.Generator, height: int, width: int, angle: float = 0.1, shift: float = 0.3):
    k = intrinsics(height, width, rng.uniform(0.8, 1.2))
    t_src = pose(rng.normal(0, 0.3, 3), rng.normal(0, 1, 3))
    t_dst = pose(rng.normal(0, angle, 3), rng.normal(0, shift, 3)) @ t_src
    return k, t_src, t_dst


def extreme_scene(seed: int, height: int = 16, width: int = 20):
    """Depths log-uniform in [1e-3, 1e5] with a sky band, random colours, and destination poses that put
    points behind the camera (170 degree turns), far off screen (1e3 to the side) or far ahead (50 back):
    (colour, depth, intrinsics, [world_to_camera, ...]); the source camera is the identity."""
    rng = np.random.default_rng(seed)
    depth = np.exp(rng.uniform(np.log(1e-3), np.log(1e5), (height, width))).astype(np.float32)
    depth[:3] = np.inf
    color = rng.uniform(0, 1, (height, width, 3)).astype(np.float32)
    poses = [pose((0, np.radians(170), 0), (0.5, 0, 0)), pose((np.radians(170), 0, 0)),
             pose(translation=(0, 0, 50.0)), pose(translation=(1e3, 0, 0))]
    return color, depth, intrinsics(height, width), poses
