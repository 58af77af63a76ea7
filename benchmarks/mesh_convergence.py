"""Mesh convergence of the plant's melt-pool area over the power range: the plant at ``h``, ``h / 2`` and,
with ``--refinements 2 4``, ``h / 4``.

``python -m fe_node validate`` checks the mesh on one single track at 250 W (``mesh_convergence_pct``). This
benchmark runs the same single track (in process, on the uniform mesh) of the ``--preset`` plant, or of the
``[plant]`` table of ``--config`` over it, at each power of ``--powers``, with the plant's element size ``h`` and
with ``h / r`` for each ``r`` of ``--refinements``. Per power it reports the mean area over the second half of the
track after the pool's build-up (20 steps) at ``h`` and ``h / 2``, their difference in % of the fine one
(``mesh_convergence_pct``, as ``validate`` defines it) and the step-to-step jitter of the area over that window
(rms of the change of its logarithm, %) at both sizes; and per mesh the area, the jitter, the keyhole depth
(:meth:`fe_node.solver.ThermalModel.keyhole_depth_m`) and the peak temperature (``t_peak_k``) over the window,
and the area's error against the finest mesh's (``error_vs_finest_pct``). A pool a few elements wide is
under-resolved: its area is low and jitters as the pool's edge crosses nodes. Whether ``h / 2`` is itself
converged shows at ``h / 4`` (8 times the nodes and 4 times the sub-steps of ``h / 2``).

Prints a table; with ``--json``, then, as the last line, JSON with ``cases`` (per power: ``power_w``,
``area_mm2_h``, ``area_mm2_h2``, ``mesh_convergence_pct``, ``jitter_pct_h``, ``jitter_pct_h2``, ``n_states``,
``meshes`` (per element size: ``h_um``, ``area_mm2``, ``jitter_pct``, ``keyhole_depth_um``, ``peak_temperature_k``,
``error_vs_finest_pct``)), ``h_um``, ``refinements``, ``track_mm``, ``preset`` and ``config``.

Usage: ``python benchmarks/mesh_convergence.py [--preset physical] [--config FILE.toml]
[--powers 60 100 140 174 250] [--track-mm 5] [--refinements 2 [4]] [--json]``
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fe_node.cli import plant_table  # noqa: E402
from fe_node.presets import DEFAULT, NAMES  # noqa: E402
from fe_node.scan import ScanPlan  # noqa: E402
from fe_node.scenarios import scenario  # noqa: E402
from fe_node.settings import Settings  # noqa: E402
from fe_node.solver import ThermalModel  # noqa: E402
from messages.bus import single_threaded_blas  # noqa: E402
from messages.types import LASER_POWER_MAX_W  # noqa: E402

SPEED_M_S = 0.8
BUILD_UP_STEPS = 20
"""Steps of the pool's build-up left out of the window (as the controllers' report)."""


def steady_window(settings, power_w: float, track_m: float) -> dict:
    """The second half of a single track of ``track_m`` [m] at ``power_w`` [W], after the pool's build-up:
    ``area_m2`` (shape (n,)) and the means of the keyhole depth [m] and of the peak temperature [K]."""
    plant = ThermalModel(settings, ScanPlan.single(track_m))
    areas, depths, peaks = [], [], []
    while not plant.done:
        obs = plant.step(power_w, SPEED_M_S)
        areas.append(obs.area_m2)
        depths.append(plant.keyhole_depth_m())
        peaks.append(obs.t_peak_k)
    start = BUILD_UP_STEPS + (len(areas) - BUILD_UP_STEPS) // 2
    return {"area_m2": np.asarray(areas[start:]), "keyhole_depth_m": float(np.mean(depths[start:])),
            "peak_temperature_k": float(np.mean(peaks[start:]))}


def jitter_pct(areas: np.ndarray) -> float:
    """Rms of the step-to-step change of log(area) [%] (states with a pool)."""
    d = np.diff(np.log(areas[areas > 0]))
    return float(100.0 * np.sqrt(np.mean(d * d))) if d.size else float("nan")


def case(settings, power_w: float, track_m: float, refinements: tuple[int, ...] = (2,)) -> dict:
    """One power at the settings' element size ``h`` and at ``h / r`` for each of ``refinements`` (2 among them)."""
    sizes = (1, *sorted(set(refinements)))
    runs = [steady_window(replace(settings, h_fine_m=settings.h_fine_m / r), power_w, track_m) for r in sizes]
    means = [float(run["area_m2"].mean()) for run in runs]
    finest = means[-1]
    meshes = [{"h_um": round(settings.h_fine_m / r * 1e6, 4), "area_mm2": round(a * 1e6, 5),
               "jitter_pct": round(jitter_pct(run["area_m2"]), 2),
               "keyhole_depth_um": round(run["keyhole_depth_m"] * 1e6, 2),
               "peak_temperature_k": round(run["peak_temperature_k"], 1),
               "error_vs_finest_pct": round(100.0 * (a - finest) / finest, 2) if finest > 0 else None}
              for r, run, a in zip(sizes, runs, means, strict=True)]
    half = sizes.index(2)
    a, b = means[0], means[half]
    return {"power_w": power_w, "area_mm2_h": meshes[0]["area_mm2"], "area_mm2_h2": meshes[half]["area_mm2"],
            "mesh_convergence_pct": round(100.0 * (a - b) / b, 2) if b > 0 else None,
            "jitter_pct_h": meshes[0]["jitter_pct"], "jitter_pct_h2": meshes[half]["jitter_pct"],
            "n_states": int(runs[0]["area_m2"].size), "meshes": meshes}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--config", type=Path, help="TOML file whose [plant] table sets the plant over --preset "
                                                    "(the same table as launch.py --config)")
    parser.add_argument("--powers", type=float, nargs="+", default=[60.0, 100.0, 140.0, 174.0, 250.0],
                        help="laser powers [W] (default %(default)s)")
    parser.add_argument("--track-mm", type=float, default=5.0, help="track length [mm] (default %(default)s)")
    parser.add_argument("--refinements", type=int, nargs="+", default=[2],
                        help="element-size divisors of h to run besides h, 2 among them (default %(default)s; "
                             "2 4 adds h / 4)")
    parser.add_argument("--json", action="store_true", help="print the JSON record as the last line")
    args = parser.parse_args()
    if 2 not in args.refinements or not all(2 <= r <= 8 for r in args.refinements):
        parser.error("--refinements: divisors of h in [2, 8], 2 among them")
    if not all(0 < p <= LASER_POWER_MAX_W for p in args.powers):
        parser.error(f"--powers: every power must lie in (0, {LASER_POWER_MAX_W:g}] W")
    if not args.track_mm * 1e-3 > (BUILD_UP_STEPS + 4) * SPEED_M_S * Settings().dt_s:
        parser.error("--track-mm: the track must be longer than the pool's build-up and 4 steps (1 mm at 800 mm/s)")
    try:
        table = plant_table(args.config)
    except ValueError as err:
        parser.error(f"--config: {err}")
    try:
        settings = scenario("single-track", **{"preset": args.preset, **table}).settings
    except ValueError as err:
        parser.error(f"--config {args.config} [plant]: {err}" if args.config else str(err))
    single_threaded_blas()
    refinements = tuple(sorted(set(args.refinements)))
    cases = [case(settings, p, args.track_mm * 1e-3, refinements) for p in args.powers]
    print(f"{'power W':>8s} {'h um':>6s} {'area mm2':>9s} {'vs finest %':>11s} {'jitter %':>8s} {'keyhole um':>10s} "
          f"{'peak K':>7s}")
    for c in cases:
        for m in c["meshes"]:
            print(f"{c['power_w']:8.0f} {m['h_um']:6.2f} {m['area_mm2']:9.5f} {m['error_vs_finest_pct']:11.2f} "
                  f"{m['jitter_pct']:8.2f} {m['keyhole_depth_um']:10.1f} {m['peak_temperature_k']:7.1f}")
        print(f"{'':8s} mesh_convergence_pct (h vs h/2) {c['mesh_convergence_pct']:.2f}")
    record = {"preset": args.preset, "config": str(args.config) if args.config else None,
              "h_um": round(settings.h_fine_m * 1e6, 6), "refinements": list(refinements), "track_mm": args.track_mm,
              "cases": cases}
    if args.json:
        print(json.dumps(record))


if __name__ == "__main__":
    main()
