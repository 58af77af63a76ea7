"""Benchmark of the preview MPC's full update on the FE plant, against the cvxpy reference.

Runs ``preview-mpc`` with the shipped delay-aware model in closed loop on the FE plant
(in process, no zenoh; default the double track, 250 steps), timing every ``update``; then
solves every QP the controller solved again with the plain cvxpy formulation
(:func:`controller_node.preview_qp.solve_reference`). Prints a summary, then, as the last line,
JSON with ``median_us``, ``p99_us`` (update after the pool build-up), ``cvxpy_median_us``,
``speedup_vs_cvxpy`` (cvxpy solve median ÷ full update median), ``max_abs_diff_w`` (largest
|Δp| over all planned powers of all updates), the paths the QP took, ``warm_median_us`` (a new
controller fed the same states back to back: the update with warm caches) and the load.

Usage: ``python benchmarks/bench_preview.py [--scenario double-track]``
"""

from __future__ import annotations

import argparse
import collections
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from controller_node import ControllerSettings, make_controller
from controller_node.preview_qp import solve_reference
from controller_node.types import Measurement
from fe_node.scenarios import scenario
from fe_node.solver import ThermalModel
from gp_trainer.narx import DEFAULT_MODEL_PATH, NarxGPModel


def measurement(obs) -> Measurement:
    """An FE observation as the controller node would see it (preview fields included)."""
    speed = obs.speed_m_s or 0.8
    return Measurement(step=obs.step, time_s=obs.time_s, area_m2=obs.area_m2, t_ahead_k=obs.t_ahead_k,
                       power_w=obs.power_w, speed_m_s=speed, track=obs.track,
                       track_elapsed_s=obs.track_travelled_m / speed, track_remaining_s=obs.track_remaining_m / speed,
                       next_track=obs.next_track)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--scenario", default="double-track")
    args = parser.parse_args()
    sc = scenario(args.scenario)
    plant = ThermalModel(sc.settings, sc.plan)
    settings = ControllerSettings(set_point_m2=0.063e-6)
    ctrl = make_controller("preview-mpc", settings, NarxGPModel.load(DEFAULT_MODEL_PATH))
    load_at_start = os.getloadavg()[0]
    obs = plant.initial_observation()
    times, problems, plans, seen, prepare_times = [], [], [], [], []
    while not plant.done:
        m = measurement(obs)
        seen.append(m)
        t0 = time.perf_counter()
        cmd, diag = ctrl.update(m)
        elapsed = time.perf_counter() - t0
        if m.step >= settings.preview.observer_start_steps:
            times.append(elapsed)
            problems.append(ctrl.last_qp)
            plans.append(np.array(diag.predicted_power_w))
        t0 = time.perf_counter()
        ctrl.prepare()
        prepare_times.append(time.perf_counter() - t0)
        obs = plant.step(cmd.power_w, 0.8)
    warm = make_controller("preview-mpc", settings, NarxGPModel.load(DEFAULT_MODEL_PATH))
    warm_times = []
    for m in seen:  # the same states back to back: nothing between the updates evicts their caches
        t0 = time.perf_counter()
        warm.update(m)
        if m.step >= settings.preview.observer_start_steps:
            warm_times.append(time.perf_counter() - t0)
    ref_times, diffs, paths = [], [], collections.Counter()
    for (gamma, c, previous, margin), plan in zip(problems, plans):
        paths[ctrl.qp.solve(gamma, c, previous, margin).path] += 1
        t0 = time.perf_counter()
        reference = solve_reference(ctrl.qp, gamma, c, previous, margin)
        ref_times.append(time.perf_counter() - t0)
        diffs.append(float(np.max(np.abs(plan - reference))))
    result = {
        "median_us": round(float(np.median(times)) * 1e6, 1),
        "p99_us": round(float(np.percentile(times, 99)) * 1e6, 1),
        "cvxpy_median_us": round(float(np.median(ref_times)) * 1e6, 1),
        "speedup_vs_cvxpy": round(float(np.median(ref_times) / np.median(times)), 1),
        "max_abs_diff_w": max(diffs),
        "warm_median_us": round(float(np.median(warm_times)) * 1e6, 1),
        "prepare_median_us": round(float(np.median(prepare_times)) * 1e6, 1),
        "n_updates": len(times),
        "loadavg_1min_at_start": round(load_at_start, 2),
        "qp_paths": dict(paths),
        "scenario": args.scenario,
        "model": "gp_trainer/models/in625_narx_gp.json",
    }
    print(f"{result['n_updates']} updates on {args.scenario}: "
          f"median {result['median_us']} us, p99 {result['p99_us']} us; "
          f"cvxpy solve median {result['cvxpy_median_us']} us; max |p - p_cvxpy| = {result['max_abs_diff_w']:.3g} W")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
