"""Benchmark of the controller's full update (GP linearisation + QP + clamping).

Runs the default GP-MPC (DAQP backend) in closed loop on the synthetic plant over an
8-track layer (2000 updates, preheat jumping at each new track and decaying along it,
2 % area-measurement noise), timing every ``update``; then replays the same
measurements through the OSQP backend and the cvxpy reference in the same run.
Prints a human summary, then, as the last line, JSON with ``median_us``, ``p99_us``,
``cvxpy_median_us``, ``speedup_vs_cvxpy``, ``max_abs_diff_w`` (largest |Δp| between
the fast MPC and the cvxpy reference over all updates) and context.

Usage: ``python benchmarks/bench_controller.py [--tracks 8] [--steps-per-track 250]``
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controller_node import ControllerSettings, make_controller  # noqa: E402
from controller_node.synthetic import AnalyticMeltPoolModel, multitrack_temperature, run_closed_loop  # noqa: E402

SHIPPED = Path(__file__).resolve().parent.parent / "gp_trainer" / "models" / "in625_gp.json"


def load_model(plant: AnalyticMeltPoolModel):
    """The shipped GP if present, else a GP fitted here on 100 synthetic transitions."""
    from gp_model.model import GPModel

    if SHIPPED.exists():
        return GPModel.load(SHIPPED), "gp_model/models/in625_gp.json (shipped)"
    rng = np.random.default_rng(0)
    z = np.column_stack([rng.uniform(0.02e-6, 0.16e-6, 100), rng.uniform(300.0, 1400.0, 100),
                         rng.uniform(50.0, 350.0, 100), np.full(100, 0.8)])
    y = np.array([plant.predict(row)[0] for row in z])
    return GPModel.fit(z, y, seed=0), "GPModel fitted on 100 synthetic transitions (no shipped model)"


def timed_replay(controller, measurements) -> tuple[np.ndarray, np.ndarray]:
    """Update ``controller`` with each measurement; return powers [W] and times [s]."""
    powers, times = np.empty(len(measurements)), np.empty(len(measurements))
    for i, m in enumerate(measurements):
        t0 = time.perf_counter()
        cmd, _ = controller.update(m)
        times[i] = time.perf_counter() - t0
        powers[i] = cmd.power_w
    return powers, times


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tracks", type=int, default=8)
    parser.add_argument("--steps-per-track", type=int, default=250)
    args = parser.parse_args()

    # plant with the gp_trainer synthetic scalings (lag of a 0.5 mm pool at 0.8 m/s, Δt = 50 µs)
    plant = AnalyticMeltPoolModel(n_p=1.3, n_v=0.6, alpha=1.0 - math.exp(-50e-6 * 0.8 / 0.5e-3))
    model, model_name = load_model(plant)
    settings = ControllerSettings()
    temps = multitrack_temperature(args.tracks, args.steps_per_track)

    # closed loop, timed inside run_closed_loop's update calls via a timing wrapper
    mpc = make_controller("mpc", settings, model)
    times: list[float] = []

    class Timed:
        def update(self, m):
            t0 = time.perf_counter()
            out = mpc.update(m)
            times.append(time.perf_counter() - t0)
            return out

    run = run_closed_loop(Timed(), plant, temps, area0_m2=0.05e-6, power0_w=250.0, noise_std_m2=1.4e-9)
    fast_powers, fast_times = run.power_w, np.array(times)

    def variant(solver: str):
        mpc = dataclasses.replace(settings.mpc, solver=solver)
        return make_controller("mpc", dataclasses.replace(settings, mpc=mpc), model)

    osqp_powers, osqp_times = timed_replay(variant("osqp"), run.measurements)
    ref_powers, ref_times = timed_replay(variant("cvxpy"), run.measurements)

    err = run.area_m2 / settings.set_point_m2 - 1.0
    open_loop = run_closed_loop(make_controller("open-loop", settings), plant, temps, area0_m2=0.05e-6)
    ol_err = open_loop.area_m2 / settings.set_point_m2 - 1.0
    result = {
        "median_us": round(float(np.median(fast_times)) * 1e6, 1),
        "p99_us": round(float(np.percentile(fast_times, 99)) * 1e6, 1),
        "cvxpy_median_us": round(float(np.median(ref_times)) * 1e6, 1),
        "speedup_vs_cvxpy": round(float(np.median(ref_times) / np.median(fast_times)), 1),
        "max_abs_diff_w": float(np.max(np.abs(fast_powers - ref_powers))),
        "osqp_median_us": round(float(np.median(osqp_times)) * 1e6, 1),
        "osqp_max_abs_diff_w": float(np.max(np.abs(osqp_powers - ref_powers))),
        "n_updates": len(run.measurements),
        "solver": settings.mpc.solver,
        "n_fallbacks": mpc.n_fallbacks,
        "model": model_name,
        "plant": "controller_node.synthetic.AnalyticMeltPoolModel(n_p=1.3, n_v=0.6, alpha=0.077), 2 % area noise",
        "closed_loop_rmse_rel": round(float(np.sqrt(np.mean(err[50:] ** 2))), 4),
        "open_loop_rmse_rel": round(float(np.sqrt(np.mean(ol_err[50:] ** 2))), 4),
    }
    print(f"{result['n_updates']} updates, model: {model_name}")
    print(f"fast MPC ({settings.mpc.solver}): median {result['median_us']} us, p99 {result['p99_us']} us; "
          f"osqp median {result['osqp_median_us']} us; cvxpy median {result['cvxpy_median_us']} us")
    print(f"max |p_fast - p_cvxpy| = {result['max_abs_diff_w']:.3g} W; closed-loop area RMSE "
          f"{result['closed_loop_rmse_rel']:.1%} (open loop {result['open_loop_rmse_rel']:.1%})")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
