"""Safety layer: power clamping and the fallback command.

Every command leaves through :func:`clamp_power`, so no power outside
``[p_l, p_u]`` is ever returned, whatever the controller or its model computed.
When a controller cannot produce a trustworthy command (invalid or stale
measurement, model or solver failure) :class:`FallbackPlan` supplies one: the
previous MPC plan shifted to the requested step, else the last commanded power,
else the nominal power.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

__all__ = ["clamp_power", "FallbackPlan"]


def clamp_power(power_w: float, power_min_w: float, power_max_w: float, default_w: float) -> float:
    """Clamp a power to ``[power_min_w, power_max_w]`` [W].

    Parameters
    ----------
    power_w : float
        Proposed power [W]; may be NaN or infinite.
    power_min_w, power_max_w : float
        Bounds [W], finite, ``min < max``.
    default_w : float
        Used (clamped too) when ``power_w`` is NaN [W].

    Returns
    -------
    float
        A finite power within the bounds.
    """
    if math.isnan(power_w):
        power_w = default_w if math.isfinite(default_w) else power_min_w
    return min(max(power_w, power_min_w), power_max_w)


class FallbackPlan:
    """Remembers the last good plan and the last command, and yields the safe power.

    Parameters
    ----------
    power_min_w, power_max_w : float
        Power bounds [W].
    nominal_power_w : float
        Power used before any command was issued [W].
    """

    def __init__(self, power_min_w: float, power_max_w: float, nominal_power_w: float) -> None:
        self._lo = power_min_w
        self._hi = power_max_w
        self._nominal = nominal_power_w
        self._origin_step = 0
        self._plan: tuple[float, ...] = ()
        self.last_power_w: float | None = None

    def store(self, origin_step: int, plan_w: Sequence[float]) -> None:
        """Remember a plan whose first power is for ``origin_step``.

        Parameters
        ----------
        origin_step : int
            Step produced by ``plan_w[0]``.
        plan_w : sequence of float
            Planned powers ``p[k..k+H-1]`` [W] (may be empty).
        """
        self._origin_step = origin_step
        self._plan = tuple(plan_w)

    def power_for(self, step: int) -> float:
        """Safe power [W] for the command producing ``step``.

        Returns
        -------
        float
            ``plan[step − origin]`` if the stored plan covers ``step``, else the last
            commanded power, else the nominal power; always clamped to the bounds.
        """
        index = step - self._origin_step
        if 0 <= index < len(self._plan):
            candidate = self._plan[index]
        elif self.last_power_w is not None:
            candidate = self.last_power_w
        else:
            candidate = self._nominal
        return clamp_power(candidate, self._lo, self._hi, self._nominal)
