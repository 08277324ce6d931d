import sys, torch, numpy as np
from pathlib import Path
from models.fields.train_static import load_model
from models.fields.components.sampling import camera_rays, sample_intervals
from tools.bench_fields import _static_camera
run = Path(sys.argv[1]); model = load_model(run).eval(); s = model.scene; rc = model.render_config
k0, w2c, w0, h0, where = _static_camera(run / "export", run)
o, d = camera_rays(torch.as_tensor(k0, dtype=torch.float32), torch.as_tensor(w2c, dtype=torch.float32), h0, w0)
g = torch.Generator().manual_seed(0); pick = torch.randint(o.shape[0], (4000,), generator=g)
o, d = o[pick], d[pick]
near = torch.full((o.shape[0],), float(s.near)); far = torch.full((o.shape[0],), float(s.far))
t0, t1 = model.ray_bounds(o, d, near, far)
t, delta = sample_intervals(t0, t1, rc.num_samples, spacing="linear" if model.bounded else "disparity")
p = o[:, None] + t[..., None] * d[:, None]
c = model.contract(p)
with torch.no_grad():
    sig = model.field.get_density(c.clamp(-1, 1).reshape(-1, 3))[0].reshape(t.shape)
inside = (c.abs() <= 1).all(-1)
sig = torch.where(inside, sig, torch.zeros_like(sig))
tau = sig * delta * d.norm(dim=-1, keepdim=True)
alpha = 1 - torch.exp(-tau)
T = torch.exp(-torch.cumsum(torch.cat([torch.zeros_like(tau[:, :1]), tau[:, :-1]], 1), 1))
w = T * alpha
print("near far", s.near, s.far, "N", rc.num_samples)
print("alpha quantiles per sample:", np.quantile(alpha.numpy(), [0.1, 0.25, 0.5, 0.75, 0.9]).round(5))
print("per-sample-index median alpha:", np.median(alpha.numpy(), 0).round(4)[::4])
print("per-sample-index median T:", np.median(T.numpy(), 0).round(4)[::4])
print("per-sample-index mean w:", w.numpy().mean(0).round(4)[::4])
print("t per index (ray 0):", t[0].numpy().round(2)[::4])
print("final T quantiles:", np.quantile(T[:, -1].numpy() * (1 - alpha[:, -1].numpy()), [0.1, 0.5, 0.9]))
