"""AM-Bench 2018 AMB2018-02: measured melt pools of single laser tracks on bare IN625 plates.

Data (copied here with their sources; docs/fe.md, "Calibration data"):

* B. M. Lane, J. C. Heigel, R. E. Ricker, I. Zhirnov, V. Khromchenko, J. S. Weaver, T. Q. Phan,
  M. R. Stoudt, S. Mekhontsev, L. E. Levine, "Measurements of melt pool geometry and cooling rates
  of individual laser traces on IN625 bare plates", Integrating Materials and Manufacturing
  Innovation 9 (2020) 16-30, doi:10.1007/s40192-020-00169-1: spot sizes (Table 1, D4σ diameters
  170 µm on NIST's AMMT, 100 µm on the EOS M270 "CBM"), applied powers and speeds (Table 3) and
  the CBM class means of width and depth (Table 4).
* NIST, "Results description for CHAL-AMB2018-02-AMMT-MP: melt pool geometry - width and depth",
  https://www.nist.gov/ambench/chal-amb2018-02-mp-xsection, Table 2: the AMMT case means (the
  AMMT powers are the calibrated applied powers, 137.9 and 179.2 W for 150 and 195 W commanded).

Widths and depths are those of the fusion boundary in transverse cross-sections; the plant
measures them on the solidus isotherm (the boundary of any melting).  Plate at room temperature
(not stated by the sources; 300 K assumed, as by the other models of this benchmark).
"""
from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from fe_node.scan import ScanPlan
from fe_node.settings import Settings
from fe_node.solver import ThermalModel


@dataclass(frozen=True)
class TrackCase:
    """One measured single track.

    Attributes
    ----------
    name : str
    power_w : float
        Applied laser power [W].
    speed_m_s : float
        Scan speed [m/s].
    d4sigma_m : float
        Spot D4σ (= 1/e²) diameter [m].
    width_m, depth_m : float
        Measured melt-pool width and depth [m].
    track_m : float
        Length of the simulated track [m]: at least twice the measured pool length.
    """

    name: str
    power_w: float
    speed_m_s: float
    d4sigma_m: float
    width_m: float
    depth_m: float
    track_m: float

    @property
    def beam_radius_m(self) -> float:
        """The eq. 6 radius ``r_s`` of this spot: ``exp(-3 rho² / r_s²) = exp(-2 rho² / w²)``, ``w = D4σ / 2``."""
        return 0.5 * self.d4sigma_m * math.sqrt(1.5)


CASES = (
    TrackCase("AMMT-A", 137.9, 0.4, 170e-6, 147.9e-6, 42.5e-6, 1.5e-3),
    TrackCase("AMMT-B", 179.2, 0.8, 170e-6, 123.5e-6, 36.0e-6, 1.5e-3),
    TrackCase("AMMT-C", 179.2, 1.2, 170e-6, 106.0e-6, 29.6e-6, 1.8e-3),
    TrackCase("CBM-A", 150.0, 0.4, 100e-6, 171e-6, 151e-6, 2.0e-3),
    TrackCase("CBM-B", 195.0, 0.8, 100e-6, 133e-6, 91e-6, 2.4e-3),
    TrackCase("CBM-C", 195.0, 1.2, 100e-6, 100e-6, 60e-6, 2.4e-3),
)
"""The AMB2018-02 cases (module docstring)."""

FINE_DEPTH_M = 250e-6
"""Depth of the fine band in the AM-Bench runs [m]: below the deepest measured pool (151 µm)."""
N_TAIL = 8
"""Steps at the end of a track whose pool geometry is averaged."""


def case_settings(settings: Settings, case: TrackCase) -> Settings:
    """``settings`` on a bare plate with the case's beam and a fine band below its deepest pool."""
    return replace(settings, beam_radius_m=case.beam_radius_m, powder_layer_m=0.0, n_layers=1,
                   fine_depth_m=max(settings.fine_depth_m, FINE_DEPTH_M),
                   depth_m=max(settings.depth_m, 2 * FINE_DEPTH_M), t0_k=300.0, window_m=0.0)


def track_geometry(settings: Settings, case: TrackCase) -> dict:
    """Simulated width and depth [m] of ``case`` on the plant of ``settings`` (bare plate).

    Returns
    -------
    dict
        ``width_m`` and ``depth_m`` on the solidus, mean over the last :data:`N_TAIL` steps, and
        ``t_peak_k`` [K] over the run.
    """
    s = case_settings(settings, case)
    model = ThermalModel(s, ScanPlan.single(case.track_m))
    n_steps = math.ceil(case.track_m / (case.speed_m_s * s.dt_s) - 1e-9)
    geo, peak = [], 0.0
    for k in range(n_steps - 1):     # the last step may leave the track
        peak = max(peak, model.step(case.power_w, case.speed_m_s).t_peak_k)
        if k >= n_steps - 1 - N_TAIL:
            geo.append(model.pool(s.material.t_solidus))
    return dict(width_m=float(np.mean([g["width_m"] for g in geo])),
                depth_m=float(np.mean([g["depth_m"] for g in geo])), t_peak_k=peak)
