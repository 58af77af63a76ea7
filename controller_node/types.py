"""Plain data types of the melt-pool controller (SI units throughout).

The controller's functional core is ``update(measurement) -> (command, diagnostics)``
(see :mod:`controller_node.base`).  The types here are transport-agnostic frozen
dataclasses; the zenoh node converts them from/to the message contract.

Conventions
-----------
Step ``k`` follows the discrete dynamics of the paper, eq. (1):
``x[k+1] = f(x[k], T[k], p[k], v[k])``.  A :class:`Measurement` with ``step = k``
carries ``x[k]`` and ``T[k]`` together with the power ``p[k-1]`` that was applied
during the step that produced it; the :class:`Command` answering it carries
``p[k]`` and has ``step = k + 1`` (the step its power produces).
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import numpy as np

__all__ = ["ConfigurationError", "Measurement", "Command", "Diagnostics", "PlanReport", "trusted"]


def _real(name: str, value: object) -> float:
    """Convert a real number (Python or numpy, not bool) to float, else ``ValueError``."""
    if type(value) is float:  # the common case, without the abstract-class checks below
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Real):
        raise ValueError(f"{name} must be a real number, got {type(value).__name__}")
    return float(value)


def _step(name: str, value: object) -> int:
    """Validate a step index: a non-negative int (numpy integers accepted), else ``ValueError``."""
    if type(value) is int and value >= 0:  # the common case, without the abstract-class checks below
        return value
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, numbers.Integral):
        raise ValueError(f"{name} must be a non-negative int, got {type(value).__name__}")
    if value < 0:
        raise ValueError(f"{name} must be >= 0, got {value}")
    return int(value)


class ConfigurationError(Exception):
    """The controller cannot serve this plant as configured (e.g. another sample period); the
    node refuses the run with this one-line message instead of falling back."""


@dataclass(frozen=True, slots=True)
class Measurement:
    """One sensor sample of the melt pool, eq. (1) inputs at step ``k``.

    Parameters
    ----------
    step : int
        Step index ``k`` (>= 0).
    time_s : float
        Simulation time of the sample [s].
    area_m2 : float
        Melt-pool top-surface area ``x[k]`` [m²].
    t_ahead_k : float
        Surface temperature ahead of the laser ``T[k]`` [K] (measurable disturbance).
    power_w : float
        Laser power ``p[k-1]`` applied during the step that produced this sample [W].
    speed_m_s : float
        Scan speed ``v`` [m/s].
    track : int or None
        Track index, when the plant reports it (a history model only uses the previous
        sample of the same track).
    track_elapsed_s, track_remaining_s : float or None
        Scan-plan preview: time since the current track started and until it ends [s].
    next_track : bool or None
        Another track follows the current one (False on the layer's last track).
    layer : int or None
        Layer of a multi-layer build (each starts a new pool on fresh powder), if reported.

    Notes
    -----
    Construction checks types only (``ValueError`` for non-numbers and bad steps).
    Non-finite or physically impossible *values* (NaN, inf, negative area, zero
    speed) are accepted on purpose: a sensor dropout must still produce a safe
    command, so the controller detects them (:meth:`is_plausible`) and falls back.
    """

    step: int
    time_s: float
    area_m2: float
    t_ahead_k: float
    power_w: float
    speed_m_s: float
    track: int | None = None
    track_elapsed_s: float | None = None
    track_remaining_s: float | None = None
    next_track: bool | None = None
    layer: int | None = None

    def __post_init__(self) -> None:
        object.__setattr__(self, "step", _step("step", self.step))
        if self.layer is not None:
            object.__setattr__(self, "layer", _step("layer", self.layer))
        for name in ("track_elapsed_s", "track_remaining_s"):
            if getattr(self, name) is not None:
                object.__setattr__(self, name, _real(name, getattr(self, name)))
        if self.track is not None:
            object.__setattr__(self, "track", _step("track", self.track))
        for name in ("time_s", "area_m2", "t_ahead_k", "power_w", "speed_m_s"):
            object.__setattr__(self, name, _real(name, getattr(self, name)))

    def is_plausible(self) -> bool:
        """Return True when every field is finite and physically possible.

        Returns
        -------
        bool
            ``area >= 0``, ``T > 0`` K, ``power >= 0``, ``speed > 0`` and all finite.
        """
        isfinite, elapsed, remaining = math.isfinite, self.track_elapsed_s, self.track_remaining_s
        return (
            isfinite(self.time_s)
            and 0.0 <= self.area_m2 < math.inf
            and 0.0 < self.t_ahead_k < math.inf
            and 0.0 <= self.power_w < math.inf
            and 0.0 < self.speed_m_s < math.inf
            and (elapsed is None or 0.0 <= elapsed < math.inf)
            and (remaining is None or 0.0 <= remaining < math.inf)
        )


@dataclass(frozen=True, slots=True)
class Command:
    """Laser command ``u[k] = (p[k], v[k])`` for the step it will produce.

    Parameters
    ----------
    step : int
        The step this command produces (``measurement.step + 1``).
    power_w : float
        Laser power [W], finite and >= 0 (the controller also keeps it within its
        power bounds).
    speed_m_s : float
        Scan speed [m/s], finite and > 0.
    """

    step: int
    power_w: float
    speed_m_s: float

    def __post_init__(self) -> None:
        object.__setattr__(self, "step", _step("step", self.step))
        power = _real("power_w", self.power_w)
        speed = _real("speed_m_s", self.speed_m_s)
        if not (math.isfinite(power) and power >= 0.0):
            raise ValueError(f"power_w must be finite and >= 0, got {power}")
        if not (math.isfinite(speed) and speed > 0.0):
            raise ValueError(f"speed_m_s must be finite and > 0, got {speed}")
        object.__setattr__(self, "power_w", power)
        object.__setattr__(self, "speed_m_s", speed)


@dataclass(frozen=True, slots=True, kw_only=True)
class PlanReport:
    """What a control law planned, shared by its :class:`~controller_node.base.Proposal` and the
    :class:`Diagnostics` of the update that used it.

    Parameters
    ----------
    predicted_area_m2 : tuple of float
        MPC predicted areas ``x[k+1..k+H]`` [m²] (empty for baselines/fallback).
    predicted_power_w : tuple of float
        MPC planned powers ``p[k..k+H-1]`` [W], kept for the fallback (empty for baselines).
    model_std_m2 : float or None
        GP predictive standard deviation of ``x[k+1]`` at the operating point [m²],
        None when not computed.
    feedforward_w : float
        Temperature feed-forward included in the command [W] (0 when off).
    reference_power_w : float or None
        MPC steady-state reference power of the normalised problem [W].
    solver_iterations : int
        QP iterations (0 when no QP was solved).
    """

    predicted_area_m2: tuple[float, ...] = ()
    predicted_power_w: tuple[float, ...] = ()
    model_std_m2: float | None = None
    feedforward_w: float = 0.0
    reference_power_w: float | None = None
    solver_iterations: int = 0


PLAN_REPORT_FIELDS = tuple(PlanReport.__dataclass_fields__)
"""The names of :class:`PlanReport`'s fields, in order."""


@dataclass(frozen=True, slots=True)
class Diagnostics(PlanReport):
    """What the controller did in one ``update``: the :class:`PlanReport` of the control law it
    used (defaults when it fell back) and these.

    Parameters
    ----------
    solve_time_s : float
        Wall time of the whole update (linearisation + QP + clamping) [s].
    status : str
        ``"ok"`` or the fallback reason: ``"invalid_measurement"``, ``"stale"``,
        ``"model_error"``, ``"solver_failed"``, ``"solver_error"``, or a solver status.
    fallback : bool
        True when the command is the safe fallback, not the controller's own output.
    n_fallbacks : int
        Fallbacks since construction/reset.
    """

    solve_time_s: float
    status: str
    fallback: bool
    n_fallbacks: int


_WRITERS: dict[type, tuple] = {}


def trusted(cls: type, *values: object) -> object:
    """An instance of the frozen slots dataclass ``cls`` (:class:`Command`, :class:`Diagnostics`) with its
    fields, in :func:`dataclasses.fields` order, set to ``values`` as given: no ``__init__`` and no
    ``__post_init__`` checks or conversions. For values the caller has checked, on the controller's
    state-to-command path, where a frozen dataclass's constructor (each field through
    ``object.__setattr__``, then the checks) costs microseconds on cold caches.
    ``tests/test_controller_types.py`` checks it equal to the constructor's result."""
    writers = _WRITERS.get(cls)
    if writers is None:
        writers = _WRITERS[cls] = tuple(getattr(cls, f.name).__set__ for f in fields(cls))
    if len(values) != len(writers):
        raise TypeError(f"{cls.__name__} has {len(writers)} fields, got {len(values)} values")
    instance = object.__new__(cls)
    for write, value in zip(writers, values):
        write(instance, value)
    return instance
