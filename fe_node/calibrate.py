"""Calibration of the plant against the AM-Bench single tracks (``python -m fe_node calibrate``).

Fits the dense-metal ``absorptivity``, the ``keyhole_radius_factor`` (:mod:`fe_node.keyhole`),
the liquid conductivity factors ``liquid_k_factor_xy`` and ``liquid_k_factor_z`` (Marangoni flow)
and the penetration depth of the absorbed power ``penetration_depth_m`` (c of eq. 6) of
:class:`~fe_node.settings.Settings` to the measured widths and depths of
:data:`fe_node.am_bench.CASES`: Nelder-Mead on :func:`objective`, each evaluation the six tracks
on the bare plate with evaporation and keyhole onset on.  The record it
writes (:data:`fe_node.presets.CALIBRATION_PATH`) holds the fitted values, the data source, the per-case
residuals and the command; :class:`~fe_node.settings.Settings` takes its defaults from it.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
from scipy.optimize import minimize

from fe_node.am_bench import CASES, TrackCase, track_geometry
from fe_node.settings import Settings

FIT_BOUNDS = {"absorptivity": (0.15, 0.7), "keyhole_radius_factor": (0.1, 1.0),
              "liquid_k_factor_xy": (1.0, 6.0), "liquid_k_factor_z": (1.0, 6.0),
              "penetration_depth_m": (0.0, 60e-6)}
"""Fitted settings and their bounds."""
ERROR_SCALES_PCT = {"width_error_pct": 10.0, "depth_error_pct": 15.0}
"""Scale [%] of each kind of error in :func:`objective`: the acceptance limits of ``validate``
(:data:`fe_node.validate.CHECKS`), so that a width and a depth error count alike at their limits."""
NORM_ORDER = 8
"""Order p of the error norm of :func:`objective`: near the largest error (p -> inf) yet smooth."""
SOURCE = ("AM-Bench 2018 AMB2018-02, IN625 bare-plate single tracks: Lane et al., Integr. Mater. Manuf. "
          "Innov. 9 (2020) 16-30, doi:10.1007/s40192-020-00169-1 (Tables 1, 3, 4); NIST CHAL-AMB2018-02-AMMT-MP "
          "results, Table 2")


def case_errors(settings: Settings, cases: tuple[TrackCase, ...] = CASES) -> list[dict]:
    """Simulated against measured width and depth of each case, errors in % of the measurement."""
    rows = []
    for case in cases:
        g = track_geometry(settings, case)
        rows.append(dict(case=case.name, power_w=case.power_w, speed_mm_s=case.speed_m_s * 1e3,
                         d4sigma_um=round(case.d4sigma_m * 1e6, 3),
                         width_um=g["width_m"] * 1e6, measured_width_um=case.width_m * 1e6,
                         width_error_pct=100 * (g["width_m"] - case.width_m) / case.width_m,
                         depth_um=g["depth_m"] * 1e6, measured_depth_um=case.depth_m * 1e6,
                         depth_error_pct=100 * (g["depth_m"] - case.depth_m) / case.depth_m,
                         t_peak_k=g["t_peak_k"]))
    return rows


def objective(rows: list[dict]) -> float:
    """Cost [-] of the per-case errors of :func:`case_errors`: the p-norm (:data:`NORM_ORDER`) of
    the 12 errors, each over its :data:`ERROR_SCALES_PCT`.  Near the largest scaled error, so the
    fit serves each case's limit rather than the mean (least squares left the keyholing case
    outside its limits while the others were well inside)."""
    scaled = [abs(r[k]) / v for r in rows for k, v in ERROR_SCALES_PCT.items()]
    return float(np.sum(np.power(scaled, NORM_ORDER)) ** (1.0 / NORM_ORDER))


def _with(base: Settings, x: np.ndarray) -> Settings:
    return replace(base, **{k: float(v) for k, v in zip(FIT_BOUNDS, x)})


def calibrate(base: Settings, max_evaluations: int = 40, log=print) -> dict:
    """Fit :data:`FIT_BOUNDS`'s settings on ``base`` (module docstring), starting from ``base``'s
    values with a simplex of 20 % steps; returns the record of the best evaluated point."""
    lo, hi = (np.array(b) for b in zip(*FIT_BOUNDS.values()))
    x0 = np.array([getattr(base, k) for k in FIT_BOUNDS], dtype=float)
    best = {"cost": math.inf, "x": x0}

    def cost(x):
        if np.any(x < lo) or np.any(x > hi):
            return 1e6 * (1.0 + float(np.sum(np.maximum(lo - x, 0) + np.maximum(x - hi, 0))))
        rows = case_errors(_with(base, x))
        c = objective(rows)
        log(" ".join(f"{k}={v:.4g}" for k, v in zip(FIT_BOUNDS, x)) + f"  cost {c:.4f}")
        if c < best["cost"]:
            best.update(cost=c, x=x.copy())
        return c

    steps = 0.2 * np.where(x0 > 0, x0, hi - lo)
    simplex = np.clip(np.vstack([x0, x0 + np.diag(steps)]), lo, hi)
    res = minimize(cost, x0, method="Nelder-Mead",
                   options=dict(maxfev=max_evaluations, initial_simplex=simplex, xatol=1e-4, fatol=1e-3))
    fitted = {k: float(f"{v:.4g}") for k, v in zip(FIT_BOUNDS, best["x"])}
    rows = case_errors(replace(base, **fitted))
    errors = [r[e] for r in rows for e in ("width_error_pct", "depth_error_pct")]
    return dict(source=SOURCE, command="python -m fe_node calibrate", start=dict(zip(FIT_BOUNDS, x0.tolist())),
                fitted=fitted,
                fixed={k: getattr(base, k) for k in ("evaporation", "keyhole", "h_fine_m", "powder_absorptivity")},
                objective=f"p-norm, p = {NORM_ORDER}, of the errors over {ERROR_SCALES_PCT}",
                evaluations=int(res.nfev), cost=best["cost"],
                rms_error_pct=math.sqrt(float(np.mean(np.square(errors)))),
                max_width_error_pct=max(abs(r["width_error_pct"]) for r in rows),
                max_depth_error_pct=max(abs(r["depth_error_pct"]) for r in rows), cases=rows)
