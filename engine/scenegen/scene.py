"""The random scene description: pure numpy, deterministic by seed, no GL.

``make_scene(SceneConfig(seed=s))`` samples everything a frame needs: a camera path, a static environment
(textured ground, props, walls, thin structures), independently moving rigid objects, materials, lighting
and the sky. Every path is a closed-form function of continuous time in seconds, so the pose of frame
``i`` is the path at ``i / fps`` and "frame N" (one step past the last frame, needed for the last frame's
flow) is just the path evaluated further.

Conventions (those of ``engine/core/frames.py``): world z is up and the ground is the plane z = 0; scene units
are metres; cameras are OpenCV cameras (x right, y down, z forward) given as rigid ``world_to_camera``
matrices; intrinsics put the principal point at the image centre, pixel centres at +0.5.

Independent parts of the scene draw from independent random streams (one ``SeedSequence`` child each),
so e.g. asking for more objects does not change the camera path or the lighting of a seed.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field, replace
from typing import Optional

import numpy as np

from engine.conventions.cameras import look_at
from engine.core.config import option
from engine.core.errors import InputError
from engine.core.frames import Camera, SceneObject

#: Camera path types ``SceneConfig.camera_path`` may name ("random" picks one per seed).
CAMERA_PATHS = ("static", "pan", "orbit", "dolly", "strafe", "handheld", "crane")
#: Lighting styles ``SceneConfig.lighting`` may name ("random" picks one per seed).
LIGHTING_STYLES = ("sunny", "overcast", "golden", "night")
#: Procedural texture patterns, in the order of the shader's ``u_pattern`` switch.
PATTERNS = ("noise", "checker", "stripes", "cells", "bricks", "marble")
#: Shapes of moving objects.
OBJECT_SHAPES = ("box", "sphere", "cylinder", "torus", "cone", "compound", "rod")
#: Motion presets of moving objects (all are parameter choices of one formula, see ``Motion``).
MOTIONS = ("linear", "wander", "circle", "approach", "bounce", "spin")
#: Primitive shapes a ``Part`` can have, with the meaning of ``Part.size``.
PART_SHAPES = {
    "box": "half extents (hx, hy, hz)",
    "sphere": "radius (r,)",
    "cylinder": "radius and half height along z (r, hz)",
    "cone": "base radius and half height along z, apex at +hz (r, hz)",
    "torus": "major and minor radius, around z (R, r)",
    "plane": "half extents (hx, hy) of a +z facing rectangle",
    "room": "half extents (hx, hy, hz) of an inward-facing box without floor, standing on z = 0",
}

#: Closest a camera centre may come to any surface's bounding volume, in metres.
CAMERA_CLEARANCE = 0.6
#: Half size of the ground plane, metres.
GROUND_HALF_SIZE = 200.0


@dataclass(frozen=True)
class SceneConfig:
    """What to generate. Ranges are inclusive ``(low, high)`` pairs sampled per seed."""

    width: int = option(640, "frame width in pixels")
    height: int = option(360, "frame height in pixels")
    num_frames: int = option(60, "number of frames to render")
    fps: float = option(30.0, "frames per second (frame i is at time i / fps)")
    seed: int = option(0, "random seed: the same seed gives the same scene and the same pixels")
    num_objects: tuple[int, int] = option((1, 6), "range of the number of moving objects")
    object_speed: float = option(1.0, "scale of object speeds (linear and angular)")
    pause_probability: float = option(0.2, "probability that an object stops for a while mid-sequence")
    camera_path: str = option("random", "camera path: random, " + ", ".join(CAMERA_PATHS))
    camera_speed: float = option(1.0, "scale of camera speeds")
    shake_probability: float = option(0.3, "probability of handheld shake on top of a non-handheld path")
    fov_range: tuple[float, float] = option((45.0, 75.0), "range of the vertical field of view, degrees")
    zoom_probability: float = option(0.0, "probability of a slow zoom (intrinsics that change per frame)")
    lighting: str = option("random", "lighting style: random, " + ", ".join(LIGHTING_STYLES))
    num_point_lights: tuple[int, int] = option((0, 3), "range of the number of point lights (night: at least 2)")
    shadows: bool = option(True, "sun shadows (shadow map)")
    fog_probability: float = option(0.3, "probability of distance fog")
    sky_probability: float = option(0.75, "probability of an open sky at infinite depth (else an enclosing room)")
    thin_structures: str = option("random", "thin structures (poles, wires, fences, grilles): random, on, off")
    thin_probability: float = option(0.7, "probability of thin structures when thin_structures is random")
    num_props: tuple[int, int] = option((3, 10), "range of the number of static boxes and pillars")
    back_wall_probability: float = option(0.6, "probability of large walls behind the stage")
    supersample: int = option(2, "colour supersampling factor per axis (ground truth is never supersampled)")
    shadow_map_size: int = option(2048, "sun shadow map resolution in texels per side")
    render_noise: float = option(0.0, "relative standard deviation of per-pixel Monte Carlo-like noise on the "
                                      "colour, as a path tracer with few samples per pixel leaves (0: none; e.g. "
                                      "0.05); drawn per frame from the seed, depth and ground truth stay exact")

    def __post_init__(self) -> None:
        checks = [
            (self.width >= 1 and self.height >= 1, "width and height must be >= 1"),
            (self.num_frames >= 1, "num_frames must be >= 1"),
            (self.fps > 0, "fps must be > 0"),
            (0 <= self.num_objects[0] <= self.num_objects[1], "num_objects must be (low, high), 0 <= low <= high"),
            (self.object_speed >= 0 and self.camera_speed >= 0, "speeds must be >= 0"),
            (self.camera_path == "random" or self.camera_path in CAMERA_PATHS,
             f"camera_path must be random or one of {', '.join(CAMERA_PATHS)}"),
            (self.lighting == "random" or self.lighting in LIGHTING_STYLES,
             f"lighting must be random or one of {', '.join(LIGHTING_STYLES)}"),
            (self.thin_structures in ("random", "on", "off"), "thin_structures must be random, on or off"),
            (1.0 <= self.fov_range[0] <= self.fov_range[1] < 170.0, "fov_range must be (low, high) in (1, 170)"),
            (0 <= self.num_point_lights[0] <= self.num_point_lights[1] <= 4, "num_point_lights must be within 0..4"),
            (0 <= self.num_props[0] <= self.num_props[1], "num_props must be (low, high), 0 <= low <= high"),
            (1 <= self.supersample <= 4, "supersample must be 1..4"),
            (64 <= self.shadow_map_size <= 8192, "shadow_map_size must be 64..8192"),
            (math.isfinite(self.render_noise) and 0.0 <= self.render_noise <= 1.0, "render_noise must be in [0, 1]"),
        ]
        for name in ("pause_probability", "shake_probability", "zoom_probability", "fog_probability",
                     "sky_probability", "thin_probability", "back_wall_probability"):
            checks.append((0.0 <= getattr(self, name) <= 1.0, f"{name} must be in [0, 1]"))
        for ok, problem in checks:
            if not ok:
                raise InputError(problem, field="SceneConfig")


# ----------------------------------------------------------------------------------------------------
# Small geometry helpers
# ----------------------------------------------------------------------------------------------------

def rotation_about(axis: np.ndarray, angle) -> np.ndarray:
    """Rotation matrices (..., 3, 3) by ``angle`` radians (scalar or array) about the unit ``axis`` (Rodrigues)."""
    a = np.asarray(axis, np.float64)
    a = a / np.linalg.norm(a)
    ang = np.asarray(angle, np.float64)
    c, s = np.cos(ang)[..., None, None], np.sin(ang)[..., None, None]
    k = np.array([[0.0, -a[2], a[1]], [a[2], 0.0, -a[0]], [-a[1], a[0], 0.0]])
    return np.eye(3) + s * k + (1.0 - c) * (k @ k)


def rigid(rotation: np.ndarray, translation) -> np.ndarray:
    """4x4 rigid transforms (..., 4, 4) from rotations (..., 3, 3) and translations (..., 3)."""
    rotation = np.asarray(rotation, np.float64)
    translation = np.asarray(translation, np.float64)
    shape = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    out = np.zeros(shape + (4, 4))
    out[..., :3, :3] = rotation
    out[..., :3, 3] = translation
    out[..., 3, 3] = 1.0
    return out


def _random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def _unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def _yaw(angle: float) -> np.ndarray:
    return rotation_about(np.array([0.0, 0.0, 1.0]), angle)


# ----------------------------------------------------------------------------------------------------
# Materials, parts, objects
# ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Material:
    """A procedural texture evaluated in the fragment shader in object (or world) space, plus Blinn gloss."""

    pattern: str
    """one of ``PATTERNS``"""
    colors: np.ndarray = field(repr=False)
    """(3, 3) linear RGB albedos: two main colours and an accent (mortar, veins, cell edges)"""
    scale: float
    """pattern frequency in cycles per metre"""
    rotation: np.ndarray = field(repr=False)
    """(3, 3) rotation of the 3D pattern space"""
    angle: float
    """rotation of 2D patterns (checker, cells, bricks) in their projection plane, radians"""
    offset: np.ndarray = field(repr=False)
    """(3,) pattern-space offset"""
    detail: float
    """amplitude of the fine multiplicative noise that every pattern gets"""
    macro: float
    """amplitude of a low-frequency multiplicative tint variation (breaks up repetition)"""
    specular: float
    """Blinn specular strength"""
    shininess: float
    """Blinn exponent"""
    seed: int
    """noise seed of this material"""


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Part:
    """One primitive shape placed by ``transform`` (parent_from_part: world for static parts, object otherwise)."""

    name: str
    shape: str
    """a key of ``PART_SHAPES``"""
    size: tuple[float, ...]
    """shape parameters, see ``PART_SHAPES``"""
    transform: np.ndarray = field(repr=False)
    material: int
    """index into ``Scene.materials``"""
    casts_shadow: bool = True

    def bounding_box(self) -> np.ndarray:
        """Half extents (3,) of the part's box in its own frame (the box that encloses the shape)."""
        s = self.size
        if self.shape == "box":
            return np.array(s[:3], np.float64)
        if self.shape == "room":  # stands on z = 0: encloses [0, 2 hz], so does a half height of 2 hz
            return np.array([s[0], s[1], 2 * s[2]], np.float64)
        if self.shape == "sphere":
            return np.full(3, s[0])
        if self.shape in ("cylinder", "cone"):
            return np.array([s[0], s[0], s[1]])
        if self.shape == "torus":
            return np.array([s[0] + s[1], s[0] + s[1], s[1]])
        if self.shape == "plane":
            return np.array([s[0], s[1], 0.0])
        raise ValueError(f"unknown shape {self.shape}")

    def bounding_radius(self) -> float:
        """Radius of a sphere about the parent origin that encloses the part."""
        return float(np.linalg.norm(self.transform[:3, 3]) + np.linalg.norm(self.bounding_box()))


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Motion:
    """Rigid motion in continuous time; every preset of ``MOTIONS`` is one choice of these parameters.

    With the motion clock ``s`` (time minus any pause), the position is

        anchor + velocity (s - t_ref) + amplitude * sin(frequency s + phase)
               + circle_radius (cos(w_c s + p_c), sin(w_c s + p_c), 0) + hop |sin(w_h s + p_h)| z

    and the rotation is ``R(spin_axis, spin_rate (s - t_ref)) @ orientation``.
    """

    kind: str
    anchor: np.ndarray = field(repr=False)
    t_ref: float = 0.0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    amplitude: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    frequency: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    phase: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    circle: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """(radius, angular speed, phase)"""
    hop: tuple[float, float, float] = (0.0, 0.0, 0.0)
    """(height, angular speed, phase) of a bounce"""
    spin_axis: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]), repr=False)
    spin_rate: float = 0.0
    orientation: np.ndarray = field(default_factory=lambda: np.eye(3), repr=False)
    pause: tuple[float, float] = (math.inf, math.inf)
    """(start, end) in seconds of a stop, (inf, inf) for none"""

    def clock(self, t) -> np.ndarray:
        """The motion clock: time with the pause interval removed (constant while paused)."""
        t = np.asarray(t, np.float64)
        a, b = self.pause
        if not math.isfinite(a):
            return t
        return np.where(t < a, t, np.where(t < b, a, t - (b - a)))

    def position(self, t) -> np.ndarray:
        """Object origin in world coordinates, (..., 3)."""
        s = self.clock(t)[..., None]
        p = self.anchor + self.velocity * (s - self.t_ref) + self.amplitude * np.sin(self.frequency * s + self.phase)
        r, w, ph = self.circle
        if r:
            ang = w * s[..., 0] + ph
            p = p + r * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
        h, wh, phh = self.hop
        if h:
            p = p + np.stack([np.zeros_like(s[..., 0])] * 2 + [h * np.abs(np.sin(wh * s[..., 0] + phh))], -1)
        return p

    def rotation(self, t) -> np.ndarray:
        """Object rotation (..., 3, 3)."""
        s = self.clock(t)
        return rotation_about(self.spin_axis, self.spin_rate * (s - self.t_ref)) @ self.orientation

    def world_from_object(self, t) -> np.ndarray:
        """Rigid world-from-object transforms (..., 4, 4) at time(s) ``t`` seconds."""
        return rigid(self.rotation(t), self.position(t))


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class MovingObject:
    """A rigid moving object: parts in object space, one id, one motion."""

    id: int
    """1..N, the value of the object_id channel"""
    name: str
    kind: str
    """one of ``OBJECT_SHAPES``"""
    parts: tuple[Part, ...]
    motion: Motion

    def bounding_radius(self) -> float:
        return max(p.bounding_radius() for p in self.parts)

    def world_from_object(self, t) -> np.ndarray:
        return self.motion.world_from_object(t)


