"""Sampling a scene: ``make_scene(config)`` draws the camera path, static environment, thin structures,
moving objects, materials, lighting and sky of ``config.seed`` (types in ``engine.scenegen.scene``).

Independent parts of the scene draw from independent random streams (one ``SeedSequence`` child each),
so e.g. asking for more objects does not change the camera path or the lighting of a seed.
"""
from __future__ import annotations

import math
from dataclasses import replace
from typing import Optional

import numpy as np

from engine.scenegen.scene import (CAMERA_CLEARANCE, CAMERA_PATHS, GROUND_HALF_SIZE, LIGHTING_STYLES, MOTIONS,
                                   OBJECT_SHAPES, PATTERNS, CameraPath, Lighting, Material, Motion, MovingObject, Part,
                                   PointLight, Scene, SceneConfig, Sky, random_rotation, random_unit, rigid,
                                   yaw_rotation)

__all__ = ["make_scene", "box_distance"]


def _hsv_to_rgb(h: float, s: float, v: float) -> np.ndarray:
    k = (np.array([5.0, 3.0, 1.0]) + h * 6.0) % 6.0
    return v - v * s * np.clip(np.minimum(k, 4.0 - k), 0.0, 1.0)


def _albedo(rng: np.random.Generator, hue: Optional[float] = None,
            value: tuple[float, float] = (0.04, 0.75)) -> np.ndarray:
    h = rng.uniform() if hue is None else hue % 1.0
    s = rng.choice([rng.uniform(0.0, 0.25), rng.uniform(0.25, 0.9)])
    v = rng.uniform(*value)
    return _hsv_to_rgb(h, s, v)


_SCALES = {  # cycles per metre, by role
    "ground": (0.25, 2.5), "wall": (0.3, 2.5), "prop": (0.6, 4.0), "object": (1.0, 6.0), "thin": (2.0, 8.0),
}


def _material(rng: np.random.Generator, role: str, patterns: tuple[str, ...] = PATTERNS) -> Material:
    pattern = str(rng.choice(patterns))
    hue = rng.uniform()
    c0 = _albedo(rng, hue)
    scheme = rng.integers(3)  # 0: same hue other value, 1: complementary, 2: random
    if scheme == 0:
        c1 = _albedo(rng, hue + rng.uniform(-0.05, 0.05))
    elif scheme == 1:
        c1 = _albedo(rng, hue + 0.5 + rng.uniform(-0.1, 0.1))
    else:
        c1 = _albedo(rng)
    if np.abs(c0 - c1).max() < 0.08:  # keep the pattern visible (trackable)
        c1 = np.clip(c1 + rng.choice([-1, 1]) * 0.25, 0.02, 0.85)
    c2 = _albedo(rng, value=(0.02, 0.85))
    lo, hi = _SCALES[role]
    glossy = rng.uniform() < 0.4
    return Material(
        pattern=pattern, colors=np.stack([c0, c1, c2]), scale=float(math.exp(rng.uniform(math.log(lo), math.log(hi)))),
        rotation=random_rotation(rng), angle=float(rng.uniform(0, 2 * np.pi)), offset=rng.uniform(-50, 50, 3),
        detail=float(rng.uniform(0.1, 0.6)), macro=float(rng.uniform(0.0, 0.6)),
        specular=float(rng.uniform(0.2, 0.8) if glossy else rng.uniform(0.0, 0.1)),
        shininess=float(rng.uniform(20, 150) if glossy else rng.uniform(4, 20)), seed=int(rng.integers(1 << 30)))


class _Builder:
    """Mutable state while sampling: materials and parts being collected."""

    def __init__(self, config: SceneConfig) -> None:
        self.config = config
        self.materials: list[Material] = []
        self.static: list[Part] = []
        duration = config.num_frames / config.fps
        self.times = np.arange(config.num_frames + 1) / config.fps
        self.duration = duration
        self.t_mid = 0.5 * duration
        self.thin = False

    def material(self, rng: np.random.Generator, role: str, patterns: tuple[str, ...] = PATTERNS) -> int:
        self.materials.append(_material(rng, role, patterns))
        return len(self.materials) - 1


