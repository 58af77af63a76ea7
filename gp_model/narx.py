"""Delay-aware melt-pool model: a nonlinear lag regression with the paper's SE-ARD GP on its residual.

The power→area response of the plant is a ramp over one pool length (10–15 steps) and the
temperature ahead acts with lags of 5–13 steps, so a one-step model ``x[k+1] = f(x[k], ...)``
cannot represent it (docs/gp.md, "Delay-aware model"). This model keeps the pool's memory in its
regressor, in lagged powers and temperatures only (no lagged areas):

    z[k+1] = c₀ + Σ_{i<n_p} (b_i p[k+1−i] + q_i φ(p[k+1−i])) + Σ_{j<n_T} c_j T[k−j]
             + Σ_{j<n_Tq} d_j T[k−j]² + Σ_{i<n_x} e_i p[k+1−i] T[k−i] + Σ_{l<n_F} g_l F[k+1−l]
             + c_s + h_s P̄ + r(ψ_k)
    x[k+1] = exp(z[k+1])  (output "log"; "identity": x = z),   r ~ GP(0, k_SE-ARD)

* ``p[j]`` [W] is the power applied during the step j−1 → j (``state[j].power_w``; 0 before
  laser-on), ``T[j]`` [K] the temperature ahead in state j (before the first state: ``T[0]``).
* The lag part (least squares in z on scaled columns) is the delay. Its power map φ, the
  squared T lags and the log output carry the area's nonlinearity in power and temperature. The
  power map is ``φ(p) = p²`` (``"square"``) or ``φ(p) = log(1 + p/p_s)`` (``"log1p"``, p_s =
  :data:`LOG_POWER_SCALE_W`): the log map's gain ``1/(p_s + p)`` falls with power and keeps its sign
  beyond the identification runs' powers, where fitted squares can turn the response around
  (``benchmarks/power_sensitivity.py``). The lag-matched
  interactions ``p[k+1−i] T[k−i]`` give each past power the gain of the substrate it heated
  (``quadratic=False`` and ``interaction=False`` in :meth:`NarxGPModel.fit` leave them out).
* ``F[j]`` [K] is the turnaround feature of :mod:`gp_model.plan_feature`: the previous track's heat
  at the laser in state j, linear in the powers applied along that track's end and known ahead
  from the scan plan (``feature_lags=0`` in :meth:`NarxGPModel.fit` leaves it out).
* ``c_s + h_s P̄`` are the remnant terms of :class:`gp_model.plan_feature.RemnantFeature`: for the
  state k+1 that is s < n_R states after a turn, an offset and a slope in the previous track's mean
  last power P̄ [W], learned per s (the previous track's molten end joined to the new pool; 0
  elsewhere; ``remnant=None`` in :meth:`NarxGPModel.fit` leaves them out). They are fitted on what the
  rest of the lag part leaves: fitted jointly, the per-state terms take over the turnaround feature's
  lags (both linear in the previous track's powers), whose kernel then turns negative.
* The GP of eq. (1)–(5) (SE-ARD kernel, hyper-parameters by maximum marginal likelihood on
  seeded random samples, :mod:`gp_model.kernel`) learns the residual in z on
  ``ψ_k = (T[k] [K], log(1 + min(s_k, 100)), mean(p[k+2−n_p..k+1]) [W])`` with ``s_k`` the states
  since the current track started, and gives the predictive variance. Without its mean-power input
  (``gp_power_input=False`` in :meth:`NarxGPModel.fit`) the GP is one of the first two: the response
  to power is then the lag part's alone, which holds beyond the runs' powers (a GP reverts to its
  zero mean there).
* The lag part's least squares may carry a smoothness prior ``λ Σ (θ_{i+1} − θ_i)²`` over the
  consecutive lags of T ahead, its square, p × T and F (:func:`smoothing_rows`,
  :data:`SMOOTHED_GROUPS`): nearly collinear lags otherwise take alternating signs that cancel
  along a track but not across a turnaround.
* :func:`gp_trainer.narx_fit.select_and_fit` chooses the lags, the output map, the squared lags,
  the interactions, the feature lags, the GP's length-scale floor and λ by the 40-step rollout error
  on held-out runs.
* Over a horizon the temperature ahead is forecast from the scan plan
  (:func:`forecast_t_ahead`): after a turnaround it follows the learned turnaround profile
  (:attr:`NarxGPModel.turn_profile_k`), the rise of T ahead over the state before the turn; with
  the turnaround feature, plus β times the feature's deviation from its mean after a turn
  (:func:`adjust_forecast`), so the forecast follows the plan's powers before the turn.

Everything is SI; the model file records the sample period and the definition of every input.
"""

from __future__ import annotations

import itertools
import math
import os
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg
from numba import njit

from gp_model.build_up import ROLLOUT_STRIDE, build_up_steps, rollout_horizon, steps_at
from gp_model.errors import DatasetError, ModelFormatError, ModelVersionError
from gp_model.files import is_format, read_document, write_document
from gp_model.kernel import (
    HyperBounds,
    fit_hyperparameters,
    gram,
    squared_differences,
)
from gp_model.plan_feature import RemnantFeature, TurnFeature, remnant_series, turn_feature_series
from messages.types import LASER_POWER_MAX_W

FORMAT_NAME = "meltloop-narx-gp-model"
FORMAT_VERSION = 6
READABLE_VERSIONS = (3, 4, 5, 6)
"""Format 5 is format 6 with the power map ``"square"``, the GP on all of :data:`RESIDUAL_INPUTS` and the
map's coefficients under ``power_square_coefficients``; format 4 also without the remnant terms
(``remnant_feature`` null), format 3 also without the turnaround feature (``turn_feature`` null)."""
OUTPUTS = ("log", "identity")
_LOG_AREA_MAX = 700.0  # exp overflows beyond ~709
RESIDUAL_INPUTS = ("t_ahead_k", "log1p_steps_since_track_start", "mean_power_w")
"""The residual GP's inputs ψ, in order; a GP without the mean-power input takes the first two."""
POWER_MAPS = ("square", "log1p")
DEFAULT_POWER_MAP = "log1p"
"""The power map of a model fitted without another (:meth:`NarxGPModel.fit`); files of format ≤ 5 are ``"square"``."""
LOG_POWER_SCALE_W = 25.0
"""p_s [W] of the ``"log1p"`` power map ``log(1 + p/p_s)``: its gain ``1/(p_s + p)`` falls by 15× from 0 to
350 W, as the plant's gain in log area falls from ~0.009/W at 120 W to ~0.003/W at 300 W (+30 W steps,
``benchmarks/power_sensitivity.py``)."""
STEPS_SINCE_START_CAP = 100
SPEED_TOLERANCE = 0.01
"""Relative difference of two scan speeds that makes them different processes (runs of one model, a
plant and its model)."""


def steps_since_start_feature(steps: np.ndarray) -> np.ndarray:
    """The GP's track-position input ``log(1 + min(s, 100))``: resolves the first states after a
    turnaround, where the area changes fastest, as finely as the GP's length-scales allow."""
    return np.log1p(np.minimum(steps, STEPS_SINCE_START_CAP))
SMOOTHED_GROUPS = (False, False, True, True, True, True, False, False)
"""Which lag kernels the smoothness prior of :meth:`NarxGPModel.fit` acts on, in the order power, power²,
T, T², p × T, F, the remnant's slopes and offsets: not the power's, the ramp over one pool length that the
staircases excite step by step (smoothed, it spreads over the 32 lags and the preview MPC over-corrects), nor
the remnant's (fitted apart, on the residual), but the kernels of the slow, nearly collinear T ahead and
turnaround feature."""
DEFAULT_BOUNDS = HyperBounds()

MONOTONE_POWER_W = (0.0, LASER_POWER_MAX_W)
"""Powers [W] over which :meth:`NarxGPModel.fit` holds the lag part's steady-state gain in power
non-negative: every power a controller may command (the contract's bounds)."""


def map_power(p: np.ndarray | float, power_map: str) -> np.ndarray:
    """``φ(p)`` of the power map ``power_map`` (:data:`POWER_MAPS`) at powers ``p`` [W]."""
    p = np.asarray(p, dtype=float)
    return p * p if power_map == "square" else np.log1p(p / LOG_POWER_SCALE_W)


