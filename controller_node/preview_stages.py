"""The preview MPC's stages as named structures: the estimator, the predictor, the planner, the run
they act on and the workspace they fill (:mod:`controller_node.preview_kernel` runs them).

Each is a numba ``StructRef``: one object with named fields that compiled code reads and writes
and Python holds (its proxy class below), passed to a compiled call as one pointer. The arrays of
a structure are views into one block allocated once (:func:`carve`), so an update allocates nothing
and reads its data from a few contiguous blocks, as the flat arrays before them did.

- :class:`Estimator`: the disturbance observer (offset-free control) and the one-step errors it
  sees after a turn, as do-mpc's estimator, ``d̂ = estimator.make_step(area, power)``.
- :class:`Predictor`: the delay-aware model's constants (FIR part, SE-ARD residual GP, T-ahead
  forecast), what predicts x̂ over the horizon and its Jacobian in the planned powers.
- :class:`Planner`: the condensed QP's constants (set point, scale, weights, bounds).
- :class:`Run`: the run's histories, previous plan, turnaround profile and learned corrections,
  and its estimator.
- :class:`Workspace`: what one update computes (prediction, linearisation, QP terms and step, the
  prepared moments of the real-time iteration).
- :class:`StateContext`: where a state sits (histories to fill, scan-plan position, tracked rows),
  the update's inputs besides the measured T ahead and area.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit, types
from numba.experimental import structref

__all__ = ["MOMENTS", "Estimator", "Planner", "Predictor", "Run", "StateContext", "Workspace", "carve", "estimate",
           "forget_prediction", "hold_prediction", "map_power", "map_power_slope", "new_estimator", "new_planner",
           "new_predictor", "new_run", "new_workspace", "reset_estimator"]

MOMENTS = 12
"""Terms of the series in which the feedback phase moves the GP's kernel sums (and, without bound
tightening, the variance) to the measured T ahead (:func:`controller_node.preview_kernel.feedback_into`)."""


@njit(cache=True, inline="always")
def map_power(power_w, map_scale_w):  # pragma: no cover (compiled)
    """φ(p) of :func:`gp_model.narx.map_power`: ``p²`` (``map_scale_w`` 0, the ``"square"`` map) or
    ``log(1 + p/p_s)`` (``map_scale_w`` p_s [W], the ``"log1p"`` map)."""
    return power_w * power_w if map_scale_w == 0.0 else math.log1p(power_w / map_scale_w)


@njit(cache=True, inline="always")
def map_power_slope(power_w, map_scale_w):  # pragma: no cover (compiled)
    """φ'(p) of :func:`map_power`: ``2p`` or ``1/(p_s + p)``."""
    return 2.0 * power_w if map_scale_w == 0.0 else 1.0 / (map_scale_w + power_w)


class StateContext(NamedTuple):
    """Where a state sits: the update's inputs besides the measured T ahead and area (one typed
    tuple for the compiled call; the preview MPC compares it with the state it prepared for)."""

    p_fill: int
    """Copies of ``power_w`` pushed into the power history (one per step since the last state)."""
    power_w: float
    """Power applied during the step that produced the state, p[k−1] of the plant [W]."""
    t_fill: int
    """Copies of the measured T ahead pushed into the temperature history."""
    observe: bool
    """The state follows the last one and the pool is built up: the estimator compares its area
    with the last prediction."""
    since: int
    """States since the current track's first state."""
    on_first: bool
    """The state is on the layer's first track (no turnaround behind it)."""
    to_end: int
    """States until the current track's last (−1: no turn ahead)."""
    has_turn_base: bool
    """A turn is behind the state: ``turn_base_k`` is the T ahead before it."""
    turn_base_k: float
    """T ahead in the state before the last turn [K] (meaningful with ``has_turn_base``)."""
    learned: bool
    """The learned turnaround correction applies to the prediction."""
    blind: int
    """Leading rows of the horizon inside the pool build-up, not tracked by the QP."""


_F1, _F2 = types.Array(types.float64, 1, "C"), types.Array(types.float64, 2, "C")
_I1, _B1 = types.Array(types.int64, 1, "C"), types.Array(types.boolean, 1, "C")


@structref.register
class EstimatorType(types.StructRef):
    """The numba type of :class:`Estimator`."""


@structref.register
class PredictorType(types.StructRef):
    """The numba type of :class:`Predictor`."""


