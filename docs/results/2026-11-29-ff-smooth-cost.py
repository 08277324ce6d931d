"""Cost a step of RegNeRF's depth smoothness (``priors.smooth``, commit 3fdbfae) against one main batch.

``python docs/results/2026-11-29-ff-smooth-cost.py RUN N`` (from the repository root, at 3fdbfae): RUN a trained
static run, one torch thread; N steps each of (render 1024 train rays + backward) without and with the prior's
patches (4 of 8x8 from virtual cameras, render + depth_smoothness + backward), twice, alternating.
"""
import sys, time
import torch
from models.fields.data.select import load_run_views
from models.fields.losses import LOSS_TERMS, LossInputs, LossTerm
from models.fields.priors.smooth import SmoothPrior, SmoothState
from models.fields.train_static import load_model
from models.fields.trainer import all_rays

torch.set_num_threads(1)
run, n = sys.argv[1], int(sys.argv[2])
model = load_model(run)
train, _ = load_run_views(run)
rays = all_rays(train, model.scene)
state = SmoothState(train, SmoothPrior(enabled=True))
gen = torch.Generator().manual_seed(0)
idx = torch.randint(len(rays.origins), (1024,), generator=gen)

def step(with_prior):
    out = model.render_rays(rays.origins[idx], rays.directions[idx], rays.near[idx], rays.far[idx], jitter=True,
                            generator=gen)
    loss = (out.color - rays.color[idx]).square().mean()
    if with_prior:
        extras = state.extras(model, gen)
        loss = loss + 0.1 * LOSS_TERMS["depth_smoothness"](LossInputs(None, None, out, 0, LossTerm("depth_smoothness"), extras))
    model.zero_grad()
    loss.backward()

for w in (False, True, False, True):
    t = time.perf_counter()
    for _ in range(n):
        step(w)
    print(f"{'with' if w else 'without'} smooth: {1000 * (time.perf_counter() - t) / n:.1f} ms/step")