def map_power_slope(p: np.ndarray | float, power_map: str) -> np.ndarray:
    """``φ'(p)`` of the power map ``power_map`` at powers ``p`` [W]."""
    p = np.asarray(p, dtype=float)
    return 2.0 * p if power_map == "square" else 1.0 / (LOG_POWER_SCALE_W + p)


def static_power_gains(sizes: Sequence[int], powers_w: Sequence[float], temperatures_k: Sequence[float],
                       power_map: str) -> np.ndarray:
    """Rows ``a`` with ``a @ θ`` the lag part's steady-state gain ``∂z/∂p`` [1/W] at each pair of a
    power ``p`` and a temperature ahead ``T`` (every lag at that p and T): ``Σ b_i + φ'(p) Σ q_i +
    T Σ e_i`` of the power map ``power_map``, for coefficients θ in the order of
    :meth:`NarxGPModel.design`; ``sizes`` the group sizes (n_p, n_p, n_T, n_Tq, n_x, n_F, n_R, n_R).
    Shape (len(powers) · len(temperatures), len(θ))."""
    n_p, _, n_t, n_tq, n_x, *_ = sizes
    rows = []
    for p in powers_w:
        for t in temperatures_k:
            a = np.zeros(1 + sum(sizes))
            a[1:1 + n_p] = 1.0
            a[1 + n_p:1 + 2 * n_p] = map_power_slope(p, power_map)
            start = 1 + 2 * n_p + n_t + n_tq
            a[start:start + n_x] = t
            rows.append(a)
    return np.array(rows)


def least_squares_with_gains(A: np.ndarray, b: np.ndarray, gains: np.ndarray) -> np.ndarray:
    """``argmin ||A θ − b||`` subject to ``gains @ θ >= 0``: :func:`numpy.linalg.lstsq` when its solution
    holds the constraints, else the constrained problem on the QR factor of ``A``'s non-zero columns
    (cvxpy, Clarabel; the coefficients of zero columns, terms left out of the model, stay 0)."""
    theta = np.linalg.lstsq(A, b, rcond=None)[0]
    if np.all(gains @ theta >= 0.0):
        return theta
    import cvxpy as cp

    used = np.flatnonzero(np.any(A != 0.0, axis=0))
    q, r = np.linalg.qr(A[:, used])
    x = cp.Variable(used.size)
    problem = cp.Problem(cp.Minimize(cp.sum_squares(r @ x - q.T @ b)), [gains[:, used] @ x >= 0.0])
    problem.solve(solver=cp.CLARABEL)
    if problem.status not in (cp.OPTIMAL, cp.OPTIMAL_INACCURATE) or x.value is None:
        raise DatasetError(f"the lag part's fit with non-negative power gains failed: {problem.status}")
    theta = np.zeros(A.shape[1])
    theta[used] = x.value
    return theta


@dataclass(frozen=True)
class RunSeries:
    """One recorded run as aligned arrays (state order, consecutive steps), SI units.

    Attributes
    ----------
    name : str
        Source name (e.g. the recording stem).
    area_m2, t_ahead_k, power_w : numpy.ndarray, shape (n,)
        ``x[j]``, ``T[j]`` and the power ``p[j]`` applied during step j−1 → j (``p[0] = 0``).
    track : numpy.ndarray of int, shape (n,)
        Track index of each state.
    sample_period_s : float
        Step duration Δt [s].
    layer : numpy.ndarray of int, shape (n,), optional
        Layer of each state (a multi-layer build; ``None``: one layer). Every layer starts a new
        pool on fresh powder, so its first track follows no turnaround.
    speed_m_s : float, optional
        The run's constant scan speed [m/s] (``None``: not recorded).
    """

    name: str
    area_m2: np.ndarray
    t_ahead_k: np.ndarray
    power_w: np.ndarray
    track: np.ndarray
    sample_period_s: float
    layer: np.ndarray | None = None
    speed_m_s: float | None = None

    def __len__(self) -> int:
        return int(self.area_m2.shape[0])

    def layers(self) -> np.ndarray:
        """Layer of every state, shape (n,) (zeros for one layer)."""
        return np.zeros(len(self), dtype=int) if self.layer is None else np.asarray(self.layer)

    def _starts(self, *keys: np.ndarray) -> np.ndarray:
        """Index of the first state of the run of equal ``keys`` each state is in, shape (n,)."""
        change = np.zeros(len(self), dtype=bool)
        change[:1] = True
        for key in keys:
            change[1:] |= key[1:] != key[:-1]
        return np.maximum.accumulate(np.where(change, np.arange(len(self)), 0))

    def _ends(self, *keys: np.ndarray) -> np.ndarray:
        """Index of the last state of the run of equal ``keys`` each state is in, shape (n,)."""
        n = len(self)
        change = np.zeros(n, dtype=bool)
        change[-1:] = True
        for key in keys:
            change[:-1] |= key[1:] != key[:-1]
        return np.minimum.accumulate(np.where(change, np.arange(n), n - 1)[::-1])[::-1]

    def steps_since_track_start(self) -> np.ndarray:
        """``s_j``: states since the first state of the current track, shape (n,)."""
        return np.arange(len(self)) - self._starts(self.layers(), self.track)

    def steps_to_track_end(self) -> np.ndarray:
        """``e_j``: states until the last state of the current track (0 on it), shape (n,)."""
        return self._ends(self.layers(), self.track) - np.arange(len(self))

    def steps_since_layer_start(self) -> np.ndarray:
        """States since the first state of the current layer (laser-on on its powder), shape (n,)."""
        return np.arange(len(self)) - self._starts(self.layers())

    def turn_starts(self) -> np.ndarray:
        """First states of the tracks that follow a turnaround (not a layer's first track), shape (m,)."""
        lay = self.layers()
        return np.flatnonzero((np.diff(self.track) != 0) & (np.diff(lay) == 0)) + 1

    def first_track_of_layer(self) -> np.ndarray:
        """True on the states of each layer's first track, shape (n,)."""
        lay = self.layers()
        return self._starts(lay, self.track) == self._starts(lay)

    def last_track_of_layer(self) -> np.ndarray:
        """True on the states of each layer's last track (no turnaround after it), shape (n,)."""
        lay = self.layers()
        return self._ends(lay, self.track) == self._ends(lay)


def series_from_states(states: Sequence[Any], name: str) -> RunSeries:
    """A :class:`RunSeries` from ``MeltPoolState`` messages of one run (mm² → m², step order).

    Raises
    ------
    DatasetError
        Fewer than 2 states, missing steps, an inconsistent sample period or a scan speed that varies.
    """
    states = sorted(states, key=lambda s: s.step)
    if len(states) < 2:
        raise DatasetError(f"{name}: fewer than 2 plant states")
    steps = np.array([s.step for s in states])
    if np.any(np.diff(steps) != 1):
        raise DatasetError(f"{name}: states are not consecutive steps (lost messages?)")
    time_s = np.array([s.time_s for s in states])
    periods = np.diff(time_s)
    period = float(np.median(periods))
    if not period > 0 or np.max(np.abs(periods - period)) > 0.01 * period:
        raise DatasetError(f"{name}: the sample period varies ({periods.min():.3g}-{periods.max():.3g} s)")
    speeds = np.array([s.speed_mm_s for s in states]) * 1e-3
    speed = float(np.median(speeds))
    if np.max(np.abs(speeds - speed)) > SPEED_TOLERANCE * speed:
        raise DatasetError(f"{name}: the scan speed varies ({speeds.min():.4g}-{speeds.max():.4g} m/s); "
                           "the model holds one speed")
    power = np.array([s.power_w for s in states], dtype=float)
    if steps[0] == 0:
        power[0] = 0.0
    return RunSeries(name=name, area_m2=np.array([s.area_mm2 for s in states]) * 1e-6,
                     t_ahead_k=np.array([s.t_ahead_k for s in states], dtype=float), power_w=power,
                     track=np.array([s.track for s in states], dtype=int), sample_period_s=period,
                     layer=np.array([s.layer or 0 for s in states], dtype=int), speed_m_s=speed)


