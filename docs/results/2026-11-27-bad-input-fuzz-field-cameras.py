"""The GL field renderer against its numpy oracle (render_field) on hard cameras, 48x32. Usage:
python docs/results/2026-11-27-bad-input-fuzz-field-cameras.py FIELD_EXPORT_DIR"""
import sys, warnings
import numpy as np
warnings.simplefilter("ignore")
from engine.fields.render import load_field, render_field
from engine.fields.gl import GlFieldRenderer
a = load_field(sys.argv[1])
W, H = 48, 32
def look_at(eye, target=np.zeros(3), up=np.array([0, 0, 1.0])):
    f = target - eye; f /= np.linalg.norm(f)
    r = np.cross(f, up); 
    if np.linalg.norm(r) < 1e-9: r = np.cross(f, np.array([0, 1.0, 0]))
    r /= np.linalg.norm(r); u = np.cross(f, r)
    R = np.stack([r, u, f]); T = np.eye(4); T[:3, :3] = R; T[:3, 3] = -R @ eye; return T
cases = {
  "normal": (look_at(np.array([4.0, 0, 1.0])), 60.0, (0.0, W / 2, H / 2)),
  "inside box centre": (look_at(np.array([0.01, 0.02, 0.03]), np.array([1.0, 0.0, 0.0])), 40.0, (0.0, W / 2, H / 2)),
  "on box face": (look_at(np.array([1.4512, 0, 0.2])), 40.0, (0.0, W / 2, H / 2)),
  "far 1e3": (look_at(np.array([1000.0, 0, 0])), 5000.0, (0.0, W / 2, H / 2)),
  "looking away": (look_at(np.array([4.0, 0, 0]), np.array([8.0, 0, 0])), 40.0, (0.0, W / 2, H / 2)),
  "tiny fov": (look_at(np.array([4.0, 0, 1.0])), 1e5, (0.0, W / 2, H / 2)),
  "huge fov": (look_at(np.array([4.0, 0, 1.0])), 1.0, (0.0, W / 2, H / 2)),
  "skew K": (look_at(np.array([4.0, 0, 1.0])), 60.0, (30.0, W / 2, H / 2)),
  "off-centre pp": (look_at(np.array([4.0, 0, 1.0])), 60.0, (0.0, -200.0, 500.0)),
  "axis-aligned ray": (look_at(np.array([0.0, 0, 5.0]), np.zeros(3), np.array([0, 1.0, 0])), 60.0, (0.0, W / 2, H / 2)),
}
with GlFieldRenderer(a, W, H) as r:
    for name, (T, f, (skew, cx, cy)) in cases.items():
        K = np.array([[f, skew, cx], [0, f, cy], [0, 0, 1.0]])
        try:
            ref = render_field(a, K, T, H, W)
            got = r.render(K, T)
        except Exception as e:
            print(name, "ERR", type(e).__name__, str(e)[:100]); continue
        dc = np.abs(got["color"] - ref["color"]).max()
        fin = np.isfinite(ref["depth"]) == np.isfinite(got["depth"])
        both = np.isfinite(ref["depth"]) & np.isfinite(got["depth"])
        dd = np.abs(got["depth"][both] - ref["depth"][both]).max() if both.any() else 0
        print(f"{name:20s} colour max diff {dc:.2e}  depth inf agree {fin.mean():.4f}  depth max diff {dd:.2e}  nan {np.isnan(got['color']).any()} {np.isnan(ref['color']).any()} opacity {ref['opacity'].mean():.3f}")
