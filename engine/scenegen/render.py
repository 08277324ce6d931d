"""The moderngl renderer of a ``Scene``: colour plus exact ground truth, headless (EGL, llvmpipe works).

Per frame, with one GL context reused across frames:

1. sun shadow map (orthographic depth-only pass), if ``config.shadows``;
2. colour at ``supersample`` x the resolution (geometry, then the sky behind it), box-downsampled on the
   GPU to one colour per pixel;
3. ground truth at the native resolution, never supersampled, so every value belongs to the surface
   seen through the pixel centre: planar depth (camera-space z written by the shader in float32), object
   id, moving mask, flow and object_flow. Every vertex is transformed three ways - camera(t) from
   object(t), camera(t+1) from object(t+1), camera(t) from object(t+1) - and the fragment shader projects
   the three interpolated camera-space points, so flow = project(t+1 view) - project(t view) is exact for
   rigid motion (camera-space points are affine on a triangle; perspective-correct interpolation keeps
   them exact). The sky gets the flow of a point at infinity: only the camera rotation moves it.
4. motion vectors as an engine writes them (current -> previous frame, camera included), computed
   exactly on the CPU from that pass's depth and object ids (``engine.geometry.motion``).

All render targets are float32. Camera space is OpenCV's; ``clip_from_camera`` maps it to GL clip space
and rows are flipped on readback (GL images are bottom-up).

This is the ground-truth mode (evaluation, training data). ``engine.scenegen.live.LiveSceneRenderer`` is the
live mode, for the live loop: colour, depth and motion vectors in one pass, as a game draws them, left on the
GPU; both build on ``ScenePasses`` (programs, vertex batches, shadow map, uniforms).
"""
from __future__ import annotations

import math
from typing import Iterator, Optional

import numpy as np
from tqdm import tqdm

from engine.conventions import OPENGL_TO_OPENCV, projection_from_intrinsics
from engine.core.errors import InputError
from engine.core.frames import Camera, Frame, rigid_inverse
from engine.geometry.motion import rigid_motion_vectors
from engine.scenegen import glsl
from engine.scenegen.meshes import merge_parts
from engine.scenegen.scene import PATTERNS, Scene

#: Near and far clip distances in metres (planar depth is exact in between; the scene stays inside).
NEAR, FAR = 0.05, 2000.0


def clip_from_camera(intrinsics: np.ndarray, width: int, height: int, near: float = NEAR,
                     far: float = FAR) -> np.ndarray:
    """GL clip-space matrix (4, 4) for OpenCV camera points and pinhole ``intrinsics``.

    NDC x = 2 u / width - 1 and NDC y = 1 - 2 v / height with (u, v) = K (x/z, y/z) in pixels (pixel
    centres at +0.5), so GL's bottom-up window row j is image row height - 1 - j. Depth maps z in
    [near, far] to NDC [-1, 1]. The mapping flips only y, so counter-clockwise front faces stay
    counter-clockwise.
    """
    return projection_from_intrinsics(intrinsics, width, height, near, far) @ OPENGL_TO_OPENCV  # its own inverse


def _scaled(intrinsics: np.ndarray, factor: float) -> np.ndarray:
    k = intrinsics.copy()
    k[:2] *= factor  # pixel (u + 0.5) / factor: sub-pixel sample centres of the supersampled grid
    return k


def _sun_matrix(direction: np.ndarray, half_extent: float, depth: float = 400.0) -> np.ndarray:
    """Orthographic GL clip-from-world matrix looking down the sun direction at the origin."""
    s = direction / np.linalg.norm(direction)
    helper = np.array([0.0, 0.0, 1.0]) if abs(s[2]) < 0.99 else np.array([1.0, 0.0, 0.0])
    r = np.cross(helper, s)
    r /= np.linalg.norm(r)
    u = np.cross(s, r)
    m = np.eye(4)
    m[0, :3] = r / half_extent
    m[1, :3] = u / half_extent
    m[2, :3] = -s / depth  # closer to the sun: smaller depth
    return m


#: Vertex layout each scene program reads from a batch's buffer (position, normal; ``12x`` skips the normal).
_LAYOUTS = {"color": ("3f 3f", "in_pos", "in_nrm"), "live": ("3f 3f", "in_pos", "in_nrm"),
            "truth": ("3f 12x", "in_pos"), "shadow": ("3f 12x", "in_pos")}


