"""Verification of the thermal model against energy balance, Eagar-Tsai and a finer mesh.

* Eagar-Tsai: constant properties k = 20 W/(m K), rho = 8440 kg/m³, cp = 600 J/(kg K),
  no latent heat, no surface losses, 250 W, a = 0.4, r_s = 50 µm, 800 mm/s, 3 mm track;
  the FE top-surface area (mean over the last 10 steps) vs the analytic one.
* Mesh convergence: the same FE case at ``h`` and ``h / 2``.
* Energy: largest |error| of the energy balance over a double track with IN625
  (temperature-dependent, latent heat) and convection + radiation; the same run gives
  ``peak_temperature_k`` (the hottest node over the run).
* Time step: IN625 single track (3 mm, 250 W, 800 mm/s, default settings at ``h``), the
  area with the default sub-steps vs 8 times as many (``dt_convergence_pct``).
* IN625 reference: the melting column of :mod:`fe_node.reference`
  (``in625_reference_error_pct``: largest nodal temperature error, % of the surface rise).
* Powder: the same single track on a 25 µm powder layer over the bare plate
  (``powder_area_ratio``, :class:`~fe_node.settings.Settings` ``powder_layer_m``), and its
  peak temperature with evaporative cooling on (``peak_temperature_evaporation_k``).
"""
from __future__ import annotations

import numpy as np

from fe_node.driver import run_open_loop
from fe_node.eagar_tsai import EagarTsai, EagarTsaiCase
from fe_node.material import Material
from fe_node.reference import in625_reference
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.settings import Settings
from fe_node.solver import ThermalModel


def fe_eagar_tsai_area(case: EagarTsaiCase, h_fine_m: float, track_m: float = 3e-3,
                       n_avg: int = 10) -> float:
    """FE top-surface melt-pool area [m²] for an Eagar-Tsai case (mean of last steps)."""
    settings = Settings(material=Material.constant(case.k, case.rho, case.cp),
                        absorptivity=case.absorptivity, beam_radius_m=case.beam_radius_m,
                        h_fine_m=h_fine_m, t0_k=case.t0_k, t_amb_k=case.t0_k,
                        h_conv_w_m2k=0.0, emissivity=0.0)
    model = ThermalModel(settings, ScanPlan.single(track_m))
    areas = []
    while not model.done:
        areas.append(model.step(case.power_w, case.speed_m_s).area_m2)
    return float(np.mean(areas[-n_avg:]))


POWDER_LAYER_M = 25e-6
"""Powder layer of the powder check [m] (one element at the default mesh)."""


def track(settings: Settings, track_m: float = 3e-3, power_w: float = 250.0, speed_m_s: float = 0.8,
          n_avg: int = 10) -> tuple[float, float]:
    """Single track: top-surface melt-pool area [m²] (mean of the last ``n_avg`` steps) and peak temperature [K]."""
    model = ThermalModel(settings, ScanPlan.single(track_m))
    obs = []
    while not model.done:
        obs.append(model.step(power_w, speed_m_s))
    return float(np.mean([o.area_m2 for o in obs[-n_avg:]])), float(max(o.t_peak_k for o in obs))


def validate(h_fine_m: float = 25e-6, progress: bool = False) -> dict:
    """Run the three checks; returns the JSON-ready report (see module docstring)."""
    case = EagarTsaiCase()
    analytic = EagarTsai(case).geometry()["area_m2"]
    fe_h = fe_eagar_tsai_area(case, h_fine_m)
    fe_h2 = fe_eagar_tsai_area(case, h_fine_m / 2)
    obs = run_open_loop(scenario("double-track", h_fine_m=h_fine_m), progress=progress)
    n_default = ThermalModel(Settings(h_fine_m=h_fine_m), ScanPlan.single(1e-3)).n_substeps
    areas = {n: track(Settings(h_fine_m=h_fine_m, min_substeps=n))[0] for n in (n_default, 8 * n_default)}
    powder = track(Settings(h_fine_m=h_fine_m, powder_layer_m=POWDER_LAYER_M))[0]
    _, peak_evaporation = track(Settings(h_fine_m=h_fine_m, evaporation=True))
    reference = in625_reference(Settings(h_fine_m=h_fine_m))
    return dict(
        energy_error_pct=float(max(abs(o.energy_error_pct) for o in obs)),
        energy_case="double-track IN625, 2 x 5 mm, 250 W, 800 mm/s, convection + radiation",
        eagar_tsai_area_error_pct=100 * (fe_h - analytic) / analytic,
        mesh_convergence_pct=100 * (fe_h - fe_h2) / fe_h2,
        mesh_convergence_h_um=[round(h_fine_m * 1e6, 6), round(h_fine_m * 0.5e6, 6)],
        fe_area_h2_mm2=fe_h2 * 1e6,
        dt_convergence_pct=100 * (areas[n_default] - areas[8 * n_default]) / areas[8 * n_default],
        dt_convergence_area_mm2=dict(default=areas[n_default] * 1e6, substeps_x8=areas[8 * n_default] * 1e6),
        dt_convergence_substeps=[n_default, 8 * n_default],
        in625_reference_error_pct=reference["error_pct"],
        in625_reference=reference,
        peak_temperature_k=float(max(o.t_peak_k for o in obs)),
        peak_temperature_evaporation_k=peak_evaporation,
        powder_area_ratio=powder / areas[n_default],
        powder_layer_um=round(POWDER_LAYER_M * 1e6, 6),
        eagar_tsai_case=dict(case.as_dict(), fe_area_mm2=fe_h * 1e6,
                             analytic_area_mm2=analytic * 1e6, h_um=round(h_fine_m * 1e6, 6)),
    )