def _common_speed(runs: Sequence[RunSeries], speed_m_s: float | None) -> float:
    """The one scan speed [m/s] of ``runs`` and ``speed_m_s`` (``DatasetError`` naming the runs if
    they differ by more than :data:`SPEED_TOLERANCE`, or if none is known)."""
    known = [(r.name, r.speed_m_s) for r in runs if r.speed_m_s is not None]
    if speed_m_s is not None:
        known.append(("speed_m_s", float(speed_m_s)))
    if not known:
        raise DatasetError("the runs record no scan speed: give speed_m_s")
    speed = known[0][1]
    other = [f"{name} {v:.4g} m/s" for name, v in known if abs(v - speed) > SPEED_TOLERANCE * speed]
    if other:
        raise DatasetError(f"runs at different scan speeds: {known[0][0]} {speed:.4g} m/s, {', '.join(other)}")
    return speed


def smoothing_rows(sizes: Sequence[int], smoothing: float, smoothed: Sequence[bool] | None = None) -> np.ndarray:
    """Rows ``√λ (θ_{i+1} − θ_i)`` over consecutive lags within each group of ``sizes`` consecutive
    coefficients (after the intercept) whose ``smoothed`` flag is set (default: every group), appended
    to the scaled least squares of :meth:`NarxGPModel.fit`: a smoothness prior on those lag kernels,
    ``λ`` = ``smoothing`` ≥ 0 relative to the unit-norm columns (0: no rows)."""
    if not (math.isfinite(smoothing) and smoothing >= 0):
        raise DatasetError(f"smoothing must be a finite number >= 0, got {smoothing}")
    n = 1 + sum(sizes)
    flags = [True] * len(sizes) if smoothed is None else list(smoothed)
    if smoothing == 0:
        return np.zeros((0, n))
    rows, start = [], 1
    for size, flag in zip(sizes, flags, strict=True):
        for i in range(start, start + size - 1 if flag else start):
            row = np.zeros(n)
            row[i], row[i + 1] = -1.0, 1.0
            rows.append(row)
        start += size
    return math.sqrt(smoothing) * np.array(rows).reshape(-1, n)


def turn_profile(runs: Iterable[RunSeries], length: int) -> np.ndarray:
    """Mean rise of T ahead after a turnaround, ``T[start+s] − T[start−1]`` for s = 0..length−1 [K].

    Averaged over every track start after a turnaround (not a layer's first track) of every run;
    where fewer states exist the mean is over the tracks that have them (the last value is held
    if none do).
    """
    sums, counts = np.zeros(length), np.zeros(length)
    for run in runs:
        for start in run.turn_starts():
            seg = run.t_ahead_k[start:start + length] - run.t_ahead_k[start - 1]
            sums[:seg.size] += seg
            counts[:seg.size] += 1
    if counts[0] == 0:
        return np.zeros(length)
    profile = sums / np.maximum(counts, 1)
    last = int(np.flatnonzero(counts)[-1])
    profile[last + 1:] = profile[last]
    return profile


def forecast_t_ahead(t_now_k: float, steps_since_start: int, on_first_track: bool, steps_to_end: int | None,
                     profile_k: np.ndarray, horizon: int, t_base_k: float | None = None,
                     persistence: float = 1.0) -> np.ndarray:
    """Forecast ``T[k+1..k+H]`` [K] from the scan plan and a turnaround profile.

    * First track (nothing scanned beside it): T is held.
    * A track after a turn: ``T̂[k+j] = T_b + P[s_k+j] + ρ^j (T[k] − T_b − P[s_k])`` with ``T_b``
      the temperature in the state before the turn, ``P`` the profile and ρ the persistence
      of the current deviation from it (fitted on the training runs).
    * After the current track's last state (in ``steps_to_end + 1`` steps), T rises by the
      profile over the forecast value at that state. Beyond the profile's end it is held.

    Parameters
    ----------
    t_now_k : float
        ``T[k]`` [K].
    steps_since_start : int
        ``s_k``, states since the current track's first state.
    on_first_track : bool
        The current track is the first of the layer.
    steps_to_end : int or None
        ``e_k``: states until the current track's last state (None: no turn foreseen).
    profile_k : numpy.ndarray, shape (S,)
        Turnaround profile [K] (:func:`turn_profile`).
    horizon : int
        ``H``.
    t_base_k : float or None
        ``T_b`` [K]; None: the current deviation from the profile is taken as 0.
    persistence : float
        ρ in [0, 1].

    Returns
    -------
    numpy.ndarray, shape (H,)
    """
    out = np.empty(horizon)
    forecast_into(float(t_now_k), int(steps_since_start), bool(on_first_track),
                   -1 if steps_to_end is None else int(steps_to_end), np.asarray(profile_k, dtype=float),
                   t_base_k is not None, 0.0 if t_base_k is None else float(t_base_k),
                   persistence ** np.arange(1.0, horizon + 1), out)
    return out


@njit(cache=True, nogil=True)
def forecast_into(t_now, since, on_first, to_end, profile, has_base, t_base, decay,
                  out):  # pragma: no cover (compiled)
    """:func:`forecast_t_ahead` into ``out``, shape (H,), compiled: the preview MPC calls it in every
    update, with ``to_end = −1`` for no turn foreseen, ``has_base`` False for no ``T_b`` (``t_base``
    [K] is then not read) and ``decay = ρ^j``, j = 1..H."""
    horizon, last = out.size, profile.size - 1
    here = profile[min(since, last)]
    base = t_base if has_base else t_now - here
    deviation = t_now - base - here
    for i in range(horizon):
        j = i + 1
        if on_first:
            out[i] = t_now
        else:
            out[i] = base + profile[min(since + j, last)] + deviation * decay[i]
    if to_end < 0 or to_end >= horizon:
        return
    t_end = out[to_end - 1] if to_end > 0 else t_now
    for i in range(to_end, horizon):
        out[i] = t_end + profile[max(min(i - to_end, last), 0)]


@njit(cache=True, nogil=True)
def adjust_forecast(out, f_future, f_now, f_mean, gain, since, on_first, to_end,
                    decay):  # pragma: no cover (compiled)
    """Add the turnaround feature's part to a T-ahead forecast of :func:`forecast_into`, in place.

    With ``ΔF = F − F̄[s]`` (the feature [K] over its mean at s states after a turn, 0 on a layer's
    first track and beyond F̄), the forecast's deviation from the profile becomes
    ``β ΔF[k+j] + ρʲ (T[k] − T_b − P[s_k] − β ΔF[k])``: on the current track
    ``β (ΔF[k+j] − ρʲ ΔF[k])`` is added, after the turn ahead (``to_end`` ≥ 0) ``β ΔF[k+j]`` plus
    what the current track's last state got. ``f_future`` F[k+1..k+H], ``f_now`` F[k] [K], ``gain``
    β [-], ``decay`` ρʲ."""
    n_mean = f_mean.size
    d_now = f_now - f_mean[since] if not on_first and since < n_mean else 0.0
    at_end = 0.0
    for i in range(out.size):
        j = i + 1
        if to_end < 0 or j <= to_end:
            s = since + j
            d = f_future[i] - f_mean[s] if not on_first and s < n_mean else 0.0
            add = gain * (d - decay[i] * d_now)
            if j == to_end:
                at_end = add
        else:
            s = j - to_end - 1
            add = at_end + gain * (f_future[i] - f_mean[s] if s < n_mean else 0.0)
        out[i] += add


def turn_bases(run: RunSeries) -> np.ndarray:
    """``T_b`` of every state: T ahead in the state before its track's first state (NaN on a layer's first track)."""
    base = np.full(len(run), np.nan)
    for a, b in itertools.pairwise(np.r_[run.turn_starts(), len(run)]):
        base[a:b] = run.t_ahead_k[a - 1]
    base[run.first_track_of_layer()] = np.nan
    return base


def run_forecast(run: RunSeries, k: int, horizon: int, profile_k: np.ndarray, persistence: float) -> np.ndarray:
    """:func:`forecast_t_ahead` at state k of a recorded run (scan plan from its track indices)."""
    s, e = run.steps_since_track_start(), run.steps_to_track_end()
    base = turn_bases(run)[k]
    return forecast_t_ahead(run.t_ahead_k[k], int(s[k]), bool(run.first_track_of_layer()[k]),
                            None if run.last_track_of_layer()[k] else int(e[k]), profile_k, horizon,
                            None if np.isnan(base) else float(base), persistence)