def box_distance(points: np.ndarray, part: Part) -> np.ndarray:
    """Distance from world points (N, 3) to a static part's oriented bounding box."""
    inv = np.linalg.inv(part.transform)
    local = points @ inv[:3, :3].T + inv[:3, 3]
    excess = np.maximum(np.abs(local) - part.bounding_box(), 0.0)
    return np.linalg.norm(excess, axis=-1)


def _clear_of_camera(part: Part, eyes: np.ndarray, margin: float) -> bool:
    return bool(box_distance(eyes, part).min() > margin)


def _sample_camera(rng: np.random.Generator, cfg: SceneConfig, b: _Builder) -> CameraPath:
    kind = cfg.camera_path if cfg.camera_path != "random" else str(rng.choice(cfg.camera_paths))
    speed = cfg.camera_speed
    fov = float(rng.uniform(*cfg.fov_range))
    dist = float(rng.uniform(5.0, 14.0))
    height = float(rng.choice([rng.uniform(0.5, 1.2), rng.uniform(1.2, 3.5)]))
    azimuth = float(rng.uniform(0, 2 * np.pi))
    target = np.array([*rng.uniform(-1.5, 1.5, 2), rng.uniform(0.3, 1.5)])
    half = 0.5 * b.duration
    radial = np.array([math.cos(azimuth), math.sin(azimuth), 0.0])
    side = np.array([-radial[1], radial[0], 0.0])
    eye0 = dist * radial + np.array([0, 0, height])
    kw: dict = dict(kind=kind, centre=eye0, t_mid=b.t_mid, target=target, fov_deg=fov)

    def capped(v: float, max_travel: float) -> float:  # speed such that |v| * half <= max_travel
        return math.copysign(min(abs(v), max_travel / max(half, 1e-9)), v)

    if kind == "pan":
        rate = rng.choice([-1, 1]) * rng.uniform(0.1, 0.45) * speed
        direction = target - eye0
        kw.update(look_mode="direction", direction=direction / np.linalg.norm(direction), pan_rate=float(rate))
    elif kind == "orbit":
        rate = rng.choice([-1, 1]) * rng.uniform(0.5, 2.5) / dist * speed
        kw.update(centre=np.array([0.0, 0.0, height]), radius=dist, angle0=azimuth, angular_rate=float(rate))
    elif kind == "dolly":
        forward = -radial * rng.choice([1.0, 1.0, -1.0])  # mostly forward, sometimes backward
        v = capped(rng.uniform(0.5, 2.5) * speed, 0.45 * dist)
        direction = target - eye0
        kw.update(velocity=forward * v, look_mode="direction", direction=direction / np.linalg.norm(direction))
    elif kind == "strafe":
        v = capped(rng.choice([-1, 1]) * rng.uniform(0.5, 2.0) * speed, 0.6 * dist)
        kw.update(velocity=side * v)
        if rng.uniform() < 0.5:  # fixed orientation; otherwise keep looking at the target (an arc shot)
            direction = target - eye0
            kw.update(look_mode="direction", direction=direction / np.linalg.norm(direction))
    elif kind == "crane":
        height = max(height, 1.0)
        v = rng.choice([-1, 1]) * rng.uniform(0.3, 1.0) * speed
        v = capped(v, max(height - 0.4, 0.1)) if v < 0 else capped(v, 5.0)
        kw.update(centre=dist * radial + np.array([0, 0, height]), velocity=np.array([0.0, 0.0, v]))
    elif kind == "handheld":
        drift = capped(rng.uniform(0.0, 0.4) * speed, 1.0)
        kw.update(velocity=random_unit(rng) * np.array([1, 1, 0.2]) * drift)

    shake = kind == "handheld" or rng.uniform() < cfg.shake_probability
    if shake:
        strong = kind == "handheld"
        pos = rng.uniform(0.01, 0.05 if strong else 0.015, 3) * speed
        rot = np.radians(rng.uniform(0.2, 1.2 if strong else 0.4, 3)) * speed
        kw.update(shake_position=pos, shake_rotation=rot,
                  shake_frequency=rng.uniform(0.3, 3.0, (6, 3)) * np.array([1.0, 2.1, 4.3]),
                  shake_phase=rng.uniform(0, 2 * np.pi, (6, 3)))
    if rng.uniform() < cfg.zoom_probability:
        kw.update(zoom_rate=float(rng.choice([-1, 1]) * rng.uniform(0.05, 0.25) / max(b.duration, 1.0)))
    return CameraPath(**kw)


