"""A monocular cut of an rgbd-rig trained and scored as ``2026-12-01-dynamic-monocular.py train`` does, with the
time-smoothness choice of ``interleave train dynamic`` (``choose_time_smoothness``) and optional loss weights:

    PYTHONPATH=. python docs/results/2026-12-01-monocular-time-smoothness.py RIG RUN STEPS SEED [NAME=W,...]

``NAME=W`` are ``--loss`` weights (``time_smoothness=1e-3``: the weight before this page); a weight given for
``time_smoothness`` is explicit, as on the command line. The canonical field is the tri-planes
(``field.canonical_time=false``), as every monocular cut of the earlier pages. Writes ``RUN/scores.json``.
"""
from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

from models.fields.train_dynamic import choose_time_smoothness
from models.fields.trainer import apply_loss_weights

_spec = importlib.util.spec_from_file_location("monocular", Path(__file__).with_name("2026-12-01-dynamic-monocular.py"))
monocular = importlib.util.module_from_spec(_spec)
_spec.loader.exec_module(monocular)


def main(rig: str, run: str, steps: str, seed: str, losses: str = "") -> None:
    specs = [s for s in losses.split(",") if s]
    explicit = any(s.partition("=")[0] == "time_smoothness" for s in specs)
    choose_canonical_time = monocular.choose_canonical_time

    def choose(config, views, explicit_canonical=False):
        config = choose_canonical_time(apply_loss_weights(config, specs), views, explicit=explicit_canonical)
        return choose_time_smoothness(config, views, explicit=explicit)

    monocular.choose_canonical_time = lambda config, views, explicit=False: choose(config, views, explicit)
    monocular.train(rig, run, steps, seed, "field.canonical_time=false")


if __name__ == "__main__":
    main(*sys.argv[1:])