def fit_persistence(runs: Sequence[RunSeries], profile_k: np.ndarray) -> float:
    """ρ of :func:`forecast_t_ahead` with the smallest mean absolute forecast error on ``runs``, over the
    rollout horizon from every :data:`~gp_model.build_up.ROLLOUT_STRIDE`-th state (both as time at the runs'
    sample period, :mod:`gp_model.build_up`)."""
    period = runs[0].sample_period_s
    horizon, stride, build_up = rollout_horizon(period), steps_at(ROLLOUT_STRIDE, period), build_up_steps(period)
    grid = (0.0, 0.5, 0.7, 0.8, 0.9, 0.95, 0.98, 1.0)
    plans = []  # per run: (run, s, e, T_b, first track, last track), computed once
    for run in runs:
        plans.append((run, run.steps_since_track_start(), run.steps_to_track_end(), turn_bases(run),
                      run.first_track_of_layer(), run.last_track_of_layer(), run.steps_since_layer_start()))
    errors = []
    for rho in grid:
        err = [np.mean(np.abs(forecast_t_ahead(run.t_ahead_k[k], int(s[k]), bool(first[k]),
                                               None if last[k] else int(e[k]), profile_k, horizon,
                                               None if np.isnan(base[k]) else float(base[k]), rho)
                              - run.t_ahead_k[k + 1:k + horizon + 1]))
               for run, s, e, base, first, last, since in plans
               for k in range(build_up, len(run) - horizon - 1, stride) if since[k] >= build_up]
        errors.append(np.mean(err) if err else 0.0)
    return float(grid[int(np.argmin(errors))])


