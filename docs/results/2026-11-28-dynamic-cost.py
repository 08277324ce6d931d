"""Where a dynamic field's training step goes: torch profiler and CPU time per step, one torch thread.

``python docs/results/2026-11-28-dynamic-cost.py MODE VARIANT RIG_DIR OUT.json [--rays N]`` (from the repository
root), MODE ``profile``, ``cpu`` or ``pair``, VARIANT ``kplanes``, ``default`` (derf, canonical time, flow prior),
``sfderf`` (``--no-field.canonical-time``) or ``noprior`` (default without the prior). Trains on the rig as
``interleave train dynamic --train-cameras cam0,cam1,cam3 --test-cameras cam2`` does, or on a D-NeRF scene's train
split read at ``--downscale N`` (default config otherwise; ``--rays`` sets the prior's matched pairs a step) for
131 / 201 steps in a temporary folder, and writes:

- ``profile``: the torch profiler over steps 100-130 (after the occupancy grid's warm-up), each op's total and
  self time and calls, with the forward regions labelled (``## render``, ``## motion_field``,
  ``## canonical_density``, ``## canonical_colour``, ``## kplanes_density``, ``## prior_rays``, ``## losses``)
  and ``## backward`` / ``## optimizer``, and ``parts_ms``: the ops' self time a step summed by part of the
  step (:func:`part_of`; the profiler's times are wall times, so they match the CPU time on a quiet machine
  only);
- ``cpu``: process CPU time and wall time per step over steps 100-200 (CPU time: less sensitive to other
  jobs on a shared machine than wall time);
- ``pair``: VARIANT is a comma-separated list of variants, trained in lock step in one process (one thread
  each, a token passed at every step, so only one runs at a time and all see the same load), and the thread
  CPU time per step over steps 100-200 of each, with its ratio to the first
  (``docs/results/2026-11-28-dynamic-cost-2.md``). A variant may carry config overrides after colons, a
  dotted path into ``DynamicTrainConfig`` (tuples with ``+``): ``default:field.motion.hidden=16``,
  ``default:field.motion.resolutions=16+32``. ``VARIANT@reference`` (``default@reference``, in any mode) trains
  with the training step of the code before the fourth cost pass (:data:`REFERENCE`,
  ``docs/results/2026-11-29-dynamic-cost-4.md``), so that the old and the new step run in one lock step.

``python docs/results/2026-11-28-dynamic-cost.py lookups - - OUT.json`` times the plane-grid builds instead
(no training): a hex lookup of 59k points at the default's three scales (space and time planes, forward and
backward) with the strided grids of ab37b71 (a gather by index, then a permute) against ``plane_grid`` /
``time_grid``, with and without the coordinates' gradient, and ``flow_l1`` against the mean of the mask's
gather; thread CPU time, the variants interleaved, the middle half of 12 repeats averaged.

The regions are labelled by wrapping the methods in ``torch.profiler.record_function``; the step boundaries
come from ``train_dynamic``'s ``extras_fn`` hook (called after the rendering of each step).
"""
import argparse
import dataclasses
import json
import os
import tempfile
import threading
import time
from typing import Optional

import torch
from torch.profiler import ProfilerActivity, profile, record_function

import models.fields.components.encodings as enc
import models.fields.dynamic.model as dm
import models.fields.priors.flow as pf
import models.fields.train_dynamic as td
import models.fields.trainer as tr
from models.fields.data.select import detect_dynamic_dataset, select_dynamic_views
from models.fields.train_dynamic import DynamicTrainConfig, choose_dynamic_priors, train_dynamic

REGIONS = [(dm.MotionField, "forward", "## motion_field"),
           (dm.CanonicalField, "get_density", "## canonical_density"),
           (dm.CanonicalField, "get_outputs", "## canonical_colour"),
           (dm.KPlanesField, "_density", "## kplanes_density"),
           (pf.SparseFlowState, "extras", "## prior_rays"), (tr, "assemble_loss", "## losses"),
           (dm.DynamicFieldModel, "render_placed", "## render"), (torch.Tensor, "backward", "## backward"),
           (torch.optim.Adam, "step", "## optimizer")]

#: Threads training a ``VARIANT@reference`` variant: they run the step as the code before 2026-11-29's fourth
#: cost pass did (``docs/results/2026-11-29-dynamic-cost-4.md``): every MLP as ``nn.Sequential`` (autograd's
#: weight gradient of the first layer) and the prior's matched rays in a ``render_rays`` call of their own
#: after the batch's (``SparseFlowState.extras``), not in one pass with it.
REFERENCE = threading.local()


