"""Does the preview MPC's model respond to a power step as the plant does, over the power range? Plant vs model.

For each base power p of ``--powers`` the FE plant (in process, ``--preset``) scans one track of the
``layer`` scenario at p for ``--settle`` steps, then from a copy of it twice for ``--after`` steps: at p,
and at p + ``--delta-w``. The plant's change of the area at the end is its response to the step. The
delay-aware model predicts both continuations from the same state (:meth:`gp_model.narx.NarxGPModel.rollout`:
the applied powers as the plan, T ahead measured up to the step and forecast after it); its change of the
predicted area at the end is the model's response. On one track the plant is at steady state before
the step, so the two are the steady-state gains of the area in power.

Prints a table; with ``--json``, then, as the last line, JSON with ``cases`` (per base power:
``power_w``, ``plant_darea_pct``, ``model_darea_pct``, ``model_to_plant_ratio``) and
``ratio_min``, ``ratio_max`` over the cases (1: the model's gain is the plant's).

Usage: ``python benchmarks/power_sensitivity.py [--preset physical] [--powers 120 180 240 300] [--delta-w 30]
[--settle 150] [--after 80] [--model FILE] [--json]``
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fe_node.presets import DEFAULT, NAMES  # noqa: E402
from fe_node.scenarios import TRAINING_MESH, scenario  # noqa: E402
from fe_node.solver import ThermalModel  # noqa: E402
from gp_model.narx import NarxGPModel, RunSeries  # noqa: E402
from gp_model.shipped import default_model_path  # noqa: E402
from messages.types import LASER_POWER_MAX_W  # noqa: E402

SPEED_M_S = 0.8


def plant_run(plant: ThermalModel, powers_w: list[float]) -> list:
    """The plant's observations over ``powers_w`` (one step each), in place."""
    return [plant.step(p, SPEED_M_S) for p in powers_w]


def series(name: str, states: list, sample_period_s: float) -> RunSeries:
    """A run of observations (the first the initial one) as the model reads it."""
    return RunSeries(name, np.array([s.area_m2 for s in states]), np.array([s.t_ahead_k for s in states]),
                     np.array([s.power_w for s in states]), np.zeros(len(states), dtype=int), sample_period_s,
                     speed_m_s=SPEED_M_S)


def case(preset: str, model: NarxGPModel, power_w: float, delta_w: float, settle: int, after: int) -> dict:
    """Plant's and model's change of the area [% of the unstepped one] ``after`` steps after a step of
    ``delta_w`` from ``power_w``."""
    sc = scenario("layer", preset=preset, n_tracks=1, mesh=TRAINING_MESH)   # the plant the models were learned on
    plant = ThermalModel(sc.settings, sc.plan)
    states = [plant.initial_observation(), *plant_run(plant, [power_w] * settle)]
    twin = copy.deepcopy(plant)
    flat = states + plant_run(plant, [power_w] * after)
    stepped = states + plant_run(twin, [power_w + delta_w] * after)
    period = sc.settings.dt_s
    end = [s[-1].area_m2 for s in (flat, stepped)]
    predicted = [model.rollout(series(name, run, period), settle, after)[-1]
                 for name, run in (("flat", flat), ("stepped", stepped))]
    plant_pct, model_pct = (100.0 * (b / a - 1.0) for a, b in (end, predicted))
    return {"power_w": power_w, "plant_darea_pct": round(plant_pct, 3), "model_darea_pct": round(model_pct, 3),
            "model_to_plant_ratio": round(model_pct / plant_pct, 3) if plant_pct else None}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--powers", type=float, nargs="+", default=[120.0, 180.0, 240.0, 300.0],
                        help="base powers [W] (default %(default)s)")
    parser.add_argument("--delta-w", type=float, default=30.0, help="the step [W] (default %(default)s)")
    parser.add_argument("--settle", type=int, default=150, help="steps at the base power (default %(default)s)")
    parser.add_argument("--after", type=int, default=80, help="steps after the step (default %(default)s)")
    parser.add_argument("--model", type=Path, help="delay-aware model file (default: the shipped model of the plant)")
    parser.add_argument("--json", action="store_true", help="print the JSON record as the last line")
    args = parser.parse_args()
    if not all(0 <= p and p + args.delta_w <= LASER_POWER_MAX_W for p in args.powers):
        parser.error(f"--powers and --delta-w: every power and power + step must lie in [0, {LASER_POWER_MAX_W:g}] W")
    if args.settle < 1 or args.after < 1:
        parser.error("--settle and --after must be >= 1")
    model = NarxGPModel.load(args.model or default_model_path(scenario("layer", preset=args.preset).settings
                                                                 .powder_layer_m))
    cases = [case(args.preset, model, p, args.delta_w, args.settle, args.after) for p in args.powers]
    print(f"{'power W':>8s} {'plant %':>8s} {'model %':>8s} {'ratio':>6s}")
    for c in cases:
        ratio = "" if c["model_to_plant_ratio"] is None else f"{c['model_to_plant_ratio']:.3f}"
        print(f"{c['power_w']:8.0f} {c['plant_darea_pct']:8.2f} {c['model_darea_pct']:8.2f} {ratio:>6s}")
    ratios = [c["model_to_plant_ratio"] for c in cases if c["model_to_plant_ratio"] is not None]
    record = {"preset": args.preset, "delta_w": args.delta_w, "settle": args.settle, "after": args.after,
              "cases": cases, "ratio_min": min(ratios, default=None), "ratio_max": max(ratios, default=None)}
    if args.json:
        print(json.dumps(record))


if __name__ == "__main__":
    main()