@structref.register
class PlannerType(types.StructRef):
    """The numba type of :class:`Planner`."""


@structref.register
class RunType(types.StructRef):
    """The numba type of :class:`Run`."""


@structref.register
class WorkspaceType(types.StructRef):
    """The numba type of :class:`Workspace`."""


ESTIMATOR = EstimatorType([
    ("gain", types.float64), ("b0", types.float64), ("q0", types.float64), ("e0", types.float64),
    ("map_scale_w", types.float64), ("log_output", types.boolean), ("disturbance_m2", types.float64),
    ("has_prediction", types.boolean),
    ("z_base", types.float64), ("t_ahead_k", types.float64), ("correction_m2", types.float64),
    ("turn_errors", _F1), ("turn_error_seen", _B1)])
PREDICTOR = PredictorType([
    ("intercept", types.float64), ("b", _F1), ("q", _F1), ("map_scale_w", types.float64), ("cc", _F1), ("d", _F1),
    ("e", _F1),
    ("gp_input_mean", _F1), ("gp_input_scale", _F1), ("gp_prior_variance", types.float64),
    ("gp_noise_variance", types.float64), ("w0_max", types.float64), ("gp_points", _F2), ("gp_beta", _F1),
    ("gp_slope_weights", _F1), ("var_factor", _F2), ("series_weights", _F2), ("decay", _F1),
    ("log_output", types.boolean), ("n_variance", types.int64), ("steps_cap", types.float64), ("g", _F1),
    ("feature_kernel", _F2), ("feature_jac", _F2), ("has_feature", types.boolean), ("feature_gain", types.float64),
    ("feature_mean", _F1), ("remnant_kernel", _F2), ("remnant_offsets", _F1)])
PLANNER = PlannerType([
    ("set_point_m2", types.float64), ("power_scale_w", types.float64), ("move_weight", types.float64),
    ("v_lo", types.float64), ("v_hi", types.float64), ("e_lo", types.float64), ("e_hi", types.float64),
    ("z_sigma", types.float64), ("weights", _F1), ("moves", _F2)])
RUN = RunType([
    ("p_hist", _F1), ("t_hist", _F1), ("plan", _F1), ("profile", _F1), ("current", _F1), ("following", _F1),
    ("p_long", _F1), ("f_hist", _F1), ("prev_powers", _F1), ("track_feature", _F1), ("track_remnant", _F1),
    ("estimator", ESTIMATOR)])
WORKSPACE = WorkspaceType([
    ("gamma", _F2), ("hess", _F2), ("chol", _F2), ("c", _F1), ("predicted", _F1), ("z", _F1), ("std", _F1),
    ("f", _F1), ("v", _F1), ("areas", _F1), ("gp_slope", _F1), ("inv_diag", _F1), ("slopes", _F1),
    ("jac_u", _F1), ("psi", _F2), ("kern", _F2), ("bits", _I1), ("powers", _F1), ("temps", _F1),
    ("forecast", _F1), ("correction", _F1), ("w0", _F1), ("mean_moments", _F2), ("slope_moments", _F2),
    ("variance_moments", _F2), ("powers_of_w0", _F2), ("feats", _F1), ("gp_t_slope", _F1), ("rems", _F1),
    ("mapped", _F1), ("mapped_slope", _F1), ("has_step", types.boolean), ("width", types.int64)])