def _install_reference_switch() -> None:
    fast_mlp, fast_step = enc.MLP.forward, td.DynamicKind.render_step

    def mlp_forward(self, x):
        return self.net(x) if getattr(REFERENCE, "on", False) else fast_mlp(self, x)

    def render_step(self, priors, model, batch, inputs, step, generator):
        if not getattr(REFERENCE, "on", False):
            return fast_step(self, priors, model, batch, inputs, step, generator)
        outputs = model.render_rays(batch.origins, batch.directions, batch.near, batch.far, inputs, jitter=True,
                                    generator=generator)
        return outputs, (priors.extras(model, generator) if priors is not None else {})

    enc.MLP.forward, td.DynamicKind.render_step = mlp_forward, render_step


ACTIVATIONS = {"aten::clamp_min", "aten::threshold_backward", "aten::tanh", "aten::tanh_backward", "aten::sigmoid",
               "aten::sigmoid_backward", "aten::relu"}


def part_of(event) -> str:
    """The part of a step a profiled op belongs to (``profile`` mode's ``parts_ms``): the plane lookups by
    their planes' channels (8: the canonical field's or K-Planes', 4: the motion field's), the MLPs' matmuls
    and activations, the plane features' products, concatenations, gathers and scatters, the optimizer's and
    the losses' forward ops (by their region), and the rest (small elementwise ops, Python and dispatch)."""
    name, shapes = event.name, event.input_shapes
    parent = event.cpu_parent
    while parent is not None:
        if parent.name in ("## optimizer", "## losses"):
            return parent.name[3:]
        parent = parent.cpu_parent
    if name in ("aten::grid_sampler_2d", "aten::grid_sampler_2d_backward"):
        channels = shapes[1 if name.endswith("backward") else 0][1]
        return f"plane lookups, {channels} channels, {'backward' if name.endswith('backward') else 'forward'}"
    if name in ("aten::mm", "aten::addmm"):
        return "MLP matmuls"
    if name in ACTIVATIONS:
        return "MLP activations"
    if name == "aten::mul" and len(shapes) == 2 and len(shapes[0]) == 2 and shapes[0][0] in (4, 8) \
            and shapes[0] == shapes[1]:
        return "plane feature products"
    if name in ("aten::cat", "aten::stack"):
        return "cat / stack"
    if name in ("aten::index", "aten::_index_put_impl_", "aten::nonzero", "aten::gather", "aten::index_select"):
        return "gathers / scatters"
    return "other"


def label(owner, name: str, text: str) -> None:
    inner = getattr(owner, name)

    def wrapped(*args, **kwargs):
        with record_function(text):
            return inner(*args, **kwargs)

    setattr(owner, name, wrapped)


def config_for(variant: str, rays: int) -> DynamicTrainConfig:
    cfg = DynamicTrainConfig()
    if variant == "kplanes":
        cfg = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, kind="kplanes"))
    elif variant == "sfderf":
        cfg = dataclasses.replace(cfg, field=dataclasses.replace(cfg.field, canonical_time=False))
    cfg = choose_dynamic_priors(cfg, "" if variant == "noprior" else None)
    if rays:
        flow = dataclasses.replace(cfg.priors.flow, rays=rays)
        cfg = dataclasses.replace(cfg, priors=dataclasses.replace(cfg.priors, flow=flow))
    return cfg


def override(cfg, path: str, text: str):
    """``cfg`` with the dotted field ``path`` set from ``text`` (parsed by the current value's type)."""
    head, _, rest = path.partition(".")
    current = getattr(cfg, head)
    if rest:
        return dataclasses.replace(cfg, **{head: override(current, rest, text)})
    if isinstance(current, tuple):
        value = tuple(type(current[0])(v) for v in text.split("+"))
    elif isinstance(current, bool):
        value = text.lower() in ("1", "true", "yes")
    else:
        value = type(current)(text)
    return dataclasses.replace(cfg, **{head: value})


def spec_config(spec: str, rays: int) -> DynamicTrainConfig:
    """``VARIANT[@reference][:path=value...]`` -> its config."""
    variant, *pairs = spec.split(":")
    variant = variant.split("@")[0]
    cfg = config_for(variant, rays)
    for pair in pairs:
        path, _, text = pair.partition("=")
        cfg = override(cfg, path, text)
    return cfg


