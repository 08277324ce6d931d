"""Scratch: a render-time occupancy grid for a field without one; GL time, evals and PSNR vs torch."""
import sys, json, shutil, time, math
import numpy as np, torch
from pathlib import Path
from models.fields.train_static import load_model
from engine.fields.render import load_field
from engine.fields.gl import GlFieldRenderer
from tools.bench_fields import _static_camera, _torch_renderer
from engine.fields.camera_path import scale_intrinsics
from engine.core.colorspace import display_encode
from engine.eval.metrics import psnr

run = Path(sys.argv[1]); res = int(sys.argv[2]); alpha = float(sys.argv[3]); dilate = int(sys.argv[4])
model = load_model(run); model.eval()
src = run / "export"
t0 = time.time()
r = res
lat = torch.linspace(-1, 1, 2 * r + 1)
dens = torch.empty(2 * r + 1, 2 * r + 1, 2 * r + 1)
with torch.no_grad():
    for i in range(2 * r + 1):
        g = torch.stack(torch.meshgrid(lat[i:i+1], lat, lat, indexing="ij"), -1).reshape(-1, 3)
        dens[i] = model.field.get_density(g)[0].reshape(2 * r + 1, 2 * r + 1)
# per-cell max over its 3x3x3 lattice points
d = dens.unsqueeze(0).unsqueeze(0)
cellmax = torch.nn.functional.max_pool3d(d, kernel_size=3, stride=2)[0, 0]   # (r, r, r)
rc = model.render_config; s = model.scene; N = rc.num_samples
if model.bounded:
    step = 2.0 * float(model.half_size.norm()) / N * torch.ones(r)
    stepz = step.view(1, 1, r)
else:
    zhi = torch.linspace(-1, 1, r + 1)[1:]                      # far edge of each z cell
    zhi = zhi.clamp(max=1 - 2 * s.near / s.far) if math.isfinite(s.far) else zhi.clamp(max=1 - 1e-6)
    tz = 2 * s.near / (1 - zhi)                                    # planar depth at that edge
    stepz = (tz ** 2 * (1 / s.near - 1 / min(s.far, 1e30)) / N).view(1, 1, r) * 1.5
alpha_cell = 1 - torch.exp(-cellmax * stepz)
occ = alpha_cell > alpha
if dilate:
    occ = torch.nn.functional.max_pool3d(occ[None, None].float(), 2 * dilate + 1, 1, dilate)[0, 0] > 0
if model.occupancy is not None and int(model.occupancy.updates) > 0:
    occ = occ & model.occupancy.occupied
print(f"grid {res}^3 alpha {alpha} dilate {dilate}: occupied {occ.float().mean():.3f} in {time.time()-t0:.1f} s")
dst = Path(f"/tmp/glf/occ_export_{run.name}")
shutil.rmtree(dst, ignore_errors=True); shutil.copytree(src, dst)
npz = dict(np.load(dst / "field.npz")); npz["occupancy"] = occ.numpy().astype(np.uint8)
np.savez_compressed(dst / "field.npz", **npz)
man = json.loads((dst / "field.json").read_text()); man["occupancy"] = {"array": "occupancy", "resolution": res, "occupied_fraction": float(occ.float().mean())}
(dst / "field.json").write_text(json.dumps(man))

W = H = 512
k0, w2c, w0, h0, where = _static_camera(src, run)
K = scale_intrinsics(k0, w0, h0, W, H) if (w0, h0) != (W, H) else k0
ref = _torch_renderer(model, s.near, s.far)(K, w2c, H, W)
for name, exp in (("no grid", src), ("grid", dst)):
    with GlFieldRenderer(load_field(exp), W, H) as g:
        g.render(K, w2c); ts = []
        for _ in range(5):
            t = time.perf_counter(); out = g.render(K, w2c); ts.append(time.perf_counter() - t)
    p = psnr(display_encode(ref["color"]), display_encode(out["color"]))
    print(f"{name:8s} {1e3*np.median(ts):7.1f} ms  PSNR vs torch {p:.1f} dB  max|dc| {np.abs(out['color']-ref['color']).max():.2e}")
