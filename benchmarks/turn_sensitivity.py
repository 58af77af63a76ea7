"""Does the preview MPC's model see what power before a turnaround does after it? Plant vs model.

Runs ``preview-mpc`` with the shipped delay-aware model in closed loop on the FE plant (in
process, as ``bench_preview.py``; on the uniform mesh, the one its models were learned on), as
``launch.py``'s controller node runs it: with the model's process record (its operating power at
laser-on) and the real-time iteration's preparation after each command.
``--before`` states before the chosen turnaround it copies the plant and replays the next
``--horizon`` commands twice from that copy: as applied, and with ``--delta-w`` added to the first
``--steps`` of them. The plant's change of the area and of the temperature ahead is set beside the
change the controller's own linearisation at that state predicts (``Γ Δv`` of the QP it solved,
:mod:`controller_node.preview_qp`).

Prints a table and the ratio of the model's to the plant's mean change of the area over the states
15–30 after the turn; with ``--json``, then, as the last line, JSON with ``state`` (states after the
snapshot, 1..H), ``states_after_turn``, ``plant_darea_pct``, ``model_darea_pct`` (change of the area,
% of the set point), ``plant_dt_ahead_k``, the mean changes over the states 15–30 after the turn
(``plant_darea_pct_turn_15_30``, ``model_darea_pct_turn_15_30``) and ``model_to_plant_ratio``,
the second over the first (1: the model sees the pre-turn power change as the plant does; null
without a change of the plant's), and the same over the states 1–7 after the turn, where the new pool
forms (``plant_darea_pct_turn_1_7``, ``model_darea_pct_turn_1_7``, ``model_to_plant_ratio_turn_1_7``).

Usage: ``python benchmarks/turn_sensitivity.py [--preset physical] [--scenario layer] [--turn 2]
[--before 12] [--steps 10] [--delta-w -20] [--model FILE] [--json]``
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_preview import measurement  # noqa: E402

from controller_node import ControllerSettings, make_controller  # noqa: E402
from controller_node.process import process_table  # noqa: E402
from fe_node.presets import DEFAULT, NAMES  # noqa: E402
from fe_node.scenarios import TRAINING_MESH, scenario  # noqa: E402
from fe_node.solver import ThermalModel  # noqa: E402
from gp_model.narx import NarxGPModel  # noqa: E402
from gp_model.shipped import default_model_path  # noqa: E402
from messages.config import build  # noqa: E402

SPEED_M_S = 0.8
LATE_WINDOW = (15, 30)
"""States after the turn (first and last) of ``model_to_plant_ratio``: the pool grown on the new track."""
EARLY_WINDOW = (1, 7)
"""States after the turn of ``model_to_plant_ratio_turn_1_7``: the new pool's first states, where the preview
MPC's dip after each turn sits."""