def lock_step(train, cfgs: list, first: int, last: int, references: Optional[list] = None) -> list[float]:
    """Train ``cfgs`` in lock step (threads passing a token after each step's render); each one's thread CPU
    seconds over steps ``first`` .. ``last`` (the steps between the hook calls, the waits excluded).
    ``references[i]``: config i runs the reference step (:data:`REFERENCE`)."""
    references = references or [False] * len(cfgs)
    if any(references):
        _install_reference_switch()
    turn, done = [0], set()
    cond = threading.Condition()
    cpu = [0.0] * len(cfgs)
    resumed: list = [None] * len(cfgs)

    def next_turn(i: int) -> int:
        j = (i + 1) % len(cfgs)
        while j in done and j != i:
            j = (j + 1) % len(cfgs)
        return j

    def run(i: int) -> None:
        def hook(model, batch, outputs, step):
            if resumed[i] is not None and first < step <= last:
                cpu[i] += time.thread_time() - resumed[i]
            with cond:
                turn[0] = next_turn(i)
                cond.notify_all()
                cond.wait_for(lambda: turn[0] == i)
            resumed[i] = time.thread_time()
            return {}

        REFERENCE.on = references[i]
        with cond:
            cond.wait_for(lambda: turn[0] == i)
        try:
            with tempfile.TemporaryDirectory() as tmp:
                train_dynamic(train, cfgs[i], tmp, progress=False, device="cpu", extras_fn=hook)
        finally:
            with cond:
                done.add(i)
                turn[0] = next_turn(i)
                cond.notify_all()

    threads = [threading.Thread(target=run, args=(i,)) for i in range(len(cfgs))]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    return cpu


def strided_grids(coords, times):
    """The grids as ab37b71 built them (the oracle of the lookups mode): a gather by index, then a permute."""
    grid = coords[:, torch.tensor([[0, 1], [0, 2], [1, 2]])].permute(1, 0, 2).unsqueeze(1)
    return grid, torch.stack([coords, times[:, None].expand(-1, 3)], dim=-1).permute(1, 0, 2).unsqueeze(1)