class _Batch:
    """Geometry drawn with one material and one transform: vertex buffer and one VAO per scene program
    (``vaos[name]``; ``shadow`` draws into the shadow map)."""

    def __init__(self, ctx, programs: dict, vertices: np.ndarray, material: int, obj: int, shadow: bool) -> None:
        self.material, self.obj, self.shadow = material, obj, shadow
        self.vbo = ctx.buffer(vertices.tobytes())
        self.vaos = {name: ctx.vertex_array(programs[name], [(self.vbo, *layout)])
                     for name, layout in _LAYOUTS.items() if name in programs}

    def release(self) -> None:
        for item in (*self.vaos.values(), self.vbo):
            item.release()


def _mat(m: np.ndarray) -> bytes:
    """Column-major float32 bytes of a row-major matrix, as GL wants them."""
    return np.ascontiguousarray(np.asarray(m, np.float64).T, dtype=np.float32).tobytes()


class ScenePasses:
    """The GL objects of one scene on a moderngl context current on the calling thread: the programs of
    ``SOURCES``, one vertex batch per material and transform, the sun's shadow map, the uniforms that stay,
    and the passes both renderers draw (the shadow map); a subclass adds its render targets (``_targets``)
    and its frames. ``release_objects`` frees them (the context is the subclass's)."""

    #: (vertex, fragment) sources of the programs; the full-screen ones (``FULLSCREEN_VS``) are the passes that
    #: draw the sky or a whole image
    SOURCES: dict[str, tuple[str, str]] = {"shadow": (glsl.SHADOW_VS, glsl.SHADOW_FS)}

    def __init__(self, scene: Scene, ctx) -> None:
        import moderngl

        self.scene = scene
        self._moderngl = moderngl
        self.ctx = ctx
        self._owned: list = []
        self.batches: list[_Batch] = []
        self._build(ctx, scene.config)

    # -------------------------------------------------------------------------------------- set-up
    def _program(self, vs: str, fs: str):
        prog = self.ctx.program(vertex_shader=vs, fragment_shader=fs)
        self._owned.append(prog)
        return prog

    def _build(self, ctx, cfg) -> None:
        scene = self.scene
        self.programs = {name: self._program(vs, fs) for name, (vs, fs) in self.SOURCES.items()}
        self._names = {k: set(p) for k, p in self.programs.items()}

        # batches: static parts grouped by (material, casts shadow); object parts by (object, material)
        self.batches: list[_Batch] = []
        groups: dict[tuple[int, int, bool], list] = {}
        for part in scene.static_parts:
            groups.setdefault((0, part.material, part.casts_shadow), []).append(part)
        for obj in scene.objects:
            for part in obj.parts:
                groups.setdefault((obj.id, part.material, True), []).append(part)
        # roughly front to back, so that early depth tests skip hidden fragments: objects, props, then
        # the ground and the room (the parts that cast no shadow) that fill the rest of the image
        order = sorted(groups, key=lambda key: (key[0] == 0, not key[2]))
        for oid, mat, shadow in order:
            self.batches.append(_Batch(ctx, self.programs, merge_parts(groups[oid, mat, shadow]), mat, oid, shadow))

        tri = np.array([[-1.0, -1.0], [3.0, -1.0], [-1.0, 3.0]], np.float32)
        self._fs_vbo = ctx.buffer(tri.tobytes())
        self._owned.append(self._fs_vbo)
        self.fullscreen = {k: ctx.vertex_array(p, [(self._fs_vbo, "2f", "in_xy")])
                           for k, p in self.programs.items() if self.SOURCES[k][0] is glsl.FULLSCREEN_VS}
        self._owned += list(self.fullscreen.values())
        self._targets(cfg.width, cfg.height, cfg.supersample)
        self.shadow_map = None
        if cfg.shadows:
            size = cfg.shadow_map_size
            self.shadow_map = self._texture((size, size), depth=True)
            self.shadow_map.compare_func = "<="
            self.shadow_map.filter = (self._moderngl.LINEAR, self._moderngl.LINEAR)
            self.fbo_shadow = self._framebuffer([], self.shadow_map)
            eyes = scene.camera.eye(np.arange(cfg.num_frames + 1) / cfg.fps)
            self._shadow_extent = float(np.clip(np.linalg.norm(eyes[:, :2], axis=1).max() + 10.0, 20.0, 60.0))
            self.sun_matrix = _sun_matrix(scene.lighting.sun_direction, self._shadow_extent)
        self._set_constants()

    def _texture(self, size: tuple[int, int], depth: bool = False):
        """A float32 RGBA (or depth) texture the renderer owns."""
        tex = self.ctx.depth_texture(size) if depth else self.ctx.texture(size, 4, dtype="f4")
        self._owned.append(tex)
        return tex

    def _framebuffer(self, colors: list, depth):
        fbo = self.ctx.framebuffer(color_attachments=colors, depth_attachment=depth)
        self._owned.append(fbo)
        return fbo

    def _targets(self, w: int, h: int, s: int) -> None:
        """Make the render targets of frames (H, W) = (``h``, ``w``), colour supersampled ``s`` x."""

    # -------------------------------------------------------------------------------------- uniforms

    def _set(self, program: str, name: str, value) -> None:
        """Set a uniform if the program exists and its compiled form kept it (unused uniforms are optimised
        away)."""
        if name not in self._names.get(program, ()):
            return
        u = self.programs[program][name]
        if isinstance(value, np.ndarray):
            if value.ndim == 2:
                u.write(_mat(value))
            else:
                u.write(np.ascontiguousarray(value, np.float32).tobytes())
        else:
            u.value = value

    def _set_constants(self) -> None:
        for prog in ("color", "live"):
            self._set_lighting(prog)
        for prog in ("sky_color", "sky_live"):
            self._set_sky(prog)
        self._set("downsample", "u_factor", int(self.scene.config.supersample))
        self._set("downsample", "u_image", 0)

    def _set_lighting(self, prog: str) -> None:
        """The lights, fog and shadow map of the shading (``glsl.SHADING``) of program ``prog``."""
        light = self.scene.lighting
        self._set(prog, "u_sun_dir", light.sun_direction)
        self._set(prog, "u_sun_col", light.sun_color)
        self._set(prog, "u_amb_sky", light.ambient_sky)
        self._set(prog, "u_amb_ground", light.ambient_ground)
        lights = light.point_lights[:4]
        self._set(prog, "u_num_lights", len(lights))
        pos, col = np.zeros((4, 3)), np.zeros((4, 3))
        for i, pl in enumerate(lights):
            pos[i], col[i] = pl.position, pl.color
        self._set(prog, "u_light_pos", pos.reshape(-1))
        self._set(prog, "u_light_col", col.reshape(-1))
        self._set(prog, "u_fog", float(light.fog_density))
        self._set(prog, "u_fog_col", light.fog_color)
        self._set(prog, "u_shadows", int(self.shadow_map is not None))
        if self.shadow_map is not None:
            bias = np.array([[0.5, 0, 0, 0.5], [0, 0.5, 0, 0.5], [0, 0, 0.5, 0.5], [0, 0, 0, 1.0]])
            self._set(prog, "u_shadow_mat", bias @ self.sun_matrix)
            self._set(prog, "u_shadow_texel", 2.0 * self._shadow_extent / self.scene.config.shadow_map_size)
            self._set(prog, "u_shadow_map", 0)

    def _set_sky(self, prog: str) -> None:
        """The sky's colours, clouds and sun (``glsl.SKY_FUNCTION``) of program ``prog``."""
        light, sky = self.scene.lighting, self.scene.sky
        self._set(prog, "u_sun_dir", light.sun_direction)
        self._set(prog, "u_sun_col", light.sun_color)
        for name, value in (("u_zenith", sky.zenith), ("u_horizon", sky.horizon), ("u_below", sky.below),
                            ("u_cloud_col", sky.cloud_color)):
            self._set(prog, name, np.asarray(value, np.float64))
        self._set(prog, "u_coverage", float(sky.cloud_coverage))
        self._set(prog, "u_cloud_scale", float(sky.cloud_scale))
        self._set(prog, "u_sun_disk", float(sky.sun_disk))
        self._set(prog, "u_sun_cos", float(math.cos(sky.sun_size)))
        self._set(prog, "u_seed", int(sky.seed) & 0xFFFFFFFF)

    def _set_material(self, index: int, prog: str = "color") -> None:
        m = self.scene.materials[index]
        self._set(prog, "u_pattern", PATTERNS.index(m.pattern))
        for i in range(3):
            self._set(prog, f"u_col{i}", m.colors[i])
        self._set(prog, "u_scale", float(m.scale))
        self._set(prog, "u_detail", float(m.detail))
        self._set(prog, "u_macro", float(m.macro))
        self._set(prog, "u_specular", float(m.specular))
        self._set(prog, "u_shininess", float(m.shininess))
        self._set(prog, "u_tex_rot", m.rotation)
        c, s = math.cos(m.angle), math.sin(m.angle)
        self._set(prog, "u_tex_rot2", np.array([[c, -s], [s, c]]))
        self._set(prog, "u_tex_offset", m.offset)
        self._set(prog, "u_seed", int(m.seed) & 0xFFFFFFFF)

    # -------------------------------------------------------------------------------------- passes
    def _check_index(self, index: int) -> None:
        n = self.scene.config.num_frames
        if not 0 <= index < n:
            raise InputError(f"must be in [0, {n}), got {index}", field="index")

    def _object_transforms(self, index: int) -> np.ndarray:
        """(objects + 1, 4, 4) world_from_object of frame ``index`` (any integer: the paths are defined for all
        times), slot 0 the static world's identity (``_slots``)."""
        m = np.eye(4)[None].repeat(len(self.scene.objects) + 1, 0)
        if self.scene.objects:
            m[1:] = self.scene.object_transforms(index)
        return m

    def _slots(self) -> dict[int, int]:
        """Object id -> its row in ``_object_transforms`` (0: the static world)."""
        return {0: 0, **{o.id: i + 1 for i, o in enumerate(self.scene.objects)}}

    def _shadow_pass(self, transforms: np.ndarray) -> None:
        """The sun's shadow map of the shadow-casting batches at ``transforms`` (``_object_transforms``)."""
        if self.shadow_map is None:
            return
        mgl, ctx, slot = self._moderngl, self.ctx, self._slots()
        self.fbo_shadow.use()
        self.fbo_shadow.clear(depth=1.0)
        ctx.enable(mgl.DEPTH_TEST)
        ctx.disable(mgl.CULL_FACE)
        ctx.depth_func = "<"
        ctx.polygon_offset = (2.0, 4.0)
        for b in self.batches:
            if b.shadow:
                self._set("shadow", "u_light_from_obj", self.sun_matrix @ transforms[slot[b.obj]])
                b.vaos["shadow"].render(mgl.TRIANGLES)
        ctx.polygon_offset = (0.0, 0.0)

    # -------------------------------------------------------------------------------------- clean-up
    def release_objects(self) -> None:
        """Free the scene's GL objects (safe to call twice; on the thread where the context is current)."""
        for b in self.batches:
            b.release()
        self.batches = []
        for item in reversed(self._owned):
            item.release()
        self._owned = []


