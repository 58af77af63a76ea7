"""Mesh convergence of the plant's melt-pool area over the power range: the default plant at ``h`` and ``h / 2``.

``python -m fe_node validate`` checks the mesh on one single track at 250 W (``mesh_convergence_pct``). This
benchmark runs the same single track (in process, on the uniform mesh, ``--preset``) at each power of ``--powers``
with the preset's element size ``h`` and with ``h / 2``, and reports for each: the mean area over the second half
of the track after the pool's build-up (20 steps) at both sizes, their difference in % of the fine one
(``mesh_convergence_pct``, as ``validate`` defines it), and the step-to-step jitter of the area over that window
(rms of the change of its logarithm, %) at both sizes. A pool a few elements wide is under-resolved: its area is
low and jitters as the pool's edge crosses nodes.

Prints a table; with ``--json``, then, as the last line, JSON with ``cases`` (per power: ``power_w``,
``area_mm2_h``, ``area_mm2_h2``, ``mesh_convergence_pct``, ``jitter_pct_h``, ``jitter_pct_h2``, ``n_states``),
``h_um``, ``track_mm`` and ``preset``.

Usage: ``python benchmarks/mesh_convergence.py [--preset physical] [--powers 60 100 140 174 250] [--track-mm 5]
[--json]``
"""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

from fe_node.presets import DEFAULT, NAMES, preset  # noqa: E402
from fe_node.scan import ScanPlan  # noqa: E402
from fe_node.settings import Settings  # noqa: E402
from fe_node.solver import ThermalModel  # noqa: E402
from messages.bus import single_threaded_blas  # noqa: E402
from messages.types import LASER_POWER_MAX_W  # noqa: E402

SPEED_M_S = 0.8
BUILD_UP_STEPS = 20
"""Steps of the pool's build-up left out of the window (as the controllers' report)."""


def steady_areas(settings, power_w: float, track_m: float) -> np.ndarray:
    """The pool's area [m²] over the second half of a single track of ``track_m`` [m] at ``power_w`` [W], after
    the build-up, shape (n,)."""
    plant = ThermalModel(settings, ScanPlan.single(track_m))
    areas = []
    while not plant.done:
        areas.append(plant.step(power_w, SPEED_M_S).area_m2)
    after = np.asarray(areas[BUILD_UP_STEPS:])
    return after[len(after) // 2:]


def jitter_pct(areas: np.ndarray) -> float:
    """Rms of the step-to-step change of log(area) [%] (states with a pool)."""
    d = np.diff(np.log(areas[areas > 0]))
    return float(100.0 * np.sqrt(np.mean(d * d))) if d.size else float("nan")


def case(settings, power_w: float, track_m: float) -> dict:
    """One power at the settings' element size and at half of it."""
    coarse = steady_areas(settings, power_w, track_m)
    fine = steady_areas(replace(settings, h_fine_m=settings.h_fine_m / 2), power_w, track_m)
    a, b = float(coarse.mean()), float(fine.mean())
    return {"power_w": power_w, "area_mm2_h": round(a * 1e6, 5), "area_mm2_h2": round(b * 1e6, 5),
            "mesh_convergence_pct": round(100.0 * (a - b) / b, 2) if b > 0 else None,
            "jitter_pct_h": round(jitter_pct(coarse), 2), "jitter_pct_h2": round(jitter_pct(fine), 2),
            "n_states": int(coarse.size)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--preset", choices=NAMES, default=DEFAULT, help="plant preset (default %(default)s)")
    parser.add_argument("--powers", type=float, nargs="+", default=[60.0, 100.0, 140.0, 174.0, 250.0],
                        help="laser powers [W] (default %(default)s)")
    parser.add_argument("--track-mm", type=float, default=5.0, help="track length [mm] (default %(default)s)")
    parser.add_argument("--json", action="store_true", help="print the JSON record as the last line")
    args = parser.parse_args()
    if not all(0 < p <= LASER_POWER_MAX_W for p in args.powers):
        parser.error(f"--powers: every power must lie in (0, {LASER_POWER_MAX_W:g}] W")
    if not args.track_mm * 1e-3 > (BUILD_UP_STEPS + 4) * SPEED_M_S * Settings().dt_s:
        parser.error("--track-mm: the track must be longer than the pool's build-up and 4 steps (1 mm at 800 mm/s)")
    single_threaded_blas()
    settings = Settings(**preset(args.preset))
    cases = [case(settings, p, args.track_mm * 1e-3) for p in args.powers]
    print(f"{'power W':>8s} {'area h mm2':>11s} {'area h/2':>9s} {'diff %':>7s} {'jitter h %':>11s} {'h/2 %':>6s}")
    for c in cases:
        print(f"{c['power_w']:8.0f} {c['area_mm2_h']:11.5f} {c['area_mm2_h2']:9.5f} {c['mesh_convergence_pct']:7.2f} "
              f"{c['jitter_pct_h']:11.2f} {c['jitter_pct_h2']:6.2f}")
    record = {"preset": args.preset, "h_um": round(settings.h_fine_m * 1e6, 6), "track_mm": args.track_mm,
              "cases": cases}
    if args.json:
        print(json.dumps(record))


if __name__ == "__main__":
    main()
