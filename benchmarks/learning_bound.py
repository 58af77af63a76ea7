"""An offline learning bound for a case: what the power alone has been shown to reach on it.

Norm-optimal iterative learning control (ILC; Amann, Owens and Rogers, IEE Proc. Control Theory
Appl. 143 (1996) 217-224) of the open-loop power profile against the FE plant, in process: each
iteration runs the whole case with the profile ``p_j`` and updates it from that run's area error
``e_j = x_sp − x_j`` inside the evaluation window (outside it, the pool's build-up, zero),

    p_{j+1} = clip(p_j + γ (GᵀG + λI)⁻¹ Gᵀ e_j, 0, P_max),   λ = ρ (K (1 − a))²,

with ``G`` the lifted impulse response of the process's first-order-plus-dead-time model (gain
``K`` [m²/W], time constant τ, dead time θ steps, ``a = exp(−Δt/τ)``: the power of step k moves
the area of state ``k + 1 + j`` by ``K (1 − a) a^(j−θ)``, ``j ≥ θ``), fitted on the process's
training staircases (``provenance.controller.pid.fopdt`` of the model, ``gp_trainer.pid_tuning``),
truncated where ``a^j < 10⁻⁶``; ``γ`` the learning gain and ``ρ`` the regularisation. The
iterations start from the model's operating power. The bound is the lowest RMSE over the
iterations, on the same window and metric as ``launch.py`` (:func:`controller_node.report.metrics`):
a controller that sees no future error in advance cannot be expected to beat it by much.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

from controller_node.report import Trace, metrics, window_mask
from fe_node.multilevel import plant_model
from fe_node.scenarios import Scenario
from gp_trainer.pid_tuning import Fopdt
from messages.types import LASER_POWER_MAX_W

__all__ = ["BoundSettings", "learning_bound"]


@dataclass(frozen=True)
class BoundSettings:
    """The learning bound's iteration (SI)."""

    iterations: int
    """FE runs of the case (each a full run)."""
    gain: float
    """Learning gain γ in (0, 1]."""
    process: Fopdt
    """The process's first-order-plus-dead-time model (``gp_trainer.pid_tuning``)."""
    start_power_w: float
    """Power of the first iteration's profile [W]."""
    regularisation: float = 1.0
    """ρ (> 0): the update's penalty on power changes, relative to the model's one-step gain."""

    def __post_init__(self) -> None:
        if not (isinstance(self.iterations, int) and self.iterations >= 1):
            raise ValueError(f"iterations must be an int >= 1, got {self.iterations!r}")
        if not 0 < self.gain <= 1:
            raise ValueError(f"gain must be in (0, 1], got {self.gain}")
        if not self.regularisation > 0:
            raise ValueError(f"regularisation must be > 0, got {self.regularisation}")
        if not 0 <= self.start_power_w <= LASER_POWER_MAX_W:
            raise ValueError(f"start_power_w must be in [0, {LASER_POWER_MAX_W}] W, got {self.start_power_w}")


def run_profile(sc: Scenario, powers_w: np.ndarray, max_steps: int | None) -> Trace:
    """One open-loop FE run of ``sc`` on the mesh its settings name (:func:`~fe_node.multilevel.plant_model`)
    with the power ``powers_w[k]`` on step k → k+1 (the last value beyond the profile) at the plan's
    speed; the trace of its states (step 0 first)."""
    plant = plant_model(sc.settings, sc.plan, sc.layer_plans)
    states = [plant.initial_observation()]
    while not plant.done and (max_steps is None or plant.step_index < max_steps):
        k = plant.step_index
        states.append(plant.step(float(powers_w[min(k, powers_w.size - 1)]), sc.profile.command(k)[1]))
    return Trace(time_s=np.array([s.time_s for s in states]), area_mm2=np.array([s.area_m2 * 1e6 for s in states]),
                 power_w=np.array([s.power_w for s in states]), t_ahead_k=np.array([s.t_ahead_k for s in states]),
                 track=np.array([s.track for s in states]), layer=np.array([s.layer for s in states]))


def norm_optimal_step(error_m2: np.ndarray, settings: BoundSettings) -> np.ndarray:
    """``(GᵀG + λI)⁻¹ Gᵀ e`` [W], shape (n,), for the errors ``e`` [m²] of the states 1..n (module docstring;
    ``GᵀG`` is banded, solved with :func:`scipy.linalg.solveh_banded`)."""
    fopdt = settings.process
    a = math.exp(-fopdt.sample_period_s / fopdt.time_constant_s)
    theta, n = fopdt.delay_steps, error_m2.size
    length = min(n, theta + 1 + math.ceil(math.log(1e-6) / math.log(a)))
    h = np.zeros(length)                         # h[j]: ∂x[k+1+j] / ∂p[k]
    h[theta:] = fopdt.gain_m2_per_w * (1 - a) * a ** np.arange(length - theta)
    gt_e = np.array([h[: n - k] @ error_m2[k:k + length][: n - k] for k in range(n)])
    bands = np.zeros((length, n))                # upper form of GᵀG: (GᵀG)[k, k+d] = Σ_j h[j] h[j+d]
    for d in range(length):
        bands[length - 1 - d, d:] = _band(h, d, n)
    bands[length - 1] += settings.regularisation * (fopdt.gain_m2_per_w * (1 - a)) ** 2
    return scipy.linalg.solveh_banded(bands, gt_e)


def _band(h: np.ndarray, d: int, n: int) -> np.ndarray:
    """The d-th diagonal of GᵀG, (GᵀG)[k, k+d] for k = 0..n−1−d: Σ_j h[j] h[j+d] over the rows
    ``k + 1 + j + d ≤ n`` that exist (the end of the run cuts the sum)."""
    m = h.size
    products = h[: m - d] * h[d:]
    cumulative = np.concatenate((np.zeros(1), np.cumsum(products)))
    rows_left = n - d - np.arange(n - d)         # states after k + d: the sum holds j + d + k < n
    return cumulative[np.minimum(rows_left, m - d)]


def learning_bound(sc: Scenario, setpoint_m2: float, settings: BoundSettings, max_steps: int | None = None) -> dict:
    """The case's learning bound (module docstring).

    Parameters
    ----------
    sc : Scenario
        The case's plant and plan.
    setpoint_m2 : float
        Area set point [m²].
    settings : BoundSettings
    max_steps : int or None
        End each run after this many steps (None: the whole case).

    Returns
    -------
    dict
        ``bound_rmse_pct`` (the lowest RMSE over the iterations, % of the set point),
        ``bound_iteration`` (the iteration that reached it, 0 first) and ``rmse_by_iteration_pct``.
    """
    powers = np.full(1, settings.start_power_w)
    rmse = []
    for _ in range(settings.iterations):
        trace = run_profile(sc, powers, max_steps)
        rmse.append(metrics(trace, setpoint_m2 * 1e6).steady_rmse_pct)
        n = trace.area_mm2.size - 1                  # steps run: p[0 .. n−1] move x[1 .. n]
        if powers.size < n:
            powers = np.concatenate((powers, np.full(n - powers.size, powers[-1])))
        error_m2 = np.where(window_mask(trace), setpoint_m2 - trace.area_mm2 * 1e-6, 0.0)[1:]
        powers = np.clip(powers[:n] + settings.gain * norm_optimal_step(error_m2, settings), 0.0, LASER_POWER_MAX_W)
    best = int(np.argmin(rmse))
    return {"bound_rmse_pct": round(float(rmse[best]), 2), "bound_iteration": best,
            "rmse_by_iteration_pct": [round(float(r), 2) for r in rmse]}