def _sample_lighting(rng: np.random.Generator, cfg: SceneConfig) -> Lighting:
    style = cfg.lighting if cfg.lighting != "random" else str(rng.choice(LIGHTING_STYLES, p=[0.4, 0.2, 0.25, 0.15]))
    azimuth = rng.uniform(0, 2 * np.pi)
    if style == "sunny":
        elev, sun = rng.uniform(25, 75), rng.uniform(1.0, 2.0)
        tint = _hsv_to_rgb(rng.uniform(0.05, 0.15), rng.uniform(0, 0.15), 1)
        sky_amb = _hsv_to_rgb(rng.uniform(0.55, 0.65), rng.uniform(0.2, 0.5), 1) * rng.uniform(0.2, 0.45)
    elif style == "overcast":
        elev, sun, tint = rng.uniform(30, 80), rng.uniform(0.1, 0.5), np.ones(3)
        sky_amb = _hsv_to_rgb(rng.uniform(0.5, 0.65), rng.uniform(0.0, 0.15), 1) * rng.uniform(0.5, 0.9)
    elif style == "golden":
        elev, sun = rng.uniform(5, 20), rng.uniform(1.0, 2.2)
        tint = _hsv_to_rgb(rng.uniform(0.03, 0.1), rng.uniform(0.3, 0.6), 1)
        sky_amb = _hsv_to_rgb(rng.uniform(0.6, 0.8), rng.uniform(0.2, 0.5), 1) * rng.uniform(0.12, 0.3)
    else:  # night: a dim moon and several lamps
        elev, sun, tint = rng.uniform(20, 70), rng.uniform(0.02, 0.12), _hsv_to_rgb(rng.uniform(0.55, 0.65), 0.3, 1)
        sky_amb = _hsv_to_rgb(rng.uniform(0.55, 0.7), rng.uniform(0.3, 0.6), 1) * rng.uniform(0.01, 0.05)
    elev = math.radians(elev)
    direction = np.array([math.cos(elev) * math.cos(azimuth), math.cos(elev) * math.sin(azimuth), math.sin(elev)])
    ground_amb = sky_amb * rng.uniform(0.2, 0.5) * _hsv_to_rgb(rng.uniform(0.05, 0.15), rng.uniform(0, 0.3), 1)
    lo, hi = cfg.num_point_lights
    count = int(rng.integers(lo, hi + 1))
    if style == "night":
        count = max(count, 2)
    lights = []
    for _ in range(min(count, 4)):
        pos = np.array([*rng.uniform(-8, 8, 2), rng.uniform(1.0, 5.0)])
        power = rng.uniform(2.0, 12.0) if style == "night" else rng.uniform(1.0, 6.0)
        color = _hsv_to_rgb(rng.uniform(), rng.uniform(0.0, 0.7), 1) * power
        lights.append(PointLight(position=pos, color=color))
    fog = float(rng.uniform(0.002, 0.015)) if rng.uniform() < cfg.fog_probability else 0.0
    return Lighting(style=style, sun_direction=direction, sun_color=tint * sun, ambient_sky=sky_amb,
                    ambient_ground=ground_amb, point_lights=tuple(lights), fog_density=fog, fog_color=np.zeros(3))


