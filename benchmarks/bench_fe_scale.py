"""Cost per FE step against part size, the multi-level mesh against the uniform one, and their
agreement on the default layer.

Usage: ``python benchmarks/bench_fe_scale.py [--sides-mm 2 4 8 16] [--layers 1 10 25 50] [--steps 64]
[--repeats 3] [--layer-steps N] [--json]``.  Last line of stdout is JSON.

Side sweep: for each side L a square layer of L / hatch tracks of length L (hatch 0.1 mm) on the
default plant (the ``layer`` scenario's settings and power) is built with ``mesh = "uniform"``
(the whole-plan fine band) and ``mesh = "multilevel"`` (:mod:`fe_node.multilevel`, the parts' 2.4 mm
fine box).  After 5
warm-up steps, ``--steps`` steps (default :data:`~fe_node.multilevel.PART_STEPS`, so that a window
holds one step of the part level) are timed one by one, the two meshes alternating so both see the
same machine load; ``ms_per_step`` is the mean CPU time of a step in this process (BLAS on one
thread, so on a quiet machine it is the wall time, and other jobs on a shared machine do not
inflate it), the multi-level mesh's moves included; ``wall_ms_per_step`` the mean wall time. Each
timed window (a side case's ``--steps``, a layer of the layer sweep) is run ``--repeats`` times from
copies of the plants taken at its start (the same steps: the plants are deterministic), and the
median of the windows' means is reported, so that a passing burst of load on a shared machine does
not decide a case.

Layer sweep: one 2 mm track built ``max(--layers)`` layers high on the default plant (25 µm
layers), both meshes alternating; ``ms_per_step`` is the mean over the steps of each layer in
``--layers`` (the uniform grid gains a row of elements per layer, the multi-level fine box does
not: buried layers coarsen).

Default layer: the ``layer`` scenario run to its end (or ``--layer-steps``) on its default mesh
(multi-level with a 3.2 mm fine box, :data:`fe_node.scenarios.LAYER_MESH`) and on the uniform mesh,
alternating; the melt-pool area traces are compared from step 20 on, as a share of the uniform
mesh's mean area.

Across the cases: this host's speed drifts by tens of percent within minutes, and the cases run
one after the other, so after the sweeps every case's multi-level window is run again ``--repeats``
times from its start copy, the cases taking turns (round ``r`` runs every case once before round
``r + 1``); ``ms_per_step_multilevel_interleaved`` is the median of those windows' means, and
``cost_ratio_max_min`` is taken over it.

Keys: ``cases`` (per side: ``side_mm``, and per layer count: ``layers``; each with
``nodes_uniform``, ``nodes_multilevel``, ``ms_per_step_uniform``, ``ms_per_step_multilevel``,
``wall_ms_per_step_uniform``, ``wall_ms_per_step_multilevel`` (the two meshes alternating within the case),
``ms_per_step_multilevel_interleaved``, and ``area_mm2_uniform``, ``area_mm2_multilevel``: the mean melt-pool
area over the case's window, as a step's cost grows with the pool), ``cost_ratio_max_min`` (the multi-level
``ms_per_step_multilevel_interleaved`` over all cases, max / min), ``max_nodes`` (the largest multi-level node
count), ``speedup_vs_uniform`` (CPU time) and ``wall_speedup_vs_uniform``, ``area_rms_diff_pct``,
``area_max_diff_pct``, ``layer_steps``, ``layer_ms_per_step_uniform``,
``layer_ms_per_step_multilevel`` (CPU) and ``layer_wall_ms_per_step_*``, ``load_avg``.
"""
from __future__ import annotations

import argparse
import copy
import json
import os
import statistics
import sys
import time

import numpy as np

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), ".."))

from fe_node.multilevel import PART_STEPS, plant_model  # noqa: E402
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


def record(case: dict, mesh: str, windows: list[list[tuple[float, float, float]]]) -> None:
    """Put the median over ``windows`` of their mean CPU and wall ms per step (each window a list of
    (CPU s, wall s, area m²) per step) into ``case``, and the mean melt-pool area of the first window [mm²]
    (the windows repeat the same steps)."""
    for key, k in ((f"ms_per_step_{mesh}", 0), (f"wall_ms_per_step_{mesh}", 1)):
        case[key] = round(1e3 * statistics.median(statistics.fmean(t[k] for t in w) for w in windows), 2)
    case[f"area_mm2_{mesh}"] = round(1e6 * statistics.fmean(t[2] for t in windows[0]), 4)


def timed_window(scs, models, steps: int) -> list[list[tuple[float, float, float]]]:
    """Step ``models`` (one per scenario of ``scs``) ``steps`` times, alternating: per model, (CPU s, wall s,
    melt-pool area m²) per step."""
    times = [[] for _ in models]
    for _ in range(steps):
        for i, (sc, model) in enumerate(zip(scs, models)):
            cpu, wall, obs = timed_step(sc, model)
            times[i].append((cpu, wall, obs.area_m2))
    return times


def repeated(scs, start: list, steps: int, repeats: int) -> list[list[list[tuple[float, float, float]]]]:
    """``repeats - 1`` more runs of a window of ``steps`` steps from copies of the plants ``start`` taken at its
    start: per model, its windows."""
    return [list(w) for w in zip(*(timed_window(scs, [copy.deepcopy(m) for m in start], steps)
                                   for _ in range(repeats - 1)))] if repeats > 1 else [[] for _ in start]


