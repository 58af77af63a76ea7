"""Smooth analytic melt-pool model, multi-track temperature profile and a closed-loop loop.

Used by the tests and ``benchmarks/bench_controller.py`` as a stand-in plant (and as
a stand-in model where no GP is at hand).  The model is a first-order lag towards a
quasi-steady area that follows Rosenthal-like scalings::

    x_ss(T, p, v) = x_ref · (p̃ / p_ref)^n_p · ((T_l − T_amb) / d̃(T))^n_T · (v_ref / v)^n_v
    x[k+1]        = x[k] + α · (x_ss − x[k])

with smooth positive surrogates ``p̃ = sqrt(p² + p_s²)`` and
``d̃ = (d + sqrt(d² + w²)) / 2``, ``d = T_l − T`` (finite and differentiable everywhere
for finite inputs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from messages import in625

from .types import Diagnostics, Measurement

__all__ = ["AnalyticMeltPoolModel", "multitrack_temperature", "ClosedLoopResult", "run_closed_loop"]


@dataclass(frozen=True)
class AnalyticMeltPoolModel:
    """Analytic one-step model with the ``GPModel`` API (SI units, ``z`` shape (4,)).

    Parameters
    ----------
    area_ref_m2 : float
        Quasi-steady area at ``(p_ref, T_amb, v_ref)`` [m²].
    power_ref_w, speed_ref_m_s, t_ambient_k, t_liquidus_k : float
        Reference power [W], speed [m/s], ambient and liquidus temperatures [K].
    n_p, n_t, n_v : float
        Exponents of power, preheat and speed.
    alpha : float
        Lag per step (0 < alpha <= 1).
    std_m2 : float
        Constant predictive standard deviation reported by :meth:`predict` [m²].
    """

    area_ref_m2: float = 0.07e-6
    power_ref_w: float = 250.0
    speed_ref_m_s: float = 0.8
    t_ambient_k: float = 300.0
    t_liquidus_k: float = in625.T_LIQUIDUS_K
    n_p: float = 1.2
    n_t: float = 0.5
    n_v: float = 0.5
    alpha: float = 0.3
    std_m2: float = 2e-9
    power_soft_w: float = 5.0
    t_soft_k: float = 50.0

    def _steady(self, z: np.ndarray) -> tuple[float, float, float, float]:
        """Return ``x_ss`` [m²] and its partials w.r.t. T, p, v."""
        t, p, v = float(z[1]), float(z[2]), float(z[3])
        p_eff = math.sqrt(p * p + self.power_soft_w**2)
        d = self.t_liquidus_k - t
        root = math.sqrt(d * d + self.t_soft_k**2)
        d_eff = 0.5 * (d + root)
        x_ss = (
            self.area_ref_m2
            * (p_eff / self.power_ref_w) ** self.n_p
            * ((self.t_liquidus_k - self.t_ambient_k) / d_eff) ** self.n_t
            * (self.speed_ref_m_s / v) ** self.n_v
        )
        dd_eff_dt = -0.5 * (1.0 + d / root)
        return (
            x_ss,
            -x_ss * self.n_t / d_eff * dd_eff_dt,
            x_ss * self.n_p * p / (p_eff * p_eff),
            -x_ss * self.n_v / v,
        )

    def mean_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Mean of ``x[k+1]`` [m²] and its gradient w.r.t. ``z``, shape (4,)."""
        x = float(z[0])
        x_ss, d_t, d_p, d_v = self._steady(z)
        mean = x + self.alpha * (x_ss - x)
        jac = np.array([1.0 - self.alpha, self.alpha * d_t, self.alpha * d_p, self.alpha * d_v])
        return mean, jac

    def predict(self, z: np.ndarray) -> tuple[float, float]:
        """Mean [m²] and (constant) variance [m⁴] of ``x[k+1]``."""
        x = float(z[0])
        x_ss = self._steady(z)[0]
        return x + self.alpha * (x_ss - x), self.std_m2**2

    def steady_power_w(self, area_m2: float, t_k: float, speed_m_s: float) -> float:
        """Power [W] whose quasi-steady area is ``area_m2`` at ``(T, v)`` (for checks)."""
        d = self.t_liquidus_k - t_k
        d_eff = 0.5 * (d + math.sqrt(d * d + self.t_soft_k**2))
        ratio = (
            area_m2
            / self.area_ref_m2
            / ((self.t_liquidus_k - self.t_ambient_k) / d_eff) ** self.n_t
            / (self.speed_ref_m_s / speed_m_s) ** self.n_v
        )
        p_eff = self.power_ref_w * ratio ** (1.0 / self.n_p)
        return math.sqrt(max(p_eff**2 - self.power_soft_w**2, 0.0))


