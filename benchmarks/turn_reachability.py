"""How close can a laser power profile hold the pool through a turnaround? A profile optimised on the FE plant.

Runs ``preview-mpc`` with the shipped delay-aware model in closed loop on the default plant (in process, with the
model's process record, the mesh and the real-time iteration's preparation as the nodes of ``launch.py``: its
commands to 1e-11 W) and copies the plant ``--before`` states before the chosen turnaround. From that copy it
optimises the next ``--free`` commands (within the controller's power bounds; the commands after them stay as the MPC
applied them) on copies of the plant itself: L-BFGS-B on forward differences of ``--eps-w``, at most ``--iterations``
iterations, from the MPC's own commands. The cost over the ``--window`` states after the copy is ``mean(e²) + w ·
mean(max(0, e − o)² + max(0, −u − e)²)``, ``e`` the area error [% of the set point], ``o``/``u`` the ``--over-
pct``/``--under-pct`` band and ``w`` ``--band-weight``.

The optimum is local: the profile is one the plant admits, so its over / under is a level that some open-loop power
reaches at that turn, not a bound on every controller. Beside it, the MPC's own over / under on the same states.

Prints a table; with ``--json``, then, as the last line, JSON with ``turn``, ``before``, ``window_states``,
``states_after_turn``, ``mpc_power_w``, ``profile_power_w`` (the window's commands), ``mpc_error_pct``,
``profile_error_pct`` (area error per state), ``mpc_over_pct``, ``mpc_under_pct``, ``mpc_rms_pct``,
``profile_over_pct``, ``profile_under_pct``, ``profile_rms_pct``, ``iterations`` and ``plant_runs``.

Usage: ``python benchmarks/turn_reachability.py [--preset physical] [--scenario layer] [--turn 1] [--before 6]
[--free 28] [--window 38] [--iterations 9] [--json]``
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
from pathlib import Path

import numpy as np
from scipy.optimize import minimize

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from bench_preview import measurement  # noqa: E402

from controller_node import ControllerSettings, make_controller  # noqa: E402
from controller_node.process import process_table  # noqa: E402
from fe_node.node import plant_model  # noqa: E402
from fe_node.presets import DEFAULT, NAMES  # noqa: E402
from fe_node.scenarios import scenario  # noqa: E402
from gp_model.narx import NarxGPModel  # noqa: E402
from gp_model.shipped import default_model_path  # noqa: E402
from messages.config import build  # noqa: E402


def band_cost(error_pct: np.ndarray, over_pct: float, under_pct: float, weight: float) -> float:
    """``mean(e²) + weight · mean(max(0, e − over)² + max(0, −under − e)²)`` of area errors ``e`` [%], shape (n,)."""
    excess = np.maximum(0.0, error_pct - over_pct) ** 2 + np.maximum(0.0, -under_pct - error_pct) ** 2
    return float(np.mean(error_pct ** 2) + weight * np.mean(excess))


def excursions(error_pct: np.ndarray) -> tuple[float, float, float]:
    """(over, under, RMS) [%] of area errors ``e`` [%], shape (n,): ``max(e, 0)``, ``max(−e, 0)``, ``√mean(e²)``."""
    return max(float(error_pct.max()), 0.0), max(float(-error_pct.min()), 0.0), float(np.sqrt(np.mean(error_pct ** 2)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--scenario", default="layer")
    parser.add_argument("--setpoint-mm2", type=float, default=0.063)
    parser.add_argument("--h-um", type=float, help="fine element size [µm] (default: the scenario's)")
    parser.add_argument("--turn", type=int, default=1, help="which turnaround (0 = the first)")
    parser.add_argument("--before", type=int, default=6, help="states between the copy and the turn")
    parser.add_argument("--free", type=int, default=28, help="commands optimised after the copy")
    parser.add_argument("--window", type=int, default=38, help="states after the copy the cost scores")
    parser.add_argument("--over-pct", type=float, default=6.0, help="upper edge of the band [%% of the set point]")
    parser.add_argument("--under-pct", type=float, default=9.0, help="lower edge of the band [%% below the set point]")
    parser.add_argument("--band-weight", type=float, default=20.0, help="weight of the squared excess beyond it")
    parser.add_argument("--eps-w", type=float, default=2.0, help="forward-difference step [W]")
    parser.add_argument("--iterations", type=int, default=9, help="L-BFGS-B iterations at most")
    parser.add_argument("--json", action="store_true", help="print the JSON record as the last line")
    args = parser.parse_args()
    if not 1 <= args.free <= args.window:
        parser.error("--free must be in [1, --window]")
    sc = scenario(args.scenario, preset=args.preset, **({} if args.h_um is None else {"h_fine_m": args.h_um * 1e-6}))
    plant = plant_model(sc.settings, sc.plan, sc.layer_plans)
    sp = args.setpoint_mm2 * 1e-6
    model_path = default_model_path(sc.settings.powder_layer_m)
    settings = build(ControllerSettings, process_table(model_path), "[controller]", set_point_m2=sp)  # as launch.py
    ctrl = make_controller("preview-mpc", settings, NarxGPModel.load(model_path))
    obs = plant.initial_observation()
    commands, turns, snapshot, start, prev_track = [], 0, None, 0, obs.track
    while not plant.done and (snapshot is None or len(commands) < start + args.window):
        m = measurement(obs)
        if obs.track != prev_track:
            turns += 1
        prev_track = obs.track
        to_turn = round(m.track_remaining_s / ctrl.model.sample_period_s) if m.next_track else None
        if snapshot is None and turns == args.turn and to_turn == args.before:
            snapshot, start, speed = copy.deepcopy(plant), len(commands), m.speed_m_s
        cmd, _ = ctrl.update(m)
        ctrl.prepare()                          # as the node after each command (the real-time iteration)
        commands.append(cmd.power_w)
        obs = plant.step(cmd.power_w, m.speed_m_s)
    if snapshot is None or len(commands) < start + args.window:
        parser.error(f"the run has no turnaround {args.turn} with {args.before} states before it and "
                     f"{args.window} after the copy")
    applied = np.array(commands[start:start + args.window])
    runs = [0]

    def errors(free_w: np.ndarray) -> np.ndarray:
        """Area error [% of the set point] of the window's states with the first commands ``free_w``."""
        runs[0] += 1
        p, out = copy.deepcopy(snapshot), []
        for power in np.concatenate((free_w, applied[args.free:])):
            out.append((p.step(float(power), speed).area_m2 - sp) / sp * 100.0)
        return np.array(out)

    mpc_error = errors(applied[:args.free])
    result = minimize(lambda v: band_cost(errors(v), args.over_pct, args.under_pct, args.band_weight),
                      applied[:args.free], method="L-BFGS-B", bounds=[(settings.power_min_w, settings.power_max_w)]
                      * args.free, options={"maxiter": args.iterations, "eps": args.eps_w})
    profile = np.concatenate((result.x, applied[args.free:]))
    profile_error = errors(result.x)
    after = np.arange(1, args.window + 1) - args.before      # 0: the first state of the next track
    mpc, best = excursions(mpc_error), excursions(profile_error)
    record = {
        "scenario": args.scenario, "turn": args.turn, "before": args.before, "window_states": args.window,
        "states_after_turn": after.tolist(), "mpc_power_w": np.round(applied, 2).tolist(),
        "profile_power_w": np.round(profile, 2).tolist(), "mpc_error_pct": np.round(mpc_error, 3).tolist(),
        "profile_error_pct": np.round(profile_error, 3).tolist(),
        **{f"mpc_{k}_pct": round(v, 2) for k, v in zip(("over", "under", "rms"), mpc)},
        **{f"profile_{k}_pct": round(v, 2) for k, v in zip(("over", "under", "rms"), best)},
        "iterations": int(result.nit), "plant_runs": runs[0],
    }
    print("states after the turn:", " ".join(f"{a:6d}" for a in after[::2]))
    print("MPC power [W]:        ", " ".join(f"{x:6.0f}" for x in applied[::2]))
    print("MPC area error [%]:   ", " ".join(f"{x:6.1f}" for x in mpc_error[::2]))
    print("profile power [W]:    ", " ".join(f"{x:6.0f}" for x in profile[::2]))
    print("profile area error [%]:", " ".join(f"{x:6.1f}" for x in profile_error[::2]))
    print(f"over / under / RMS over the window: MPC {mpc[0]:.2f} / {mpc[1]:.2f} / {mpc[2]:.2f} %, "
          f"optimised profile {best[0]:.2f} / {best[1]:.2f} / {best[2]:.2f} % ({result.nit} iterations, "
          f"{runs[0]} plant runs)")
    if args.json:
        print(json.dumps(record))


if __name__ == "__main__":
    main()