def _sample_sky(rng: np.random.Generator, cfg: SceneConfig, light: Lighting) -> Sky:
    visible = bool(rng.uniform() < cfg.sky_probability)
    style = light.style
    brightness = {"sunny": 1.0, "overcast": 0.9, "golden": 0.55, "night": 0.03}[style] * rng.uniform(0.6, 1.2)
    zenith = _hsv_to_rgb(rng.uniform(0.55, 0.66), rng.uniform(0.35, 0.8) if style != "overcast" else 0.08, 1) * 0.6
    horizon = _hsv_to_rgb(rng.uniform(0.05, 0.6), rng.uniform(0.0, 0.5 if style == "golden" else 0.2), 1)
    coverage = {"sunny": (0.0, 0.5), "overcast": (0.6, 1.0), "golden": (0.1, 0.6), "night": (0.0, 0.6)}[style]
    return Sky(visible=visible, zenith=zenith * brightness, horizon=horizon * brightness,
               below=horizon * brightness * 0.6, cloud_color=np.ones(3) * brightness * rng.uniform(0.8, 1.3),
               cloud_coverage=float(rng.uniform(*coverage)), cloud_scale=float(rng.uniform(0.5, 3.0)),
               sun_disk=0.0 if style == "overcast" else float(rng.uniform(8, 30) * (0.05 if style == "night" else 1)),
               sun_size=float(math.radians(rng.uniform(0.4, 1.2))), seed=int(rng.integers(1 << 30)))


def _in_view_point(rng: np.random.Generator, camera: CameraPath, t: float, cfg: SceneConfig,
                   depth: tuple[float, float], u_range=(0.1, 0.9), v_range=(0.15, 0.85),
                   log_depth: bool = False) -> np.ndarray:
    """A world point seen by the camera at time t at a random pixel and depth (planar z, log-uniform if asked)."""
    k = camera.intrinsics(t, cfg.width, cfg.height)
    u, v = rng.uniform(*u_range) * cfg.width, rng.uniform(*v_range) * cfg.height
    z = math.exp(rng.uniform(math.log(depth[0]), math.log(depth[1]))) if log_depth else rng.uniform(*depth)
    cam = np.array([(u - k[0, 2]) / k[0, 0] * z, (v - k[1, 2]) / k[1, 1] * z, z])
    w2c = camera.world_to_camera(t)
    return w2c[:3, :3].T @ (cam - w2c[:3, 3])


def _place_static(rng, b: _Builder, eyes: np.ndarray, make, tries: int = 20, margin: float = 1.0) -> list[Part]:
    """Call ``make(rng)`` -> parts until all are clear of the camera path; [] if no try succeeds."""
    for _ in range(tries):
        parts = make(rng)
        if all(_clear_of_camera(p, eyes, margin) for p in parts):
            return parts
    return []


def _sample_static(rng: np.random.Generator, cfg: SceneConfig, b: _Builder, camera: CameraPath, sky: Sky) -> None:
    eyes = camera.eye(b.times)
    max_cam = float(np.linalg.norm(eyes[:, :2], axis=1).max())
    ground = b.material(rng, "ground")
    b.static.append(Part("ground", "plane", (GROUND_HALF_SIZE, GROUND_HALF_SIZE), np.eye(4), ground,
                         casts_shadow=False))
    if not sky.visible:
        hx, hy, hz = rng.uniform(45, 110), rng.uniform(45, 110), rng.uniform(12, 40)
        room = b.material(rng, "wall", ("noise", "cells", "bricks", "checker", "marble"))
        b.static.append(Part("room", "room", (hx, hy, hz), rigid(yaw_rotation(rng.uniform(0, np.pi)), [0, 0, 0]),
                             room, casts_shadow=False))

    # props: boxes and pillars anywhere around the stage
    shared = [b.material(rng, "prop") for _ in range(int(rng.integers(1, 4)))]
    lo, hi = cfg.num_props
    for i in range(int(rng.integers(lo, hi + 1))):
        mat = int(rng.choice(shared)) if rng.uniform() < 0.5 else b.material(rng, "prop")

        def make(r, i=i, mat=mat):
            radius = r.uniform(2.0, 35.0)
            ang = r.uniform(0, 2 * np.pi)
            pos = np.array([radius * math.cos(ang), radius * math.sin(ang), 0.0])
            yaw = yaw_rotation(r.uniform(0, np.pi))
            kind = r.choice(["box", "box", "pillar", "round"])
            if kind == "box":
                h = r.uniform(0.2, 1.5, 3) * np.array([1, 1, r.uniform(0.5, 2.0)])
                return [Part(f"box{i}", "box", tuple(h), rigid(yaw, pos + [0, 0, h[2]]), mat)]
            if kind == "pillar":
                h = np.array([*r.uniform(0.15, 0.5, 2), r.uniform(1.0, 4.0)])
                return [Part(f"pillar{i}", "box", tuple(h), rigid(yaw, pos + [0, 0, h[2]]), mat)]
            rr, hz = r.uniform(0.15, 0.8), r.uniform(0.3, 3.0)
            return [Part(f"column{i}", "cylinder", (rr, hz), rigid(yaw, pos + [0, 0, hz]), mat)]
        b.static += _place_static(rng, b, eyes, make, margin=1.0)

    # large walls beyond the stage (outside the camera's range, so they never hide the stage for long)
    if rng.uniform() < cfg.back_wall_probability:
        mat = b.material(rng, "wall", ("bricks", "cells", "noise", "stripes", "checker"))
        for i in range(int(rng.integers(1, 4))):
            def make(r, i=i):
                radius = r.uniform(max_cam + 4.0, max_cam + 30.0)
                ang = r.uniform(0, 2 * np.pi)
                length, height, thick = r.uniform(8, 30), r.uniform(3, 12), r.uniform(0.2, 0.8)
                pos = np.array([radius * math.cos(ang), radius * math.sin(ang), height])
                rot = yaw_rotation(ang + np.pi / 2 + r.uniform(-0.3, 0.3))
                size = (length / 2, thick / 2, height / 2)
                return [Part(f"wall{i}", "box", size, rigid(rot, pos - [0, 0, height / 2]), mat)]
            b.static += _place_static(rng, b, eyes, make, margin=2.0)

    thin = cfg.thin_structures == "on" or (cfg.thin_structures == "random" and rng.uniform() < cfg.thin_probability)
    if thin:
        _sample_thin(rng, cfg, b, camera, eyes)
    b.thin = thin