def multitrack_temperature(
    n_tracks: int,
    steps_per_track: int,
    t_ambient_k: float = 300.0,
    peak_rise_k: float = 900.0,
    decay_steps: float = 25.0,
    rise_per_track_k: float = 40.0,
) -> np.ndarray:
    """Surface temperature ahead of the laser over a multi-track layer (paper Fig. 9 shape).

    Track ``j`` starts hot next to the just-scanned track and cools exponentially
    along the track: ``T = T_amb + j·rise + [j > 0]·peak·exp(−s / decay)``.

    Parameters
    ----------
    n_tracks, steps_per_track : int
        Layout of the layer.
    t_ambient_k, peak_rise_k, rise_per_track_k : float
        Temperatures [K].
    decay_steps : float
        Exponential decay length along a track [steps].

    Returns
    -------
    numpy.ndarray
        ``T[k]`` [K], shape (n_tracks · steps_per_track,).
    """
    s = np.arange(steps_per_track, dtype=float)
    tracks = [
        t_ambient_k + j * rise_per_track_k + (peak_rise_k * np.exp(-s / decay_steps) if j > 0 else 0.0 * s)
        for j in range(n_tracks)
    ]
    return np.concatenate(tracks)


@dataclass(frozen=True)
class ClosedLoopResult:
    """Closed-loop trajectories of :func:`run_closed_loop`.

    Attributes
    ----------
    area_m2 : numpy.ndarray
        True ``x[1..N]`` [m²], shape (N,).
    power_w : numpy.ndarray
        ``p[0..N-1]`` [W], shape (N,).
    diagnostics : list of Diagnostics
        One per update.
    measurements : list of Measurement
        The measurements fed to the controller, ``x[0..N-1]``.
    """

    area_m2: np.ndarray
    power_w: np.ndarray
    diagnostics: list[Diagnostics]
    measurements: list[Measurement]


def run_closed_loop(
    controller,
    plant: AnalyticMeltPoolModel,
    temperature_k: np.ndarray,
    area0_m2: float = 0.07e-6,
    power0_w: float = 250.0,
    speed_m_s: float = 0.8,
    dt_s: float = 50e-6,
    noise_std_m2: float = 0.0,
    seed: int = 0,
) -> ClosedLoopResult:
    """Run ``controller`` in closed loop on ``plant`` over the temperature sequence.

    Parameters
    ----------
    controller : controller_node.base.Controller
        Any registry controller.
    plant : AnalyticMeltPoolModel
        Plant (its mean is the true next area).
    temperature_k : numpy.ndarray
        ``T[k]`` [K], shape (N,).
    area0_m2, power0_w, speed_m_s, dt_s : float
        Initial area [m²], power applied before step 0 [W], speed [m/s], step [s].
    noise_std_m2 : float
        Std of the Gaussian noise added to the measured (not the true) area [m²].
    seed : int
        Noise seed.

    Returns
    -------
    ClosedLoopResult
    """
    rng = np.random.default_rng(seed)
    x, p = area0_m2, power0_w
    areas, powers, diags, meas = [], [], [], []
    for k, t in enumerate(temperature_k):
        measured = max(x + noise_std_m2 * rng.standard_normal(), 0.0) if noise_std_m2 > 0 else x
        m = Measurement(step=k, time_s=k * dt_s, area_m2=measured, t_ahead_k=float(t), power_w=p, speed_m_s=speed_m_s)
        cmd, diag = controller.update(m)
        if cmd.step != k + 1:
            raise RuntimeError(f"command for step {cmd.step}, expected {k + 1}")
        p = cmd.power_w
        x = plant.predict(np.array([x, t, p, cmd.speed_m_s]))[0]
        areas.append(x)
        powers.append(p)
        diags.append(diag)
        meas.append(m)
    return ClosedLoopResult(np.array(areas), np.array(powers), diags, meas)
