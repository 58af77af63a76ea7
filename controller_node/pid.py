"""PID baseline on the melt-pool area with anti-windup and output clamping."""

from __future__ import annotations

from .base import Controller, Proposal
from .types import Measurement

__all__ = ["PIDController"]


class PIDController(Controller):
    """Discrete PID on the relative area error ``e = (x_sp − x[k]) / x_sp``.

    ``p[k] = p_nom + kp·e[k] + I[k] + kd·(e[k] − e[k−1])`` with
    ``I[k] = I[k−1] + ki·e[k]``.  Anti-windup by integrator clamping: when the error
    pushes the output past a power bound, the integral grows only up to the
    headroom left by the other terms (``p_u − p_nom − kp·e − kd·Δe``), never beyond,
    so it leaves saturation as soon as the error reverses.  The base class clamps
    the output to the power bounds.

    Parameters
    ----------
    settings : ControllerSettings
        ``settings.pid`` gains [W per unit relative error].
    """

    name = "pid"

    def reset(self) -> None:
        """Forget history, including the integral state."""
        super().reset()
        self.integral_w = 0.0
        self._previous: tuple[int, float] | None = None

    def _propose(self, m: Measurement) -> Proposal:
        s = self.settings
        gains = s.pid
        error = (s.set_point_m2 - m.area_m2) / s.set_point_m2
        derivative = 0.0
        if self._previous is not None and self._previous[0] == m.step - 1:
            derivative = error - self._previous[1]
        self._previous = (m.step, error)
        base = s.nominal_power_w + gains.kp_w * error + gains.kd_w * derivative
        candidate = self.integral_w + gains.ki_w * error
        if error > 0.0 and base + candidate > s.power_max_w:
            candidate = max(self.integral_w, s.power_max_w - base)
        elif error < 0.0 and base + candidate < s.power_min_w:
            candidate = min(self.integral_w, s.power_min_w - base)
        self.integral_w = candidate
        return Proposal(base + self.integral_w)