def _bar(name: str, a: np.ndarray, c: np.ndarray, half_width: float, mat: int, round_: bool = False) -> Part:
    """A thin bar (box or cylinder) from world point a to world point c."""
    d = c - a
    length = float(np.linalg.norm(d))
    z = d / length
    helper = np.array([1.0, 0, 0]) if abs(z[0]) < 0.9 else np.array([0, 1.0, 0])
    x = np.cross(helper, z)
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    transform = rigid(np.stack([x, y, z], 1), (a + c) / 2)
    if round_:
        return Part(name, "cylinder", (half_width, length / 2), transform, mat)
    return Part(name, "box", (half_width, half_width, length / 2), transform, mat)


def _sample_thin(rng: np.random.Generator, cfg: SceneConfig, b: _Builder, camera: CameraPath, eyes: np.ndarray) -> None:
    metal = b.material(rng, "thin", ("noise", "stripes", "marble"))
    t = b.t_mid

    # poles, with wires between neighbours
    poles = []
    for i in range(int(rng.integers(2, 6))):
        def make(r, i=i):
            base = _in_view_point(r, camera, t, cfg, (2.5, 20.0))
            base[2] = 0.0
            height = r.uniform(2.0, 7.0)
            return [_bar(f"pole{i}", base, base + [0, 0, height], r.uniform(0.015, 0.05), metal, round_=True)]
        parts = _place_static(rng, b, eyes, make, margin=0.8)
        b.static += parts
        poles += parts
    wire_mat = b.material(rng, "thin", ("noise",))
    def near_top(pole: Part) -> np.ndarray:
        return pole.transform[:3, 3] + pole.transform[:3, 2] * pole.size[1] * rng.uniform(0.7, 0.98)

    for i in range(len(poles) - 1):
        top_a, top_b = near_top(poles[i]), near_top(poles[i + 1])
        wire = _bar(f"wire{i}", top_a, top_b, rng.uniform(0.004, 0.012), wire_mat, round_=True)
        if _clear_of_camera(wire, eyes, 0.8):
            b.static.append(wire)
    # long overhead wires across the view
    for i in range(int(rng.integers(0, 3))):
        def make(r, i=i):
            mid = _in_view_point(r, camera, t, cfg, (4.0, 15.0), v_range=(0.05, 0.45))
            d = yaw_rotation(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0]) * r.uniform(10, 30)
            d[2] = r.uniform(-1, 1)
            return [_bar(f"overhead{i}", mid - d / 2, mid + d / 2, r.uniform(0.004, 0.012), wire_mat, round_=True)]
        b.static += _place_static(rng, b, eyes, make, margin=0.8)

    # a fence of thin vertical bars with rails, across the view
    if rng.uniform() < 0.7:
        fence_mat = b.material(rng, "thin", ("noise", "stripes"))

        def make(r):
            mid = _in_view_point(r, camera, t, cfg, (2.5, 10.0))
            mid[2] = 0.0
            length = r.uniform(3.0, 10.0)
            along = yaw_rotation(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0])
            height, spacing = r.uniform(0.8, 2.0), r.uniform(0.08, 0.3)
            hw = r.uniform(0.006, 0.02)
            a, c = mid - along * length / 2, mid + along * length / 2
            n = int(length / spacing) + 1
            parts = [_bar(f"fence_bar{j}", p, p + [0, 0, height], hw, fence_mat)
                     for j, p in enumerate(np.linspace(a, c, n))]
            for j, z in enumerate(r.uniform(0.1, 0.3, 1).tolist() + [height - 0.05]):
                parts.append(_bar(f"fence_rail{j}", a + [0, 0, z], c + [0, 0, z], hw * 1.5, fence_mat))
            return parts
        b.static += _place_static(rng, b, eyes, make, margin=0.8)

    # a grille: a vertical square lattice of thin bars
    if rng.uniform() < 0.5:
        grille_mat = b.material(rng, "thin", ("noise", "marble"))

        def make(r):
            centre = _in_view_point(r, camera, t, cfg, (3.0, 12.0))
            size = r.uniform(1.0, 3.0)
            centre[2] = max(centre[2], size / 2 + r.uniform(0.0, 1.0))
            along = yaw_rotation(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0])
            up = np.array([0.0, 0, 1])
            cell, hw = r.uniform(0.1, 0.35), r.uniform(0.005, 0.015)
            offsets = np.arange(-size / 2, size / 2 + 1e-6, cell)
            parts = []
            for name, a, c in (("grille_v", along, up), ("grille_h", up, along)):  # bars along c, spaced along a
                parts += [_bar(f"{name}{j}", centre + a * o - c * size / 2, centre + a * o + c * size / 2, hw,
                               grille_mat) for j, o in enumerate(offsets)]
            return parts
        b.static += _place_static(rng, b, eyes, make, margin=0.8)


