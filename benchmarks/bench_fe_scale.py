"""Cost per FE step against part size, the multi-level mesh against the uniform one, and their
agreement on the default layer.

Usage: ``python benchmarks/bench_fe_scale.py [--sides-mm 2 4 8 16] [--layers 1 10 25 50] [--steps 50]
[--layer-steps N] [--json]``.  Last line of stdout is JSON.

Side sweep: for each side L a square layer of L / hatch tracks of length L (hatch 0.1 mm) on the
default plant (the ``layer`` scenario's settings and power) is built with ``mesh = "uniform"``
(the whole-plan fine band) and ``mesh = "multilevel"`` (:mod:`fe_node.multilevel`).  After 5
warm-up steps, ``--steps`` steps are timed one by one, the two meshes alternating so both see the
same machine load; ``ms_per_step`` is the mean CPU time of a step in this process (BLAS on one
thread, so on a quiet machine it is the wall time, and other jobs on a shared machine do not
inflate it), the multi-level mesh's moves included; ``wall_ms_per_step`` the mean wall time.

Layer sweep: one 2 mm track built ``max(--layers)`` layers high on the default plant (25 µm
layers), both meshes alternating; ``ms_per_step`` is the mean over the steps of each layer in
``--layers`` (the uniform grid gains a row of elements per layer, the multi-level fine box does
not: buried layers coarsen).

Default layer: the ``layer`` scenario run to its end (or ``--layer-steps``) on both meshes,
alternating; the melt-pool area traces are compared from step 20 on, as a share of the uniform
mesh's mean area.

Keys: ``cases`` (per side: ``side_mm``, and per layer count: ``layers``; each with
``nodes_uniform``, ``nodes_multilevel``, ``ms_per_step_uniform``, ``ms_per_step_multilevel``,
``wall_ms_per_step_uniform``, ``wall_ms_per_step_multilevel``), ``cost_ratio_max_min`` (the
multi-level ``ms_per_step`` over all cases, max / min), ``max_nodes`` (the largest multi-level node
count), ``speedup_vs_uniform`` (CPU time) and ``wall_speedup_vs_uniform``, ``area_rms_diff_pct``,
``area_max_diff_pct``, ``layer_steps``, ``layer_ms_per_step_uniform``,
``layer_ms_per_step_multilevel`` (CPU) and ``layer_wall_ms_per_step_*``, ``load_avg``.
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
from messages.bus import single_threaded_blas  # noqa: E402

HATCH_M = 1e-4
MESHES = ("uniform", "multilevel")


def nodes(model) -> int:
    """Nodes of a plant (the three grids of a multi-level one)."""
    return getattr(model, "n_nodes", model.grid.n_nodes)


def timed_step(sc, model):
    """One step of ``model`` under its scenario's command: (CPU seconds, wall seconds, observation)."""
    c0, w0 = time.process_time(), time.perf_counter()
    obs = model.step(*sc.profile.command(model.step_index))
    return time.process_time() - c0, time.perf_counter() - w0, obs


def record(case: dict, mesh: str, times: list[tuple[float, float]]) -> None:
    """Put the mean CPU and wall ms per step of ``times`` ((CPU s, wall s) per step) into ``case``."""
    case[f"ms_per_step_{mesh}"] = round(1e3 * statistics.fmean(c for c, _ in times), 2)
    case[f"wall_ms_per_step_{mesh}"] = round(1e3 * statistics.fmean(w for _, w in times), 2)


def side_case(side_mm: float, steps: int) -> dict:
    """Time both meshes on a square layer of side ``side_mm``."""
    side = side_mm * 1e-3
    scs = [scenario("layer", n_tracks=max(1, round(side / HATCH_M)), track_length_m=side, hatch_m=HATCH_M, mesh=m)
           for m in MESHES]
    models = [plant_model(sc.settings, sc.plan) for sc in scs]
    times = [[], []]
    for k in range(5 + steps):
        for i, (sc, model) in enumerate(zip(scs, models)):
            cpu, wall, _ = timed_step(sc, model)
            if k >= 5:
                times[i].append((cpu, wall))
    case = {"side_mm": side_mm}
    for m, model, t in zip(MESHES, models, times):
        case[f"nodes_{m}"] = nodes(model)
        record(case, m, t)
    print(f"{side_mm:g} mm: uniform {case['nodes_uniform']} nodes {case['ms_per_step_uniform']} ms/step; "
          f"multilevel {case['nodes_multilevel']} nodes {case['ms_per_step_multilevel']} ms/step "
          f"({models[1].n_remeshes} moves)", file=sys.stderr, flush=True)
    return case


