"""Temperature feed-forward (paper IV.B) and the ``feedforward`` baseline controller.

The paper adds "a differential plus direct feedback from the initial temperature" to
the MPC command.  Here ::

    Δp = K_T · (g_direct · (T[k] − T_ref) + g_diff · (T[k] − T[k−1])),   K_T = −(∂f/∂T)/(∂f/∂p)

``K_T`` [W/K] is the power change that leaves the model's next area — and, since
both partials share ``1/(1 − ∂f/∂x)``, its steady state — unchanged when the
temperature changes; it is negative (hotter substrate → less power).
"""

from __future__ import annotations

import math

from .base import Controller, Proposal
from .model import DynamicsModel, linearise, operating_point
from .settings import ControllerSettings, FeedForwardSettings
from .types import Measurement

__all__ = ["temperature_feedforward_w", "FeedForwardController"]


def temperature_feedforward_w(ff: FeedForwardSettings, gain_w_per_k: float, t_k: float, t_prev_k: float) -> float:
    """Feed-forward power [W] for the temperature ``T[k]`` and its change.

    Parameters
    ----------
    ff : FeedForwardSettings
        Gains, reference temperature and clamp.
    gain_w_per_k : float
        ``K_T`` [W/K]; a non-finite gain gives 0.
    t_k, t_prev_k : float
        ``T[k]`` and ``T[k−1]`` [K] (equal when ``T[k−1]`` is unknown).

    Returns
    -------
    float
        ``Δp`` clamped to ``±ff.max_abs_w`` [W].
    """
    delta = gain_w_per_k * (ff.direct_gain * (t_k - ff.reference_temperature_k)
                            + ff.differential_gain * (t_k - t_prev_k))
    if not math.isfinite(delta):
        return 0.0
    return min(max(delta, -ff.max_abs_w), ff.max_abs_w)


class FeedForwardController(Controller):
    """Baseline: nominal power plus temperature feed-forward only (no area feedback).

    ``p[k] = p_nom + Δp`` with ``settings.feedforward``; ``K_T`` is
    ``feedforward.gain_w_per_k`` or, if None, taken once from the model at the nominal
    point ``(x_sp, T_ref, p_nom, v_nom)``.

    Parameters
    ----------
    settings : ControllerSettings
        Nominal power/speed, set point, ``feedforward`` settings.
    model : DynamicsModel, optional
        Needed only when ``feedforward.gain_w_per_k`` is None.
    """

    name = "feedforward"

    def __init__(self, settings: ControllerSettings, model: DynamicsModel | None = None) -> None:
        ff = settings.feedforward
        if ff.gain_w_per_k is not None:
            self.gain_w_per_k = ff.gain_w_per_k
        else:
            if model is None:
                raise ValueError("feedforward needs a model or feedforward.gain_w_per_k")
            z = operating_point(model, settings.set_point_m2, ff.reference_temperature_k, settings.nominal_power_w,
                                settings.nominal_speed_m_s)
            try:
                lin = linearise(model, z)
            except Exception as exc:  # report any model failure as a configuration error
                raise ValueError(f"model failed at the nominal point: {exc}") from exc
            if lin is None or lin.b <= 0.0:
                raise ValueError("model gives no usable power sensitivity at the nominal point")
            self.gain_w_per_k = lin.temperature_gain_w_per_k()
        super().__init__(settings)

    def reset(self) -> None:
        """Forget history, including the previous temperature."""
        super().reset()
        self._previous: Measurement | None = None

    def _propose(self, m: Measurement) -> Proposal:
        prev = self._previous
        t_prev = prev.t_ahead_k if prev is not None and prev.step == m.step - 1 else m.t_ahead_k
        self._previous = m
        delta = temperature_feedforward_w(self.settings.feedforward, self.gain_w_per_k, m.t_ahead_k, t_prev)
        return Proposal(self.settings.nominal_power_w + delta, feedforward_w=delta)