def _object_parts(rng: np.random.Generator, kind: str, scale: float, mat: int, mat2: int) -> tuple[list[Part], float]:
    """Parts of a moving object in object space and the height of its origin above its lowest point."""
    eye4 = np.eye(4)
    if kind == "box":
        h = scale * rng.uniform(0.4, 1.0, 3)
        return [Part("box", "box", tuple(h), eye4, mat)], float(h[2])
    if kind == "sphere":
        return [Part("sphere", "sphere", (scale,), eye4, mat)], scale
    if kind == "cylinder":
        r, hz = scale * rng.uniform(0.4, 1.0), scale * rng.uniform(0.3, 1.0)
        return [Part("cylinder", "cylinder", (r, hz), eye4, mat)], hz
    if kind == "cone":
        r, hz = scale * rng.uniform(0.5, 1.0), scale * rng.uniform(0.5, 1.0)
        return [Part("cone", "cone", (r, hz), eye4, mat)], hz
    if kind == "torus":
        big = scale * rng.uniform(0.6, 1.0)
        return [Part("torus", "torus", (big, big * rng.uniform(0.15, 0.45)), eye4, mat)], big * 0.45
    if kind == "rod":  # a thin spinning bar or a propeller of two: thin moving structure
        length, hw = scale * rng.uniform(1.5, 2.5), rng.uniform(0.01, 0.04)
        parts = [Part("rod", "box", (length / 2, hw, hw), eye4, mat)]
        if rng.uniform() < 0.5:
            parts.append(Part("rod2", "box", (hw, length / 2, hw), eye4, mat2))
        return parts, hw
    # compound: a body with two or three attached primitives, two materials
    body = scale * rng.uniform(0.35, 0.7, 3)
    parts = [Part("body", "box", tuple(body), eye4, mat)]
    for j in range(int(rng.integers(2, 4))):
        shape = str(rng.choice(["sphere", "box", "cylinder"]))
        offset = rng.uniform(-1, 1, 3) * body
        offset[int(rng.integers(3))] = rng.choice([-1, 1]) * body[int(rng.integers(3))]
        s = scale * rng.uniform(0.15, 0.4)
        size = {"sphere": (s,), "box": tuple(s * rng.uniform(0.5, 1.0, 3)), "cylinder": (s * 0.6, s)}[shape]
        parts.append(Part(f"part{j}", shape, size, rigid(random_rotation(rng), offset), mat2))
    lowest = max(float(body[2]), max(-p.transform[2, 3] + np.linalg.norm(p.bounding_box()) for p in parts[1:]))
    return parts, lowest


