"""Where the GL field renderer's time goes on llvmpipe, and how many field evaluations a frame needs.

Scratch measurement script of docs/results/2026-11-27-field-render-cost.md (run from the repository root):
    python docs/results/2026-11-27-field-render-cost.py RUN_DIR [RUN_DIR ...] --json OUT.json
Each RUN_DIR is a trained static field with its export (RUN_DIR/export). Variants are made by editing the
generated GLSL (an evaluation counter, no march, an emptied occupancy grid) or the renderer's options.
"""
import argparse, json, re, shutil, sys, tempfile, time
from pathlib import Path
import numpy as np
from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr
from engine.fields.camera_path import scale_intrinsics
from engine.fields.gl import GlFieldRenderer
from engine.fields.render import load_field
from models.fields.train_static import load_model
from tools.bench_fields import _static_camera, _torch_renderer


def recompile(g, source):
    def f():
        g.program = g.ctx.compute_shader(source)
        g._set_static_uniforms()
        for unit in range(len(g._textures)):
            g._set(f"planes{unit}", unit)
    g._run(f)


def count_source(source):
    """The shader with the number of evaluated samples per pixel written to the opacity output."""
    out = source.replace("bool done = false;", "bool done = false; int nev = 0;")
    out = re.sub(r"(while \(kept != 0u\) \{\n\s*int j = findLSB\(kept\);)", r"\1 nev++;", out)
    out = out.replace("out_opacity[o] = acc;", "out_opacity[o] = float(nev);")
    assert out.count("nev") == 3, "the shader template changed"
    return out


def timed(g, k, w2c, repeat=3):
    g.render(k, w2c)
    walls = []
    for _ in range(repeat):
        t = time.perf_counter()
        out = g.render(k, w2c)
        walls.append(time.perf_counter() - t)
    return 1e3 * float(np.median(walls)), out


def macs_per_evaluation(assets):
    layers = list(assets.density_layers) + list(assets.color_layers)
    total = sum(int(w.size) for w, _ in layers)
    enc = sum(int(w.shape[1]) for w, _ in assets.color_layers[:1]) - (assets.density_layers[-1][0].shape[0] - 1)
    return total - enc * int(assets.color_layers[0][0].shape[0])  # the direction columns run once per pixel


def empty_grid_export(export: Path, tmp: Path) -> Path:
    dst = Path(tempfile.mkdtemp(dir=tmp)) / "export"
    shutil.copytree(export, dst)
    npz = dict(np.load(dst / "field.npz"))
    man = json.loads((dst / "field.json").read_text())
    res = man["occupancy"]["resolution"] if man.get("occupancy") else 64
    npz["occupancy"] = np.zeros((res,) * 3, np.uint8)
    np.savez_compressed(dst / "field.npz", **npz)
    man["occupancy"] = {"array": "occupancy", "resolution": res, "occupied_fraction": 0.0}
    (dst / "field.json").write_text(json.dumps(man))
    return dst


def main():
    ap = argparse.ArgumentParser()
    ap.add_argument("runs", nargs="+", type=Path)
    ap.add_argument("--sizes", default="512x512,1920x1080")
    ap.add_argument("--json", type=Path)
    args = ap.parse_args()
    records = []
    tmp = Path(tempfile.mkdtemp())
    for run in args.runs:
        export = run / "export"
        assets = load_field(export)
        model = load_model(run)
        k0, w2c, w0, h0, where = _static_camera(export, run)
        for size in args.sizes.split(","):
            w, h = map(int, size.split("x"))
            k = scale_intrinsics(k0, w0, h0, w, h) if (w0, h0) != (w, h) else k0
            ref = _torch_renderer(model, model.scene.near, model.scene.far)(k, w2c, h, w) if w * h <= 512 * 512 else None
            rec = {"run": run.name, "size": size, "camera": where, "bounded": bool(assets.bounded),
                   "occupancy_fraction": None if assets.occupancy is None else float(assets.occupancy.mean()),
                   "macs_per_evaluation": macs_per_evaluation(assets)}
            g = GlFieldRenderer(assets, w, h)
            rec["ms"], out = timed(g, k, w2c)
            if ref is not None:
                rec["psnr_vs_torch"] = psnr(display_encode(ref["color"]), display_encode(out["color"]))
            recompile(g, count_source(g.source))
            n = g.render(k, w2c)["opacity"]
            blocks = n[: h // 2 * 2, : w // 4 * 4].reshape(h // 2, 2, w // 4, 4).max(axis=(1, 3))
            rec.update(evaluations_per_pixel=float(n.mean()), pixels_with_evaluations=float((n > 0).mean()),
                       evaluations_per_hit_pixel=float(n[n > 0].mean()) if (n > 0).any() else 0.0,
                       evaluations_per_pixel_4x2_block_max=float(blocks.mean()),
                       gmac_per_frame=float(n.sum()) * rec["macs_per_evaluation"] / 1e9)
            recompile(g, g.source.replace("bool done = false;", "bool done = true;"))
            rec["ms_no_march"] = timed(g, k, w2c)[0]
            g.release()
            with GlFieldRenderer(load_field(empty_grid_export(export, tmp)), w, h) as ge:
                rec["ms_march_no_evaluation"] = timed(ge, k, w2c)[0]
            if ref is not None:
                sweep = []
                for teps in (1e-4, 1e-3, 1e-2, 3e-2):
                    with GlFieldRenderer(assets, w, h, transmittance_eps=teps) as gt:
                        ms, o = timed(gt, k, w2c)
                        recompile(gt, count_source(gt.source))
                        ne = float(gt.render(k, w2c)["opacity"].mean())
                    sweep.append({"transmittance_eps": teps, "ms": ms, "evaluations_per_pixel": ne,
                                  "psnr_vs_torch": psnr(display_encode(ref["color"]), display_encode(o["color"]))})
                rec["transmittance_sweep"] = sweep
                samples = []
                for ns in (48, 32):
                    a = load_field(export)
                    a.manifest["render"]["num_samples"] = ns
                    with GlFieldRenderer(a, w, h) as gs:
                        ms, o = timed(gs, k, w2c)
                    samples.append({"num_samples": ns, "ms": ms,
                                    "psnr_vs_torch_64": psnr(display_encode(ref["color"]), display_encode(o["color"]))})
                rec["fewer_samples"] = samples
            print(json.dumps(rec), flush=True)
            records.append(rec)
    shutil.rmtree(tmp, ignore_errors=True)
    if args.json:
        args.json.write_text(json.dumps(records, indent=2) + "\n")


if __name__ == "__main__":
    main()