class SceneRenderer(ScenePasses):
    """Renders frames of one scene with colour and exact ground truth (module docstring) on a GL context of its
    own; release it (or use ``with``) when done. ``engine.scenegen.live.LiveSceneRenderer`` is the live mode:
    colour, depth and motion vectors in one pass, left on the GPU.

    >>> with SceneRenderer(make_scene(SceneConfig(width=64, height=48, num_frames=2))) as r:  # doctest: +SKIP
    ...     frame = r.render_frame(0)
    """

    SOURCES = {"color": (glsl.GEOMETRY_VS, glsl.GEOMETRY_FS), "truth": (glsl.TRUTH_VS, glsl.TRUTH_FS),
               "shadow": (glsl.SHADOW_VS, glsl.SHADOW_FS), "sky_color": (glsl.FULLSCREEN_VS, glsl.SKY_COLOR_FS),
               "sky_truth": (glsl.FULLSCREEN_VS, glsl.SKY_TRUTH_FS),
               "downsample": (glsl.FULLSCREEN_VS, glsl.DOWNSAMPLE_FS)}

    def __init__(self, scene: Scene) -> None:
        import moderngl

        self.ctx = moderngl.create_standalone_context(backend="egl")
        try:
            super().__init__(scene, self.ctx)
        except Exception:
            self.release()
            raise

    def _targets(self, w: int, h: int, s: int) -> None:
        """Colour at ``s`` x the size and its downsampled copy; the ground truth's two targets."""
        self.color_ss = self._texture((w * s, h * s))
        self.fbo_ss = self._framebuffer([self.color_ss], self._texture((w * s, h * s), depth=True))
        self.color = self._texture((w, h))
        self.fbo_color = self._framebuffer([self.color], None)
        self.geometry, self.flow = self._texture((w, h)), self._texture((w, h))
        self.fbo_truth = self._framebuffer([self.geometry, self.flow], self._texture((w, h), depth=True))

    # -------------------------------------------------------------------------------------- frames
    def render_frame(self, index: int, camera: int = 0) -> Frame:
        """Render frame ``index`` (0 <= index < num_frames) with colour and every ground-truth channel;
        ``camera`` (a rig's camera number) only keys the colour noise of ``config.render_noise``, so that
        each camera of a rig gets its own."""
        mgl, ctx, scene, cfg = self._moderngl, self.ctx, self.scene, self.scene.config
        self._check_index(index)
        w, h, s = cfg.width, cfg.height, cfg.supersample
        cam0, cam1 = scene.camera_at(index), scene.camera_at(index + 1)
        v0, v1 = cam0.world_to_camera, cam1.world_to_camera
        m0, m1 = self._object_transforms(index), self._object_transforms(index + 1)
        moves = np.concatenate([[False], scene.object_moves(index)]) if scene.objects else np.array([False])
        slot = self._slots()

        # 1. sun shadow map
        self._shadow_pass(m0)

        # 2. colour, supersampled
        ctx.enable(mgl.DEPTH_TEST | mgl.CULL_FACE)
        self.fbo_ss.use()
        self.fbo_ss.clear(0.0, 0.0, 0.0, 1.0, depth=1.0)
        ctx.depth_func = "<"
        self._set("color", "u_proj", clip_from_camera(_scaled(cam0.intrinsics, s), w * s, h * s))
        self._set("color", "u_eye", cam0.position)
        if self.shadow_map is not None:
            self.shadow_map.use(location=0)
        for b in self.batches:
            self._set_material(b.material)
            self._set("color", "u_model", m0[slot[b.obj]])
            self._set("color", "u_cam_from_obj", v0 @ m0[slot[b.obj]])
            b.vaos["color"].render(mgl.TRIANGLES)
        ctx.depth_func = "<="
        if self.scene.sky.visible:
            k_inv = np.linalg.inv(_scaled(cam0.intrinsics, s))
            self._set("sky_color", "u_world_from_pixel", v0[:3, :3].T @ k_inv)
            self._set("sky_color", "u_height", float(h * s))
            self.fullscreen["sky_color"].render(mgl.TRIANGLES)
        ctx.disable(mgl.DEPTH_TEST)
        self.fbo_color.use()
        self.color_ss.use(location=0)
        self.fullscreen["downsample"].render(mgl.TRIANGLES)

        # 3. ground truth at native resolution
        ctx.enable(mgl.DEPTH_TEST | mgl.CULL_FACE)
        ctx.depth_func = "<"
        self.fbo_truth.use()
        self.fbo_truth.clear(0.0, 0.0, 0.0, 0.0, depth=1.0)
        k0, k1 = cam0.intrinsics, cam1.intrinsics
        kvec = lambda k: (float(k[0, 0]), float(k[1, 1]), float(k[0, 2]), float(k[1, 2]))  # noqa: E731
        for prog in ("truth", "sky_truth"):
            self._set(prog, "u_k", kvec(k0))
            self._set(prog, "u_k1", kvec(k1))
        self._set("truth", "u_proj", clip_from_camera(k0, w, h))
        for b in self.batches:
            i = slot[b.obj]
            self._set("truth", "u_cam_from_obj", v0 @ m0[i])
            self._set("truth", "u_cam1_from_obj1", v1 @ m1[i])
            self._set("truth", "u_cam_from_obj1", v0 @ m1[i])
            self._set("truth", "u_id", float(b.obj))
            self._set("truth", "u_moving", float(moves[i]))
            b.vaos["truth"].render(mgl.TRIANGLES)
        ctx.depth_func = "<="
        self._set("sky_truth", "u_k_inv", np.linalg.inv(k0))
        self._set("sky_truth", "u_rot", v1[:3, :3] @ v0[:3, :3].T)
        self._set("sky_truth", "u_height", float(h))
        self.fullscreen["sky_truth"].render(mgl.TRIANGLES)
        ctx.depth_func = "<"

        def read(fbo, attachment):
            data = np.frombuffer(fbo.read(attachment=attachment, components=4, dtype="f4"), np.float32)
            return data.reshape(h, w, 4)[::-1]

        color = np.ascontiguousarray(read(self.fbo_color, 0)[..., :3])
        if cfg.render_noise > 0:
            rng = np.random.default_rng([cfg.seed, index, NOISE_STREAM, camera])
            color = monte_carlo_noise(color, cfg.render_noise, rng)
        geo = read(self.fbo_truth, 0)
        flow = read(self.fbo_truth, 1)
        depth = np.where(geo[..., 3] > 0.5, geo[..., 0], np.inf).astype(np.float32)
        object_id = np.rint(geo[..., 1]).astype(np.int32)
        camera = Camera(cam0.intrinsics, cam0.world_to_camera)
        return Frame(index=index, time=scene.time(index), color=color, depth=depth, camera=camera,
                     object_id=object_id, moving=geo[..., 2] > 0.5,
                     flow=np.ascontiguousarray(flow[..., :2]), object_flow=np.ascontiguousarray(flow[..., 2:]),
                     motion_vectors=self.motion_vectors(index, depth, object_id, camera))

    def motion_vectors(self, index: int, depth: np.ndarray, object_id: np.ndarray, camera: Camera,
                       previous: Optional[int] = None) -> np.ndarray:
        """What an engine writes as motion vectors: exact current -> previous vectors of frame ``index``
        (rigid objects + camera, from the truth pass's depth and ids at pixel centres) to frame ``previous``
        (default ``index - 1``: a renderer drawing every k-th frame points to ``index - k``). Frame 0 points to
        frame -1 of the paths (defined for all times)."""
        scene = self.scene
        previous = index - 1 if previous is None else int(previous)
        motions = {}
        if scene.objects:
            now, before = scene.object_transforms(index), scene.object_transforms(previous)
            motions = {o.id: before[i] @ rigid_inverse(now[i]) for i, o in enumerate(scene.objects)}
        return rigid_motion_vectors(depth, camera, scene.camera_at(previous), object_id, motions)

    # -------------------------------------------------------------------------------------- clean-up
    def release(self) -> None:
        """Free every GL object and the context (safe to call twice)."""
        if getattr(self, "_owned", None) is not None:
            self.release_objects()
        if self.ctx is not None:
            self.ctx.release()
            self.ctx = None

    def __enter__(self) -> "SceneRenderer":
        return self

    def __exit__(self, *exc) -> None:
        self.release()


