"""Real-time rendering of an exported dynamic radiance field at a given time: the static field's compute shader
(``engine/fields/gl.py``) with the motion field in front of the canonical lookup.

``GlDynamicRenderer(assets, width, height).render(K, world_to_camera, time)`` renders what
:func:`engine.fields.dynamic.render_dynamic_field` (the numpy reference, its test oracle) renders: colour (H, W, 3)
linear RGB, planar depth (H, W) with ``+inf`` where the opacity is below ``OPACITY_EPS``, and opacity, for
the assets ``interleave export dynamic`` writes (``docs/field-assets.md``, "Dynamic fields"). Headless
moderngl (EGL; Mesa llvmpipe is enough), no torch.

The shader is :func:`engine.fields.gl.generate_shader`'s, with the same ray setup, sampling, occupancy skipping
(the time-agnostic grid of the export), chunked loop over kept samples, early ray termination and colour
skip, and the same error bounds (``transmittance_eps``, ``num_samples * color_eps``). Its two hooks add:

- **DeRF** (``kind="derf"``): per evaluated sample, before the canonical tri-plane lookup, the motion
  field's hex-planes at (c, tau): per scale and channel group the product of the xy, xz, yz planes (one
  ``RGBA32F`` array texture per scale, as the canonical planes) times the product of the xt, yt, zt planes
  (one array texture per scale of size R x Rt: the spatial coordinate along the width, tau along the height),
  the flow MLP (literals, straight-line vec4 ``dot``s), ``flow = max_flow * tanh(.)`` and
  ``c = clamp(c + flow, -1, 1)``; the canonical field then runs unchanged on c (a canonical field with time
  planes, ``canonical_temporal``, multiplies their xt, yt, zt product at (c, tau) into its features, as
  K-Planes below). The colour MLP's time input [tau, sin(2^k tau), cos(2^k tau)] is per frame: computed on
  the CPU (``time_encoding_np``) and applied once per pixel with the view-direction columns.
- **DeRF with motion slots** (``field.motion``): instead of the hex-planes and flow MLP, the logit planes (one
  ``RGBA32F`` array texture, K + 1 channels in groups of four, summed over xy, xz, yz), the still bias and a
  softmax (literals), the key table as a (3 K) x Rt texture read by ``texelFetch`` at the two keys around tau,
  ``flow = max_flow * tanh(A c + T)`` of the weighted sums.
- **K-Planes** (``kind="kplanes"``): the ``spatial`` planes are the tri-planes; after their lookup each
  feature group is multiplied by the xt, yt, zt product at (c, tau).

A field trained with deferred shading (``field.shading``) takes the static shader's deferred path: its features
are composited and the colour MLP runs once per pixel, the encoded time with the view direction.

Plane lookups are ``grid_sample(align_corners=True, padding_mode="border")`` as in the static shader:
``filtering="hardware"`` (the sampler's bilinear filter at ``(x + 0.5) / W, (y + 0.5) / H``) or ``"exact"``
(four ``texelFetch`` + float32 lerp). Float32 planes only (no uint8 path for dynamic assets yet).

>>> with GlDynamicRenderer(load_dynamic_field("runs/dyn/export"), 960, 540) as r:     # doctest: +SKIP
...     frames = [r.render(K, world_to_camera, t) for t in (0.2, 0.4, 0.6)]

``python -m tools.bench_fields dynamic EXPORT_DIR --sizes 160x90,512x512`` times this renderer against the
numpy and onnxruntime paths of :mod:`engine.fields.dynamic` and (when torch is importable) the torch renderer.
"""
from __future__ import annotations

import time as time_module
from pathlib import Path
from typing import Optional, Union

import numpy as np

from engine.core.errors import InputError
from engine.core.frames import MAX_MOTION_DIAGONALS, validate_intrinsics, validate_pose
from engine.fields.dynamic import (JACOBIAN_STEP, MAX_NEWTON_STEP, MIN_JACOBIAN_DET, MOTION_ITERATIONS,
                                   MOTION_TOLERANCE, NEWTON_SETTLED, DynamicAssets, check_coherence, load_dynamic_field,
                                   normalize_time, time_before, time_encoding_np)