# ----------------------------------------------------------------------------------------------------
# Camera, lighting, sky
# ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class CameraPath:
    """A camera path in continuous time with look-at, optional handheld shake and zoom.

    eye(t) = centre + radius (cos(angle0 + angular_rate t'), sin(...), 0) + velocity t' + shake,
    with t' = t - t_mid. In ``look_mode`` "target" the camera looks at ``target + target_velocity t'``;
    in "direction" mode it looks along ``direction`` turned about z by ``pan_rate t'`` (pans, dollies,
    strafes with fixed orientation). Shake adds smooth noise (sums of sines) to position and rotation.
    """

    kind: str
    centre: np.ndarray = field(repr=False)
    t_mid: float
    radius: float = 0.0
    angle0: float = 0.0
    angular_rate: float = 0.0
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    look_mode: str = "target"
    target: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    target_velocity: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    direction: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0]), repr=False)
    pan_rate: float = 0.0
    shake_position: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    """amplitudes (m) of the position shake along world x, y, z"""
    shake_rotation: np.ndarray = field(default_factory=lambda: np.zeros(3), repr=False)
    """amplitudes (rad) of the rotation shake about camera x, y, z"""
    shake_frequency: np.ndarray = field(default_factory=lambda: np.ones((6, 3)), repr=False)
    """(6 channels, 3 sines) frequencies in Hz"""
    shake_phase: np.ndarray = field(default_factory=lambda: np.zeros((6, 3)), repr=False)
    fov_deg: float = 60.0
    """vertical field of view at t_mid, degrees"""
    zoom_rate: float = 0.0
    """d log(focal length) / dt"""

    def _shake(self, t) -> np.ndarray:
        t = np.asarray(t, np.float64)
        weights = np.array([1.0, 0.5, 0.25])
        waves = np.sin(2 * np.pi * self.shake_frequency * t[..., None, None] + self.shake_phase)  # (..., 6, 3)
        return (waves * weights).sum(-1) / weights.sum()  # (..., 6) in [-1, 1]

    def eye(self, t) -> np.ndarray:
        """Camera centre(s) in world coordinates, (..., 3)."""
        t = np.asarray(t, np.float64)
        tp = (t - self.t_mid)[..., None]
        ang = self.angle0 + self.angular_rate * tp[..., 0]
        ring = self.radius * np.stack([np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)
        return self.centre + ring + self.velocity * tp + self._shake(t)[..., :3] * self.shake_position

    def world_to_camera(self, t: float) -> np.ndarray:
        """Rigid OpenCV world-to-camera matrix (4, 4) at time ``t`` seconds."""
        eye = self.eye(t)
        tp = t - self.t_mid
        if self.look_mode == "target":
            rot = look_at(eye, self.target + self.target_velocity * tp)
        else:
            rot = look_at(eye, eye + _yaw(self.pan_rate * tp) @ self.direction)
        shake = self._shake(t)[3:] * self.shake_rotation
        for axis, angle in zip(np.eye(3), shake):
            rot = rotation_about(axis, angle) @ rot
        return rigid(rot, -rot @ eye)

    def focal(self, t: float, height: int) -> float:
        """Focal length in pixels (fx = fy) at time ``t`` for an image ``height`` pixels tall."""
        f0 = 0.5 * height / math.tan(math.radians(self.fov_deg) / 2)
        return f0 * math.exp(self.zoom_rate * (t - self.t_mid))

    def intrinsics(self, t: float, width: int, height: int) -> np.ndarray:
        """Pinhole K (3, 3): square pixels, principal point at the image centre (pixel centres at +0.5)."""
        f = self.focal(t, height)
        return np.array([[f, 0.0, width / 2.0], [0.0, f, height / 2.0], [0.0, 0.0, 1.0]])


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class PointLight:
    """An omnidirectional light with inverse-square falloff (radiant intensity per colour channel)."""

    position: np.ndarray
    color: np.ndarray


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Lighting:
    """Sun + hemisphere ambient + point lights + fog, all in linear RGB."""

    style: str
    sun_direction: np.ndarray
    """unit vector towards the sun (world)"""
    sun_color: np.ndarray
    """sun irradiance (a white albedo-1 surface facing the sun shows this value)"""
    ambient_sky: np.ndarray
    """ambient light from above (hemisphere term, normal pointing up)"""
    ambient_ground: np.ndarray
    """ambient light from below (normal pointing down)"""
    point_lights: tuple[PointLight, ...]
    fog_density: float
    """per metre; 0 for none"""
    fog_color: np.ndarray


@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Sky:
    """The sky at infinite depth (a function of direction only, so its motion is rotation-only)."""

    visible: bool
    """False: an enclosing room replaces the sky and every pixel has finite depth"""
    zenith: np.ndarray
    horizon: np.ndarray
    below: np.ndarray
    """colour below the horizon (seen past the ground's edge)"""
    cloud_color: np.ndarray
    cloud_coverage: float
    cloud_scale: float
    sun_disk: float
    """radiance of the sun disk (0: hidden)"""
    sun_size: float
    """angular radius of the sun disk, radians"""
    seed: int


# ----------------------------------------------------------------------------------------------------
# The scene
# ----------------------------------------------------------------------------------------------------

@dataclass(frozen=True, eq=False)  # holds arrays: compare by identity
class Scene:
    """A complete, renderable scene; ``render_scene`` turns it into frames."""

    config: SceneConfig
    camera: CameraPath
    lighting: Lighting
    sky: Sky
    materials: tuple[Material, ...]
    static_parts: tuple[Part, ...]
    """background geometry (object id 0), transforms are world_from_part"""
    objects: tuple[MovingObject, ...]
    thin: bool
    """whether thin structures were generated"""

    @property
    def width(self) -> int:
        return self.config.width

    @property
    def height(self) -> int:
        return self.config.height

    @property
    def num_frames(self) -> int:
        return self.config.num_frames

    def time(self, index: int) -> float:
        """Time of frame ``index`` in seconds (defined past the last frame too)."""
        return index / self.config.fps

    def camera_at(self, index: int) -> Camera:
        """The camera of frame ``index`` (index == num_frames gives the extrapolated next camera)."""
        t = self.time(index)
        return Camera(self.camera.intrinsics(t, self.width, self.height), self.camera.world_to_camera(t))

    def object_transforms(self, index: int) -> np.ndarray:
        """world_from_object (num_objects, 4, 4) of every moving object at frame ``index``."""
        t = self.time(index)
        if not self.objects:
            return np.zeros((0, 4, 4))
        return np.stack([o.world_from_object(t) for o in self.objects])

    def object_moves(self, index: int) -> np.ndarray:
        """(num_objects,) bool: whether each object's transform changes between frame index and index + 1."""
        a, b = self.object_transforms(index), self.object_transforms(index + 1)
        return np.abs(b - a).reshape(len(self.objects), -1).max(-1, initial=0.0) > 1e-9

    def scene_objects(self) -> list[SceneObject]:
        """The objects list for rgbd-seq: per-frame world_from_object (num_frames, 4, 4), ids 1..N."""
        times = np.arange(self.num_frames) / self.config.fps
        out = []
        for obj in self.objects:
            transforms = obj.world_from_object(times)
            moving = bool(np.abs(np.diff(transforms, axis=0)).max(initial=0.0) > 1e-9)
            out.append(SceneObject(id=obj.id, name=obj.name, moving=moving, world_from_object=transforms))
        return out


# ----------------------------------------------------------------------------------------------------
# Sampling
# ----------------------------------------------------------------------------------------------------

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
        rotation=_random_rotation(rng), angle=float(rng.uniform(0, 2 * np.pi)), offset=rng.uniform(-50, 50, 3),
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
    kind = cfg.camera_path if cfg.camera_path != "random" else str(rng.choice(CAMERA_PATHS))
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
        kw.update(velocity=_unit(rng) * np.array([1, 1, 0.2]) * drift)

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
        b.static.append(Part("room", "room", (hx, hy, hz), rigid(_yaw(rng.uniform(0, np.pi)), [0, 0, 0]),
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
            yaw = _yaw(r.uniform(0, np.pi))
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
                rot = _yaw(ang + np.pi / 2 + r.uniform(-0.3, 0.3))
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
            d = _yaw(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0]) * r.uniform(10, 30)
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
            along = _yaw(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0])
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
            along = _yaw(r.uniform(0, np.pi)) @ np.array([1.0, 0, 0])
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
        parts.append(Part(f"part{j}", shape, size, rigid(_random_rotation(rng), offset), mat2))
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


def _try_object(rng, cfg, b: _Builder, camera: CameraPath, kind: str, mat: int, mat2: int, oid: int,
                speed: float) -> tuple[MovingObject, float]:
    """One candidate object and the lowest height its origin may take (above that it clears the ground)."""
    scale = float(rng.uniform(0.25, 1.0))
    parts, rest = _object_parts(rng, kind, scale, mat, mat2)
    radius = max(p.bounding_radius() for p in parts)
    grounded = kind in ("box", "cylinder", "cone", "compound") and rng.uniform() < 0.45
    motion_kind = str(rng.choice(MOTIONS, p=[0.22, 0.22, 0.16, 0.16, 0.12, 0.12]))
    anchor = _in_view_point(rng, camera, b.t_mid, cfg, (1.5, 18.0), log_depth=True)
    if grounded:
        anchor[2] = rest
        orientation = _yaw(rng.uniform(0, 2 * np.pi))
        axis = np.array([0.0, 0.0, 1.0])
        spin = rng.choice([0.0, rng.uniform(-2.0, 2.0)])
        floor = rest
    else:
        anchor[2] = float(np.clip(anchor[2], radius + 0.05, radius + 3.5))
        orientation = _random_rotation(rng)
        axis = _unit(rng)
        spin = 0.0 if rng.uniform() < 0.15 else rng.choice([-1, 1]) * rng.uniform(0.3, 3.5)
        floor = radius + 0.02
    if kind == "rod" or (motion_kind == "spin" and spin == 0):  # a "spin" object must turn
        spin = rng.choice([-1, 1]) * rng.uniform(1.5, 5.0 if kind == "rod" else 3.0)
    kw: dict = dict(kind=motion_kind, anchor=anchor, t_ref=b.t_mid, spin_axis=axis, spin_rate=float(spin * speed),
                    orientation=orientation)
    horizontal = np.array([1.0, 1.0, 0.0])
    if motion_kind == "linear":
        v = _unit(rng) * (horizontal if grounded else np.array([1, 1, 0.3])) * rng.uniform(0.3, 3.0)
        kw.update(velocity=v * speed)
    elif motion_kind == "wander":
        amp = rng.uniform(0.3, 2.5, 3) * (horizontal if grounded else np.array([1, 1, 0.4]))
        kw.update(amplitude=amp, frequency=rng.uniform(0.4, 2.0, 3) * speed, phase=rng.uniform(0, 2 * np.pi, 3))
    elif motion_kind == "circle":
        r = rng.uniform(0.5, 3.0)
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
        v = _unit(rng) * horizontal * rng.uniform(0.0, 1.5)
        anchor[2] = floor
        kw.update(anchor=anchor, velocity=v * speed,
                  hop=(float(rng.uniform(0.3, 1.5)), float(rng.uniform(2.0, 5.0) * speed),
                       float(rng.uniform(0, np.pi))))
    if rng.uniform() < cfg.pause_probability and b.duration > 0:
        start = rng.uniform(0.1, 0.6) * b.duration
        kw.update(pause=(float(start), float(start + rng.uniform(0.2, 0.5) * b.duration)))
    return MovingObject(id=oid, name=f"{kind}{oid}", kind=kind, parts=tuple(parts), motion=Motion(**kw)), floor


def make_scene(config: SceneConfig) -> Scene:
    """Sample a complete scene from ``config`` (deterministic: the same config gives the same scene).

    >>> scene = make_scene(SceneConfig(seed=3, width=64, height=48, num_frames=4))
    >>> scene.camera_at(0).intrinsics[0, 2]
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
