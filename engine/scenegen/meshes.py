"""Triangle meshes of the primitive shapes of ``scene.PART_SHAPES`` (pure numpy).

Meshes are flat triangle lists: positions (T*3, 3) and normals (T*3, 3), float32, counter-clockwise
seen from the side the normals point to (outside, or inside for the room), so back-face culling works.
Triangle counts stay moderate because the renderer is a CPU rasterizer (llvmpipe).
"""
from __future__ import annotations

import numpy as np

from engine.scenegen.scene import Part


def _orient(pos: np.ndarray, nrm: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Reorder each triangle's vertices so its winding agrees with its vertex normals; drop degenerate ones."""
    tri = pos.reshape(-1, 3, 3)
    tn = nrm.reshape(-1, 3, 3)
    geo = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    keep = np.linalg.norm(geo, axis=1) > 1e-12
    flip = np.einsum("ij,ij->i", geo, tn.sum(1)) < 0
    tri[flip] = tri[flip][:, [0, 2, 1]]
    tn[flip] = tn[flip][:, [0, 2, 1]]
    return tri[keep].reshape(-1, 3), tn[keep].reshape(-1, 3)


def _grid(points: np.ndarray, normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two triangles per cell of a (rows, cols, 3) grid of points and normals."""
    a, b = points[:-1, :-1], points[:-1, 1:]
    c, d = points[1:, :-1], points[1:, 1:]
    na, nb, nc, nd = normals[:-1, :-1], normals[:-1, 1:], normals[1:, :-1], normals[1:, 1:]
    pos = np.stack([a, b, d, a, d, c], axis=2).reshape(-1, 3)
    nrm = np.stack([na, nb, nd, na, nd, nc], axis=2).reshape(-1, 3)
    return pos, nrm


def _box(h: np.ndarray, inward: bool = False, floor: bool = True, cells: int = 1) -> tuple[np.ndarray, np.ndarray]:
    pos, nrm = [], []
    for axis in range(3):
        for sign in (-1.0, 1.0):
            if not floor and axis == 2 and sign < 0:
                continue
            u, v = [i for i in range(3) if i != axis]
            s = np.linspace(-1, 1, cells + 1)
            gu, gv = np.meshgrid(s, s, indexing="ij")
            p = np.zeros(gu.shape + (3,))
            p[..., axis] = sign * h[axis]
            p[..., u] = gu * h[u]
            p[..., v] = gv * h[v]
            n = np.zeros_like(p)
            n[..., axis] = -sign if inward else sign
            a, b = _grid(p, n)
            pos.append(a)
            nrm.append(b)
    return np.concatenate(pos), np.concatenate(nrm)


def _revolve(profile: np.ndarray, profile_normals: np.ndarray, segments: int) -> tuple[np.ndarray, np.ndarray]:
    """Surface of revolution about z of a (k, 2) (radius, z) profile with (k, 2) (n_r, n_z) normals."""
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    c, s = np.cos(ang)[None, :], np.sin(ang)[None, :]
    r, z = profile[:, :1], profile[:, 1:]
    pts = np.stack([r * c, r * s, np.broadcast_to(z, (len(profile), segments + 1))], -1)
    nr, nz = profile_normals[:, :1], profile_normals[:, 1:]
    nrm = np.stack([nr * c, nr * s, np.broadcast_to(nz, (len(profile), segments + 1))], -1)
    return _grid(pts, nrm)


def _disc(radius: float, z: float, up: bool, segments: int) -> tuple[np.ndarray, np.ndarray]:
    ang = np.linspace(0, 2 * np.pi, segments + 1)
    rim = np.stack([radius * np.cos(ang), radius * np.sin(ang), np.full_like(ang, z)], -1)
    centre = np.array([0.0, 0.0, z])
    pos = np.stack([np.broadcast_to(centre, rim[:-1].shape), rim[:-1], rim[1:]], 1).reshape(-1, 3)
    nrm = np.tile([0.0, 0.0, 1.0 if up else -1.0], (len(pos), 1))
    return pos, nrm


def _sphere(r: float, segments: int = 28, rings: int = 14) -> tuple[np.ndarray, np.ndarray]:
    theta = np.linspace(-np.pi / 2, np.pi / 2, rings + 1)
    normals = np.stack([np.cos(theta), np.sin(theta)], -1)
    return _revolve(normals * r, normals, segments)


def _cylinder(r: float, hz: float, segments: int) -> tuple[np.ndarray, np.ndarray]:
    side = _revolve(np.array([[r, -hz], [r, hz]]), np.array([[1.0, 0.0], [1.0, 0.0]]), segments)
    top, bottom = _disc(r, hz, True, segments), _disc(r, -hz, False, segments)
    return np.concatenate([side[0], top[0], bottom[0]]), np.concatenate([side[1], top[1], bottom[1]])


def _cone(r: float, hz: float, segments: int = 24) -> tuple[np.ndarray, np.ndarray]:
    slope = np.array([2 * hz, r]) / np.hypot(2 * hz, r)
    side = _revolve(np.array([[r, -hz], [1e-4 * r, hz]]), np.array([slope, slope]), segments)
    bottom = _disc(r, -hz, False, segments)
    return np.concatenate([side[0], bottom[0]]), np.concatenate([side[1], bottom[1]])


def _torus(big: float, small: float, segments: int = 28, rings: int = 12) -> tuple[np.ndarray, np.ndarray]:
    phi = np.linspace(0, 2 * np.pi, rings + 1)
    normals = np.stack([np.cos(phi), np.sin(phi)], -1)
    profile = np.stack([big + small * np.cos(phi), small * np.sin(phi)], -1)
    return _revolve(profile, normals, segments)


def shape_mesh(shape: str, size: tuple[float, ...]) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals (float64) of one primitive in its own frame."""
    if shape == "box":
        pos, nrm = _box(np.asarray(size, np.float64))
    elif shape == "room":
        h = np.asarray(size, np.float64)
        pos, nrm = _box(h, inward=True, floor=False, cells=4)
        pos = pos + [0.0, 0.0, h[2]]  # stands on z = 0
    elif shape == "sphere":
        pos, nrm = _sphere(size[0])
    elif shape == "cylinder":
        thin = size[0] < 0.1  # poles and wires: few segments
        pos, nrm = _cylinder(size[0], size[1], 8 if thin else 24)
    elif shape == "cone":
        pos, nrm = _cone(size[0], size[1])
    elif shape == "torus":
        pos, nrm = _torus(size[0], size[1])
    elif shape == "plane":
        n = 16
        gx, gy = np.meshgrid(np.linspace(-size[0], size[0], n + 1), np.linspace(-size[1], size[1], n + 1),
                             indexing="ij")
        p = np.stack([gx, gy, np.zeros_like(gx)], -1)
        pos, nrm = _grid(p, np.broadcast_to([0.0, 0.0, 1.0], p.shape))
    else:
        raise ValueError(f"unknown shape {shape}")
    return _orient(np.array(pos, np.float64), np.array(nrm, np.float64))


def part_mesh(part: Part) -> tuple[np.ndarray, np.ndarray]:
    """Positions and normals of a part in its parent frame (world for static parts, object otherwise)."""
    pos, nrm = shape_mesh(part.shape, part.size)
    rot, trans = part.transform[:3, :3], part.transform[:3, 3]
    return pos @ rot.T + trans, nrm @ rot.T


def merge_parts(parts: list[Part]) -> np.ndarray:
    """Interleaved float32 vertex data (V, 6) = position xyz, normal xyz of several parts."""
    meshes = [part_mesh(p) for p in parts]
    pos = np.concatenate([m[0] for m in meshes])
    nrm = np.concatenate([m[1] for m in meshes])
    return np.concatenate([pos, nrm], axis=1).astype(np.float32)
