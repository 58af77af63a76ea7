"""Cost per FE step against part size: the whole-plan fine band vs the fine window that follows the laser.

Usage: ``python benchmarks/bench_fe_scale.py [--sides-mm 2 4 8 16] [--window-mm 2] [--steps 50]``.
Last line of stdout is JSON.

For each side L a square layer of L / hatch tracks of length L (hatch 0.1 mm, IN625, 250 W,
800 mm/s, default mesh and sub-steps) is built twice: with the ``h_fine_m`` band over the whole
plan (``window_m = 0``, today's default) and with the window (``window_m``, :mod:`fe_node.window`).
After 5 warm-up steps, ``--steps`` steps are timed one by one, the two meshes alternating so both
see the same machine load; ``ms_per_step_*`` is the mean, so the window's remeshes (one per
``window_m / 2`` of travel along a track) are included.

Keys: ``sides_mm``, ``window_m``, ``nodes_full``, ``nodes_window``, ``ms_per_step_full``,
``ms_per_step_window``, ``steps``, ``load_avg``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time
from dataclasses import replace

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from fe_node.scan import ScanPlan  # noqa: E402
from fe_node.settings import Settings  # noqa: E402
from fe_node.solver import ThermalModel  # noqa: E402

HATCH_M = 1e-4


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides-mm", type=float, nargs="+", default=[2.0, 4.0, 8.0, 16.0])
    parser.add_argument("--window-mm", type=float, default=2.0)
    parser.add_argument("--steps", type=int, default=50)
    args = parser.parse_args()
    result = {"sides_mm": args.sides_mm, "window_m": args.window_mm * 1e-3, "nodes_full": [], "nodes_window": [],
              "ms_per_step_full": [], "ms_per_step_window": [], "steps": args.steps,
              "load_avg": [round(os.getloadavg()[0], 2)]}
    for side_mm in args.sides_mm:
        side = side_mm * 1e-3
        plan = ScanPlan.layer(max(1, round(side / HATCH_M)), side, HATCH_M)
        models = [ThermalModel(replace(Settings(), window_m=w), plan) for w in (0.0, args.window_mm * 1e-3)]
        times = [[], []]
        for k in range(5 + args.steps):
            for i, model in enumerate(models):
                t0 = time.perf_counter()
                model.step(250.0, 0.8)
                if k >= 5:
                    times[i].append(time.perf_counter() - t0)
        for key, model, t in (("full", models[0], times[0]), ("window", models[1], times[1])):
            result[f"nodes_{key}"].append(model.grid.n_nodes)
            result[f"ms_per_step_{key}"].append(round(1e3 * statistics.fmean(t), 2))
        print(f"{side_mm:g} mm: full {models[0].grid.n_nodes} nodes {result['ms_per_step_full'][-1]} ms/step; "
              f"window {models[1].grid.n_nodes} nodes {result['ms_per_step_window'][-1]} ms/step "
              f"({models[1].n_remeshes} remeshes)", file=sys.stderr, flush=True)
        del models
    result["load_avg"].append(round(os.getloadavg()[0], 2))
    print(json.dumps(result))


if __name__ == "__main__":
    main()