from engine.fields.gl import (CAMERA_GLSL, COLOR_EPS, TRANSMITTANCE_EPS, GlFieldRenderer, ShaderParams, available,
                              camera_uniforms, check_options, contract_glsl, generate_shader, inline_params,
                              linear_code, mlp_hidden_code, pad_matrix, scene_uniforms, set_uniforms, texture_layers)
from engine.fields.render import PLANE_AXES

__all__ = ["GlDynamicRenderer", "available", "motion_shader", "slot_key_layers"]


def _groups(plane: np.ndarray) -> int:
    return -(-plane.shape[1] // 4)


def _plane_block(sampler: str, a: str, b: str, width: int, height: int, filtering: str,
                 targets: list[tuple[int, str, str]]) -> list[str]:
    """GLSL reading one plane (a (3 G)-layer array texture of size width x height) at coordinate ``a`` along
    the width and ``b`` along the height, both in [-1, 1] (``align_corners=True``, border): ``targets`` are
    ``(layer, vec4 variable, "=" or "*=")``."""
    wm1, hm1 = float(width - 1), float(height - 1)
    lines = ["{", f"    float x = clamp(({a} + 1.0) * 0.5 * {wm1!r}, 0.0, {wm1!r});",
             f"    float y = clamp(({b} + 1.0) * 0.5 * {hm1!r}, 0.0, {hm1!r});"]
    if filtering == "exact":
        lines += [f"    float x0 = min(floor(x), {float(width - 2)!r}), y0 = min(floor(y), {float(height - 2)!r});",
                  "    float fx = x - x0, fy = y - y0;", "    ivec2 i0 = ivec2(int(x0), int(y0));"]
    else:
        lines.append(f"    vec2 uv = (vec2(x, y) + 0.5) * vec2({1.0 / width!r}, {1.0 / height!r});")
    for layer, name, op in targets:
        if filtering == "exact":
            f = [f"texelFetch({sampler}, ivec3(i0 + ivec2({dx}, {dy}), {layer}), 0)"
                 for dx, dy in ((0, 0), (1, 0), (0, 1), (1, 1))]
            val = f"({f[0]} * (1.0 - fx) + {f[1]} * fx) * (1.0 - fy) + ({f[2]} * (1.0 - fx) + {f[3]} * fx) * fy"
        else:
            val = f"texture({sampler}, vec3(uv, {float(layer)!r}))"
        lines.append(f"    {name} {op} {val};")
    return lines + ["}"]


def _time_plane_code(temporal: list[np.ndarray], filtering: str, prefix: str, sampler: str) -> list[str]:
    """Per scale s and group g the vec4 ``<prefix><s>_<g>``: product of the xt, yt, zt planes at (c, tau)."""
    lines = []
    for s, plane in enumerate(temporal):
        g = _groups(plane)
        lines.append("vec4 " + ", ".join(f"{prefix}{s}_{gi}" for gi in range(g)) + ";")
        for k in range(3):
            lines += _plane_block(f"{sampler}{s}", f"c.{'xyz'[k]}", "tau", plane.shape[3], plane.shape[2], filtering,
                                  [(k * g + gi, f"{prefix}{s}_{gi}", "=" if k == 0 else "*=") for gi in range(g)])
    return lines


def _bounded_flow(assets: DynamicAssets, motion: str) -> tuple[list[str], str]:
    """The lines and the GLSL expression of ``max_flow * tanh(motion)`` (``motion`` a vec3 expression)."""
    return ([f"vec3 fe = exp(-2.0 * abs({motion}));  // tanh, without overflow"],
            f"{assets.max_flow!r} * sign({motion}) * ((1.0 - fe) / (1.0 + fe))")


def slot_key_layers(keys: np.ndarray) -> np.ndarray:
    """(Rt, K, 12) slot keys -> the (1, Rt, 3 K, 4) array texture ``motion_keys``: row i (height) is key i,
    texel 3 k + q holds values 4 q .. 4 q + 3 of slot k (dA row-major, then T)."""
    rows, k = keys.shape[:2]
    return np.ascontiguousarray(keys.reshape(1, rows, 3 * k, 4), np.float32)


def _slot_flow_code(assets: DynamicAssets, filtering: str) -> tuple[list[str], list[str], str]:
    """DeRF with motion slots: the logit planes (one array texture, channel groups as the plane textures) summed
    over xy, xz, yz plus the still bias, a softmax over K + 1 slots, the moving slots' keys (``motion_keys``,
    :func:`slot_key_layers`) read at the two keys around tau and mixed, ``m = A c + T`` of the weighted sums,
    then ``max_flow * tanh(m)`` (:func:`engine.fields.dynamic.slot_motion_np`)."""
    logits, bias, keys = assets.slots
    rows, k = keys.shape[:2]
    g = _groups(logits)
    decls = ["uniform sampler2DArray motion_logits;", "uniform sampler2DArray motion_keys;"]
    lines = ["// motion slots: logits at c, softmax, keys at tau, mixed affine motion",
             "vec4 " + ", ".join(f"sl_{gi}" for gi in range(g)) + ";"]
    for p, (a, b) in enumerate(PLANE_AXES):
        lines += _plane_block("motion_logits", f"c.{'xyz'[a]}", f"c.{'xyz'[b]}", logits.shape[3], logits.shape[2],
                              filtering, [(p * g + gi, f"sl_{gi}", "=" if p == 0 else "+=") for gi in range(g)])
    z = [f"sz{j}" for j in range(k + 1)]
    lines += [f"float {z[j]} = sl_{j // 4}.{'xyzw'[j % 4]} + {float(bias[j])!r};" for j in range(k + 1)]
    top = z[0]
    for name in z[1:]:
        top = f"max({top}, {name})"
    lines.append(f"float sz_max = {top};")
    lines += [f"float se{j} = exp({z[j]} - sz_max);" for j in range(k + 1)]
    lines.append("float se_sum = " + " + ".join(f"se{j}" for j in range(k + 1)) + ";")
    rm1 = float(rows - 1)
    lines += [f"float sx = (clamp(tau, -1.0, 1.0) + 1.0) * {0.5 * rm1!r};",
              f"float si = clamp(floor(sx), 0.0, {float(rows - 2)!r});",
              "float sa = sx - si;", "int sk = int(si);",
              "vec4 sm0 = vec4(0.0), sm1 = vec4(0.0), sm2 = vec4(0.0);"]
    for slot in range(k):
        lines.append(f"{{ float w = se{slot + 1} / se_sum;")
        for q in range(3):
            t0 = f"texelFetch(motion_keys, ivec3({3 * slot + q}, sk, 0), 0)"
            t1 = f"texelFetch(motion_keys, ivec3({3 * slot + q}, sk + 1, 0), 0)"
            lines.append(f"  sm{q} += w * ({t0} * (1.0 - sa) + {t1} * sa);")
        lines.append("}")
    lines.append("vec3 smo = vec3(dot(sm0.xyz, c), dot(vec3(sm0.w, sm1.xy), c), dot(vec3(sm1.zw, sm2.x), c)) "
                 "+ sm2.yzw;")
    bounded, flow = _bounded_flow(assets, "smo")
    return decls, lines + bounded, flow


def _flow_code(assets: DynamicAssets, filtering: str, params: ShaderParams) -> tuple[list[str], list[str], str]:
    """DeRF: sampler declarations, the code that evaluates the motion field at (c, tau) (hex-plane features,
    flow MLP; or the motion slots, :func:`_slot_flow_code`) and the GLSL expression of its flow,
    ``max_flow * tanh(.)`` (contracted units)."""
    if assets.slots is not None:
        return _slot_flow_code(assets, filtering)
    spatial, temporal = assets.planes["motion_spatial"], assets.planes["motion_temporal"]
    decls = []
    lines = ["// motion field: hex-plane features at (c, tau), flow MLP"]
    feats, col_map, base = [], [], 0
    for s, plane in enumerate(spatial):
        decls += [f"uniform sampler2DArray motion_s{s};", f"uniform sampler2DArray motion_t{s};"]
        g, c = _groups(plane), plane.shape[1]
        lines.append("vec4 " + ", ".join(f"ms{s}_{gi}" for gi in range(g)) + ";")
        for k, (a, b) in enumerate(PLANE_AXES):
            lines += _plane_block(f"motion_s{s}", f"c.{'xyz'[a]}", f"c.{'xyz'[b]}", plane.shape[3], plane.shape[2],
                                  filtering, [(k * g + gi, f"ms{s}_{gi}", "=" if k == 0 else "*=") for gi in range(g)])
        feats += [f"(ms{s}_{gi} * mt{s}_{gi})" for gi in range(g)]
        col_map += [base + ch for ch in range(c)]
        base += 4 * g
    lines += _time_plane_code(temporal, filtering, "mt", "motion_t")
    layers = assets.flow_layers
    hidden, xs = mlp_hidden_code("fh", params, feats, layers[:-1], np.asarray(col_map))
    w_last, b_last = layers[-1]
    out_off = params.add(pad_matrix(w_last, 4, 4 * len(xs), np.asarray(col_map) if len(layers) == 1 else None))
    b_off = params.add(np.pad(b_last, (0, 4 - b_last.shape[0])))
    out, (fo,) = linear_code("fo", xs, out_off, 1, [f"P[{b_off}]"], False)
    bounded, flow = _bounded_flow(assets, f"{fo}.xyz")
    return decls, lines + hidden + out + bounded, flow


def _motion_code(assets: DynamicAssets, filtering: str, params: ShaderParams) -> tuple[list[str], list[str], list[str]]:
    """DeRF: declarations and the per-sample code that moves c to the canonical point (no code after)."""
    decls, lines, flow = _flow_code(assets, filtering, params)
    decls = ["uniform float tau;",
             f"uniform float time_enc[{2 * int(assets.manifest['field']['time_frequencies']) + 1}];"] + decls
    lines = lines + [f"c = clamp(c + {flow}, -1.0, 1.0);"]
    temporal = assets.canonical_temporal
    if temporal is None:
        return decls, lines, []
    # a canonical field with time planes: their xt, yt, zt product at (canonical point, tau) into its features
    decls += [f"uniform sampler2DArray canonical_t{s};" for s in range(len(temporal))]
    after = [f"f{s}_{gi} *= ct{s}_{gi};" for s, plane in enumerate(temporal) for gi in range(_groups(plane))]
    return decls, lines + _time_plane_code(temporal, filtering, "ct", "canonical_t"), after


def _kplanes_code(assets: DynamicAssets, filtering: str, params: ShaderParams) -> tuple[list[str], list[str], list[str]]:
    """K-Planes: the xt, yt, zt product before the tri-plane lookup, multiplied into its features after."""
    temporal = assets.planes["temporal"]
    decls = ["uniform float tau;"] + [f"uniform sampler2DArray temporal{s};" for s in range(len(temporal))]
    after = [f"f{s}_{gi} *= kt{s}_{gi};" for s, plane in enumerate(temporal) for gi in range(_groups(plane))]
    return decls, _time_plane_code(temporal, filtering, "kt", "temporal"), after


_MOTION_TEMPLATE = """
#version 450
layout(local_size_x = 8, local_size_y = 8) in;
layout(std430, binding = 2) readonly buffer RgbdBuf { vec4 rgbd[]; };
layout(std430, binding = 5) writeonly buffer MotionBuf { vec2 out_motion[]; };
%(samplers)s

uniform ivec2 size;             // W, H
uniform dvec4 k_vals;           // this frame's K00 (fx), K01, K02 (cx), K11 (fy)
uniform double k_cy;            // K12
uniform dmat3 rot;              // this frame's world_to_camera rotation: rot[i][j] = R[i, j]
uniform vec3 origin;            // this frame's camera centre, float32
uniform mat3 prev_rot;          // the earlier camera: q = prev_rot p + prev_t
uniform vec3 prev_t;
uniform vec4 prev_k;            // the earlier K00, K01, K02, K11
uniform float prev_k12;
uniform float tau_now;
uniform float tau_prev;
uniform float tau_before;       // the interval before: 2 tau_prev - tau_now
uniform float coherence;        // < 0: the field's motion as it is; else coherent_motion's ratio
uniform float max_vector;       // MAX_MOTION_DIAGONALS frame diagonals, px
uniform vec3 box_center;
uniform vec3 box_half;
uniform mat3 ndc_rot;
uniform vec3 ndc_t;
uniform vec4 ndc_k;
uniform float ndc_k12;
uniform vec2 ndc_size;
uniform float ndc_margin;
uniform float scene_near;

const float NAN = uintBitsToFloat(0x7fc00000u);

vec3 motion_flow(vec3 c, float tau) {
%(flow)s
}

%(camera_glsl)s

%(contract_glsl)s

vec3 uncontract(vec3 c) {
%(uncontract)s
}

// the point at tau that the motion field maps to the same canonical point (earlier_points: one fixed-point step
// from c, then up to ITERATIONS Newton steps, stopping once settled; each with the Jacobian by forward differences,
// solved by Cramer's rule, a fixed-point step where it is near singular, at most MAX_STEP long); residual: the
// max |e + flow(e, tau) - canonical| at the point returned
vec3 invert(vec3 canonical, vec3 c, float tau, out float residual) {
    vec3 e = canonical - motion_flow(c, tau);
    for (int i = 0; i <= ITERATIONS; ++i) {  // the last residual is the found check's
        vec3 at = clamp(e, -1.0, 1.0);
        vec3 f = motion_flow(at, tau);
        vec3 g = e + f - canonical;
        residual = max(abs(g.x), max(abs(g.y), abs(g.z)));
        if (residual <= SETTLED || i == ITERATIONS) break;
        vec3 c0 = (motion_flow(at + vec3(JSTEP, 0.0, 0.0), tau) - f) / JSTEP + vec3(1.0, 0.0, 0.0);
        vec3 c1 = (motion_flow(at + vec3(0.0, JSTEP, 0.0), tau) - f) / JSTEP + vec3(0.0, 1.0, 0.0);
        vec3 c2 = (motion_flow(at + vec3(0.0, 0.0, JSTEP), tau) - f) / JSTEP + vec3(0.0, 0.0, 1.0);
        vec3 r0 = cross(c1, c2);
        float det = dot(c0, r0);
        vec3 step = abs(det) >= MIN_DET ? vec3(dot(r0, g), dot(cross(c2, c0), g), dot(cross(c0, c1), g)) / det : g;
        float len = length(step);
        if (len > MAX_STEP) step *= MAX_STEP / len;
        e -= step;
    }
    return e;
}

bool settled(vec3 e, float residual) {
    return all(lessThanEqual(abs(e), vec3(1.0))) && residual <= TOLERANCE;
}

void main() {
    ivec2 pix = ivec2(gl_GlobalInvocationID.xy);
    if (pix.x >= size.x || pix.y >= size.y) return;
    int o = pix.y * size.x + pix.x;
    vec3 d = pixel_ray(pix);  // the renderer's ray through the pixel centre (camera z = 1)
    float depth = rgbd[o].w;
    vec3 q;
    if (isinf(depth)) {
        q = prev_rot * d;           // the background: a direction, rotation only
    } else {
        vec3 p = origin + depth * d;
        vec3 c = contract(p);
        if (all(lessThanEqual(abs(c), vec3(1.0)))) {
            vec3 canonical = c + motion_flow(c, tau_now);
            float residual, residual_before;
            vec3 e = invert(canonical, c, tau_prev, residual);
            bool found = settled(e, residual);
            vec3 moved = found ? uncontract(e) : vec3(NAN);
            if (found && coherence >= 0.0) {  // coherent_motion: a motion that turned leaves the point in place
                vec3 b = invert(canonical, c, tau_before, residual_before);
                bool outside = any(greaterThan(abs(b), vec3(1.0)));
                vec3 last = p - moved;
                bool turned = length(last - (moved - uncontract(b))) > coherence * length(last);
                if (!outside && (!settled(b, residual_before) || turned)) moved = p;
            }
            p = moved;
        }
        q = prev_rot * p + prev_t;
    }
    vec2 mv = vec2(NAN);
    bool finite = !any(isnan(q)) && !any(isinf(q));
    if (finite && q.z > 1e-9 * max(1.0, max(abs(q.x), abs(q.y)))) {
        vec2 at = vec2(prev_k.x * q.x / q.z + prev_k.y * q.y / q.z + prev_k.z, prev_k.w * q.y / q.z + prev_k12);
        mv = at - (vec2(pix) + 0.5);
        if (max(abs(mv.x), abs(mv.y)) > max_vector) mv = vec2(NAN);
    }
    out_motion[o] = mv;
}
"""

_BOX_UNCONTRACT = "    return c * box_half + box_center;"
_NDC_UNCONTRACT = """    if (c.z >= 1.0) return vec3(NAN);   // at or beyond infinity
    float z = 2.0 * scene_near / (1.0 - c.z);
    float pu = (c.x * (1.0 + ndc_margin) + 1.0) * (ndc_size.x / 2.0);
    float pv = (c.y * (1.0 + ndc_margin) + 1.0) * (ndc_size.y / 2.0);
    float y = (pv - ndc_k12) * z / ndc_k.w;
    float x = ((pu - ndc_k.z) * z - ndc_k.y * y) / ndc_k.x;
    return transpose(ndc_rot) * (vec3(x, y, z) - ndc_t);"""


def motion_shader(assets: DynamicAssets, filtering: str, iterations: int = MOTION_ITERATIONS) -> str:
    """GLSL of the motion-vector pass of a DeRF export (:func:`engine.fields.dynamic.field_motion_vectors` on
    the GPU): per pixel, the rendered depth's point, the motion field inverted at the earlier time, the
    earlier camera's projection; the flow MLP's weights as literals."""
    params = ShaderParams()
    if assets.has_motion:
        decls, lines, flow = _flow_code(assets, filtering, params)
    else:  # K-Planes: no motion model, nothing moves
        decls, lines, flow = [], [], "vec3(0.0)"
    body = "\n".join("    " + line for line in lines + [f"return {flow};"])
    bounded = assets.bounded
    source = _MOTION_TEMPLATE % {
        "samplers": "\n".join(decls), "flow": body, "camera_glsl": CAMERA_GLSL, "contract_glsl": contract_glsl(bounded),
        "uncontract": _BOX_UNCONTRACT if bounded else _NDC_UNCONTRACT}
    for name, value in (("ITERATIONS", str(int(iterations))), ("TOLERANCE", repr(float(MOTION_TOLERANCE))),
                        ("SETTLED", repr(float(NEWTON_SETTLED))),
                        ("JSTEP", repr(float(JACOBIAN_STEP))), ("MIN_DET", repr(float(MIN_JACOBIAN_DET))),
                        ("MAX_STEP", repr(float(MAX_NEWTON_STEP)))):
        source = source.replace(name, value)
    return inline_params(source, params.array())


class GlDynamicRenderer(GlFieldRenderer):
    """One headless GL context with the compute shader, textures and buffers of one exported dynamic field.

    Args:
        assets: :func:`engine.fields.dynamic.load_dynamic_field`'s result, or the export folder.
        width, height: the output size in pixels (fixed for the renderer).
        filtering, transmittance_eps, color_eps, weights: as :class:`engine.fields.gl.GlFieldRenderer`.

    Raises:
        InputError: bad size or option.
    """

    def __init__(self, assets: Union[DynamicAssets, str, Path], width: int, height: int, *,
                 filtering: str = "hardware", transmittance_eps: float = TRANSMITTANCE_EPS,
                 color_eps: float = COLOR_EPS, weights: str = "inline") -> None:
        if not isinstance(assets, DynamicAssets):
            assets = load_dynamic_field(assets)
        check_options(width, height, filtering=filtering, color_mode="per-sample", weights=weights,
                       transmittance_eps=transmittance_eps, color_eps=color_eps)
        self.assets = assets
        self.width, self.height = int(width), int(height)
        self.quantized = False
        self.filtering = filtering
        self.color_mode = "per-sample"
        self.transmittance_eps = float(transmittance_eps)
        self.color_eps = float(color_eps)
        if assets.has_motion:
            frequencies = int(assets.manifest["field"]["time_frequencies"])
            extra = [f"time_enc[{i}]" for i in range(2 * frequencies + 1)]
            extra_planes = ([] if assets.slots is not None else
                            [("motion_s", assets.planes["motion_spatial"]),
                             ("motion_t", assets.planes["motion_temporal"])])
            if assets.canonical_temporal is not None:
                extra_planes.append(("canonical_t", assets.canonical_temporal))
            code = _motion_code
        else:
            frequencies, extra = 0, []
            extra_planes = [("temporal", assets.planes["temporal"])]
            code = _kplanes_code
        self._time_frequencies = frequencies
        self.source, packed, _, self.params_kind = generate_shader(
            assets, assets.canonical_planes, None, filtering=filtering, color_mode="per-sample",
            params_kind="const" if weights == "inline" else "ubo", extra_encoding=extra,
            sample_code=lambda params: code(assets, filtering, params))
        textures = [(f"planes{s}", texture_layers(p, _groups(p))) for s, p in enumerate(assets.canonical_planes)]
        if assets.slots is not None:
            textures += [("motion_logits", texture_layers(assets.slots.logits, _groups(assets.slots.logits))),
                         ("motion_keys", slot_key_layers(assets.slots.keys))]
        for prefix, planes in extra_planes:
            textures += [(f"{prefix}{s}", texture_layers(p, _groups(p))) for s, p in enumerate(planes)]
        self._units = {name: unit for unit, (name, _) in enumerate(textures)}
        self._motion_program = self._motion = None
        self._setup(packed, textures, "f4")

    def render(self, intrinsics, world_to_camera, time: float, *, earlier_world_to_camera=None,
               earlier_time: Optional[float] = None, earlier_intrinsics=None,
               coherence: Optional[float] = None) -> dict[str, np.ndarray]:
        """Render the field at ``time`` (the data's units) from a camera (OpenCV axes, rigid world-to-camera,
        pixel centres at +0.5); with ``earlier_world_to_camera`` and ``earlier_time`` also its motion vectors
        to the frame that camera (with ``earlier_intrinsics``, default the same K) sees at that time.

        Returns:
            ``color`` (H, W, 3) float32 linear RGB, ``depth`` (H, W) float32 planar (+inf where the opacity
            is below ``OPACITY_EPS``), ``opacity`` (H, W) float32, ``seconds`` (dispatches and read-backs);
            with an earlier frame, ``motion_vectors`` (H, W, 2) float32: engine-style vectors (pixels, x right,
            y down, camera motion included, NaN where there is none), what
            :func:`engine.fields.dynamic.field_motion_vectors` computes from this render's depth with
            ``coherence`` (its test oracle), a second pass over the rendered depth.

        Raises:
            InputError: a time outside the trained range (the message names both), bad intrinsics or pose, an
                earlier camera without a time or the reverse.
        """
        if (earlier_world_to_camera is None) != (earlier_time is None):
            raise InputError("takes both earlier_world_to_camera and earlier_time, or neither",
                             field="earlier_time")
        tau = normalize_time(time, self.assets.time_range)
        motion = None
        if earlier_time is not None:
            motion = self._motion_dispatcher(intrinsics, world_to_camera, tau, earlier_world_to_camera,
                                             normalize_time(earlier_time, self.assets.time_range),
                                             earlier_intrinsics, coherence)

        def set_time() -> None:
            self._set("tau", float(tau))
            if self.assets.has_motion:
                enc = time_encoding_np(np.array([tau], np.float32), self._time_frequencies)[0]
                try:
                    self.program["time_enc"].write(np.ascontiguousarray(enc, np.float32).tobytes())
                except KeyError:  # optimised out: the colour MLP ignores time
                    pass
        self._run(set_time)
        out = super().render(intrinsics, world_to_camera)
        if motion is not None:
            def run():
                start = time_module.perf_counter()
                motion()
                n = self.width * self.height
                return (np.frombuffer(self._motion.read(size=8 * n), np.float32).reshape(self.height, self.width, 2)
                        .copy(), time_module.perf_counter() - start)
            out["motion_vectors"], seconds = self._run(run)
            out["seconds"] += seconds
        return out

    def _motion_dispatcher(self, intrinsics, world_to_camera, tau, earlier_world_to_camera, tau_prev,
                           earlier_intrinsics, coherence: Optional[float] = None):
        """The checked motion pass (over the depth the next render writes), to run with the context current."""
        check_coherence(coherence)
        tau_before = time_before(tau, tau_prev)
        if coherence is None or tau_before is None:  # as coherent_motion: no check
            coherence, tau_before = -1.0, 0.0
        camera = camera_uniforms(intrinsics, world_to_camera)
        prev_k, prev_k12 = camera["k_vals"], camera["k_cy"]  # K00, K01, K02, K11 and K12: the same K by default
        if earlier_intrinsics is not None:
            k = validate_intrinsics(earlier_intrinsics, field_name="earlier_intrinsics")
            prev_k, prev_k12 = (float(k[0, 0]), float(k[0, 1]), float(k[0, 2]), float(k[1, 1])), float(k[1, 2])
        prev = validate_pose(earlier_world_to_camera, field_name="earlier_world_to_camera").astype(np.float32)
        values = {**camera, "prev_rot": tuple(float(x) for x in prev[:3, :3].flatten(order="F")),  # column-major
                  "prev_t": tuple(float(x) for x in prev[:3, 3]), "prev_k": prev_k, "prev_k12": prev_k12,
                  "tau_now": float(tau), "tau_prev": float(tau_prev),
                  "tau_before": float(tau_before), "coherence": float(coherence)}
        if self._motion_program is None:
            self._run(self._build_motion_pass)

        def dispatch() -> None:
            set_uniforms(self._motion_program, values)
            for unit, tex in enumerate(self._textures):
                tex.use(location=unit)
            self._rgbd.bind_to_storage_buffer(2)
            self._motion.bind_to_storage_buffer(5)
            self._motion_program.run(-(-self.width // 8), -(-self.height // 8), 1)
            self.ctx.memory_barrier()
        return dispatch

    def _build_motion_pass(self) -> None:
        """Compile the motion pass (on first use) and set what does not change between frames."""
        self._motion_program = program = self.ctx.compute_shader(motion_shader(self.assets, self.filtering))
        self._motion = self.ctx.buffer(reserve=8 * self.width * self.height)
        self._buffers += [self._motion, program]  # released with the buffers
        set_uniforms(program, {**scene_uniforms(self.assets, self.width, self.height),
                               "max_vector": float(MAX_MOTION_DIAGONALS * np.hypot(self.height, self.width)),
                               **{name: unit for name, unit in self._units.items() if name.startswith("motion_")}})