class Estimator(structref.StructRefProxy):
    """The disturbance observer (offset-free control): ``d̂ ← d̂ + L (x[k] − x̂[k|k−1] − d̂)`` with
    x̂[k|k−1] the last update's prediction of this state completed with the power applied; after a
    turn the one-step error is kept by state since the turn (:func:`estimate`).

    Fields: ``gain`` L; ``b0``, ``q0``, ``e0``, ``map_scale_w``, ``log_output`` (the model's terms in
    p[k] that complete the prediction, ``b0 p + q0 φ(p) + e0 T p``, :func:`map_power`);
    ``disturbance_m2`` d̂ [m²]; ``has_prediction`` (an x̂[k|k−1] is held); ``z_base`` its z without
    the p[k] terms, ``t_ahead_k`` [K] and ``correction_m2`` [m²] in it; ``turn_errors`` [m²] and
    ``turn_error_seen`` by state since the turn. Build with :func:`new_estimator`.
    """

    __slots__ = ()

    def make_step(self, area_m2: float, power_w: float, since_turn: int | None = None) -> float:
        """:func:`estimate`: d̂ [m²] after a state's area [m²] with the power applied [W]
        (``since_turn``: its states since the track's first after a turn, None on a layer's first track)."""
        after_turn = since_turn is not None
        return estimate(self, float(power_w), float(area_m2), after_turn, int(since_turn) if after_turn else -1)

    def reset(self) -> None:
        """d̂ = 0, no prediction held, no error seen after a turn."""
        reset_estimator(self)

    def forget_prediction(self) -> None:
        """Hold no x̂[k|k−1]: the next state's area is not compared."""
        forget_prediction(self)

    def hold_prediction(self, z_base: float, t_ahead_k: float, correction_m2: float) -> None:
        """Hold x̂[k+1|k] for the next state (:func:`hold_prediction`)."""
        hold_prediction(self, float(z_base), float(t_ahead_k), float(correction_m2))

    @property
    def disturbance_m2(self) -> float:
        """d̂ [m²] (settable: the estimate to start from)."""
        return _estimator_fields(self)[0]

    @disturbance_m2.setter
    def disturbance_m2(self, value: float) -> None:
        _set_disturbance(self, float(value))

    @property
    def has_prediction(self) -> bool:
        """An x̂[k|k−1] is held."""
        return _estimator_fields(self)[1]

    @property
    def prediction(self) -> tuple[float, float, float]:
        """The held x̂[k|k−1]: z without the p[k] terms, T ahead [K], learned correction [m²]."""
        return _estimator_fields(self)[2:]


class Predictor(structref.StructRefProxy):
    """The delay-aware model's constants (:mod:`gp_model.narx`): ``intercept`` c₀; ``b``, ``q``
    (powers, mapped by φ: ``map_scale_w``, :func:`map_power`), ``cc``, ``d`` (temperatures,
    squared), ``e`` (power × temperature) coefficients; the residual GP's input mean and scale, prior
    and noise variances, largest ``|W_a0|`` (``w0_max``), per training point ``gp_points`` (rows ``W_a`` and
    ``−‖W_a‖²/2``), ``gp_beta`` β_a, ``gp_slope_weights`` W_a2 β_a, ``var_factor`` σ_f L⁻¹ and ``series_weights``
    (N, 2 MOMENTS: β_a W_a0ʲ then W_a2 β_a W_a0ʲ); the T-ahead forecast's ``decay`` ρʲ;
    ``log_output``; ``n_variance`` rows with a variance; ``steps_cap`` of the steps-since-start
    input; the turnaround feature's (:mod:`gp_model.plan_feature`) coefficients ``g`` [z/K] (empty
    without it), kernel ``feature_kernel`` K[s, e] [K/W] and ``feature_jac``
    ``M[r, e] = Σ_{l ≤ r} g_l K[r − l, e]`` (∂z of the r-th state after a turn by the power e states
    before it); ``has_feature``, and the feature's part of the T-ahead forecast, ``feature_gain`` β
    and ``feature_mean`` F̄[s] [K] (:func:`gp_model.narx.adjust_forecast`); the remnant terms'
    (:class:`gp_model.plan_feature.RemnantFeature`) ``remnant_kernel`` W[s, e] [z/W], shape (n_R, E_R)
    (n_R = 0: none; also in ``feature_jac``) and ``remnant_offsets`` c_s [z]. Build with
    :func:`new_predictor`."""

    __slots__ = ()


class Planner(structref.StructRefProxy):
    """The condensed QP's constants (:class:`controller_node.preview_qp.PreviewQP`): ``set_point_m2``
    x_sp, ``power_scale_w`` P, ``move_weight`` r, the bounds ``v_lo``, ``v_hi`` of ``v`` and
    ``e_lo``, ``e_hi`` of ``e``, ``z_sigma`` (bound tightening), the row ``weights`` and the move
    penalty ``moves`` 2 r DᵀD. Build with :func:`new_planner`."""

    __slots__ = ()


class Run(structref.StructRefProxy):
    """What a run carries from one update to the next: ``p_hist`` p[k], p[k−1], … [W]; ``t_hist``
    T[k−n_T+1 .. k] [K]; ``plan`` the previous plan [W]; ``profile`` the turnaround profile [K];
    ``current`` and ``following`` the learned corrections after the current track's turn and after
    the next [m²]; ``p_long`` p[k], p[k−1], … [W] over the turnaround feature's sources; ``f_hist``
    the feature F[k−n_F+1 .. k] [K]; ``prev_powers`` the previous track's last powers, newest first
    [W], ``track_feature`` the current track's F by state since its start [K] and ``track_remnant``
    its remnant terms ``c_s + Σ_e W[s, e] p`` [z] (all three set at a turn); its ``estimator``. Build
    with :func:`new_run`."""

    __slots__ = ()


