"""Temperature between layers: the multi-level mesh against the uniform one over a part's layers.

Usage: ``python benchmarks/bench_fe_layers.py [--layers 10] [--points 64] [--json]``.  Last line of
stdout is JSON.

The example part (``part`` scenario, default plant: 25 µm layers, 67° hatch rotation, contours,
100 W) is built ``--layers`` layers high with ``mesh = "uniform"`` and ``mesh = "multilevel"``,
both stepped alternately.  At the start of each layer after the first (when the last layer is
done, before the new powder is spread on it), the temperature is sampled on the top surface at
``--points`` points evenly spaced along the next layer's scan path; the record is the mean rise
above the preheat temperature.

Keys: ``layers`` (per layer start: ``layer``, ``rise_k_uniform``, ``rise_k_multilevel``,
``diff_pct``), ``layer_start_max_diff_pct`` (the largest ``|diff_pct|``), ``steps``,
``ms_per_step_uniform``, ``ms_per_step_multilevel``, ``load_avg``.
"""
from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from fe_node.multilevel import plant_model  # noqa: E402
from fe_node.scenarios import scenario  # noqa: E402

MESHES = ("uniform", "multilevel")


def surface_points(plan, top_m: float, n: int) -> np.ndarray:
    """``n`` points [m] along ``plan``'s scan path, on the top surface at height ``top_m``."""
    s = np.linspace(0.0, plan.total_length, n + 2)[1:-1]
    _, xy, _ = plan.locate(s)
    return np.hstack([xy, np.full((n, 1), top_m)])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--layers", type=int, default=10)
    parser.add_argument("--points", type=int, default=64)
    parser.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    args = parser.parse_args()
    load = [round(os.getloadavg()[0], 2)]
    scs = [scenario("part", n_layers=args.layers, mesh=m) for m in MESHES]
    models = [plant_model(sc.settings, sc.plan, sc.layer_plans) for sc in scs]
    t0_k = scs[0].settings.t0_k
    times, records = [[], []], []
    while not models[0].done:
        if models[0].layer_done:
            points = surface_points(scs[0].layer_plans[models[0].layer + 1], float(models[0].grid.zs[-1]), args.points)
            models[1].sync("part")
            rise = [float(np.mean(m.temperature_at(points))) - t0_k for m in models]
            for model in models:
                model.add_layer()
            records.append({"layer": models[0].layer + 1, "rise_k_uniform": round(rise[0], 2),
                            "rise_k_multilevel": round(rise[1], 2),
                            "diff_pct": round(100 * (rise[1] - rise[0]) / rise[0], 2)})
            print(records[-1], file=sys.stderr, flush=True)
        for i, (sc, model) in enumerate(zip(scs, models)):
            t0 = time.perf_counter()
            model.step(*sc.profile.command(model.step_index))
            times[i].append(time.perf_counter() - t0)
    load.append(round(os.getloadavg()[0], 2))
    result = {"layers": records, "layer_start_max_diff_pct": max(abs(r["diff_pct"]) for r in records),
              "steps": len(times[0]), "ms_per_step_uniform": round(1e3 * statistics.fmean(times[0]), 2),
              "ms_per_step_multilevel": round(1e3 * statistics.fmean(times[1]), 2), "load_avg": load}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
