"""``python -m fe_node validate``: the plant checked against analytic, numerical and measured references.

Every figure has a limit (:data:`CHECKS`); the command exits 1 naming each failed check.

* ``energy_error_pct``: largest |error| of the energy balance (absorbed = stored, latent heat
  included, + convection, radiation, evaporation and plate losses) over a double track
  (2 x 5 mm, 250 W, 800 mm/s) on the plant; the same run gives ``peak_temperature_k`` (the
  hottest node over the run).
* ``eagar_tsai_area_error_pct``: the FE top-surface area against Eagar-Tsai's moving Gaussian
  source (constant properties k = 20 W/(m K), rho = 8440 kg/m³, cp = 600 J/(kg K), no latent
  heat, no losses, 250 W, a = 0.4, r_s = 50 µm, 800 mm/s, 3 mm track).
* ``mesh_convergence_pct``: the plant's single-track area (3 mm, 250 W, 800 mm/s) at ``h``
  against ``h / 2``; ``dt_convergence_pct``: the same track with the default sub-steps against
  8 times as many.
* ``in625_reference_error_pct``: the melting column of :mod:`fe_node.reference`.
* ``am_bench_width_error_pct``, ``am_bench_depth_error_pct``: the largest |error| of the plant's
  widths and depths over the AM-Bench single tracks (:mod:`fe_node.am_bench`), each on the bare
  plate with its measured beam.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np

from fe_node.am_bench import CASES
from fe_node.calibrate import case_errors
from fe_node.driver import run_open_loop
from fe_node.eagar_tsai import EagarTsai, EagarTsaiCase
from fe_node.material import Material
from fe_node.reference import in625_reference
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.settings import Settings
from fe_node.solver import ThermalModel

CHECKS = {
    "energy_error_pct": (-1e-6, 1e-6),
    "peak_temperature_k": (0.0, 3500.0),
    "eagar_tsai_area_error_pct": (-5.0, 5.0),
    "mesh_convergence_pct": (-1.5, 1.5),
    "dt_convergence_pct": (-1.5, 1.5),
    "in625_reference_error_pct": (0.0, 2.0),
    "am_bench_width_error_pct": (0.0, 10.0),
    "am_bench_depth_error_pct": (0.0, 15.0),
}
"""Each checked figure and its closed interval of acceptance."""


def fe_eagar_tsai_area(case: EagarTsaiCase, h_fine_m: float, track_m: float = 3e-3,
                       n_avg: int = 10) -> float:
    """FE top-surface melt-pool area [m²] for an Eagar-Tsai case (mean of last steps)."""
    settings = Settings(material=Material.constant(case.k, case.rho, case.cp),
                        absorptivity=case.absorptivity, beam_radius_m=case.beam_radius_m,
                        h_fine_m=h_fine_m, t0_k=case.t0_k, t_amb_k=case.t0_k,
                        h_conv_w_m2k=0.0, emissivity=0.0, powder_layer_m=0.0, evaporation=False,
                        keyhole=False, liquid_k_factor_xy=1.0, liquid_k_factor_z=1.0)
    model = ThermalModel(settings, ScanPlan.single(track_m))
    areas = []
    while not model.done:
        areas.append(model.step(case.power_w, case.speed_m_s).area_m2)
    return float(np.mean(areas[-n_avg:]))


def track(settings: Settings, track_m: float = 3e-3, power_w: float = 250.0, speed_m_s: float = 0.8,
          n_avg: int = 10) -> tuple[float, float]:
    """Single track: top-surface melt-pool area [m²] (mean of the last ``n_avg`` steps) and peak temperature [K]."""
    model = ThermalModel(settings, ScanPlan.single(track_m))
    obs = []
    while not model.done:
        obs.append(model.step(power_w, speed_m_s))
    return float(np.mean([o.area_m2 for o in obs[-n_avg:]])), float(max(o.t_peak_k for o in obs))


def failures(report: dict) -> list[str]:
    """One line per figure of ``report`` outside its :data:`CHECKS` interval."""
    out = []
    for key, (lo, hi) in CHECKS.items():
        value = report[key]
        if not lo <= value <= hi:
            out.append(f"{key} = {value:.4g} outside [{lo:g}, {hi:g}]")
    return out


def validate(s: Settings, progress: bool = False) -> dict:
    """Run the checks on the plant of settings ``s`` (``python -m fe_node validate``: the default
    plant's, :data:`fe_node.presets.DEFAULT`); the JSON-ready report: every :data:`CHECKS` figure,
    ``passed``, ``failed`` and the details of each check."""
    h = s.h_fine_m
    et = EagarTsaiCase()
    analytic = EagarTsai(et).geometry()["area_m2"]
    fe_et = fe_eagar_tsai_area(et, h)
    obs = run_open_loop(replace(scenario("double-track"), settings=s), progress=progress)
    area_h2 = track(replace(s, h_fine_m=h / 2))[0]
    n_default = ThermalModel(s, ScanPlan.single(1e-3)).n_substeps
    areas = {n: track(replace(s, min_substeps=n))[0] for n in (n_default, 8 * n_default)}
    reference = in625_reference(s)
    am_bench = case_errors(s, CASES)
    report = dict(
        energy_error_pct=float(max(abs(o.energy_error_pct) for o in obs)),
        peak_temperature_k=float(max(o.t_peak_k for o in obs)),
        eagar_tsai_area_error_pct=100 * (fe_et - analytic) / analytic,
        mesh_convergence_pct=100 * (areas[n_default] - area_h2) / area_h2,
        dt_convergence_pct=100 * (areas[n_default] - areas[8 * n_default]) / areas[8 * n_default],
        in625_reference_error_pct=reference["error_pct"],
        am_bench_width_error_pct=max(abs(r["width_error_pct"]) for r in am_bench),
        am_bench_depth_error_pct=max(abs(r["depth_error_pct"]) for r in am_bench),
    )
    failed = failures(report)
    return dict(report, passed=not failed, failed=failed, checks={k: list(v) for k, v in CHECKS.items()},
                details=dict(
                    energy_case="double-track, 2 x 5 mm, 250 W, 800 mm/s, on the plant",
                    eagar_tsai=dict(et.as_dict(), fe_area_mm2=fe_et * 1e6, analytic_area_mm2=analytic * 1e6),
                    mesh_convergence=dict(h_um=[round(h * 1e6, 6), round(h * 0.5e6, 6)],
                                          area_mm2=[areas[n_default] * 1e6, area_h2 * 1e6]),
                    dt_convergence=dict(substeps=[n_default, 8 * n_default],
                                        area_mm2=[areas[n_default] * 1e6, areas[8 * n_default] * 1e6]),
                    in625_reference=reference, am_bench=am_bench))
