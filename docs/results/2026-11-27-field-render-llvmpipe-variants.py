"""Experiments on the GL field renderer on llvmpipe (issue 24, >= 5 fps at 512x512), 2026-11-27.

    python docs/results/2026-11-27-field-render-llvmpipe-variants.py OUT.json LEGO_EXPORT FF_EXPORT [REPS]

Every render is at 512x512 on the export's held-out camera (``tools.bench_fields``' camera). Parts:

- ``stages``: the default renderer against shader edits that remove one cost (the frames change; the times
  say what the removed part costs): ``no_texture`` (each plane fetch replaced by arithmetic on its
  coordinates), ``no_color`` (the colour branch never taken), and the options ``filtering="exact"``,
  ``quantized=True`` (uint8 planes), ``textureLod(..., 0)`` instead of ``texture``.
- ``patches``: the renderer with a patch applied (``*.patch`` beside this script: ``split-locate``, the test pass
  computing only the bin centre; ``macro``, that plus a 3D DDA over a 16^3 coarse grid marking candidate
  samples), two instances of each alternating with two of the default (the first instance made in a process
  can run a few % slower); frames and counts compared bit for bit.
- ``eps``: ``transmittance_eps`` 1e-4 (default) and 9e-3 (the largest with a colour error bound under 0.01,
  i.e. >= 40 dB whatever the field: T + 64 * color_eps): time, PSNR against the numpy reference, colour and
  depth errors.
- ``rays`` (numpy, lego only): per ray, samples tested, evaluated, and coloured (weight > color_eps), and what a
  coarse grid would leave to test.
"""
import importlib.util, json, re, subprocess, sys, tempfile
from pathlib import Path

import numpy as np

from engine.fields import gl
from engine.fields.camera_path import scale_intrinsics
from engine.fields.render import (_ray_box, _samples, camera_rays_np, contract_np, load_field, query_field,
                                  render_field)
from tools.bench_fields import _static_camera

S = 512
HERE = Path(__file__).resolve().parent
STEM = "2026-11-27-field-render-llvmpipe-variants"


def camera(exp):
    k, w2c, w, h, _ = _static_camera(exp, exp.parent)
    return scale_intrinsics(k, w, h, S, S), w2c


def edited(assets, edit, **kw):
    original = gl.generate_shader

    def generate(*args, **kwargs):
        source, *rest = original(*args, **kwargs)
        return (edit(source), *rest)
    gl.generate_shader = generate
    try:
        return gl.GlFieldRenderer(assets, S, S, count_evaluations=True, **kw)
    finally:
        gl.generate_shader = original


def alternate(renderers, k, w2c, reps):
    times = {n: [] for n in renderers}
    last = {}
    for _ in range(reps):
        for n, r in renderers.items():
            o = r.render(k, w2c)
            times[n].append(o["seconds"] * 1e3)
            last[n] = o
    return times, last


def stages(exp, reps):
    a = load_field(exp)
    k, w2c = camera(exp)
    no_texture = lambda s: re.sub(r"texture\(planes(\d+), vec3\(uv, ([0-9.]+)\)\)", r"(vec4(uv, uv.yx) * (1.0 + \2))", s)
    lod = lambda s: re.sub(r"texture\(planes(\d+), vec3\(uv, ([0-9.]+)\)\)", r"textureLod(planes\1, vec3(uv, \2), 0.0)", s)
    same = lambda s: s
    rs = {"default": edited(a, same), "no_texture": edited(a, no_texture),
          "no_color": edited(a, lambda s: s.replace("if (w > color_eps) {", "if (false) {")),
          "exact_filtering": edited(a, same, filtering="exact"), "uint8_planes": edited(a, same, quantized=True),
          "textureLod": edited(a, lod)}
    times, last = alternate(rs, k, w2c, reps)
    return {n: {"median_ms": float(np.median(times[n])), "ms": times[n],
                "evaluations_per_pixel": float(last[n]["evaluations"].mean()),
                "same_frame": bool(np.array_equal(last[n]["color"], last["default"]["color"]))} for n in rs}


def patched_module(patch):
    tmp = Path(tempfile.mkdtemp()) / "gl_variant.py"
    tmp.write_text(Path(gl.__file__).read_text())
    subprocess.run(["patch", "-s", str(tmp), str(patch)], check=True)
    spec = importlib.util.spec_from_file_location("gl_variant", tmp)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def patches(exps, reps):
    out = {}
    for name in ("split-locate", "macro"):
        module = patched_module(HERE / f"{STEM}-{name}.patch")
        for exp in exps:
            a = load_field(exp)
            k, w2c = camera(exp)
            rs = {"variant_1": module.GlFieldRenderer(a, S, S, count_evaluations=True),
                  "default_1": gl.GlFieldRenderer(a, S, S, count_evaluations=True),
                  "variant_2": module.GlFieldRenderer(a, S, S, count_evaluations=True),
                  "default_2": gl.GlFieldRenderer(a, S, S, count_evaluations=True)}
            times, last = alternate(rs, k, w2c, reps)
            identical = all(np.array_equal(last["variant_1"][f], last["default_1"][f])
                            for f in ("color", "depth", "opacity", "evaluations"))
            out.setdefault(name, {})[exp.parent.name] = {
                "identical": identical, **{n: float(np.median(t)) for n, t in times.items()}, "ms": times}
            for r in rs.values():
                r.release()
    return out


