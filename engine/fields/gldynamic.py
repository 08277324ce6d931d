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
  ``c = clamp(c + flow, -1, 1)``; the canonical field then runs unchanged on c. The colour MLP's time input
  [tau, sin(2^k tau), cos(2^k tau)] is per frame: computed on the CPU (``time_encoding_np``) and applied
  once per pixel with the view-direction columns.
- **K-Planes** (``kind="kplanes"``): the ``spatial`` planes are the tri-planes; after their lookup each
  feature group is multiplied by the xt, yt, zt product at (c, tau).

Plane lookups are ``grid_sample(align_corners=True, padding_mode="border")`` as in the static shader:
``filtering="hardware"`` (the sampler's bilinear filter at ``(x + 0.5) / W, (y + 0.5) / H``) or ``"exact"``
(four ``texelFetch`` + float32 lerp). Float32 planes only (no uint8 path for dynamic assets yet).

>>> with GlDynamicRenderer(load_dynamic_field("runs/dyn/export"), 960, 540) as r:     # doctest: +SKIP
...     frames = [r.render(K, world_to_camera, t) for t in (0.2, 0.4, 0.6)]

``python -m tools.bench_fields dynamic EXPORT_DIR --sizes 160x90,512x512`` times this renderer against the
numpy and onnxruntime paths of :mod:`engine.fields.dynamic` and (when torch is importable) the torch renderer.
"""
from __future__ import annotations

from pathlib import Path
from typing import Union

import numpy as np

from engine.fields.dynamic import DynamicAssets, load_dynamic_field, normalize_time, time_encoding_np
from engine.fields.gl import (COLOR_EPS, TRANSMITTANCE_EPS, GlFieldRenderer, ShaderParams, available, check_options,
                              generate_shader, linear_code, mlp_hidden_code, pad_matrix, texture_layers)
from engine.fields.render import PLANE_AXES

__all__ = ["GlDynamicRenderer", "available"]


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


def _motion_code(assets: DynamicAssets, filtering: str, params: ShaderParams) -> tuple[list[str], list[str], list[str]]:
    """DeRF: declarations and the per-sample code that moves c to the canonical point (no code after)."""
    spatial, temporal = assets.planes["motion_spatial"], assets.planes["motion_temporal"]
    decls = ["uniform float tau;",
             f"uniform float time_enc[{2 * int(assets.manifest['field']['time_frequencies']) + 1}];"]
    lines = ["// motion field: hex-plane features at (c, tau), flow MLP, c -> canonical point"]
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
    lines += hidden + out
    lines += ["vec3 fe = exp(-2.0 * abs(" + fo + ".xyz));  // tanh, without overflow",
              f"c = clamp(c + {assets.max_flow!r} * sign({fo}.xyz) * ((1.0 - fe) / (1.0 + fe)), -1.0, 1.0);"]
    return decls, lines, []


def _kplanes_code(assets: DynamicAssets, filtering: str, params: ShaderParams) -> tuple[list[str], list[str], list[str]]:
    """K-Planes: the xt, yt, zt product before the tri-plane lookup, multiplied into its features after."""
    temporal = assets.planes["temporal"]
    decls = ["uniform float tau;"] + [f"uniform sampler2DArray temporal{s};" for s in range(len(temporal))]
    after = [f"f{s}_{gi} *= kt{s}_{gi};" for s, plane in enumerate(temporal) for gi in range(_groups(plane))]
    return decls, _time_plane_code(temporal, filtering, "kt", "temporal"), after


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
            extra_planes = [("motion_s", assets.planes["motion_spatial"]),
                            ("motion_t", assets.planes["motion_temporal"])]
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
        for prefix, planes in extra_planes:
            textures += [(f"{prefix}{s}", texture_layers(p, _groups(p))) for s, p in enumerate(planes)]
        self._setup(packed, textures, "f4")

    def render(self, intrinsics, world_to_camera, time: float) -> dict[str, np.ndarray]:
        """Render the field at ``time`` (the data's units) from a camera (OpenCV axes, rigid world-to-camera,
        pixel centres at +0.5).

        Returns:
            ``color`` (H, W, 3) float32 linear RGB, ``depth`` (H, W) float32 planar (+inf where the opacity
            is below ``OPACITY_EPS``), ``opacity`` (H, W) float32, ``seconds`` (dispatch and read-back).

        Raises:
            InputError: time outside the trained range (the message names both), bad intrinsics or pose.
        """
        tau = normalize_time(time, self.assets.time_range)

        def set_time() -> None:
            self._set("tau", float(tau))
            if self.assets.has_motion:
                enc = time_encoding_np(np.array([tau], np.float32), self._time_frequencies)[0]
                try:
                    self.program["time_enc"].write(np.ascontiguousarray(enc, np.float32).tobytes())
                except KeyError:  # optimised out: the colour MLP ignores time
                    pass
        self._run(set_time)
        return super().render(intrinsics, world_to_camera)