def window_means(plant_da: np.ndarray, model_da: np.ndarray, after: np.ndarray, first: int, last: int
                 ) -> tuple[float | None, float | None, float | None]:
    """Mean change of the area [% of the set point] of the plant and of the model over the states ``first`` to
    ``last`` after the turn (``after``: each state's index after it), and the model's over the plant's (None where
    the window holds no state, or the plant's mean is 0)."""
    band = (after >= first) & (after <= last)
    if not band.any():
        return None, None, None
    plant, model = float(plant_da[band].mean()), float(model_da[band].mean())
    return plant, model, (model / plant if plant else None)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--scenario", default="layer")
    parser.add_argument("--setpoint-mm2", type=float, default=0.063)
    parser.add_argument("--turn", type=int, default=2, help="which turnaround (0 = the first)")
    parser.add_argument("--before", type=int, default=12, help="states between the snapshot and the turn")
    parser.add_argument("--steps", type=int, default=10, help="commands changed after the snapshot")
    parser.add_argument("--delta-w", type=float, default=-20.0, help="change of those commands [W]")
    parser.add_argument("--model", type=Path,
                        help="delay-aware model file (default: the shipped model of the plant's layer)")
    parser.add_argument("--json", action="store_true", help="print the JSON record as the last line")
    args = parser.parse_args()
    sc = scenario(args.scenario, preset=args.preset, mesh=TRAINING_MESH)   # the plant the models were learned on
    plant = ThermalModel(sc.settings, sc.plan)
    sp = args.setpoint_mm2 * 1e-6
    model_path = args.model or default_model_path(sc.settings.powder_layer_m)
    settings = build(ControllerSettings, process_table(model_path), "[controller]", set_point_m2=sp)  # as launch.py
    ctrl = make_controller("preview-mpc", settings, NarxGPModel.load(model_path))
    horizon = ctrl.qp.horizon
    if not 1 <= args.steps <= horizon:
        parser.error(f"--steps must be in [1, {horizon}]")
    obs = plant.initial_observation()
    commands, turns, snapshot, prev_track = [], 0, None, obs.track
    while not plant.done:
        m = measurement(obs)
        if obs.track != prev_track:
            turns += 1
        prev_track = obs.track
        cmd, _ = ctrl.update(m)
        ctrl.prepare()                          # as the node after each command (the real-time iteration)
        to_turn = round(m.track_remaining_s / ctrl.model.sample_period_s) if m.next_track else None
        if snapshot is None and turns == args.turn and to_turn == args.before:
            snapshot, problem, start = copy.deepcopy(plant), ctrl.last_qp, len(commands)
        commands.append(cmd.power_w)
        obs = plant.step(cmd.power_w, SPEED_M_S)
    if snapshot is None:
        parser.error(f"the run has no turnaround {args.turn} with {args.before} states before it")
    delta = np.zeros(horizon)
    delta[:args.steps] = args.delta_w

    def replay(change: np.ndarray) -> np.ndarray:
        p = copy.deepcopy(snapshot)
        out = []
        for i in range(min(horizon, len(commands) - start)):
            o = p.step(commands[start + i] + change[i], SPEED_M_S)
            out.append((o.area_m2, o.t_ahead_k))
        return np.array(out)

    base, changed = replay(np.zeros(horizon)), replay(delta)
    n = base.shape[0]
    gamma = problem[0]
    plant_da = (changed[:, 0] - base[:, 0]) / sp * 100.0
    model_da = (gamma @ (delta / ctrl.qp.scale))[:n] * 100.0
    dt = changed[:, 1] - base[:, 1]
    after = np.arange(1, n + 1) - args.before       # 0: the first state of the next track
    plant_band, model_band, ratio = window_means(plant_da, model_da, after, *LATE_WINDOW)
    plant_early, model_early, ratio_early = window_means(plant_da, model_da, after, *EARLY_WINDOW)
    result = {
        "scenario": args.scenario, "turn": args.turn, "before": args.before, "steps": args.steps,
        "delta_w": args.delta_w, "state": list(range(1, n + 1)), "states_after_turn": after.tolist(),
        "plant_darea_pct": np.round(plant_da, 3).tolist(), "model_darea_pct": np.round(model_da, 3).tolist(),
        "plant_dt_ahead_k": np.round(dt, 2).tolist(),
        "plant_darea_pct_turn_15_30": None if plant_band is None else round(plant_band, 3),
        "model_darea_pct_turn_15_30": None if model_band is None else round(model_band, 3),
        "model_to_plant_ratio": None if ratio is None else round(ratio, 3),
        "plant_darea_pct_turn_1_7": None if plant_early is None else round(plant_early, 3),
        "model_darea_pct_turn_1_7": None if model_early is None else round(model_early, 3),
        "model_to_plant_ratio_turn_1_7": None if ratio_early is None else round(ratio_early, 3),
    }
    print("states after the turn:", " ".join(f"{a:6d}" for a in after[::2]))
    print("plant Δarea [% sp]:   ", " ".join(f"{x:6.2f}" for x in plant_da[::2]))
    print("model Δarea [% sp]:   ", " ".join(f"{x:6.2f}" for x in model_da[::2]))
    print("plant ΔT ahead [K]:   ", " ".join(f"{x:6.1f}" for x in dt[::2]))
    for (lo, hi), r in ((LATE_WINDOW, ratio), (EARLY_WINDOW, ratio_early)):
        print(f"model / plant, mean Δarea over the states {lo}-{hi} after the turn:",
              "n/a" if r is None else f"{r:.3f}")
    if args.json:
        print(json.dumps(result))


if __name__ == "__main__":
    main()