class ResidualGP:
    """Zero-mean SE-ARD GP (eq. 1–5) on standardised inputs, target scaled to unit std.

    Parameters
    ----------
    inputs : numpy.ndarray, shape (n, d)
        Training inputs ψ (SI).
    targets : numpy.ndarray, shape (n,)
        Residuals [m²].
    signal_std, noise_std : float
        σ_f and σ_n in normalised units.
    length_scales : numpy.ndarray, shape (d,)
        ℓ_j in standard deviations of input j.
    input_mean, input_scale : numpy.ndarray, shape (d,)
        Standardisation of the inputs.
    target_scale : float
        Standard deviation of the residual [m²].
    """

    def __init__(self, *, inputs: np.ndarray, targets: np.ndarray, signal_std: float, noise_std: float,
                 length_scales: np.ndarray, input_mean: np.ndarray, input_scale: np.ndarray,
                 target_scale: float) -> None:
        self.inputs = np.asarray(inputs, dtype=float)
        self.targets = np.asarray(targets, dtype=float)
        self.signal_std, self.noise_std = float(signal_std), float(noise_std)
        self.length_scales = np.asarray(length_scales, dtype=float)
        self.input_mean = np.asarray(input_mean, dtype=float)
        self.input_scale = np.asarray(input_scale, dtype=float)
        self.target_scale = float(target_scale)
        n = self.targets.shape[0]
        U = (self.inputs - self.input_mean) / self.input_scale
        theta = np.log(np.r_[self.signal_std, self.noise_std, self.length_scales])
        ky = gram(theta, squared_differences(U)) + self.noise_std**2 * np.eye(n)
        try:
            chol = scipy.linalg.cholesky(ky, lower=True)
        except np.linalg.LinAlgError as exc:
            raise ModelFormatError("residual GP covariance is not positive definite") from exc
        alpha = scipy.linalg.cho_solve((chol, True), self.targets / self.target_scale)
        self._g = 1.0 / (self.input_scale * self.length_scales)
        self._W = np.ascontiguousarray(U / self.length_scales)
        self._half = -0.5 * np.einsum("ij,ij->i", self._W, self._W)
        sf2 = self.signal_std**2
        self._mean_w = self.target_scale * sf2 * alpha
        self._var_f = self.target_scale * sf2 * scipy.linalg.solve_triangular(chol, np.eye(n), lower=True)
        self.prior_variance = (self.target_scale**2) * sf2
        self.noise_variance = (self.target_scale * self.noise_std) ** 2

    @classmethod
    def fit(cls, inputs: np.ndarray, targets: np.ndarray, *, bounds: HyperBounds, seed: int,
            n_restarts: int) -> ResidualGP:
        """Hyper-parameters by maximum log marginal likelihood (L-BFGS-B, seeded restarts)."""
        mu = inputs.mean(axis=0)
        scale = np.where(inputs.std(axis=0) > 0, inputs.std(axis=0), 1.0)
        t_scale = max(float(np.std(targets)), 1e-30)
        theta, _ = fit_hyperparameters((inputs - mu) / scale, targets / t_scale, bounds=bounds,
                                       n_restarts=n_restarts, seed=seed)
        p = np.exp(theta)
        return cls(inputs=inputs, targets=targets, signal_std=p[0], noise_std=p[1], length_scales=p[2:],
                   input_mean=mu, input_scale=scale, target_scale=t_scale)

    def predict(self, psi: np.ndarray, n_variance: int | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Mean and latent variance at the rows of ``psi``, shape (m, d) → (m,), (r,), in target units.

        ``n_variance`` limits the variance (the O(m n²) part) to the first r rows (default: all).
        """
        w = (np.atleast_2d(psi) - self.input_mean) * self._g
        k = np.exp(w @ self._W.T + self._half - 0.5 * np.einsum("ij,ij->i", w, w)[:, None])
        rows = k.shape[0] if n_variance is None else min(n_variance, k.shape[0])
        v = k[:rows] @ self._var_f.T
        return k @ self._mean_w, np.maximum(self.prior_variance - np.einsum("ij,ij->i", v, v), 0.0)

    def kernel_terms(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """What a compiled predictor needs (:mod:`controller_node.preview_kernel`): ``(μ, g, σ², σ_n²)``
        shape (2d + 2,); per training point (columns) ``W_a`` (d rows), ``−‖W_a‖²/2``, ``β_a`` and
        ``W_a,d−1 β_a``, shape (d + 3, N); and ``σ_f L⁻¹`` shape (N, N), lower triangular
        (``var = σ² − ‖σ_f L⁻¹ k‖²``)."""
        scalars = np.r_[self.input_mean, self._g, self.prior_variance, self.noise_variance]
        points = np.vstack([self._W.T, self._half, self._mean_w, self._W[:, -1] * self._mean_w])
        return scalars, np.ascontiguousarray(points), np.ascontiguousarray(self._var_f)

    def to_dict(self) -> dict[str, Any]:
        return {"inputs": self.inputs.tolist(), "targets": self.targets.tolist(), "signal_std": self.signal_std,
                "noise_std": self.noise_std, "length_scales": self.length_scales.tolist(),
                "input_mean": self.input_mean.tolist(), "input_scale": self.input_scale.tolist(),
                "target_scale": self.target_scale}


class NarxGPModel:
    """The delay-aware model of the module docstring (construct with :meth:`fit` or :meth:`load`).

    ``z[k+1] = c₀ + Σ b_i p_i + Σ q_i φ(p_i) + Σ c_j T_j + Σ d_j T_j² + Σ e_i p_i T_i + r(ψ_k)`` with the lagged
    powers ``p_i = p[k+1−i]`` and temperatures ``T_j = T[k−j]``, and ``x[k+1] = exp(z)`` for the
    ``"log"`` output (``z`` the log of the area in m²) or ``x = z`` for ``"identity"``.

    Parameters
    ----------
    sample_period_s : float
        Δt the model was identified at [s].
    intercept : float
        ``c₀`` (units of z).
    power_coefficients, power_map_coefficients : numpy.ndarray, shape (n_p,)
        ``b_i`` [z/W] and ``q_i`` [z per unit of φ], i = 0 for ``p[k+1]``.
    temperature_coefficients : numpy.ndarray, shape (n_T,)
        ``c_j`` [z/K], j = 0 for ``T[k]``.
    temperature_square_coefficients : numpy.ndarray, shape (n_Tq,), n_Tq <= n_T
        ``d_j`` [z/K²].
    output : {"log", "identity"}
        Output map.
    power_temperature_coefficients : numpy.ndarray, shape (n_x,), n_x <= min(n_p, n_T), optional
        ``e_i`` [z/(W K)] of the lag-matched interactions ``p[k+1−i] T[k−i]``: the power of step
        k−i → k+1−i acts on material whose temperature ahead was ``T[k−i]`` when it was applied
        (a hotter substrate gives another power gain).
    residual : ResidualGP
        GP on ψ (the first 2 or all 3 of :data:`RESIDUAL_INPUTS`, :attr:`gp_inputs`), in units of z.
    power_map : {"square", "log1p"}
        φ of the power lags (:func:`map_power`).
    turn_feature : gp_model.plan_feature.TurnFeature or None
        Constants of the turnaround feature ``F`` (None: no feature).
    feature_coefficients : numpy.ndarray, shape (n_F,), optional
        ``g_l`` [z/K] of the lagged features ``F[k+1−l]`` (empty: none).
    feature_temperature_gain : float
        β [-]: T ahead's deviation from the turnaround profile per kelvin of the feature's deviation
        from its mean ``feature_profile_k`` (the forecast's part, :func:`adjust_forecast`).
    feature_profile_k : numpy.ndarray, shape (n_targets,), optional
        F̄[s]: mean feature s states after a turn of the training runs [K] (with ``turn_feature``).
    remnant_feature : gp_model.plan_feature.RemnantFeature or None
        Constants of the remnant terms (None: none).
    remnant_coefficients, remnant_offsets : numpy.ndarray, shape (n_R,), optional
        ``h_s`` [z/W] and ``c_s`` [z] of the remnant terms, s the states after a turn (with ``remnant_feature``).
    turn_profile_k : numpy.ndarray, shape (S,)
        Mean rise of T ahead after a turnaround [K] (:func:`turn_profile`).
    forecast_persistence : float
        ρ of :func:`forecast_t_ahead`.
    speed_m_s : float
        The constant scan speed of the data [m/s] (power-only control).
    provenance : Mapping, optional
        How the model was made; its ``"process"`` entry, if any, names the ``"material"``, the
        ``"powder_layer_m"`` [m] and the ``"plant"`` of the identification runs.

    Attributes
    ----------
    gp_inputs : tuple of str
        The names of the residual GP's inputs ψ, in order.
    material : str or None
        The material of the identification runs (``None``: not recorded).
    powder_layer_m : float or None
        The powder layer thickness of the identification runs' plant [m] (0: a bare plate; ``None``: not
        recorded).
    """

    def __init__(self, *, sample_period_s: float, intercept: float, power_coefficients: np.ndarray,
                 power_map_coefficients: np.ndarray, temperature_coefficients: np.ndarray,
                 temperature_square_coefficients: np.ndarray, output: str, residual: ResidualGP,
                 power_map: str = "square", power_temperature_coefficients: np.ndarray | None = None,
                 turn_feature: TurnFeature | None = None, feature_coefficients: np.ndarray | None = None,
                 feature_temperature_gain: float = 0.0, feature_profile_k: np.ndarray | None = None,
                 remnant_feature: RemnantFeature | None = None, remnant_coefficients: np.ndarray | None = None,
                 remnant_offsets: np.ndarray | None = None,
                 turn_profile_k: np.ndarray, forecast_persistence: float, speed_m_s: float,
                 provenance: Mapping[str, Any] | None = None) -> None:
        self.sample_period_s = float(sample_period_s)
        self.intercept = float(intercept)
        self.power_coefficients = np.asarray(power_coefficients, dtype=float)
        self.power_map_coefficients = np.asarray(power_map_coefficients, dtype=float)
        self.temperature_coefficients = np.asarray(temperature_coefficients, dtype=float)
        self.temperature_square_coefficients = np.asarray(temperature_square_coefficients, dtype=float)
        self.power_temperature_coefficients = np.asarray(
            () if power_temperature_coefficients is None else power_temperature_coefficients, dtype=float)
        self.turn_feature = turn_feature
        self.feature_coefficients = np.asarray(() if feature_coefficients is None else feature_coefficients,
                                               dtype=float)
        self.feature_temperature_gain = float(feature_temperature_gain)
        self.feature_profile_k = np.asarray(() if feature_profile_k is None else feature_profile_k, dtype=float)
        self.remnant_feature = remnant_feature
        self.remnant_coefficients = np.asarray(() if remnant_coefficients is None else remnant_coefficients,
                                               dtype=float)
        self.remnant_offsets = np.asarray(() if remnant_offsets is None else remnant_offsets, dtype=float)
        self.output = output
        self.residual = residual
        self.power_map = power_map
        self.turn_profile_k = np.asarray(turn_profile_k, dtype=float)
        self.forecast_persistence = float(forecast_persistence)
        self.speed_m_s = float(speed_m_s)
        self.provenance = dict(provenance or {})
        process = self.provenance.get("process", {})
        self.material = process.get("material") if isinstance(process, dict) else None
        self.powder_layer_m = process.get("powder_layer_m") if isinstance(process, dict) else None
        if not isinstance(process, dict) or not (self.material is None or isinstance(self.material, str)):
            raise ModelFormatError("NARX model: provenance.process must be an object whose material is a string")
        if not (self.powder_layer_m is None or (isinstance(self.powder_layer_m, (int, float))
                                                and not isinstance(self.powder_layer_m, bool)
                                                and 0 <= self.powder_layer_m < 1e-2)):
            raise ModelFormatError("NARX model: provenance.process.powder_layer_m must be a number in [0, 0.01) m")
        arrays = (self.power_coefficients, self.power_map_coefficients, self.temperature_coefficients,
                  self.temperature_square_coefficients, self.turn_profile_k, self.power_temperature_coefficients,
                  self.feature_coefficients, self.feature_profile_k, self.remnant_coefficients, self.remnant_offsets)
        if output not in OUTPUTS:
            raise ModelFormatError(f"NARX model: output must be one of {OUTPUTS}, got {output!r}")
        if power_map not in POWER_MAPS:
            raise ModelFormatError(f"NARX model: power_map must be one of {POWER_MAPS}, got {power_map!r}")
        if residual.inputs.ndim != 2 or residual.inputs.shape[1] not in (2, len(RESIDUAL_INPUTS)):
            raise ModelFormatError("NARX model: the residual GP takes the first 2 or all 3 of "
                                   f"{RESIDUAL_INPUTS}, got inputs of shape {residual.inputs.shape}")
        self.gp_inputs = RESIDUAL_INPUTS[:residual.inputs.shape[1]]
        if not (self.sample_period_s > 0 and self.speed_m_s > 0 and all(a.ndim == 1 for a in arrays)
                and self.power_map_coefficients.size == self.power_coefficients.size > 0
                and 0 <= self.temperature_square_coefficients.size <= self.temperature_coefficients.size > 0
                and self.power_temperature_coefficients.size <= min(self.power_coefficients.size,
                                                                    self.temperature_coefficients.size)
                and (turn_feature is not None or self.feature_coefficients.size == 0 == self.feature_profile_k.size)
                and (turn_feature is None or self.feature_profile_k.size == turn_feature.n_targets)
                and self.remnant_coefficients.size == self.remnant_offsets.size
                == (0 if remnant_feature is None else remnant_feature.n_states)
                and (remnant_feature is None or remnant_feature.offsets or not np.any(self.remnant_offsets))
                and math.isfinite(self.feature_temperature_gain)
                and self.turn_profile_k.size > 0 and 0.0 <= self.forecast_persistence <= 1.0
                and all(np.all(np.isfinite(a)) for a in arrays) and math.isfinite(self.intercept)):
            raise ModelFormatError("NARX model: non-finite or inconsistent coefficients, or a period/speed <= 0")

    @property
    def n_power_lags(self) -> int:
        return int(self.power_coefficients.size)

    @property
    def n_temperature_lags(self) -> int:
        return int(self.temperature_coefficients.size)

    @property
    def n_feature_lags(self) -> int:
        return int(self.feature_coefficients.size)

    def feature_kernel(self) -> np.ndarray:
        """``K[s, e]`` [K/W] of the turnaround feature at the model's step length and period
        (:meth:`gp_model.plan_feature.TurnFeature.kernel`); shape (1, 1) of zeros without a feature."""
        if self.turn_feature is None:
            return np.zeros((1, 1))
        return self.turn_feature.kernel(self.speed_m_s * self.sample_period_s, self.sample_period_s)

    def features(self, run: RunSeries) -> np.ndarray:
        """``F[j]`` [K] of every state of ``run``, shape (n,) (zeros without a feature)."""
        if self.turn_feature is None:
            return np.zeros(len(run))
        return turn_feature_series(self.feature_kernel(), run.power_w, run.turn_starts(),
                                   run._ends(run.layers(), run.track))

    def remnant_kernel(self) -> tuple[np.ndarray, np.ndarray]:
        """The remnant terms as the controller takes them: ``W[s, e]`` [z/W], shape (n_R, n_sources)
        (:meth:`gp_model.plan_feature.RemnantFeature.kernel`), and the offsets ``c_s`` [z], shape (n_R,);
        shapes (0, 1) and (0,) without them."""
        if self.remnant_feature is None:
            return np.zeros((0, 1)), np.zeros(0)
        return self.remnant_feature.kernel(self.remnant_coefficients), self.remnant_offsets.copy()

    def remnant_inputs(self, run: RunSeries) -> np.ndarray:
        """The remnant's regressors ``[P̄ columns, 1 columns]`` of every state of ``run``, shape (n, 2 n_R)
        (:func:`gp_model.plan_feature.remnant_series`; (n, 0) without the remnant)."""
        if self.remnant_feature is None:
            return np.zeros((len(run), 0))
        return np.hstack(remnant_series(self.remnant_feature, run.power_w, run.turn_starts(),
                                        run._ends(run.layers(), run.track)))

    def area_at(self, z: float) -> float:
        """``x = exp(z)`` or ``z`` [m²] of one ``z``, in the C library's ``exp`` as the controller's
        compiled kernel (:mod:`controller_node.preview_kernel`) evaluates it."""
        if self.output != "log":
            return float(z)
        return math.exp(z) if z <= _LOG_AREA_MAX else math.inf

    def area_and_slope(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``x = exp(z)`` or ``z`` [m²] and ``∂x/∂z`` [m² per unit of z] at ``z``, one exponential."""
        if self.output != "log":
            return z, np.ones_like(z)
        with np.errstate(over="ignore"):  # an absurd input overflows: handled just below
            x = np.exp(z)
        if np.max(z) > _LOG_AREA_MAX:  # an absurd input: inf, which the controller's safety layer rejects
            return np.full_like(np.asarray(z, dtype=float), np.inf), x
        return x, x

    def input_definitions(self) -> dict[str, str]:
        """Definition of every input (recorded in the model file)."""
        return {
            "p[k+1-i], i=0..n_p-1": "laser power applied during step k-i -> k+1-i [W] "
                                    "(state[k+1-i].power_w; 0 before laser-on); linear and mapped by power_map",
            "power_map": "phi(p) of the power_map_coefficients: 'square' p^2, 'log1p' "
                         f"log(1 + p / {LOG_POWER_SCALE_W:g} W)",
            "T[k-j], j=0..n_T-1": "temperature ahead of the laser in state k-j [K] "
                                  "(state.t_ahead_k; T[0] before the first state); linear, squared for j < n_Tq",
            "p[k+1-i] T[k-i], i=0..n_x-1": "interaction of each lagged power with the temperature ahead in the "
                                           "state it was applied from [W K]",
            "t_ahead_k": "GP input: T[k] [K]",
            "log1p_steps_since_track_start": "GP input: log(1 + s), s the states since the current track's "
                                             f"first state, capped at {STEPS_SINCE_START_CAP}",
            "F[k+1-l], l=0..n_F-1": "turnaround feature [K]: temperature rise at the laser in state k+1-l from the "
                                    "powers of the previous track's last n_sources steps (superposed Gaussian "
                                    "moving sources, adiabatic half-space, constants in turn_feature; 0 on a "
                                    "layer's first track and n_targets states after a turn)",
            "feature_temperature_gain": "beta: the T-ahead forecast after a turn adds beta (F - feature_profile_k[s]), "
                                        "s the states since the turn (T ahead's rise over the profile per K of F)",
            "c_s + h_s Pbar": "remnant terms: for the state k+1 that is s < remnant_feature.n_states states after a "
                              "turn, offset remnant_offsets[s] plus remnant_coefficients[s] [1/W] times Pbar, the "
                              "mean power of the previous track's last remnant_feature.n_sources steps [W]",
            "mean_power_w": "GP input (if in residual_gp.inputs_names): mean of p[k+1-i], i=0..n_p-1 [W]",
            "output": "melt-pool area x[k+1] [m2] (state[k+1].area_mm2 * 1e-6) "
                      "= exp(z) for output 'log', z for 'identity'",
            "sample_period_s": "duration of one step; the model is valid only at this period",
        }

    # ------------------------------------------------------------------ regressors
    def _lagged(self, run: RunSeries) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Lag matrices for every target index j = 1..n−1: powers (n−1, n_p), temperatures (n−1, n_T),
        features (n−1, n_F), and the remnant's regressors of the targets (n−1, 2 n_R)."""
        n_p, n_t, n_f = self.n_power_lags, self.n_temperature_lags, self.n_feature_lags
        p = np.r_[np.zeros(n_p), run.power_w]
        t = np.r_[np.full(n_t, run.t_ahead_k[0]), run.t_ahead_k]
        f = np.r_[np.zeros(n_f), self.features(run)]
        j = np.arange(1, len(run))
        P = p[(j + n_p)[:, None] - np.arange(n_p)[None, :]]
        T = t[(j - 1 + n_t)[:, None] - np.arange(n_t)[None, :]]
        F = f[(j + n_f)[:, None] - np.arange(n_f)[None, :]]
        return P, T, F, self.remnant_inputs(run)[1:]

    def design(self, P: np.ndarray, T: np.ndarray, F: np.ndarray, R: np.ndarray) -> np.ndarray:
        """Regressor rows ``[1, p, φ(p), T, T², p×T, F, P̄ columns, 1 columns]`` for lag matrices ``P`` (m, n_p),
        ``T`` (m, n_T), ``F`` (m, n_F) and the remnant's regressors ``R`` (m, 2 n_R)."""
        n_tq, n_x = self.temperature_square_coefficients.size, self.power_temperature_coefficients.size
        return np.column_stack([np.ones(P.shape[0]), P, map_power(P, self.power_map), T, T[:, :n_tq] ** 2,
                                P[:, :n_x] * T[:, :n_x], F, R])

    def coefficients(self) -> np.ndarray:
        """All coefficients in the order of :meth:`design`."""
        return np.r_[self.intercept, self.power_coefficients, self.power_map_coefficients,
                     self.temperature_coefficients, self.temperature_square_coefficients,
                     self.power_temperature_coefficients, self.feature_coefficients, self.remnant_coefficients,
                     self.remnant_offsets]

    def residual_inputs(self, run: RunSeries) -> np.ndarray:
        """ψ (:attr:`gp_inputs`) for every target index j = 1..n−1, shape (n−1, 2 or 3)."""
        s = steps_since_start_feature(run.steps_since_track_start()[:-1])
        if len(self.gp_inputs) == 2:
            return np.column_stack([run.t_ahead_k[:-1], s])
        return np.column_stack([run.t_ahead_k[:-1], s, self._lagged(run)[0].mean(axis=1)])

    def predict_run(self, run: RunSeries) -> tuple[np.ndarray, np.ndarray]:
        """One-step mean [m²] and latent variance [m⁴] of ``x[j]``, j = 1..n−1, with measured T
        (variance mapped from z by the output's slope)."""
        mean, var = self.residual.predict(self.residual_inputs(run))
        z = self.design(*self._lagged(run)) @ self.coefficients() + mean
        area, slope = self.area_and_slope(z)
        return area, slope * slope * var

    def forecast(self, run: RunSeries, k: int, horizon: int) -> np.ndarray:
        """T ahead ``T̂[k+1..k+H]`` [K] at state k of ``run`` (its track indices as the scan plan, its
        powers as the applied and planned ones): :func:`run_forecast` and, with a turnaround feature,
        its part (:func:`adjust_forecast`)."""
        out = run_forecast(run, k, horizon, self.turn_profile_k, self.forecast_persistence)
        if self.turn_feature is None:
            return out
        f = np.r_[self.features(run), np.zeros(horizon)]
        last = bool(run.last_track_of_layer()[k])
        adjust_forecast(out, f[k + 1:k + 1 + horizon], float(f[k]), self.feature_profile_k,
                        self.feature_temperature_gain, int(run.steps_since_track_start()[k]),
                        bool(run.first_track_of_layer()[k]), -1 if last else int(run.steps_to_track_end()[k]),
                        self.forecast_persistence ** np.arange(1.0, horizon + 1))
        return out

    def rollout(self, run: RunSeries, k: int, horizon: int) -> np.ndarray:
        """Predict ``x[k+1..k+H]`` [m²] from what is known at state k: the applied powers (as a
        perfect plan) and T ahead measured up to k, forecast after it (:func:`run_forecast`)."""
        forecast = self.forecast(run, k, horizon)
        n = k + horizon + 1
        future = RunSeries(run.name, run.area_m2[:n], np.r_[run.t_ahead_k[:k + 1], forecast][:n],
                           run.power_w[:n], run.track[:n], run.sample_period_s, run.layers()[:n])
        rows = slice(k, k + horizon)
        z = self.design(*(a[rows] for a in self._lagged(future))) @ self.coefficients() + self.residual.predict(
            self.residual_inputs(future)[rows], n_variance=0)[0]
        return self.area_and_slope(z)[0]

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(cls, runs: Sequence[RunSeries], *, n_power_lags: int, n_temperature_lags: int,
            n_temperature_square_lags: int | None = None, quadratic: bool = True, interaction: bool = False,
            feature_lags: int = 0, turn_feature: TurnFeature | None = None,
            remnant: RemnantFeature | None = None, smoothing: float = 0.0, output: str = "log",
            n_train: int = 150, bounds: HyperBounds = DEFAULT_BOUNDS, seed: int = 0, n_restarts: int = 4,
            profile_length: int = 200, speed_m_s: float | None = None,
            monotone_power_w: tuple[float, float] | None = MONOTONE_POWER_W, power_map: str = DEFAULT_POWER_MAP,
            gp_power_input: bool = True, provenance: Mapping[str, Any] | None = None) -> NarxGPModel:
        """Least squares in z for the lag part, then the residual GP on ``n_train`` seeded random samples.

        Samples whose target is in the build-up of a run or of a layer (:func:`~gp_model.build_up.build_up_steps`
        states at the runs' period: :data:`~gp_model.build_up.BUILD_UP_STEPS` at the FE step), or has no
        pool (area 0), are not fitted (the lags still see their powers). ``power_map`` is φ of
        the power lags (:data:`POWER_MAPS`); ``quadratic=False`` leaves out φ and the squared T lags
        (a plain FIR part); ``gp_power_input=False`` leaves the mean power out of the GP's inputs;
        ``interaction`` adds the lag-matched p × T terms; ``feature_lags`` > 0 the lagged turnaround features
        ``F[k+1−l]``, l < feature_lags, of ``turn_feature``; ``remnant`` the remnant terms (least squares on the lag
        part's residual, per state after a turn); ``smoothing`` λ > 0 the smoothness prior on every lag kernel
        (:func:`smoothing_rows`). The turnaround profile spans ``profile_length`` states, at least the
        feature's ``n_targets`` (the forecast's feature part is fitted against it). The model's scan
        speed is the runs' (:attr:`RunSeries.speed_m_s`), or ``speed_m_s``
        [m/s] for runs that record none. The lag part's steady-state gain in power
        (:func:`static_power_gains`) is held non-negative over ``monotone_power_w`` [W] and the runs'
        range of T ahead (at its corners: the gain is monotone in p and linear in T), so that beyond the staircases'
        powers the fitted squares do not turn the model's response to power around (``None``: unconstrained).

        Raises
        ------
        DatasetError
            No runs, mixed sample periods or speeds, no speed, or too few samples.
        """
        if not runs:
            raise DatasetError("no runs to fit")
        if output not in OUTPUTS:
            raise DatasetError(f"output must be one of {OUTPUTS}, got {output!r}")
        if power_map not in POWER_MAPS:
            raise DatasetError(f"power_map must be one of {POWER_MAPS}, got {power_map!r}")
        periods = {round(r.sample_period_s, 12) for r in runs}
        if len(periods) != 1:
            raise DatasetError(f"runs have different sample periods: {sorted(periods)} s")
        speed = _common_speed(runs, speed_m_s)
        if not quadratic:
            n_tq = 0
        elif n_temperature_square_lags is None:
            n_tq = n_temperature_lags // 2
        else:
            n_tq = n_temperature_square_lags
        n_x = min(n_power_lags, n_temperature_lags) if interaction else 0
        if feature_lags < 0 or (feature_lags and turn_feature is None):
            raise DatasetError(f"feature_lags must be >= 0, and 0 without a turn_feature, got {feature_lags}")
        feature = turn_feature
        probe = cls._probe(n_power_lags, n_temperature_lags, n_tq, runs[0].sample_period_s, n_x, feature_lags,
                           feature, speed, remnant, power_map, gp_power_input)
        X, Y, PSI = [], [], []
        for run in runs:
            lagged = probe._lagged(run)
            keep = (run.steps_since_layer_start()[1:] >= build_up_steps(run.sample_period_s)) & (run.area_m2[1:] > 0)
            X.append(probe.design(*(a[keep] for a in lagged))), Y.append(run.area_m2[1:][keep])
            PSI.append(probe.residual_inputs(run)[keep])
        X, Y, PSI = np.vstack(X), np.concatenate(Y), np.vstack(PSI)
        if not quadratic:
            X[:, 1 + n_power_lags:1 + 2 * n_power_lags] = 0.0
        n_r = 0 if remnant is None else remnant.n_states
        if n_r and not remnant.offsets:
            X[:, X.shape[1] - n_r:] = 0.0
        if Y.size < max(n_train, X.shape[1]) + 10:
            raise DatasetError(f"only {Y.size} samples for {X.shape[1]} coefficients and {n_train} GP points")
        target = np.log(Y) if output == "log" else Y
        scale = np.linalg.norm(X, axis=0)
        scale[scale == 0] = 1.0
        sizes = (n_power_lags, n_power_lags, n_temperature_lags, n_tq, n_x, feature_lags, n_r, n_r)
        rows = smoothing_rows(sizes, smoothing, SMOOTHED_GROUPS)
        remnant_columns = X[:, X.shape[1] - 2 * n_r:].copy()
        X[:, X.shape[1] - 2 * n_r:] = 0.0          # the remnant terms: fitted on what the rest leaves (below)
        t_ahead = np.concatenate([r.t_ahead_k for r in runs])
        gains = (np.zeros((0, X.shape[1])) if monotone_power_w is None
                 else static_power_gains(sizes, monotone_power_w, (float(t_ahead.min()), float(t_ahead.max())),
                                         power_map))
        theta = least_squares_with_gains(np.vstack([X / scale, rows]), np.r_[target, np.zeros(rows.shape[0])],
                                         gains / scale) / scale
        residual = target - X @ theta
        if n_r:
            r_scale = scale[scale.size - 2 * n_r:]
            theta[theta.size - 2 * n_r:] = np.linalg.lstsq(remnant_columns / r_scale, residual, rcond=None)[0] / r_scale
            residual = residual - remnant_columns @ theta[theta.size - 2 * n_r:]
        pick = np.sort(np.random.default_rng(seed).choice(Y.size, size=n_train, replace=False))
        gp = ResidualGP.fit(PSI[pick], residual[pick], bounds=bounds, seed=seed, n_restarts=n_restarts)
        profile = turn_profile(runs, max(profile_length, feature.n_targets if feature else 0))
        gain, feature_profile = probe._feature_forecast_fit(runs, profile) if feature else (0.0, None)
        record = dict(provenance or {})
        record.update(seed=seed, n_train=n_train, smoothing=smoothing, n_samples=int(Y.size),
                      monotone_power_w=None if monotone_power_w is None else list(monotone_power_w),
                      runs=[r.name for r in runs],
                      bounds={"signal_std": list(bounds.signal_std), "noise_std": list(bounds.noise_std),
                              "length_scale": list(bounds.length_scale)})
        n_p, n_t = n_power_lags, n_temperature_lags
        n_f = feature_lags
        split = theta.size - 2 * n_r
        theta, h, c = theta[:split], theta[split:split + n_r], theta[split + n_r:]
        theta, g = (theta[:theta.size - n_f], theta[theta.size - n_f:]) if n_f else (theta, None)
        return cls(sample_period_s=runs[0].sample_period_s, intercept=theta[0], power_coefficients=theta[1:1 + n_p],
                   power_map_coefficients=theta[1 + n_p:1 + 2 * n_p],
                   temperature_coefficients=theta[1 + 2 * n_p:1 + 2 * n_p + n_t],
                   temperature_square_coefficients=theta[1 + 2 * n_p + n_t:1 + 2 * n_p + n_t + n_tq],
                   power_temperature_coefficients=theta[1 + 2 * n_p + n_t + n_tq:], turn_feature=feature,
                   feature_coefficients=g, feature_temperature_gain=gain, feature_profile_k=feature_profile,
                   remnant_feature=remnant, remnant_coefficients=h if n_r else None,
                   remnant_offsets=c if n_r else None,
                   output=output, residual=gp, power_map=power_map,
                   turn_profile_k=profile, forecast_persistence=fit_persistence(runs, profile), speed_m_s=speed,
                   provenance=record)

    def _feature_forecast_fit(self, runs: Sequence[RunSeries], profile_k: np.ndarray) -> tuple[float, np.ndarray]:
        """β and F̄ of the forecast's feature part: F̄[s] the mean feature s states after a turn, β the
        least-squares slope of T ahead's rise over the profile, ``T[t₀+s] − T[t₀−1] − P[s]``, on
        ``F[t₀+s] − F̄[s]``, over every turn of ``runs``."""
        n = self.turn_feature.n_targets
        rows = []
        for run in runs:
            f, ends = self.features(run), run._ends(run.layers(), run.track)
            for start in run.turn_starts():
                s = np.arange(min(n, ends[start] + 1 - start))
                rows.append((s, f[start + s], run.t_ahead_k[start + s] - run.t_ahead_k[start - 1] - profile_k[s]))
        if not rows:
            return 0.0, np.zeros(n)
        s, f, rise = (np.concatenate(c) for c in zip(*rows, strict=True))
        counts = np.bincount(s, minlength=n)
        mean = np.bincount(s, weights=f, minlength=n) / np.maximum(counts, 1)
        d = f - mean[s]
        return (float(d @ rise / (d @ d)) if d @ d > 0 else 0.0), mean

    @classmethod
    def _probe(cls, n_p: int, n_t: int, n_tq: int, period: float, n_x: int = 0, n_f: int = 0,
               feature: TurnFeature | None = None, speed_m_s: float = 1.0,
               remnant: RemnantFeature | None = None, power_map: str = "square",
               gp_power_input: bool = True) -> NarxGPModel:
        """A shell with the right lag counts (for building regressors before the fit)."""
        if n_p < 1 or n_t < 1 or not 0 <= n_tq <= n_t:
            raise DatasetError(f"lag counts must be >= 1 (squared T lags <= T lags), got {n_p}, {n_t}, {n_tq}")
        obj = cls.__new__(cls)
        obj.power_coefficients, obj.temperature_coefficients = np.zeros(n_p), np.zeros(n_t)
        obj.temperature_square_coefficients = np.zeros(n_tq)
        obj.power_temperature_coefficients = np.zeros(n_x)
        obj.feature_coefficients, obj.turn_feature = np.zeros(n_f), feature
        obj.feature_temperature_gain, obj.feature_profile_k = 0.0, np.zeros(0)
        n_r = 0 if remnant is None else remnant.n_states
        obj.remnant_feature, obj.remnant_coefficients, obj.remnant_offsets = remnant, np.zeros(n_r), np.zeros(n_r)
        obj.sample_period_s, obj.speed_m_s = period, speed_m_s
        obj.power_map, obj.gp_inputs = power_map, RESIDUAL_INPUTS if gp_power_input else RESIDUAL_INPUTS[:2]
        return obj

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "sample_period_s": self.sample_period_s,
            "speed_m_s": self.speed_m_s,
            "inputs": self.input_definitions(),
            "structure": (
                "z[k+1] = c0 + sum_i (b_i p[k+1-i] + q_i phi(p[k+1-i])) + sum_j c_j T[k-j] + sum_{j<n_Tq} d_j T[k-j]^2"
                " + sum_{i<n_x} e_i p[k+1-i] T[k-i] + sum_{l<n_F} g_l F[k+1-l] + c_s + h_s Pbar + r(psi_k),"
                " r ~ GP(0, SE-ARD);"
                " x[k+1] = exp(z) (output 'log') or z"
            ),
            "output": self.output,
            "power_map": self.power_map,
            "intercept": self.intercept,
            "power_coefficients": self.power_coefficients.tolist(),
            "power_map_coefficients": self.power_map_coefficients.tolist(),
            "temperature_coefficients": self.temperature_coefficients.tolist(),
            "temperature_square_coefficients": self.temperature_square_coefficients.tolist(),
            "power_temperature_coefficients": self.power_temperature_coefficients.tolist(),
            "turn_feature": None if self.turn_feature is None else self.turn_feature.to_dict(),
            "feature_coefficients": self.feature_coefficients.tolist(),
            "feature_temperature_gain": self.feature_temperature_gain,
            "feature_profile_k": self.feature_profile_k.tolist(),
            "remnant_feature": None if self.remnant_feature is None else self.remnant_feature.to_dict(),
            "remnant_coefficients": self.remnant_coefficients.tolist(),
            "remnant_offsets": self.remnant_offsets.tolist(),
            "residual_gp": {"inputs_names": list(self.gp_inputs), **self.residual.to_dict()},
            "turn_profile_k": self.turn_profile_k.tolist(),
            "forecast_persistence": self.forecast_persistence,
            "provenance": self.provenance,
        }

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model as JSON, atomically."""
        return write_document(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> NarxGPModel:
        """Read a model written by :meth:`save` (``ModelFormatError`` with a one-line reason)."""
        doc = read_document(path)
        if not is_format(doc, FORMAT_NAME):
            raise ModelFormatError(f"{path} is not a {FORMAT_NAME} file")
        if doc.get("format_version") not in READABLE_VERSIONS:
            raise ModelVersionError(f"{path} has format version {doc.get('format_version')!r}, "
                                    f"this code reads {', '.join(map(str, READABLE_VERSIONS))}; retrain it")
        try:
            g = doc["residual_gp"]
            feature = doc.get("turn_feature")
            feature = None if feature is None else TurnFeature.from_dict(feature)
            remnant = doc.get("remnant_feature")
            remnant = None if remnant is None else RemnantFeature.from_dict(remnant)
            version = doc["format_version"]
            names = tuple(g["inputs_names"]) if version >= 6 else RESIDUAL_INPUTS
            if names != RESIDUAL_INPUTS[:len(names)] or np.shape(g["inputs"])[1:] != (len(names),):
                raise ModelFormatError(f"{path}: residual_gp.inputs_names must be the first 2 or all 3 of "
                                       f"{list(RESIDUAL_INPUTS)}, one per column of its inputs, got {list(names)}")
            residual = ResidualGP(inputs=np.array(g["inputs"]), targets=np.array(g["targets"]),
                                  signal_std=g["signal_std"], noise_std=g["noise_std"],
                                  length_scales=np.array(g["length_scales"]), input_mean=np.array(g["input_mean"]),
                                  input_scale=np.array(g["input_scale"]), target_scale=g["target_scale"])
            return cls(sample_period_s=doc["sample_period_s"], intercept=doc["intercept"],
                       power_coefficients=np.array(doc["power_coefficients"]),
                       power_map_coefficients=np.array(doc["power_map_coefficients" if version >= 6
                                                           else "power_square_coefficients"]),
                       power_map=doc["power_map"] if version >= 6 else "square",
                       temperature_coefficients=np.array(doc["temperature_coefficients"]),
                       temperature_square_coefficients=np.array(doc["temperature_square_coefficients"]),
                       power_temperature_coefficients=np.array(doc["power_temperature_coefficients"]),
                       turn_feature=feature, feature_coefficients=np.array(doc.get("feature_coefficients", [])),
                       feature_temperature_gain=doc.get("feature_temperature_gain", 0.0),
                       feature_profile_k=np.array(doc.get("feature_profile_k", [])),
                       remnant_feature=remnant, remnant_coefficients=np.array(doc.get("remnant_coefficients", [])),
                       remnant_offsets=np.array(doc.get("remnant_offsets", [])),
                       output=doc["output"], residual=residual, turn_profile_k=np.array(doc["turn_profile_k"]),
                       forecast_persistence=doc["forecast_persistence"], speed_m_s=doc["speed_m_s"],
                       provenance=doc.get("provenance") or {})
        except (KeyError, TypeError, ValueError) as exc:
            raise ModelFormatError(f"{path} is a corrupt model file: {exc}") from exc