class Workspace(structref.StructRefProxy):
    """What one update computes (shapes in :class:`controller_node.preview_kernel.Kernel`),
    ``has_step``: the Hessian was positive definite, so ``v`` is the unconstrained optimum, and
    ``width``: the columns of Γ left of the diagonal that may be non-zero (n_p, or H when the
    turnaround feature of a turn in the horizon reaches back to the powers before it). Build with
    :func:`new_workspace`."""

    __slots__ = ()

    @property
    def has_step(self) -> bool:
        """The Hessian was positive definite: ``v`` is the unconstrained optimum."""
        return _has_step(self)


for _typeclass, _proxy in ((EstimatorType, Estimator), (PredictorType, Predictor), (PlannerType, Planner),
                           (RunType, Run), (WorkspaceType, Workspace)):
    structref.define_boxing(_typeclass, _proxy)


def carve(shapes: dict[str, tuple[int, ...]], dtype: type = float) -> dict[str, np.ndarray]:
    """Zeroed C-contiguous arrays of ``shapes``, views into one block, in the order given."""
    sizes = [math.prod(shape) for shape in shapes.values()]
    block = np.zeros(sum(sizes), dtype=dtype)
    ends = np.cumsum(sizes)
    return {name: block[end - size:end].reshape(shape)
            for (name, shape), size, end in zip(shapes.items(), sizes, ends, strict=True)}


@njit(cache=True)
def new_estimator(gain, b0, q0, e0, map_scale_w, log_output, turn_errors,
                  turn_error_seen):  # pragma: no cover (compiled)
    """An :class:`Estimator` with d̂ = 0 and no prediction held."""
    st = structref.new(ESTIMATOR)
    st.gain, st.b0, st.q0, st.e0, st.map_scale_w, st.log_output = gain, b0, q0, e0, map_scale_w, log_output
    st.turn_errors, st.turn_error_seen = turn_errors, turn_error_seen
    reset_estimator(st)
    return st


@njit(cache=True)
def reset_estimator(st):  # pragma: no cover (compiled)
    """d̂ = 0, no prediction held, no error seen after a turn."""
    st.disturbance_m2, st.has_prediction, st.z_base, st.t_ahead_k, st.correction_m2 = 0.0, False, 0.0, 0.0, 0.0
    st.turn_errors[:] = 0.0
    st.turn_error_seen[:] = False


@njit(cache=True)
def hold_prediction(st, z_base, t_ahead_k, correction_m2):  # pragma: no cover (compiled)
    """Keep x̂[k+1|k] for the next state: its z without the p[k+1] terms, T ahead [K] and learned
    correction [m²] in it."""
    st.has_prediction, st.z_base, st.t_ahead_k, st.correction_m2 = True, z_base, t_ahead_k, correction_m2


@njit(cache=True)
def forget_prediction(st):  # pragma: no cover (compiled)
    """Hold no x̂[k|k−1]."""
    st.has_prediction = False


@njit(cache=True)
def estimate(st, power_w, area_m2, after_turn, since):  # pragma: no cover (compiled)
    """One step of the observer (:class:`Estimator`) with the state's area [m²] and the power
    applied [W]; the error is kept in ``turn_errors[since]`` after a turn. Nothing without a held
    prediction. Returns d̂ [m²]."""
    if not st.has_prediction:
        return st.disturbance_m2
    z = st.z_base + (st.b0 + st.e0 * st.t_ahead_k) * power_w + st.q0 * map_power(power_w, st.map_scale_w)
    predicted = (math.exp(z) if st.log_output else z) + st.correction_m2
    error = area_m2 - predicted - st.disturbance_m2
    if after_turn and 0 <= since < st.turn_errors.size:
        st.turn_errors[since] = error
        st.turn_error_seen[since] = True
    st.disturbance_m2 += st.gain * error
    return st.disturbance_m2


@njit(cache=True)
def _estimator_fields(st):  # pragma: no cover (compiled)
    return st.disturbance_m2, st.has_prediction, st.z_base, st.t_ahead_k, st.correction_m2


