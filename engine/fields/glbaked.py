"""Real-time rendering of a baked static field (``engine.fields.baked``): OpenGL compute shaders, one ray per pixel.

``GlBakedRenderer(baked, width, height).render(K, world_to_camera)`` renders what
:func:`engine.fields.baked.render_baked` (the numpy reference, its test oracle) renders, with the ray setup,
sampling, empty-space skipping (the occupied bricks take the occupancy grid's place), early ray termination and
compositing of ``engine.fields.gl`` (the shared template: ``march_code``, ``color_head``, ``finish_shader``).
Per kept sample the shader reads the sample's brick from the brick index (a storage buffer) and interpolates its
vertices' raw density and features trilinearly: no MLP per sample. The features are composited with the weights
and the colour MLP runs once per pixel (deferred shading, as the field was trained).

The bricks live in one texture (a one-layer 2D array, float16 ``RGBA16F``, exact for float16 densities and for
the uint8 feature codes, which the shader scales by 1/255 after compositing), each brick a compact block so that
a lookup touches few cache lines (a layout with a layer per z slice and channel group was 2.3x slower on
llvmpipe, nearly all of it cache misses): brick k is the block of V rows (y) by V^2 G texels at column
``k div P`` and row ``k mod P`` of blocks (V = brick + 1 vertices, G channel groups, P bricks a column); inside
it, vertex (x, y, z) of group q is at texel ``((q V + z) V + x, y)``. Channels are the features then, in the
last lane of the last group, the raw density. ``filtering="hardware"`` interpolates the two z slices around the
sample with the texture unit's bilinear filter and the shader mixes them (two fetches a group);
``filtering="exact"`` reads the eight vertices with ``texelFetch`` and interpolates in float32 as the reference.

>>> with GlBakedRenderer(load_baked("runs/lego/export"), 960, 540) as r:      # doctest: +SKIP
...     out = r.render(K, world_to_camera)
"""
from __future__ import annotations

import math
from pathlib import Path
from typing import Optional, Sequence, Union

import numpy as np

from engine.core.errors import InputError
from engine.fields.baked import (BAKED_TRANSMITTANCE_EPS, BakedAssets, BakedDynamicAssets, load_baked,
                                 load_baked_dynamic, time_keys)
from engine.fields.dynamic import normalize_time, time_encoding_np
from engine.fields.gl import (COLOR_EPS, GlFieldRenderer, ShaderParams, _direction_encoding,
                              check_options, color_head, finish_shader, set_uniforms)

__all__ = ["GlBakedRenderer", "GlBakedDynamicRenderer", "atlas_layout", "atlas_layers", "channel_groups",
           "generate_baked_shader", "motion_layers", "motion_code", "FLOW_BLEND_SHADER"]

#: Largest width / height of the atlas texture (OpenGL guarantees 16384 on 4.5 implementations).
MAX_ATLAS_SIDE = 16384