#: Third entry of the colour noise generator's seed ``(config.seed, frame index, NOISE_STREAM, camera)``.
NOISE_STREAM = 0x4E4F


def monte_carlo_noise(color: np.ndarray, sigma: float, rng: np.random.Generator) -> np.ndarray:
    """(H, W, 3) float32 linear RGB with the noise a path tracer leaves at few samples per pixel.

    Multiplicative and unbiased: each pixel is scaled by a shared factor (luminance noise, 80 % of the
    variance) times a per-channel factor (colour noise), both gamma-distributed with mean 1, so values stay
    non-negative, black stays black, and the product has mean 1 and standard deviation ``sigma`` with the
    long bright tail (fireflies) of Monte Carlo estimates.
    """
    if sigma <= 0:
        return color
    # (1 + a) (1 + a / 4) = 1 + sigma^2: variances a (shared) and a / 4 (per channel) of the two factors
    a = 2.0 * (math.sqrt(25.0 / 16.0 + sigma * sigma) - 1.25)
    shared = rng.gamma(1.0 / a, a, size=color.shape[:2] + (1,))
    channel = rng.gamma(4.0 / a, a / 4.0, size=color.shape)
    return (color * (shared * channel)).astype(np.float32)


def render_scene(scene: Scene, *, progress: bool = False) -> Iterator[Frame]:
    """Yield every frame of ``scene`` in order (one GL context, released when the iterator ends or closes).

    Frames follow ``engine/core/frames.py``: linear RGB colour, planar depth with +inf sky, OpenCV cameras,
    object_id (0 = background), moving, flow and object_flow in pixels to the next frame. The last
    frame's flow uses the paths one step further (they are defined for all times).
    """

    renderer = SceneRenderer(scene)
    try:
        for index in tqdm(range(scene.num_frames), desc="render", unit="frame", disable=not progress):
            yield renderer.render_frame(index)
    finally:
        renderer.release()