@njit(cache=True)
def _set_disturbance(st, value):  # pragma: no cover (compiled)
    st.disturbance_m2 = value


@njit(cache=True)
def new_predictor(intercept, b, q, map_scale_w, cc, d, e, gp_input_mean, gp_input_scale, gp_prior_variance,
                  gp_noise_variance,
                  w0_max, gp_points, gp_beta, gp_slope_weights, var_factor, series_weights, decay, log_output,
                  n_variance, steps_cap, g, feature_kernel, feature_jac, has_feature, feature_gain,
                  feature_mean, remnant_kernel, remnant_offsets):  # pragma: no cover (compiled)
    """A :class:`Predictor` of these constants."""
    st = structref.new(PREDICTOR)
    st.intercept, st.b, st.q, st.map_scale_w, st.cc, st.d, st.e = intercept, b, q, map_scale_w, cc, d, e
    st.gp_input_mean, st.gp_input_scale, st.gp_prior_variance = gp_input_mean, gp_input_scale, gp_prior_variance
    st.gp_noise_variance, st.w0_max, st.gp_points, st.gp_beta = gp_noise_variance, w0_max, gp_points, gp_beta
    st.gp_slope_weights, st.var_factor, st.series_weights, st.decay = gp_slope_weights, var_factor, series_weights, \
        decay
    st.log_output, st.n_variance, st.steps_cap = log_output, n_variance, steps_cap
    st.g, st.feature_kernel, st.feature_jac = g, feature_kernel, feature_jac
    st.has_feature, st.feature_gain, st.feature_mean = has_feature, feature_gain, feature_mean
    st.remnant_kernel, st.remnant_offsets = remnant_kernel, remnant_offsets
    return st


@njit(cache=True)
def new_planner(set_point_m2, power_scale_w, move_weight, v_lo, v_hi, e_lo, e_hi, z_sigma, weights,
                moves):  # pragma: no cover (compiled)
    """A :class:`Planner` of these constants."""
    st = structref.new(PLANNER)
    st.set_point_m2, st.power_scale_w, st.move_weight = set_point_m2, power_scale_w, move_weight
    st.v_lo, st.v_hi, st.e_lo, st.e_hi, st.z_sigma = v_lo, v_hi, e_lo, e_hi, z_sigma
    st.weights, st.moves = weights, moves
    return st


@njit(cache=True)
def new_run(p_hist, t_hist, plan, profile, current, following, p_long, f_hist, prev_powers, track_feature,
            track_remnant, estimator):  # pragma: no cover (compiled)
    """A :class:`Run` of these arrays and estimator."""
    st = structref.new(RUN)
    st.p_hist, st.t_hist, st.plan, st.profile, st.current, st.following = p_hist, t_hist, plan, profile, current, \
        following
    st.p_long, st.f_hist, st.prev_powers, st.track_feature = p_long, f_hist, prev_powers, track_feature
    st.track_remnant = track_remnant
    st.estimator = estimator
    return st


@njit(cache=True)
def new_workspace(gamma, hess, chol, c, predicted, z, std, f, v, areas, gp_slope, inv_diag, slopes, jac_u, psi, kern,
                  bits, powers, temps, forecast, correction, w0, mean_moments, slope_moments, variance_moments,
                  powers_of_w0, feats, gp_t_slope, rems, mapped, mapped_slope):  # pragma: no cover (compiled)
    """A :class:`Workspace` of these arrays, with no step."""
    st = structref.new(WORKSPACE)
    st.gamma, st.hess, st.chol, st.c, st.predicted, st.z, st.std = gamma, hess, chol, c, predicted, z, std
    st.f, st.v, st.areas, st.gp_slope, st.inv_diag, st.slopes, st.jac_u = f, v, areas, gp_slope, inv_diag, slopes, \
        jac_u
    st.psi, st.kern, st.bits, st.powers, st.temps, st.forecast = psi, kern, bits, powers, temps, forecast
    st.correction, st.w0, st.mean_moments, st.slope_moments = correction, w0, mean_moments, slope_moments
    st.variance_moments, st.powers_of_w0, st.feats, st.has_step, st.width = variance_moments, powers_of_w0, feats, \
        False, 0
    st.gp_t_slope, st.rems, st.mapped, st.mapped_slope = gp_t_slope, rems, mapped, mapped_slope
    return st


@njit(cache=True)
def _has_step(st):  # pragma: no cover (compiled)
    return st.has_step

