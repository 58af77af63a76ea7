"""Benchmark of the preview MPC's update on the FE plant, against the cvxpy reference.

Runs ``preview-mpc`` with the shipped delay-aware model in closed loop on the FE plant (in
process, no zenoh; default the double track, 250 steps) as the controller node runs it (with the
model's process record: its operating power at laser-on, as ``launch.py`` passes it): ``update``
on each state, timed (between FE steps: cold caches), then ``prepare`` for the next state after the
command, timed apart (the real-time iteration's preparation, off the state-to-command path). Then
the same loop on a fresh plant without ``prepare`` (every update is the full update); the two
alternate ``--rounds`` times. Then the states of the last loop with ``prepare`` back to back to a
fresh controller (warm caches). Last, every QP that loop solved is solved again with the plain
cvxpy formulation (:func:`controller_node.preview_qp.solve_reference`).

Prints a summary, then, as the last line, JSON: ``median_us``, ``p99_us`` (the update, state to
command and diagnostics, after the pool build-up), ``prepare_median_us``, ``feedback_updates`` (of
``n_updates``, the updates that took the feedback phase), ``full_update_median_us`` (the loops
without preparation) and ``ratio_vs_full_update`` (of the medians), ``warm_median_us``,
``cvxpy_median_us``, ``speedup_vs_cvxpy`` (cvxpy solve median ÷ update median),
``max_abs_diff_w`` (largest |Δp| over all planned powers of all updates),
``command_diff_vs_full_median_w`` and ``..._max_w`` (|Δp| between each command and that of a controller
without preparation fed the same states: the real-time iteration's linearisation lag), the paths
the QP took and the load.

Usage: ``python benchmarks/bench_preview.py [--preset physical] [--scenario double-track] [--rounds 2]
[--model FILE] [--json]`` (the last line is JSON either way).
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
from controller_node.process import process_table
from controller_node.types import Measurement
from fe_node.presets import DEFAULT, NAMES
from fe_node.scenarios import scenario
from fe_node.solver import ThermalModel
from gp_model.narx import NarxGPModel
from gp_model.shipped import default_model_path
from messages.config import build


def measurement(obs) -> Measurement:
    """An FE observation as the controller node would see it (preview fields included)."""
    speed = obs.speed_m_s or 0.8
    return Measurement(step=obs.step, time_s=obs.time_s, area_m2=obs.area_m2, t_ahead_k=obs.t_ahead_k,
                       power_w=obs.power_w, speed_m_s=speed, track=obs.track,
                       track_elapsed_s=obs.track_travelled_m / speed, track_remaining_s=obs.track_remaining_m / speed,
                       next_track=obs.next_track)


def closed_loop(sc, ctrl, settings: ControllerSettings, prepare: bool, shadow=None
                ) -> tuple[list, list, list, list, list, list]:
    """One closed loop on a fresh FE plant: the update times after the pool build-up [s], the
    preparation times [s], every state, the QPs and plans of the timed updates, and |Δp| [W]
    between each command and that of ``shadow`` (a controller without preparation, fed the same
    states after the FE step's command is fixed; not timed)."""
    plant = ThermalModel(sc.settings, sc.plan)
    obs = plant.initial_observation()
    times, prepare_times, seen, problems, plans, differences = [], [], [], [], [], []
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
        if prepare:
            t0 = time.perf_counter()
            ctrl.prepare()
            prepare_times.append(time.perf_counter() - t0)
        if shadow is not None:
            differences.append(abs(shadow.update(m)[0].power_w - cmd.power_w))
        obs = plant.step(cmd.power_w, 0.8)
    return times, prepare_times, seen, problems, plans, differences


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--scenario", default="double-track")
    parser.add_argument("--rounds", type=int, default=2, help="alternated pairs of loops with and without prepare")
    parser.add_argument("--model", type=Path, help="delay-aware model file (default: the shipped one of the plant)")
    parser.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    args = parser.parse_args()
    sc = scenario(args.scenario, preset=args.preset)
    model_path = args.model or default_model_path(sc.settings.powder_layer_m)  # default: the shipped one of its layer
    settings = build(ControllerSettings, process_table(model_path), "[controller]", set_point_m2=0.063e-6)  # as launch
    load_at_start = os.getloadavg()[0]
    times, prepare_times, full_times, differences, feedback_updates = [], [], [], [], 0
    for _ in range(args.rounds):   # alternated: this host's speed drifts by tens of percent within minutes
        ctrl = make_controller("preview-mpc", settings, NarxGPModel.load(model_path))
        shadow = make_controller("preview-mpc", settings, NarxGPModel.load(model_path))
        round_times, round_prepare, seen, problems, plans, round_differences = closed_loop(sc, ctrl, settings, True,
                                                                                           shadow)
        differences += round_differences
        times += round_times
        prepare_times += round_prepare
        feedback_updates += ctrl.n_feedback
        full_times += closed_loop(sc, make_controller("preview-mpc", settings, NarxGPModel.load(model_path)),
                                  settings, prepare=False)[0]
    warm = make_controller("preview-mpc", settings, NarxGPModel.load(model_path))
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
        "feedback_updates": feedback_updates,
        "full_update_median_us": round(float(np.median(full_times)) * 1e6, 1),
        "n_updates": len(seen) * args.rounds,
        "rounds": args.rounds,
        "ratio_vs_full_update": round(float(np.median(times) / np.median(full_times)), 3),
        "command_diff_vs_full_median_w": float(np.median(differences)),
        "command_diff_vs_full_max_w": float(np.max(differences)),
        "loadavg_1min_at_start": round(load_at_start, 2),
        "qp_paths": dict(paths),
        "scenario": args.scenario,
        "model": str(model_path),
    }
    print(f"{result['n_updates']} updates on {args.scenario}: "
          f"median {result['median_us']} us, p99 {result['p99_us']} us; "
          f"cvxpy solve median {result['cvxpy_median_us']} us; max |p - p_cvxpy| = {result['max_abs_diff_w']:.3g} W")
    print(json.dumps(result))


if __name__ == "__main__":
    main()
