"""The PID baseline tuned by a documented method on training runs only: SIMC rules on a
first-order-plus-dead-time (FOPDT) model fitted to the open-loop power staircases of ``learn``.

The FOPDT model, in discrete time along the tracks (the states at least
:data:`~controller_node.report.TURNAROUND_STEPS` after a track's start, so the turnarounds, which a
FOPDT cannot represent, do not bias it):

    x[k+1] = a x[k] + b p[k+1−d] + c,

is fitted for each delay d = 0 … :data:`MAX_DELAY_STEPS` (``p[j]`` is the power applied during step
j−1 → j, so ``d = 0`` already is one step of transport) by output-error least squares: the model is
simulated over each stretch along a track from the stretch's first measured area, and its
simulated areas are fitted to the measured ones (the one-step, equation-error fit starts it; it
trades the delay for a slower pole and gave a PID that oscillated on the FE plant). The delay of the
smallest simulation error is kept. Then ``K = b/(1−a)`` [m²/W], ``τ = −Δt/ln a`` [s] and the dead
time ``θ = (d + ½) Δt`` [s] (half a sample for the zero-order hold).

The SIMC PI rules (Skogestad 2003) with the closed-loop time constant ``τ_c = τ`` (the closed loop
as fast as the open loop, the IMC choice λ = τ):

    K_c = τ / (K (τ_c + θ)),   τ_I = min(τ, 4 (τ_c + θ)),

in the units of :class:`~controller_node.settings.PIDSettings` (relative error
``e = (x_sp − x)/x_sp``): ``kp_w = K_c x_sp``, ``ki_w = kp_w Δt/τ_I`` per step, ``kd_w = 0``.
The tight choice ``τ_c = θ`` of the SIMC paper, on the physical plant's training double track
(``python launch.py --scenario double-track --controller pid``), oscillated along the tracks:
25.46 % RMSE (26.62 % along the tracks) against 15.72 % (6.24 %) with ``τ_c = τ`` (the FOPDT model
misses the plant's nonlinearity, and the tight loop amplifies it); only that training geometry was
compared.

Reference: S. Skogestad, "Simple analytic rules for model reduction and PID controller tuning",
J. Process Control 13 (2003) 291–309, doi:10.1016/S0959-1524(02)00062-8.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from controller_node.report import TURNAROUND_STEPS
from gp_model.build_up import steps_at
from gp_model.errors import DatasetError
from gp_model.narx import RunSeries

__all__ = ["Fopdt", "MAX_DELAY_STEPS", "METHOD", "fit_fopdt", "pid_record", "simc_gains"]

MAX_DELAY_STEPS = 10
"""Largest delay d [steps] the FOPDT fit tries."""
METHOD = ("SIMC PI rules (Skogestad, J. Process Control 13 (2003) 291-309), tau_c = tau, on a FOPDT model "
          "fitted to the training power staircases along the tracks")
"""How the gains were found, as the model's record states it."""


@dataclass(frozen=True)
class Fopdt:
    """A first-order-plus-dead-time model of the area's response to power (module docstring).

    Attributes
    ----------
    gain_m2_per_w : float
        Steady gain K [m²/W] (> 0).
    time_constant_s : float
        Time constant τ [s] (> 0).
    dead_time_s : float
        Dead time θ = (d + ½) Δt [s].
    delay_steps : int
        The delay d [steps] of the best fit.
    sample_period_s : float
        Δt [s].
    residual_rms_m2 : float
        Simulation error of the fit along the tracks [m²].
    n_samples : int
        Samples of the fit.
    """

    gain_m2_per_w: float
    time_constant_s: float
    dead_time_s: float
    delay_steps: int
    sample_period_s: float
    residual_rms_m2: float
    n_samples: int


class TooFewSamplesError(DatasetError):
    """The staircases leave too few samples for a FOPDT fit where it looks (along the tracks, or over each layer)."""


def _along_track(run: RunSeries, skip_steps: int, by_layer: bool = False) -> np.ndarray:
    """Mask, shape (n,), of the states at least ``skip_steps`` after their track's (or layer's) start
    (``by_layer``: after their layer's start only)."""
    new_layer = np.diff(run.layers()) != 0
    new_track = np.r_[True, new_layer if by_layer else (np.diff(run.track) != 0) | new_layer]
    start = np.maximum.accumulate(np.where(new_track, np.arange(len(run)), 0))
    return np.arange(len(run)) - start >= skip_steps


def _stretches(runs: Sequence[RunSeries], skip_steps: int, delay: int, by_layer: bool = False
               ) -> list[tuple[np.ndarray, np.ndarray]]:
    """``(area [m²], power [W] acting on each step)`` of every stretch of consecutive states at least
    ``skip_steps`` after their track's (``by_layer``: layer's) start: ``power[j]`` drives ``area[j] → area[j+1]``."""
    out = []
    for run in runs:
        keep = _along_track(run, skip_steps, by_layer)
        keep[:max(delay, 1)] = False
        edges = np.flatnonzero(np.diff(np.r_[0, keep.astype(int), 0]))
        for start, stop in zip(edges[::2], edges[1::2]):
            if stop - start >= 2:
                k = np.arange(start, stop - 1)
                out.append((run.area_m2[start:stop], run.power_w[k + 1 - delay]))
    return out


