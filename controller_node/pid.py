"""PID baseline on the melt-pool area with anti-windup and output clamping."""

from __future__ import annotations

from .base import Controller, Proposal
from .types import Measurement

__all__ = ["PIDController"]


class PIDController(Controller):
    """Discrete PID on the relative area error ``e = (x_sp − x[k]) / x_sp``.

    ``p[k] = p_nom + kp·e[k] + I[k] + kd·(e[k] − e[k−1])``.  Anti-windup by
    conditional integration: ``I[k] = I[k−1] + ki·e[k]`` is accepted only if the
    resulting output is not saturated, or if the error drives it back from
    saturation.  The base class clamps the output to the power bounds.

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
        output = base + candidate
        saturated_high = output > s.power_max_w and error > 0.0
        saturated_low = output < s.power_min_w and error < 0.0
        if not (saturated_high or saturated_low):
            self.integral_w = candidate
        return Proposal(base + self.integral_w)