def time_lookups(repeats: int = 12) -> dict:
    """Thread CPU ms of the lookups and ``flow_l1`` variants (see the module docstring)."""
    from models.fields.components.encodings import plane_grid, read_planes
    from models.fields.dynamic.model import time_grid
    from models.fields.losses import LOSS_TERMS, LossInputs, LossTerm
    g = torch.Generator().manual_seed(0)
    n = 59000
    coords = torch.rand(n, 3, generator=g) * 2 - 1
    times = torch.rand(n, generator=g) * 2 - 1
    spatial = [torch.rand(3, 8, r, r, generator=g).requires_grad_() for r in (32, 64, 128)]
    temporal = [torch.rand(3, 8, 12, r, generator=g).requires_grad_() for r in (32, 64, 128)]
    weights = torch.rand(24, n, generator=g)
    evaluated = torch.rand(1024, 64, generator=g) < 0.9
    flow = torch.randn(1024, 64, 3, generator=g).requires_grad_()

    def lookup(build, grad: bool):
        def run():
            c = coords.clone().requires_grad_(grad)
            grid, tgrid = build(c, times)
            out = torch.cat([read_planes(s, grid) * read_planes(t, tgrid) for s, t in zip(spatial, temporal)])
            (out * weights).sum().backward()
        return run

    def flow_term(gathered: bool):
        def run():
            f = flow * evaluated[..., None]
            if gathered:
                loss = f[evaluated].abs().sum(dim=-1).mean()
            else:
                outputs = type("O", (), {"flow": f, "evaluated": evaluated, "color": f})()
                loss = LOSS_TERMS["flow_l1"](LossInputs(None, None, outputs, 0, LossTerm("flow_l1"), {}))
            loss.backward()
        return run

    runs = {"lookup_strided_grids_coords_grad": lookup(strided_grids, True),
            "lookup_plane_grid_coords_grad": lookup(lambda c, t: (plane_grid(c), time_grid(c, t)), True),
            "lookup_strided_grids": lookup(strided_grids, False),
            "lookup_plane_grid": lookup(lambda c, t: (plane_grid(c), time_grid(c, t)), False),
            "flow_l1_gathered_mean": flow_term(True), "flow_l1": flow_term(False)}
    times_ms: dict = {name: [] for name in runs}
    for _ in range(repeats):
        for name, run in runs.items():
            start = time.thread_time()
            run()
            times_ms[name].append(1000 * (time.thread_time() - start))
    quarter = repeats // 4
    return {name: sum(sorted(v)[quarter:repeats - quarter]) / (repeats - 2 * quarter) for name, v in times_ms.items()}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["profile", "cpu", "pair", "lookups"])
    parser.add_argument("variant", help="kplanes, default, sfderf or noprior, with :path=value overrides; pair: a "
                                        "comma-separated list of them")
    parser.add_argument("rig", help="an rgbd-rig (cam0, cam1, cam3 train) or a D-NeRF scene (its train split)")
    parser.add_argument("out")
    parser.add_argument("--downscale", type=int, default=0, help="D-NeRF: read the images at 1/N (lego: 8)")
    parser.add_argument("--rays", type=int, default=0)
    args = parser.parse_args()
    torch.set_num_threads(1)
    if args.mode == "lookups":
        result = {"thread_cpu_ms": time_lookups(), "load_1min_end": os.getloadavg()[0]}
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        print(json.dumps(result))
        return
    specs = args.variant.split(",")
    for spec in specs:
        if spec.split(":")[0].split("@")[0] not in ("kplanes", "default", "sfderf", "noprior") or (
                spec.split(":")[0].count("@") and not spec.split(":")[0].endswith("@reference")):
            parser.error(f"unknown variant {spec!r}")
    if args.mode != "pair" and len(specs) > 1:
        parser.error("several variants: pair mode only")
    first, last = (100, 130) if args.mode == "profile" else (100, 200)
    cfgs = [spec_config(spec, args.rays) for spec in specs]
    if detect_dynamic_dataset(args.rig) == "dnerf":
        train, _, record = select_dynamic_views("dnerf", args.rig, args.downscale or cfgs[0].downscale)
    else:
        train, _, record = select_dynamic_views("rig", args.rig, cfgs[0].downscale,
                                                train_cameras=["cam0", "cam1", "cam3"], test_cameras=["cam2"])
    cfgs = [dataclasses.replace(cfg, downscale=record["downscale"], steps=last + 1) for cfg in cfgs]
    if args.mode == "pair":
        cpu = lock_step(train, cfgs, first, last, [spec.split(":")[0].endswith("@reference") for spec in specs])
        ms = [1000 * c / (last - first) for c in cpu]
        result = {"variants": specs, "steps": [first, last], "cpu_ms_per_step": ms,
                  "ratio_to_first": [m / ms[0] for m in ms], "load_1min_end": os.getloadavg()[0]}
        with open(args.out, "w") as f:
            json.dump(result, f, indent=1)
        print(json.dumps(result))
        return
    cfg = cfgs[0]
    if specs[0].split(":")[0].endswith("@reference"):
        _install_reference_switch()
        REFERENCE.on = True
    if args.mode == "profile":
        for owner, name, text in REGIONS:
            label(owner, name, text)
    marks: dict = {}

    def hook(model, batch, outputs, step):
        if step in (first, last):
            marks[step] = (time.process_time(), time.perf_counter())
        if args.mode == "profile" and step == first:
            marks["profiler"] = profile(activities=[ProfilerActivity.CPU], record_shapes=True)
            marks["profiler"].__enter__()
        if args.mode == "profile" and step == last:
            marks["profiler"].__exit__(None, None, None)
        return {}

    with tempfile.TemporaryDirectory() as tmp:
        train_dynamic(train, cfg, tmp, progress=False, device="cpu", extras_fn=hook)
    steps = last - first
    result = {"variant": args.variant, "prior_rays": cfg.priors.flow.rays if cfg.priors.flow.enabled else 0,
              "steps": [first, last], "cpu_ms_per_step": 1000 * (marks[last][0] - marks[first][0]) / steps,
              "wall_ms_per_step": 1000 * (marks[last][1] - marks[first][1]) / steps}
    if args.mode == "profile":
        result["events"] = {e.key: {"total_ms": e.cpu_time_total / 1000, "self_ms": e.self_cpu_time_total / 1000,
                                    "calls": e.count} for e in marks["profiler"].key_averages()}
        parts: dict = {}
        for event in marks["profiler"].events():
            part = part_of(event)
            parts[part] = parts.get(part, 0.0) + event.self_cpu_time_total / 1000 / (last - first)
        result["parts_ms"] = dict(sorted(parts.items(), key=lambda kv: -kv[1]))
    with open(args.out, "w") as f:
        json.dump(result, f, indent=1)
    print(json.dumps({k: v for k, v in result.items() if k != "events"}, indent=1))


if __name__ == "__main__":
    main()