def _sample_objects(rng: np.random.Generator, cfg: SceneConfig, b: _Builder, camera: CameraPath) -> list[MovingObject]:
    eyes = camera.eye(b.times)
    lo, hi = cfg.num_objects
    count = int(rng.integers(lo, hi + 1))
    speed = cfg.object_speed
    objects: list[MovingObject] = []
    for index in range(count):
        obj_rng = np.random.default_rng(rng.integers(1 << 62))  # per-object stream: retries stay local
        kind = str(obj_rng.choice(OBJECT_SHAPES, p=[0.22, 0.18, 0.14, 0.12, 0.1, 0.16, 0.08]))
        mat, mat2 = b.material(obj_rng, "object"), b.material(obj_rng, "object")
        for _ in range(30):
            obj, floor = _try_object(obj_rng, cfg, b, camera, kind, mat, mat2, len(objects) + 1, speed)
            positions = obj.motion.position(b.times)
            ok = np.linalg.norm(positions - eyes, axis=1).min() > obj.bounding_radius() + CAMERA_CLEARANCE
            if ok and positions[:, 2].min() >= floor - 1e-6:  # never below the ground
                objects.append(obj)
                break
    return objects


#: the odds of each of ``MOTIONS`` (a subset keeps their relative odds)
MOTION_ODDS = (0.22, 0.22, 0.16, 0.16, 0.12, 0.12)


def _draw_motion(rng: np.random.Generator, kinds: tuple[str, ...]) -> str:
    """One of ``kinds`` (a subset of ``MOTIONS``) at ``MOTION_ODDS``: one uniform draw whatever the subset, so
    the rest of an object's stream is drawn alike."""
    if tuple(kinds) == MOTIONS:
        return str(rng.choice(MOTIONS, p=list(MOTION_ODDS)))
    odds = np.array([MOTION_ODDS[MOTIONS.index(k)] for k in kinds])
    return str(rng.choice(list(kinds), p=odds / odds.sum()))