def layer_cases(layers: list[int]) -> list[dict]:
    """Time both meshes in layers ``layers`` (1-based) of a one-track build."""
    scs = [scenario("layer", n_tracks=1, track_length_m=2e-3, n_layers=max(layers), mesh=m) for m in MESHES]
    models = [plant_model(sc.settings, sc.plan, sc.layer_plans) for sc in scs]
    times = {n: [[], []] for n in layers}
    nodes_at = {}
    while not models[0].done:
        for i, (sc, model) in enumerate(zip(scs, models)):
            cpu, wall, _ = timed_step(sc, model)
            n = model.layer + 1
            if n in times and model.step_index > 1:
                times[n][i].append((cpu, wall))
                nodes_at[(n, i)] = nodes(model)
    cases = []
    for n in layers:
        case = {"layers": n}
        for i, m in enumerate(MESHES):
            case[f"nodes_{m}"] = nodes_at[(n, i)]
            record(case, m, times[n][i][1:])
        print(f"layer {n}: uniform {case['nodes_uniform']} nodes {case['ms_per_step_uniform']} ms/step; "
              f"multilevel {case['nodes_multilevel']} nodes {case['ms_per_step_multilevel']} ms/step",
              file=sys.stderr, flush=True)
        cases.append(case)
    return cases


def default_layer(max_steps: int | None) -> dict:
    """Both meshes over the default layer: cost and the area traces' difference."""
    scs = [scenario("layer", mesh=m) for m in MESHES]
    models = [plant_model(sc.settings, sc.plan) for sc in scs]
    areas, times = [[], []], [[], []]
    while not models[0].done and (max_steps is None or models[0].step_index < max_steps):
        for i, (sc, model) in enumerate(zip(scs, models)):
            cpu, wall, obs = timed_step(sc, model)
            times[i].append((cpu, wall))
            areas[i].append(obs.area_m2)
    uniform, multi = (np.array(a[20:]) for a in areas)
    diff = (multi - uniform) / uniform.mean()
    cpu_ms, wall_ms = ([1e3 * statistics.fmean(t[k] for t in ts) for ts in times] for k in (0, 1))
    return {"layer_steps": len(times[0]), "layer_ms_per_step_uniform": round(cpu_ms[0], 2),
            "layer_ms_per_step_multilevel": round(cpu_ms[1], 2), "speedup_vs_uniform": round(cpu_ms[0] / cpu_ms[1], 2),
            "layer_wall_ms_per_step_uniform": round(wall_ms[0], 2),
            "layer_wall_ms_per_step_multilevel": round(wall_ms[1], 2),
            "wall_speedup_vs_uniform": round(wall_ms[0] / wall_ms[1], 2),
            "area_rms_diff_pct": round(100 * float(np.sqrt(np.mean(diff**2))), 3),
            "area_max_diff_pct": round(100 * float(np.max(np.abs(diff))), 3),
            "layer_moves": models[1].n_remeshes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--sides-mm", type=float, nargs="+", default=[2.0, 4.0, 8.0, 16.0])
    parser.add_argument("--layers", type=int, nargs="+", default=[1, 10, 25, 50])
    parser.add_argument("--steps", type=int, default=50)
    parser.add_argument("--layer-steps", type=int, default=None, help="steps of the default layer (default: all)")
    parser.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    args = parser.parse_args()
    single_threaded_blas()         # CPU time is then the step's cost (two BLAS threads had doubled it on large pools)
    load = [round(os.getloadavg()[0], 2)]
    cases = [side_case(side, args.steps) for side in args.sides_mm] + layer_cases(args.layers)
    ml = [c["ms_per_step_multilevel"] for c in cases]
    result = {"cases": cases, "cost_ratio_max_min": round(max(ml) / min(ml), 3),
              "max_nodes": max(c["nodes_multilevel"] for c in cases), **default_layer(args.layer_steps)}
    load.append(round(os.getloadavg()[0], 2))
    result["load_avg"] = load
    print(json.dumps(result))


if __name__ == "__main__":
    main()