def eps(exps, reps):
    out = {}
    for exp in exps:
        a = load_field(exp)
        k, w2c = camera(exp)
        ref = render_field(a, k, w2c, S, S)
        rs = {str(t): gl.GlFieldRenderer(a, S, S, transmittance_eps=t, count_evaluations=True) for t in (1e-4, 9e-3)}
        times, last = alternate(rs, k, w2c, reps)
        for n, o in last.items():
            e = o["color"] - ref["color"]
            both = np.isfinite(ref["depth"]) & np.isfinite(o["depth"])
            dd = np.abs(o["depth"] - ref["depth"])[both]
            out.setdefault(exp.parent.name, {})[n] = {
                "median_ms": float(np.median(times[n])), "ms": times[n],
                "psnr_vs_numpy": float(-10 * np.log10(max(float(np.mean(e ** 2)), 1e-20))),
                "max_abs_color": float(np.abs(e).max()), "depth_max": float(dd.max()),
                "depth_p99": float(np.percentile(dd, 99)), "median_depth": float(np.median(ref["depth"][both])),
                "evaluations_per_pixel": float(o["evaluations"].mean())}
        for r in rs.values():
            r.release()
    return out


def rays(exp):
    a = load_field(exp)
    k, w2c = camera(exp)
    o, d = camera_rays_np(k, w2c, S, S)
    o, d = o.astype(np.float32), d.astype(np.float32)
    sc = a.scene
    t0, t1 = _ray_box(o, d, np.float32(sc["box_min"]), np.float32(sc["box_max"]))
    t0 = np.maximum(t0, np.float32(sc["near"])).astype(np.float32)
    t1 = np.minimum(t1, np.float32(sc["far"])).astype(np.float32)
    n = int(a.manifest["render"]["num_samples"])
    t, delta = _samples(t0, t1, n, "linear")
    c = contract_np(sc, o + t[..., None] * d[:, None], 0.0)
    inside = (delta > 0) & (np.abs(c) <= 1).all(-1)
    occ = a.occupancy
    r = occ.shape[0]
    cell = np.clip(np.floor((c + 1) * 0.5 * r).astype(int), 0, r - 1)
    keep = occ[cell[..., 0], cell[..., 1], cell[..., 2]] & inside
    sigma = np.zeros(keep.shape, np.float32)
    idx = np.nonzero(keep)
    unit = d / np.linalg.norm(d, axis=-1, keepdims=True)
    sigma[idx] = query_field(a, c[idx], unit[idx[0]])[0]
    tau = np.where(keep, sigma * delta * np.linalg.norm(d, axis=-1)[:, None], 0).astype(np.float32)
    cum = np.cumsum(tau, 1)
    stopped = np.exp(-cum) < gl.TRANSMITTANCE_EPS
    before = np.zeros_like(stopped)
    before[:, 1:] = np.logical_or.accumulate(stopped, 1)[:, :-1]
    evaluated = keep & ~before
    excl = np.concatenate([np.zeros_like(cum[:, :1]), cum[:, :-1]], 1)
    weights = np.exp(-excl) * -np.expm1(-tau)
    colored = evaluated & (weights > gl.COLOR_EPS)
    chunks = np.where(stopped.any(1), stopped.argmax(1), n - 1) // 32 + 1
    tested = np.arange(n)[None] < 32 * chunks[:, None]  # the chunks of 32 a ray visits
    out = {"tested": float(tested.sum(1).mean()), "evaluated": float(evaluated.sum(1).mean()),
           "colored": float(colored.sum(1).mean())}
    padded = np.pad(occ, 1)
    grown = np.zeros_like(occ)
    for dx in range(3):
        for dy in range(3):
            for dz in range(3):
                grown |= padded[dx:dx + r, dy:dy + r, dz:dz + r]
    for m in (8, 16):
        b = r // m
        coarse = grown.reshape(m, b, m, b, m, b).any(axis=(1, 3, 5))
        mc = np.clip(np.floor((c + 1) * 0.5 * m).astype(int), 0, m - 1)
        candidate = coarse[mc[..., 0], mc[..., 1], mc[..., 2]] & inside
        out[f"tested_with_coarse_{m}"] = float((candidate & tested).sum(1).mean())
        out[f"coarse_{m}_occupied"] = float(coarse.mean())
    return out


def main():
    out_path, lego, ff = sys.argv[1], Path(sys.argv[2]), Path(sys.argv[3])
    reps = int(sys.argv[4]) if len(sys.argv) > 4 else 7
    result = {"size": S, "reps": reps, "rays_lego": rays(lego), "stages_lego": stages(lego, reps),
              "patches": patches([lego, ff], reps), "eps": eps([lego, ff], reps)}
    Path(out_path).write_text(json.dumps(result, indent=1))
    print(json.dumps({k: v for k, v in result.items() if k != "patches"}, indent=1, default=str)[:4000])


if __name__ == "__main__":
    main()