def _try_object(rng, cfg, b: _Builder, camera: CameraPath, kind: str, mat: int, mat2: int, oid: int,
                speed: float) -> tuple[MovingObject, float]:
    """One candidate object and the lowest height its origin may take (above that it clears the ground)."""
    scale = float(rng.uniform(0.25, 1.0))
    parts, rest = _object_parts(rng, kind, scale, mat, mat2)
    radius = max(p.bounding_radius() for p in parts)
    grounded = kind in ("box", "cylinder", "cone", "compound") and rng.uniform() < 0.45
    motion_kind = _draw_motion(rng, cfg.object_motions)
    anchor = _in_view_point(rng, camera, b.t_mid, cfg, (1.5, 18.0), log_depth=True)
    if grounded:
        anchor[2] = rest
        orientation = yaw_rotation(rng.uniform(0, 2 * np.pi))
        axis = np.array([0.0, 0.0, 1.0])
        spin = rng.choice([0.0, rng.uniform(-2.0, 2.0)])
        floor = rest
    else:
        anchor[2] = float(np.clip(anchor[2], radius + 0.05, radius + 3.5))
        orientation = random_rotation(rng)
        axis = random_unit(rng)
        spin = 0.0 if rng.uniform() < 0.15 else rng.choice([-1, 1]) * rng.uniform(0.3, 3.5)
        floor = radius + 0.02
    if kind == "rod" or (motion_kind == "spin" and spin == 0):  # a "spin" object must turn
        spin = rng.choice([-1, 1]) * rng.uniform(1.5, 5.0 if kind == "rod" else 3.0)
    spin = spin * speed
    if cfg.max_spin > 0:  # degrees a frame -> radians a second
        spin = float(np.clip(spin, -math.radians(cfg.max_spin) * cfg.fps, math.radians(cfg.max_spin) * cfg.fps))
    kw: dict = dict(kind=motion_kind, anchor=anchor, t_ref=b.t_mid, spin_axis=axis, spin_rate=float(spin),
                    orientation=orientation)
    horizontal = np.array([1.0, 1.0, 0.0])
    travel = cfg.object_travel
    if motion_kind == "linear":
        v = random_unit(rng) * (horizontal if grounded else np.array([1, 1, 0.3])) * rng.uniform(0.3, 3.0)
        kw.update(velocity=v * speed * travel)
    elif motion_kind == "wander":
        amp = rng.uniform(0.3, 2.5, 3) * (horizontal if grounded else np.array([1, 1, 0.4])) * travel
        kw.update(amplitude=amp, frequency=rng.uniform(0.4, 2.0, 3) * speed, phase=rng.uniform(0, 2 * np.pi, 3))
    elif motion_kind == "circle":
        r = rng.uniform(0.5, 3.0) * travel
        rate = float(rng.choice([-1, 1]) * rng.uniform(0.4, 2.0) * speed)
        kw.update(circle=(float(r), rate, float(rng.uniform(0, 2 * np.pi))))
    elif motion_kind == "approach":  # towards and away from the camera
        to_cam = camera.eye(b.t_mid) - anchor
        dist = np.linalg.norm(to_cam)
        direction = to_cam / dist * (horizontal if grounded else 1.0)
        amp = rng.uniform(0.3, 0.7) * max(dist - radius - 1.0, 0.5)
        kw.update(amplitude=direction * amp, frequency=np.full(3, rng.uniform(0.3, 1.5) * speed),
                  phase=np.full(3, rng.uniform(0, 2 * np.pi)))
    elif motion_kind == "bounce":
        v = random_unit(rng) * horizontal * rng.uniform(0.0, 1.5)
        anchor[2] = floor
        kw.update(anchor=anchor, velocity=v * speed * travel,
                  hop=(float(rng.uniform(0.3, 1.5)), float(rng.uniform(2.0, 5.0) * speed),
                       float(rng.uniform(0, np.pi))))
    if rng.uniform() < cfg.pause_probability and b.duration > 0:
        start = rng.uniform(0.1, 0.6) * b.duration
        kw.update(pause=(float(start), float(start + rng.uniform(0.2, 0.5) * b.duration)))
    return MovingObject(id=oid, name=f"{kind}{oid}", kind=kind, parts=tuple(parts), motion=Motion(**kw)), floor


def make_scene(config: SceneConfig) -> Scene:
    """Sample a complete scene from ``config`` (deterministic: the same config gives the same scene).

    >>> scene = make_scene(SceneConfig(seed=3, width=64, height=48, num_frames=4))
    >>> float(scene.camera_at(0).intrinsics[0, 2])
    32.0
    """
    streams = [np.random.default_rng(s) for s in np.random.SeedSequence(config.seed).spawn(6)]
    cam_rng, light_rng, sky_rng, static_rng, object_rng, _ = streams
    b = _Builder(config)
    camera = _sample_camera(cam_rng, config, b)
    lighting = _sample_lighting(light_rng, config)
    sky = _sample_sky(sky_rng, config, lighting)
    fog_color = sky.horizon if sky.visible else lighting.ambient_sky * 1.5
    lighting = replace(lighting, fog_color=np.asarray(fog_color, np.float64))
    _sample_static(static_rng, config, b, camera, sky)
    objects = _sample_objects(object_rng, config, b, camera)
    return Scene(config=config, camera=camera, lighting=lighting, sky=sky, materials=tuple(b.materials),
                 static_parts=tuple(b.static), objects=tuple(objects), thin=b.thin)