def side_case(side_mm: float, steps: int, repeats: int) -> tuple[dict, tuple]:
    """Time both meshes on a square layer of side ``side_mm``; the case, and its multi-level window
    (:func:`interleaved`)."""
    side = side_mm * 1e-3
    scs = [scenario("layer", n_tracks=max(1, round(side / HATCH_M)), track_length_m=side, hatch_m=HATCH_M, mesh=m)
           for m in MESHES]
    models = [plant_model(sc.settings, sc.plan) for sc in scs]
    timed_window(scs, models, 5)
    start = [copy.deepcopy(m) for m in models]
    first = timed_window(scs, models, steps)
    again = repeated(scs, start, steps, repeats)
    case = {"side_mm": side_mm}
    for i, (m, model) in enumerate(zip(MESHES, models)):
        case[f"nodes_{m}"] = nodes(model)
        record(case, m, [first[i], *again[i]])
    print(f"{side_mm:g} mm: uniform {case['nodes_uniform']} nodes {case['ms_per_step_uniform']} ms/step; "
          f"multilevel {case['nodes_multilevel']} nodes {case['ms_per_step_multilevel']} ms/step "
          f"({models[1].n_remeshes} moves)", file=sys.stderr, flush=True)
    return case, (scs[1], start[1], steps)


def layer_cases(layers: list[int], repeats: int) -> tuple[list[dict], list[tuple]]:
    """Time both meshes in layers ``layers`` (1-based) of a one-track build, each layer but its first two
    steps (the first spreads the powder); the cases, and their multi-level windows (:func:`interleaved`)."""
    scs = [scenario("layer", n_tracks=1, track_length_m=2e-3, n_layers=max(layers), mesh=m) for m in MESHES]
    models = [plant_model(sc.settings, sc.plan, sc.layer_plans) for sc in scs]
    windows, nodes_at, starts = {}, {}, {}
    while not models[0].done:
        n = models[0].layer + 1 + (models[0].layer_done and models[0].step_index > 0)   # the layer of the next step
        if n in layers and n not in windows:
            timed_window(scs, models, 2)
            start = [copy.deepcopy(m) for m in models]
            first = [[] for _ in models]
            count = 0
            while not models[0].done and not models[0].layer_done:
                for i, t in enumerate(timed_window(scs, models, 1)):
                    first[i] += t
                count += 1
            windows[n] = [[first[i], *w] for i, w in enumerate(repeated(scs, start, count, repeats))]
            starts[n] = (scs[1], start[1], count)        # (repeated() steps copies of it)
            nodes_at[n] = [nodes(m) for m in models]
        else:
            timed_window(scs, models, 1)
    cases = []
    for n in layers:
        case = {"layers": n}
        for i, m in enumerate(MESHES):
            case[f"nodes_{m}"] = nodes_at[n][i]
            record(case, m, windows[n][i])
        print(f"layer {n}: uniform {case['nodes_uniform']} nodes {case['ms_per_step_uniform']} ms/step; "
              f"multilevel {case['nodes_multilevel']} nodes {case['ms_per_step_multilevel']} ms/step",
              file=sys.stderr, flush=True)
        cases.append(case)
    return cases, [starts[n] for n in layers]


def interleaved(windows: list[tuple], repeats: int) -> list[float]:
    """Per multi-level window ``(scenario, plant at its start, steps)``, the median over ``repeats`` rounds
    of its mean CPU ms per step, each round running every window once from a copy of its start."""
    means = [[] for _ in windows]
    for _ in range(repeats):
        for i, (sc, start, steps) in enumerate(windows):
            times = timed_window([sc], [copy.deepcopy(start)], steps)[0]
            means[i].append(1e3 * statistics.fmean(t[0] for t in times))
    return [round(statistics.median(m), 2) for m in means]


def default_layer(max_steps: int | None) -> dict:
    """Both meshes over the default layer (its multi-level mesh, :data:`fe_node.scenarios.LAYER_MESH`,
    against the uniform one): cost and the area traces' difference."""
    scs = [scenario("layer", mesh="uniform"), scenario("layer")]
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
    parser.add_argument("--steps", type=int, default=PART_STEPS, help="timed steps of a side case")
    parser.add_argument("--repeats", type=int, default=3, help="runs of each timed window from its start (median)")
    parser.add_argument("--layer-steps", type=int, default=None, help="steps of the default layer (default: all)")
    parser.add_argument("--json", action="store_true", help="(the last line is JSON either way)")
    args = parser.parse_args()
    single_threaded_blas()         # CPU time is then the step's cost (two BLAS threads had doubled it on large pools)
    load = [round(os.getloadavg()[0], 2)]
    if args.repeats < 1:
        parser.error("--repeats must be >= 1")
    sides = [side_case(side, args.steps, args.repeats) for side in args.sides_mm]
    layer_records, layer_windows = layer_cases(args.layers, args.repeats)
    cases = [case for case, _ in sides] + layer_records
    ml = interleaved([window for _, window in sides] + layer_windows, args.repeats)
    for case, ms in zip(cases, ml):
        case["ms_per_step_multilevel_interleaved"] = ms
    result = {"cases": cases, "repeats": args.repeats, "cost_ratio_max_min": round(max(ml) / min(ml), 3),
              "max_nodes": max(c["nodes_multilevel"] for c in cases), **default_layer(args.layer_steps)}
    load.append(round(os.getloadavg()[0], 2))
    result["load_avg"] = load
    print(json.dumps(result))


if __name__ == "__main__":
    main()