def atlas_layout(count: int, vertices: int, groups: int) -> tuple[int, int]:
    """(bricks per column, columns) of the atlas of ``count`` bricks of ``vertices`` texels a side and ``groups``
    channel groups: a brick is a block of ``vertices`` rows by ``vertices^2 groups`` texels, stacked in columns
    at most ``MAX_ATLAS_SIDE`` texels tall."""
    per_column = max(1, min(max(count, 1), MAX_ATLAS_SIDE // vertices))
    columns = -(-max(count, 1) // per_column)
    if columns * vertices * vertices * groups > MAX_ATLAS_SIDE:
        raise InputError(f"{count} bricks of {vertices}^3 vertices do not fit a {MAX_ATLAS_SIDE}^2 atlas",
                         field="grid")
    return per_column, columns


def channel_groups(feature_dim: int) -> int:
    """RGBA texel groups a brick vertex takes: ``feature_dim`` features, then the raw density in the last lane.
    Each group costs the shader its own filtered fetches per sample, so ``feature_dim = 4 G - 1`` wastes none."""
    return -(-(feature_dim + 1) // 4)


def atlas_layers(baked: BakedAssets) -> np.ndarray:
    """(1, per_column V, columns V^2 G, 4) float16: the atlas texture (layout in the module docstring)."""
    n, v = baked.density.shape[0], baked.density.shape[1]
    groups = channel_groups(baked.feature_dim)
    per_column, columns = atlas_layout(n, v, groups)
    channels = np.zeros((columns * per_column, v, v, v, 4 * groups), np.float16)
    channels[:n, ..., :baked.feature_dim] = baked.features
    channels[:n, ..., -1] = baked.density
    # [column, row, ix, iy, iz, q, lane] -> [row, iy, column, q, iz, ix, lane]
    grid = channels.reshape(columns, per_column, v, v, v, groups, 4).transpose(1, 3, 0, 5, 4, 2, 6)
    return np.ascontiguousarray(grid.reshape(1, per_column * v, columns * v * v * groups, 4))


def generate_baked_shader(baked: BakedAssets, *, filtering: str, params_kind: str, count_evaluations: bool = False,
                          samplers: Sequence[str] = (), before: Sequence[str] = (), extra_encoding: Sequence[str] = (),
                          empty_bricks: bool = False) -> tuple[str, np.ndarray, str]:
    """GLSL source, packed parameters and where they live (as ``engine.fields.gl.finish_shader``) of a baked field.

    Hooks for a baked dynamic field (as ``engine.fields.gl.generate_shader``'s): ``samplers`` further
    declarations, ``before`` code run per evaluated sample before the brick lookup (it may move the contracted
    point ``c``), ``extra_encoding`` scalar GLSL expressions appended to the direction encoding (further per-pixel
    inputs of the colour MLP), ``empty_bricks``: a sample may land in an empty brick (a moved point: the march's
    occupancy is not the bricks'), which then gives density and features 0 (``engine.fields.baked.lookup_bricks``)."""
    grid, spec = baked.grid, baked.manifest["field"]
    b, s, r = int(grid["bricks"]), int(grid["brick"]), int(grid["resolution"])
    v = s + 1
    g = baked.feature_dim
    groups = channel_groups(baked.feature_dim)
    per_column, columns = atlas_layout(baked.density.shape[0], v, groups)
    params = ShaderParams()
    lines = list(before) + [
        f"ivec3 bk_cell = clamp(ivec3(floor((c + 1.0) * {0.5 * b!r})), ivec3(0), ivec3({b - 1}));",
        f"int bk = brick_of[(bk_cell.x * {b} + bk_cell.y) * {b} + bk_cell.z];",
        *(["bool bk_empty = bk < 0;", "bk = max(bk, 0);"] if empty_bricks else []),
        f"vec3 bk_local = clamp((c + 1.0) * {0.5 * r!r} - vec3(bk_cell * {s}), vec3(0.0), vec3({float(s)!r}));",
        f"vec3 bk_i0 = min(floor(bk_local), vec3({float(s - 1)!r}));",
        "vec3 fr = bk_local - bk_i0;",
        f"int bk_column = bk / {per_column};",
        f"ivec2 bk_tile = ivec2(bk_column * {v * v * groups} + int(bk_i0.z) * {v}, "
        f"(bk - bk_column * {per_column}) * {v});",
    ]
    if filtering == "exact":
        lines.append("ivec2 bk_xy = bk_tile + ivec2(bk_i0.xy);")
    else:
        lines.append("vec2 bk_at = vec2(bk_tile) + bk_local.xy + 0.5;  // texel centres at i + 0.5")
        lines.append(f"vec2 bk_inv = vec2({1.0 / (columns * v * v * groups)!r}, {1.0 / (per_column * v)!r});")
    for q in range(groups):
        layers = []
        for dz in (0, 1):
            shift = (q * v + dz) * v  # texels from the brick's z = i0 slice of group 0 to slice i0 + dz of group q
            if filtering == "exact":
                f = [f"texelFetch(atlas, ivec3(bk_xy + ivec2({shift + dx}, {dy}), 0), 0)" for dx, dy in
                     ((0, 0), (1, 0), (0, 1), (1, 1))]
                layers.append(f"({f[0]} * (1.0 - fr.x) + {f[1]} * fr.x) * (1.0 - fr.y) + "
                              f"({f[2]} * (1.0 - fr.x) + {f[3]} * fr.x) * fr.y")
            else:
                layers.append(f"texture(atlas, vec3((bk_at + vec2({float(shift)!r}, 0.0)) * bk_inv, 0.0))")
        lines.append(f"vec4 v{q}_0 = {layers[0]};")
        lines.append(f"vec4 v{q}_1 = {layers[1]};")
        lines.append(f"vec4 v{q} = v{q}_0 * (1.0 - fr.z) + v{q}_1 * fr.z;")
    if empty_bricks:  # no density (exp of the lowest raw value), no features
        lines.append("if (bk_empty) {")
        lines += [f"    v{q} = vec4(0.0);" for q in range(groups)]
        lines += [f"    v{groups - 1}.w = -1e30;", "}"]
    features = "\n".join("            " + line for line in lines)
    enc = _direction_encoding(spec["direction_encoding"], int(spec["direction_degree"])) + list(extra_encoding)
    per_pixel, color_net = color_head(params, enc, baked.color_layers, g, 4 * groups)
    code, residual = color_net([f"ha{q}" for q in range(groups)], "    ", "tanh")
    scale = "\n".join(f"    ha{q} *= {1.0 / 255.0!r};  // feature codes -> [0, 1]" for q in range(groups))
    scale += f"\n    ha{groups - 1}.w = 0.0;  // the density lane: no feature"
    values = {
        "samplers": "\n".join(["uniform sampler2DArray atlas;",
                                "layout(std430, binding = 5) readonly buffer BrickBuf { int brick_of[]; };",
                                *samplers]),
        "per_pixel": "\n".join(per_pixel),
        "accum_decl": "\n".join(f"    vec4 ha{q} = vec4(0.0);" for q in range(groups)),
        "features": features, "density": f"            float raw = v{groups - 1}.w;", "density_bias": 0.0,
        "max_log": float(spec["max_log_density"]), "latent": "",
        "color_sample": "\n".join(f"                ha{q} += w * v{q};" for q in range(groups)),
        "color_final": scale + "\n" + "\n".join(code) + f"\n    col = ha0.xyz + acc * {residual};",
    }
    return finish_shader(baked, params, params_kind, values, count_evaluations)


class GlBakedRenderer(GlFieldRenderer):
    """One headless GL context with the compute shader, atlas texture and buffers of one baked field; ``render``,
    ``render_to_buffer``, ``release`` and the options are :class:`engine.fields.gl.GlFieldRenderer`'s (without
    ``quantized`` and ``color_mode``: a baked field is quantised and shaded once per pixel by construction), but
    ``transmittance_eps`` defaults to ``engine.fields.baked.BAKED_TRANSMITTANCE_EPS`` (1/255: what the rest of a
    ray can add to a pixel's opacity and features is less than one 8-bit step).

    Raises:
        InputError: bad size or option, an atlas that does not fit a texture.
    """

    #: the assets this renderer takes, and their loader (a folder or manifest given instead)
    assets_type, _loader = BakedAssets, staticmethod(load_baked)

    def __init__(self, baked: Union[BakedAssets, str, Path], width: int, height: int, *, filtering: str = "hardware",
                 transmittance_eps: float = BAKED_TRANSMITTANCE_EPS, color_eps: float = COLOR_EPS,
                 weights: str = "inline", tiles_per_invocation: Optional[int] = None, count_evaluations: bool = False,
                 context=None) -> None:
        if not isinstance(baked, self.assets_type):
            baked = self._loader(baked)
        check_options(width, height, filtering=filtering, color_mode="per-sample", weights=weights,
                      transmittance_eps=transmittance_eps, color_eps=color_eps)
        self._configure(baked, width, height, quantized=True, filtering=filtering, color_mode="deferred",
                        transmittance_eps=transmittance_eps, color_eps=color_eps,
                        tiles_per_invocation=tiles_per_invocation, count_evaluations=count_evaluations)
        self.source, packed, self.params_kind = generate_baked_shader(
            baked, filtering=filtering, params_kind="const" if weights == "inline" else "ubo",
            count_evaluations=self.count_evaluations, **self._shader_hooks(baked, filtering))
        self._setup(packed, [], "f2", context)

    def _shader_hooks(self, baked: BakedAssets, filtering: str) -> dict:
        """``generate_baked_shader``'s hooks (none for a static field)."""
        return {}

    def _build(self, packed: np.ndarray, textures: list, dtype: str) -> None:
        super()._build(packed, textures, dtype)
        layers = atlas_layers(self.assets)
        self._add_texture("atlas", self.ctx.texture_array(layers.shape[2::-1], 4, layers.tobytes(), dtype="f2"))
        self._bricks = self.ctx.buffer(np.ascontiguousarray(self.assets.brick_index, np.int32).tobytes())
        self._buffers.append(self._bricks)

    def _bind(self) -> None:
        super()._bind()
        self._bricks.bind_to_storage_buffer(5)


# ----------------------------------------------------------------------------------------------------
# A baked DeRF field (engine.fields.baked.BakedDynamicAssets): the flow keys in front of the brick lookup


def motion_layers(baked: BakedDynamicAssets) -> np.ndarray:
    """(K M, M, M, 4) float16: the flow keys as one 2D array texture, layer ``k M + iz`` holding key k's z slice iz,
    texel (ix, iy) its flow in rgb."""
    keys, m = baked.motion.shape[0], baked.motion.shape[1]
    layers = np.zeros((keys, m, m, m, 4), np.float16)
    layers[..., :3] = baked.motion.transpose(0, 3, 2, 1, 4)  # [key, ix, iy, iz] -> [key, iz, iy, ix]
    return np.ascontiguousarray(layers.reshape(keys * m, m, m, 4))


#: The pass run once a frame (when the time changes): the flow grid at the frame's time, the two keys around it
#: blended linearly in float32 (``precise``: no fused multiply-add, the oracle's rounding), written to an M^3
#: RGBA32F 3D texture that the march then reads with one filtered fetch a sample (four fetches of the two keys'
#: z slices cost llvmpipe 14 ms more a 512x512 lego frame). M is defined at compile time.
FLOW_BLEND_SHADER = """#version 430
layout(local_size_x = 4, local_size_y = 4, local_size_z = 4) in;
uniform sampler2DArray keys;  // layer k M + iz: key k's z slice iz (motion_layers)
uniform int key0;
uniform float key_w;
layout(rgba32f, binding = 0) writeonly uniform image3D flow_out;

void main() {
    ivec3 v = ivec3(gl_GlobalInvocationID);
    if (any(greaterThanEqual(v, ivec3(M)))) return;
    vec3 a = texelFetch(keys, ivec3(v.xy, key0 * M + v.z), 0).xyz;
    vec3 b = texelFetch(keys, ivec3(v.xy, (key0 + 1) * M + v.z), 0).xyz;
    precise vec3 flow = a * (1.0 - key_w) + b * key_w;
    imageStore(flow_out, v, vec4(flow, 0.0));
}
"""


def motion_code(baked: BakedDynamicAssets, filtering: str) -> list[str]:
    """GLSL, per evaluated sample: ``c = clamp(c + flow, -1, 1)``, the flow the trilinear lookup of the frame's flow
    grid (``sampler3D flow``, :data:`FLOW_BLEND_SHADER`'s output; :func:`engine.fields.baked.baked_flow`)."""
    m = baked.motion.shape[1]
    lines = [f"vec3 mo_local = clamp((c + 1.0) * {0.5 * (m - 1)!r}, vec3(0.0), vec3({float(m - 1)!r}));"]
    if filtering == "exact":  # the oracle's order: bilinear in x, y on the two z slices, then linear in z
        lines += [f"vec3 mo_i0 = min(floor(mo_local), vec3({float(m - 2)!r}));",
                  "vec3 mo_f = mo_local - mo_i0;",
                  "ivec3 mo_i = ivec3(mo_i0);"]
        slices = []
        for dz in (0, 1):
            f = [f"texelFetch(flow, mo_i + ivec3({dx}, {dy}, {dz}), 0).xyz"
                 for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1))]
            slices.append(f"(({f[0]} * (1.0 - mo_f.x) + {f[1]} * mo_f.x) * (1.0 - mo_f.y) + "
                          f"({f[2]} * (1.0 - mo_f.x) + {f[3]} * mo_f.x) * mo_f.y)")
        lines.append(f"vec3 mo = {slices[0]} * (1.0 - mo_f.z) + {slices[1]} * mo_f.z;")
    else:
        lines.append(f"vec3 mo = texture(flow, (mo_local + 0.5) * {1.0 / m!r}).xyz;  // texel centres at i + 0.5")
    return lines + ["c = clamp(c + mo, -1.0, 1.0);"]


class GlBakedDynamicRenderer(GlBakedRenderer):
    """:class:`GlBakedRenderer` of a baked DeRF field: per evaluated sample the frame's flow grid moves the sample
    to its canonical point before the brick lookup, the time-agnostic occupancy grid skips samples at their own
    points, and the colour MLP reads the encoded time with the view direction. ``render(K, world_to_camera, time)``
    renders what :func:`engine.fields.baked.render_baked_dynamic` (its test oracle) renders. The flow keys stay
    on the GPU; a small pass blends the two around the frame's time into the flow grid when the time changes.

    Raises:
        InputError: bad size or option, an atlas that does not fit a texture; ``render``: a time outside the
            trained range.
    """

    assets_type, _loader = BakedDynamicAssets, staticmethod(load_baked_dynamic)

    def _shader_hooks(self, baked: BakedDynamicAssets, filtering: str) -> dict:
        self._frequencies = int(baked.manifest["field"]["time_frequencies"])
        encoded = 2 * self._frequencies + 1
        hooks = {"samplers": ["uniform sampler3D flow;", f"uniform float time_enc[{encoded}];"],
                 "before": motion_code(baked, filtering),
                 "extra_encoding": [f"time_enc[{i}]" for i in range(encoded)], "empty_bricks": True}
        return hooks

    def _build(self, packed: np.ndarray, textures: list, dtype: str) -> None:
        super()._build(packed, textures, dtype)
        m = self.assets.motion.shape[1]
        layers = motion_layers(self.assets)
        self._keys = self.ctx.texture_array((m, m, layers.shape[0]), 4, layers.tobytes(), dtype="f2")
        self._flow = self.ctx.texture3d((m, m, m), 4, dtype="f4")
        self._add_texture("flow", self._flow)
        self._blend = self.ctx.compute_shader(FLOW_BLEND_SHADER.replace("\n", f"\n#define M {m}\n", 1))
        self._buffers += [self._keys, self._blend]  # freed with the rest (``release``)
        self._blended = None

    def _blend_flow(self, key0: int, weight: float) -> None:
        """The flow grid at the time keys' blend (with the context current); skipped when it holds it already."""
        if self._blended == (key0, weight):
            return
        m = self.assets.motion.shape[1]
        set_uniforms(self._blend, {"keys": 0, "key0": key0, "key_w": weight})
        self._keys.use(location=0)
        self._flow.bind_to_image(0, read=False, write=True)
        groups = -(-m // 4)
        self._blend.run(groups, groups, groups)
        self.ctx.memory_barrier()
        self._blended = (key0, weight)

    def render(self, intrinsics, world_to_camera, time: float) -> dict[str, np.ndarray]:
        """Render the field at ``time`` (the data's units); the rest as :meth:`GlFieldRenderer.render`."""
        tau = normalize_time(time, self.assets.time_range)
        key0, weight = time_keys(tau, self.assets.motion.shape[0])
        enc = time_encoding_np(np.array([tau], np.float32), self._frequencies)[0]

        def set_time() -> None:
            self._blend_flow(key0, float(weight))
            try:
                self.program["time_enc"].write(np.ascontiguousarray(enc, np.float32).tobytes())
            except KeyError:  # optimised out: the colour MLP ignores time
                pass
        self._run(set_time)
        return super().render(intrinsics, world_to_camera)