def _simulated(theta: np.ndarray, stretches: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """Simulation errors [m²] of ``x[k+1] = a x[k] + b p + c`` over every stretch, from its first area."""
    from scipy.signal import lfilter  # here: every `python -m gp_trainer` command imports this module

    a, b, c = theta
    errors = [lfilter([1.0], [1.0, -a], b * power + c, zi=[a * area[0]])[0] - area[1:] for area, power in stretches]
    return np.concatenate(errors)


def _scaled_errors(q: np.ndarray, scale: np.ndarray, stretches: list[tuple[np.ndarray, np.ndarray]]) -> np.ndarray:
    """:func:`_simulated` at ``θ = q · scale`` in units of ``scale[2]`` (well-conditioned for the solver)."""
    return _simulated(q * scale, stretches) / scale[2]


def fit_fopdt(runs: Sequence[RunSeries], skip_steps: int | None = None, by_layer: bool = False) -> Fopdt:
    """The FOPDT model of ``runs`` (open-loop power staircases of one process), module docstring.

    Parameters
    ----------
    runs : sequence of RunSeries
        The runs, of one sample period.
    skip_steps : int, optional
        States after a track's start left out of the fit (default :data:`TURNAROUND_STEPS` at the FE step,
        the same time at another sample period: :func:`gp_model.build_up.steps_at`). The delays tried,
        up to :data:`MAX_DELAY_STEPS` at the FE step, are scaled the same way.
    by_layer : bool
        Fit over each layer's states, across its tracks (a part: its hatches are shorter than the
        turnaround window, and a few frames long at a camera's frame period); the states skipped are those
        after each layer's start.

    Raises
    ------
    DatasetError
        Runs of different sample periods, too few samples, or a fit that is not a stable positive
        gain (0 < a < 1, b > 0): the staircases do not excite the process.
    """
    from scipy.optimize import least_squares  # here: as scipy.signal in _simulated (tests/test_light_imports.py)

    periods = {round(r.sample_period_s, 12) for r in runs}
    if len(periods) != 1:
        raise DatasetError(f"the staircases have different sample periods: {sorted(periods)} s")
    dt = periods.pop()
    skip_steps = steps_at(TURNAROUND_STEPS, dt) if skip_steps is None else skip_steps
    best = None
    for delay in range(steps_at(MAX_DELAY_STEPS, dt) + 1):
        stretches = _stretches(runs, skip_steps, delay, by_layer)
        n = sum(area.size - 1 for area, _ in stretches)
        if n < 30:
            where = "over the layers" if by_layer else "along the tracks"
            raise TooFewSamplesError(f"the staircases give {n} samples {where}, too few for a FOPDT fit")
        X = np.vstack([np.column_stack([area[:-1], power, np.ones(power.size)]) for area, power in stretches])
        y = np.concatenate([area[1:] for area, _ in stretches])
        start, *_ = np.linalg.lstsq(X, y, rcond=None)                  # equation error: the initial guess
        if not 0.0 < start[0] < 1.0:
            continue
        scale = np.abs(start) + 1e-30
        fit = least_squares(_scaled_errors, np.ones(3), args=(scale, stretches),
                            bounds=([1e-6 / scale[0], -np.inf, -np.inf], [(1 - 1e-9) / scale[0], np.inf, np.inf]))
        theta = fit.x * scale
        rms = float(np.sqrt(np.mean(_simulated(theta, stretches) ** 2)))
        if best is None or rms < best[0]:
            best = (rms, delay, theta, n)
    if best is None or not best[2][1] > 0.0:
        raise DatasetError("the FOPDT fit is not a stable positive gain: the staircases do not excite the process")
    rms, delay, (a, b, _), n = best
    return Fopdt(gain_m2_per_w=float(b / (1.0 - a)), time_constant_s=float(-dt / math.log(a)),
                 dead_time_s=(delay + 0.5) * dt, delay_steps=int(delay), sample_period_s=dt,
                 residual_rms_m2=rms, n_samples=int(n))


def simc_gains(model: Fopdt, set_point_m2: float) -> dict[str, float]:
    """SIMC PI gains (module docstring) as ``kp_w``, ``ki_w`` (per step) and ``kd_w`` [W per unit
    relative error] at the set point ``set_point_m2`` [m²]."""
    if not set_point_m2 > 0:
        raise ValueError(f"set_point_m2 must be > 0, got {set_point_m2}")
    tau_c = model.time_constant_s
    kc = model.time_constant_s / (model.gain_m2_per_w * (tau_c + model.dead_time_s))
    tau_i = min(model.time_constant_s, 4.0 * (tau_c + model.dead_time_s))
    kp_w = kc * set_point_m2
    return {"kp_w": float(kp_w), "ki_w": float(kp_w * model.sample_period_s / tau_i), "kd_w": 0.0}


def pid_record(runs: Sequence[RunSeries], set_point_m2: float, part: bool = False) -> dict[str, Any]:
    """The ``pid`` entry of a model's ``provenance.controller``: the gains, the method, the FOPDT
    model (:func:`fit_fopdt`) and the runs it was fitted on. On a ``part`` whose hatches leave too few
    samples along the tracks (at a camera's frame period a hatch is a few frames), the fit runs over each
    layer (``by_layer``)."""
    by_layer = False
    try:
        model = fit_fopdt(runs)
    except TooFewSamplesError:
        if not part:
            raise
        model, by_layer = fit_fopdt(runs, by_layer=True), True
    method = METHOD.replace("along the tracks", "over each layer") if by_layer else METHOD
    return {**simc_gains(model, set_point_m2), "method": method, "fopdt": asdict(model),
            "runs": [r.name for r in runs]}
