"""Temperature between layers: the multi-level mesh against the uniform one over a part's layers.

Usage: ``python benchmarks/bench_fe_layers.py [--layers 10] [--points 64] [--json]``.  Last line of
stdout is JSON.

The example part (``part`` scenario, default plant: 25 µm layers, 67° hatch rotation, contours,
100 W, :data:`~fe_node.scenarios.PART_DWELL_S` between layers) is built ``--layers`` layers high with
``mesh = "uniform"`` and ``mesh = "multilevel"``, both stepped alternately.  When a layer is done the
temperature is sampled on its top surface at ``--points`` points evenly spaced along the next layer's
scan path, twice: at its end (before the dwell) and at the next layer's start (after the dwell and the
new powder, at the same points, now under the powder); each record is the mean rise above the preheat
temperature.

Keys: ``layers`` (per layer start: ``layer``, ``rise_k_uniform``, ``rise_k_multilevel``, ``diff_pct`` at the
layer's start; ``end_rise_k_uniform``, ``end_rise_k_multilevel``, ``end_diff_pct`` at the previous layer's
end), ``layer_start_max_diff_pct`` (the largest ``|diff_pct|``), ``layer_end_max_diff_pct``, ``steps``,
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


def mean_rise(models, points: np.ndarray, t0_k: float) -> list[float]:
    """Mean temperature rise [K] above ``t0_k`` at ``points`` [m], shape (n, 3), on the uniform and the
    multi-level model (its fields gathered onto the part level first)."""
    models[1].sync("part")
    return [float(np.mean(m.temperature_at(points))) - t0_k for m in models]


def compared(rise: list[float], prefix: str) -> dict:
    """The two meshes' rises [K] and the multi-level one's difference [%] under keys starting ``prefix``."""
    return {f"{prefix}rise_k_uniform": round(rise[0], 2), f"{prefix}rise_k_multilevel": round(rise[1], 2),
            f"{prefix}diff_pct": round(100 * (rise[1] - rise[0]) / rise[0], 2)}


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
            end = mean_rise(models, points, t0_k)
            for model in models:
                model.add_layer()
            start = mean_rise(models, points, t0_k)
            records.append({"layer": models[0].layer + 1, **compared(start, ""), **compared(end, "end_")})
            print(records[-1], file=sys.stderr, flush=True)
        for i, (sc, model) in enumerate(zip(scs, models)):
            t0 = time.perf_counter()
            model.step(*sc.profile.command(model.step_index))
            times[i].append(time.perf_counter() - t0)
    load.append(round(os.getloadavg()[0], 2))
    result = {"layers": records, "layer_start_max_diff_pct": max(abs(r["diff_pct"]) for r in records),
              "layer_end_max_diff_pct": max(abs(r["end_diff_pct"]) for r in records),
              "steps": len(times[0]), "ms_per_step_uniform": round(1e3 * statistics.fmean(times[0]), 2),
              "ms_per_step_multilevel": round(1e3 * statistics.fmean(times[1]), 2), "load_avg": load}
    print(json.dumps(result))


if __name__ == "__main__":
    main()
