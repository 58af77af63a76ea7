"""Common controller machinery: ``update(measurement) -> (command, diagnostics)``.

:class:`Controller` owns everything the controllers share — measurement checks,
staleness, exception containment, fallback, clamping, timing, diagnostics — and
delegates the control law to :meth:`Controller._propose`.
"""

from __future__ import annotations

import collections
import dataclasses
import math
import time
from abc import ABC, abstractmethod
from typing import ClassVar

from .safety import FallbackPlan, clamp_power
from .settings import ControllerSettings
from .types import PLAN_REPORT_FIELDS, Command, ConfigurationError, Diagnostics, Measurement, PlanReport, trusted

__all__ = ["Controller", "Proposal"]


Proposal = collections.namedtuple(
    "Proposal", ("power_w", "status", *PLAN_REPORT_FIELDS),
    defaults=("ok", *(f.default for f in dataclasses.fields(PlanReport))))
Proposal.__doc__ = """A control law's answer to one measurement, before the safety layer (internal to
:meth:`Controller.update`): the power, a status and, after them, the fields of the
:class:`~controller_node.types.PlanReport` of the :class:`~controller_node.types.Diagnostics`, in its order,
with its defaults (a named tuple: built on every update, it costs less than a frozen dataclass).

Attributes
----------
power_w : float
    Proposed ``p[k]`` [W] (clamped afterwards).
status : str
    ``"ok"`` (default), or a failure reason that makes the safety layer fall back.
predicted_area_m2, predicted_power_w, model_std_m2, feedforward_w, reference_power_w, solver_iterations
    As in :class:`~controller_node.types.PlanReport`.
"""


class Controller(ABC):
    """Base class of every melt-pool controller (plain Python, no transport).

    Parameters
    ----------
    settings : ControllerSettings
        Shared and controller-specific settings.
    """

    name: ClassVar[str]

    def __init__(self, settings: ControllerSettings) -> None:
        if not isinstance(settings, ControllerSettings):
            raise ValueError(f"settings must be a ControllerSettings, got {type(settings).__name__}")
        self.settings = settings
        self.reset()

    def reset(self) -> None:
        """Forget all history (plan, last command, counters, internal states)."""
        s = self.settings
        self._fallback = FallbackPlan(s.power_min_w, s.power_max_w, s.nominal_power_w)
        self._last_step: int | None = None
        self.n_fallbacks = 0

    def prepare(self) -> None:  # noqa: B027 (a hook: nothing to prepare by default)
        """Work for the next :meth:`update` that needs no new measurement, done after a command is
        sent and before the next state arrives (the node calls it; none by default)."""

    @abstractmethod
    def _propose(self, m: Measurement) -> Proposal:
        """Control law for a plausible, fresh measurement (may raise; contained by ``update``)."""

    def update(self, measurement: Measurement, now_step: int | None = None) -> tuple[Command, Diagnostics]:
        """Compute the command answering ``measurement``.

        Parameters
        ----------
        measurement : Measurement
            Sample ``k`` (area, temperature ahead, applied power, speed).
        now_step : int, optional
            Latest step the caller knows has happened (default ``measurement.step``).
            The command is for ``now_step + 1``; a measurement more than
            ``settings.max_age_steps`` older than ``now_step``, or not newer than the
            previous one, is stale.

        Returns
        -------
        command : Command
            ``step = now_step + 1``, power within ``[power_min_w, power_max_w]``,
            speed ``nominal_speed_m_s``.
        diagnostics : Diagnostics
            Status, fallback flag and count, MPC predictions, timing.
        """
        t0 = time.perf_counter()
        s = self.settings
        step = measurement.step
        now = step if now_step is None else max(int(now_step), step)
        target = now + 1
        proposal: Proposal | None = None
        if not measurement.is_plausible():
            status = "invalid_measurement"
        elif now - step > s.max_age_steps or (self._last_step is not None and step <= self._last_step):
            status = "stale"
        else:
            try:
                proposal = self._propose(measurement)
                status = proposal.status
            except ConfigurationError:
                raise  # a plant this controller cannot serve: refused, not a fallback
            except Exception as exc:  # a controller must answer, whatever its model does
                status = f"controller_error:{type(exc).__name__}"
            if status == "ok" and not math.isfinite(proposal.power_w):
                status = "non_finite_command"
        if self._last_step is None or step > self._last_step:
            self._last_step = step

        if status == "ok" and step == 0:
            proposal = proposal._replace(power_w=s.nominal_power_w)  # laser-on: every controller starts at nominal
        fallback = status != "ok"
        if fallback:
            self.n_fallbacks += 1
            power = self._fallback.power_for(target)
        else:
            power = clamp_power(proposal.power_w, s.power_min_w, s.power_max_w, s.nominal_power_w)
            self._fallback.store(target, proposal.predicted_power_w)
        self._fallback.last_power_w = power
        # checked: an int step > 0, a power within the bounds, the settings' finite speed > 0
        command = trusted(Command, target, float(power), float(s.nominal_speed_m_s))
        elapsed = time.perf_counter() - t0
        if fallback:
            return command, Diagnostics(elapsed, status, fallback, self.n_fallbacks)
        return command, trusted(Diagnostics, *proposal[2:], elapsed, status, False, self.n_fallbacks)
