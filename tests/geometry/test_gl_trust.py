"""flow2d's trust rules on the GPU (engine/geometry/backends/gl/trust.py) against their oracle,
``engine.predict.dis.trusted_motion`` with ``engine.geometry.seen_before``: the same pixels keep their motion
on >= 99.9 % of the pixels (a window mean within float rounding of the margin may decide either way), and
the kept motion is the estimate itself."""
from __future__ import annotations

import numpy as np
import pytest

from engine import geometry
from engine.core.errors import InputError
from engine.geometry.backends import gl as glb
from engine.predict.dis import (CONFIDENCE_MARGIN, CONFIDENCE_WINDOW, SMALL_MOTION, dis_calc, dis_estimator, luma8,
                                trusted_motion)
from tests.random_scenes import moving_cameras, random_scene

if not glb.available():
    pytest.skip("no EGL context with compute shaders", allow_module_level=True)


def trust():
    from engine.geometry.backends.gl.trust import GlTrust

    return GlTrust(SMALL_MOTION, CONFIDENCE_MARGIN, CONFIDENCE_WINDOW)


def both(luma_n, target, flow, depth, k, t_n, t_prev, prev_size):
    seen = geometry.seen_before(depth, k, t_n, k, t_prev, prev_size)
    ref = flow.copy()
    ref[~trusted_motion(luma_n, target, flow, seen)] = 0.0
    gpu = trust().trusted(luma_n, target, flow, depth, k, t_n, k, t_prev, prev_size)
    return ref, gpu, seen


@pytest.mark.parametrize("size", [(48, 64), (5, 3), (1, 1), (40, 300)])
def test_matches_the_cpu_rules(size):
    h, w = size
    rng = np.random.default_rng(h + w)
    color, depth = random_scene(rng, max(h, 4), max(w, 4), sky=0.2)
    color, depth = color[:h, :w], depth[:h, :w]
    k, t_prev, t_n = moving_cameras(rng, h, w, angle=0.05, shift=0.3)
    luma_n = luma8(color)
    target = luma8(np.clip(color + rng.normal(0, 0.03, color.shape).astype(np.float32), 0, 1))
    flow = rng.normal(0, 1.5, (h, w, 2)).astype(np.float32)  # half the pixels under a pixel: the margin decides
    flow[: h // 3] *= 8.0  # large motion: kept wherever seen
    ref, gpu, seen = both(luma_n, target, flow, depth, k, t_n, t_prev, (h, w))
    assert gpu.shape == flow.shape and np.isfinite(gpu).all()
    same = (ref == gpu).all(axis=-1)
    assert same.mean() >= 0.999 if h * w >= 1000 else same.all()
    assert ((gpu == flow).all(-1) | (gpu == 0).all(-1)).all()  # kept as estimated, or zeroed
    if h * w >= 1000:
        assert 0 < seen.mean() < 1  # both rules are exercised


def test_a_dis_flow_of_a_moving_square():
    rng = np.random.default_rng(3)
    h, w = 64, 96
    base = rng.uniform(0, 1, (h, w + 8, 3)).astype(np.float32)
    color_prev, color_n = base[:, :w].copy(), base[:, :w].copy()
    color_n[20:40, 30:50] = base[20:40, 26:46]  # a square moved 4 px right
    luma_n, target = luma8(color_n), luma8(color_prev)
    flow = dis_calc(dis_estimator("medium"), luma_n, target)
    depth = np.full((h, w), 5.0, np.float32)
    k, t = moving_cameras(rng, h, w)[0], np.eye(4)
    ref, gpu, _ = both(luma_n, target, flow, depth, k, t, t, (h, w))
    assert ((ref == gpu).all(-1)).mean() >= 0.999


def test_bad_thresholds_are_refused():
    from engine.geometry.backends.gl.trust import GlTrust

    with pytest.raises(InputError):
        GlTrust(1.0, 1.0, 8)
