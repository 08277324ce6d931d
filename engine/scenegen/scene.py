"""The random scene description: its types (pure numpy, no GL); ``engine.scenegen.sample.make_scene`` draws one.

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
from dataclasses import dataclass, field

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
#: Largest framebuffer side the renderer makes (width or height times supersample), pixels.
MAX_RENDER_SIDE = 8192
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
    object_speed: float = option(1.0, "scale of object speeds (linear and angular): the same paths run faster, "
                                      "so oscillations and turns also come faster")
    object_travel: float = option(1.0, "scale of the distances objects travel at unchanged rates (linear "
                                       "velocities, wander amplitudes, circle radii, bounce drift): faster "
                                       "objects on equally smooth paths; 1 keeps every seed's scene")
    pause_probability: float = option(0.2, "probability that an object stops for a while mid-sequence")
    object_motions: tuple[str, ...] = option(MOTIONS, "the motions objects draw from (MOTIONS; a subset keeps the "
                                                      "others' relative odds), e.g. linear: constant linear and "
                                                      "angular velocity")
    max_spin: float = option(0.0, "largest spin of an object, degrees a frame (faster spins are slowed to it; 0: "
                                  "no limit)")
    camera_path: str = option("random", "camera path: random, " + ", ".join(CAMERA_PATHS))
    camera_paths: tuple[str, ...] = option(CAMERA_PATHS, "the paths camera_path=random draws from")
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
            (max(self.width, self.height) * self.supersample <= MAX_RENDER_SIDE,
             f"width and height times supersample must be <= {MAX_RENDER_SIDE} (the renderer's framebuffer)"),
            (self.num_frames >= 1, "num_frames must be >= 1"),
            (self.fps > 0, "fps must be > 0"),
            (0 <= self.num_objects[0] <= self.num_objects[1], "num_objects must be (low, high), 0 <= low <= high"),
            (self.object_speed >= 0 and self.camera_speed >= 0, "speeds must be >= 0"),
            (math.isfinite(self.object_travel) and self.object_travel > 0, "object_travel must be > 0"),
            (self.camera_path == "random" or self.camera_path in CAMERA_PATHS,
             f"camera_path must be random or one of {', '.join(CAMERA_PATHS)}"),
            (len(self.camera_paths) >= 1 and set(self.camera_paths) <= set(CAMERA_PATHS),
             f"camera_paths must name some of {', '.join(CAMERA_PATHS)}"),
            (len(self.object_motions) >= 1 and set(self.object_motions) <= set(MOTIONS),
             f"object_motions must name some of {', '.join(MOTIONS)}"),
            (math.isfinite(self.max_spin) and self.max_spin >= 0, "max_spin must be finite and >= 0"),
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


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    w, x, y, z = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.normal(size=3)
    return v / np.linalg.norm(v)


def yaw_rotation(angle: float) -> np.ndarray:
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
            rot = look_at(eye, eye + yaw_rotation(self.pan_rate * tp) @ self.direction)
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
