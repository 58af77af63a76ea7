"""The preview MPC's hot path, compiled: estimate, predict, plan, apply (:func:`control_step`).

:class:`controller_node.preview.PreviewMPC` makes one call per update, :meth:`Kernel.update`
(compiled :func:`update_into`) over the stages' structures of :mod:`controller_node.preview_stages`
and the state's :class:`~controller_node.preview_stages.StateContext`:

1. **Estimate**: the :class:`~controller_node.preview_stages.Estimator` (disturbance observer)
   compares the state's area with its held x̂[k|k−1]; the state's power and T ahead enter the
   histories.
2. **Predict** (:class:`~controller_node.preview_stages.Predictor`): T ahead over the horizon
   (:func:`gp_model.narx.forecast_into`), the learned turnaround correction
   (:func:`correction_into`), and, for the planned powers ū (the previous plan, shifted), for
   m = 1..H (model of :mod:`gp_model.narx`, rows indexed ``i = m − 1``)::

    z_m = c₀ + Σ_i (b_i p_i + q_i p_i²) + Σ_j c_j T_j + Σ_{j<n_Tq} d_j T_j² + Σ_{i<n_x} e_i p_i T_i
          + Σ_{l<n_F} g_l F[k+m−l] + R_m + r(ψ_{k+m−1})
    x̂_m = exp(z_m) (log output) + d̂ + κ-learned correction_m
    ∂x̂_m/∂ū_n = x'(z_m) (b_l + 2 q_l ū_n + e_l T[k+m−1−l] + ∂r/∂ψ₂ / n_p),  l = m − 1 − n ∈ [0, n_p)
              + x'(z_m) M[m − 1 − e_k, e_k − 1 − n]   (a turn ahead, after state k + e_k; n < e_k)

   with ``p_i = p[k+m−i]``, ``T_j = T[k+m−1−j]`` (the forecast beyond k), the SE-ARD residual GP
   ``r(ψ) = Σ_a k(ψ, ψ_a) β_a`` at ψ = (T ahead, log1p(min(s, 100)), mean of the p_i), its slope
   in the mean power and its latent variance ``σ² − ‖L⁻¹ k‖²`` for the first ``n_variance`` rows.
   ``F`` is the turnaround feature (:mod:`gp_model.plan_feature`): on the current track the value
   its previous track's powers give (set at the turn), after the turn ahead ``Σ_e K[s, e] p`` of
   the current track's last powers, applied or planned, so a planned power before the turn moves
   the prediction after it through ``M = Σ_l g_l K[· − l, ·]`` (Γ is then dense in those rows).
   ``R_m`` are the remnant terms (:class:`gp_model.plan_feature.RemnantFeature`) of the state k+m, s
   states after a turn: ``c_s + Σ_e W[s, e] p[t₀ − 1 − e]``, on the current track set at the turn, after
   the turn ahead of the current track's last powers, applied or planned; ``W`` enters ``M``.
3. **Plan** (:class:`~controller_node.preview_stages.Planner`): the condensed QP of
   :mod:`controller_node.preview_qp` in ``v = u / P``, ``e = Γ v + c``::

    Γ = ∂x̂/∂ū · P / x_sp,   c = (x̂ − ∂x̂/∂ū ū − x_sp) / x_sp
    Hessian = 2 Γᵀ W Γ + 2 r DᵀD,   gradient f = 2 Γᵀ W c − 2 r (p[k] / P) e₁

   and its unconstrained optimum ``v* = −Hessian⁻¹ f`` by Cholesky.
4. **Apply**: the estimator holds x̂[k+1|k] for the next state; when ``v*`` is inside the power
   bounds and ``e = Γ v* + c`` (± the bound tightening) inside the area bounds, it is the QP's
   solution (the fast path, as :meth:`controller_node.preview_qp.PreviewQP.finish` decides) and
   becomes the plan; else the caller hands Γ, c to :meth:`~controller_node.preview_qp.PreviewQP.finish`.

The real-time iteration runs the same sequence in two phases (:class:`controller_node.preview.PreviewMPC`):
:func:`prepare_into` runs it for the state expected next into a spare workspace before it
arrives; :func:`feedback_into` runs it again when the state arrives, on the prepared Γ and
Cholesky factor, the GP's kernel sums moved to the measured T ahead by a series.

Why one compiled call over structures allocated once: between FE steps or plant frames the
controller's caches are cold, and each call from Python into compiled code or numpy then costs
microseconds of dispatch, each argument more, each fresh allocation and each small BLAS call a
cache miss (``docs/controller.md``, "Speed"). So the stages' structures are passed as one pointer
each, their arrays are views into a few blocks allocated once, the GP kernel's exponential is a
vectorisable loop (:func:`exp_into`, within 1 ulp of numpy's), and the Hessian and its Cholesky
factor are formed by loops over their band (n_p powers per row of Γ). The numpy formulation stays
the reference: ``tests/test_preview_kernel.py`` checks this kernel against the model's own
prediction (:meth:`gp_model.narx.NarxGPModel.predict_run`), its Jacobian against finite
differences, and the QP terms against :meth:`PreviewQP.hessian` / :meth:`PreviewQP.gradient`;
``tests/test_preview_replay.py`` checks the commands on recorded states.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gp_model.compiled import BoundOnFirstCall
from gp_model.narx import LOG_POWER_SCALE_W, STEPS_SINCE_START_CAP, adjust_forecast, forecast_into

from .preview_stages import (
    MOMENTS,
    StateContext,
    Workspace,
    carve,
    estimate,
    hold_prediction,
    map_power,
    map_power_slope,
    new_estimator,
    new_planner,
    new_predictor,
    new_run,
    new_workspace,
)

__all__ = ["Kernel", "control_step", "correction_into", "exp_into", "feedback_into", "prepare_into", "push_history",
           "update_into"]

_REORDER = {"reassoc", "contract"}
"""Floating-point licence of the compiled passes: sums may be reordered (vectorised) and multiply-adds
fused; NaN and infinity keep their meaning (the prediction's finiteness check relies on it)."""


@njit(cache=True, nogil=True)
def push_history(p_hist, p_fill, power_w, t_hist, t_fill, t_ahead_k):  # pragma: no cover (compiled)
    """Shift ``p_fill`` copies of ``power_w`` [W] into the front of ``p_hist`` (newest first) and
    ``t_fill`` copies of ``t_ahead_k`` [K] into the end of ``t_hist`` (oldest first), in place."""
    for i in range(p_hist.size - 1, p_fill - 1, -1):
        p_hist[i] = p_hist[i - p_fill]
    for i in range(min(p_fill, p_hist.size)):
        p_hist[i] = power_w
    n = t_hist.size
    for i in range(n - t_fill):
        t_hist[i] = t_hist[i + t_fill]
    for i in range(max(n - t_fill, 0), n):
        t_hist[i] = t_ahead_k


@njit(cache=True, nogil=True)
def correction_into(since, on_first, to_end, current, following, out):  # pragma: no cover (compiled)
    """The learned turnaround correction of the states k+1..k+H into ``out``, shape (H,) [m²].

    ``since``: states since the current track's first state; ``to_end``: states until its last
    (−1: no turn ahead). A state of the current track gets ``current[s]`` with s its states since
    the track's start (none on the layer's first track), a state after the next turn
    ``following[s]``; 0 beyond the correction's length."""
    n = current.size
    for i in range(out.size):
        m = i + 1
        if to_end < 0 or m <= to_end:
            s, post, source = since + m, not on_first, current
        else:
            s, post, source = m - to_end - 1, True, following
        out[i] = source[min(max(s, 0), n - 1)] if post and s < n else 0.0



_EXP_MAX = 709.782712893384
"""Largest argument whose exponential is finite."""
_EXP_MIN = -708.0
"""Smallest argument whose exponential :func:`exp_into` evaluates (below it: 0, an error < 3.4e-308)."""
_LOG2E, _LN2_HI, _LN2_LO = 1.4426950408889634, 6.93147180369123816490e-01, 1.90821492927058770002e-10


@njit(cache=True, nogil=True, fastmath=_REORDER)
def exp_into(a, bits):  # pragma: no cover (compiled)
    """``a ← exp(a)`` elementwise, in place, as loops the compiler vectorises (``math.exp`` in a
    compiled loop is one scalar call per element, which does not vectorise).

    ``exp(x) = 2ⁿ e^r`` with ``n = round(x / ln 2)``, ``r = x − n ln 2`` (Cody–Waite, ``|r| <= ln2/2``)
    and ``e^r`` by its Taylor polynomial to degree 13 (truncation < 2e-16 relative); ``2ⁿ`` is
    built from its exponent bits in ``bits``, int64 of ``a``'s size. Within 1 ulp of ``numpy.exp``
    (``tests/test_preview_kernel.py``); ``+inf`` above 709.78, 0 below −708 (where the true value
    is below 3.4e-308), NaN stays NaN.
    """
    flat, exponent = a.reshape(-1), bits.reshape(-1)
    for i in range(flat.size):
        x0 = flat[i]
        x = x0 if x0 >= _EXP_MIN else _EXP_MIN      # NaN too: its n must stay an integer
        x = x if x <= _EXP_MAX else _EXP_MAX
        n = math.floor(x * _LOG2E + 0.5)
        r = (x - n * _LN2_HI) - n * _LN2_LO
        e_r = 1.0 + r * (1.0 + r * (1 / 2 + r * (1 / 6 + r * (1 / 24 + r * (1 / 120 + r * (
            1 / 720 + r * (1 / 5040 + r * (1 / 40320 + r * (1 / 362880 + r * (1 / 3628800 + r * (
                1 / 39916800 + r * (1 / 479001600 + r / 6227020800))))))))))))
        e_r = math.inf if x0 > _EXP_MAX else e_r
        e_r = 0.0 if x0 < _EXP_MIN else e_r
        flat[i] = e_r if x0 == x0 else x0
        exponent[i] = (np.int64(n) + 1023) << 52
    two_n = exponent.view(np.float64)
    for i in range(flat.size):
        flat[i] *= two_n[i]


SERIES_RADIUS = 0.5
"""Largest ``|ε W_a0|`` of the feedback phase's series: their truncation is then below
``0.5¹²/12! e^0.5`` ≈ 5e-13 of ``Σ_a |k_a β_a|`` (the mean) and ``1/12! e`` ≈ 6e-9 of
``Σ_ab |k_a A_ab k_b|`` (the variance's quadratic form, whose variable ``ε (W_a0 + W_b0)`` reaches
twice the radius); beyond it the state gets the full update."""


# ---------------------------------------------------------------------------------------- the sequence
@njit(cache=True, nogil=True)
def control_step(predictor, planner, run, ws, context, t_ahead_k, area_m2, observe,
                 relinearise):  # pragma: no cover (compiled)
    """One state through the stages, in place: **estimate** (the disturbance observer with the
    state's area, :func:`~controller_node.preview_stages.estimate`), push the state into the
    histories, **predict** x̂ over the horizon at the planned powers ū (and, with ``relinearise``,
    its Jacobian), **plan** (the QP's terms and its unconstrained step), **apply** (hold x̂[k+1|k]
    for the next estimate and, when the step solves the QP, make it the plan). Returns the status
    of :meth:`Kernel.update`, or −1 without ``relinearise`` when the measured T ahead is beyond the
    prepared series (nothing changed).

    ``relinearise`` False is the feedback phase of the real-time iteration (:func:`feedback_into`):
    the GP's kernel sums come from the moments :func:`prepare_into` left in ``ws``, and the
    Jacobian, the Hessian and its factor and the learned correction stay the prepared ones.
    ``observe``: run the estimator with ``area_m2`` [m²]. Callers pass both flags as ``np.bool_``
    (a run-time boolean, not a literal ``True``), so that it compiles once, not once per value."""
    _forecast(predictor, run, context, t_ahead_k, ws)   # the plan position (and with the feature, the plan)
    if not relinearise and not _within_series(predictor, ws, t_ahead_k):
        return -1
    estimator = run.estimator
    if observe:                                                                      # estimate
        estimate(estimator, context.power_w, area_m2, context.has_turn_base, context.since)
    estimator.has_prediction = False                # no x̂[k+1|k] until this update gives one
    push_history(run.p_hist, context.p_fill, context.power_w, run.t_hist, context.t_fill, t_ahead_k)
    if predictor.has_feature:
        _push_feature(predictor, run, context)
    finite = _predict(predictor, planner, run, ws, context, estimator.disturbance_m2, relinearise)   # predict
    status = _plan(planner, ws, run.p_hist[0], context.blind, predictor.b.size, relinearise,        # plan
                   0 if finite else 2)
    _apply(run, ws, planner, predictor.b.size, status)                                              # apply
    return status


@njit(cache=True, nogil=True)
def update_into(predictor, planner, run, ws, context, t_ahead_k, area_m2):  # pragma: no cover (compiled)
    """The full update of a state (:func:`control_step`) at its measured T ahead [K] and area [m²];
    the status of :meth:`Kernel.update`."""
    return control_step(predictor, planner, run, ws, context, t_ahead_k, area_m2, context.observe, np.bool_(True))


@njit(cache=True, nogil=True)
def feedback_into(predictor, planner, run, ws, context, t_ahead_k, area_m2):  # pragma: no cover (compiled)
    """Feedback phase of a real-time iteration: the update of the state that :func:`prepare_into`
    prepared ``ws`` for (same ``context``), with its measured T ahead ``t_ahead_k`` [K] and area
    ``area_m2`` [m²]. The prediction x̂ at ū is the model's own at the measured T ahead, as in
    :func:`update_into`, except that the GP's kernel sums come from the prepared moments: with ``ε``
    the row's shift of the scaled T input, ``k_a(w + ε e₀) = k_a(w) exp(ε W_a0 − w₀ ε − ε²/2)``, so
    ``Σ_a k_a β_a`` moves to ``exp(−w₀ ε − ε²/2) Σ_j εʲ/j! Σ_a k_a β_a W_a0ʲ`` (the mean-power
    moment likewise, and the variance's quadratic form with ``exp(−2 w₀ ε − ε²)`` and
    ``(W_a0 + W_b0)ʲ``); with bound tightening the variance rows are computed from their kernel
    values instead (:func:`_series_variance`). The Jacobian Γ, the Hessian and its factor stay those
    of the forecast T ahead (the real-time iteration's linearisation); ``c``, the gradient, the step
    and the bound checks are those of the new prediction. Returns :func:`update_into`'s status, or
    −1, changing nothing in ``run``, when a shift is outside :data:`SERIES_RADIUS` (the caller then
    runs the full update)."""
    return control_step(predictor, planner, run, ws, context, t_ahead_k, area_m2, context.observe, np.bool_(False))


@njit(cache=True, nogil=True)
def prepare_into(predictor, planner, run, scratch, ws, context, t_ahead_k):  # pragma: no cover (compiled)
    """Preparation phase of a real-time iteration: :func:`update_into` for the state expected next
    (``context``, T ahead ``t_ahead_k`` [K] forecast; the area is not known yet, so the estimator
    does not run) on a copy of ``run`` in ``scratch`` (``run`` is not changed), into ``ws``; then,
    per row m, the moments of the GP's kernel sums in the scaled T input,
    ``Σ_a k_ma β_a W_a0ʲ`` and ``Σ_a k_ma β_a W_a2 W_a0ʲ``, j < :data:`MOMENTS`, the row's scaled
    T input w_m0 and, for the variance rows when the feedback takes the variance from the series
    (:func:`_series_variance`), the moments of its quadratic form ``Σ_ab k_a A_ab k_b (W_a0 + W_b0)ʲ``,
    ``A = (σ_f L⁻¹)ᵀ σ_f L⁻¹`` (for :func:`feedback_into`). True if the prepared step exists
    (finite prediction, positive definite Hessian)."""
    _copy_run(run, scratch)
    status = control_step(predictor, planner, scratch, ws, context, t_ahead_k, 0.0, np.bool_(False), np.bool_(True))
    kern, psi, w0 = ws.kern, ws.psi, ws.w0
    mean_moments, slope_moments, variance_moments = ws.mean_moments, ws.slope_moments, ws.variance_moments
    powers_of_w0, gp_points, var_factor = ws.powers_of_w0, predictor.gp_points, predictor.var_factor
    mean0, scale0, n_variance = predictor.gp_input_mean[0], predictor.gp_input_scale[0], predictor.n_variance
    sums = np.dot(kern, predictor.series_weights)   # (H, 2 MOMENTS): Σ_a k_ma β_a W_a0ʲ, Σ_a k_ma β_a W_a2 W_a0ʲ
    for row in range(kern.shape[0]):
        for j in range(MOMENTS):
            mean_moments[row, j] = sums[row, j]
            slope_moments[row, j] = sums[row, MOMENTS + j]
        w0[row] = (psi[row, 0] - mean0) * scale0
    for row in range(0 if _series_variance(planner) else n_variance, n_variance):
        for a in range(kern.shape[1]):              # k ∘ W_0ⁱ, i < MOMENTS, as columns
            weighted = kern[row, a]
            for i in range(MOMENTS):
                powers_of_w0[a, i] = weighted
                weighted *= gp_points[0, a]
        projected = np.dot(var_factor, powers_of_w0)   # y_i = σ_f L⁻¹ (k ∘ W_0ⁱ)
        gram = np.dot(projected.T, projected)
        for j in range(MOMENTS):                    # Q_j = Σ_i C(j, i) y_iᵀ y_{j−i} = kᵀA(W_a0 + W_b0)ʲk
            binomial, total = 1.0, 0.0
            for i in range(j + 1):
                total += binomial * gram[i, j - i]
                binomial = binomial * (j - i) / (i + 1)
            variance_moments[row, j] = total
    return status != 2 and ws.has_step


@njit(cache=True, nogil=True)
def _copy(target, source):  # pragma: no cover (compiled)
    """``target[:] = source`` for two 1-D arrays of one length, as a loop (numpy's slice assignment
    compiles a formatted shape error, seconds of compilation in each process that builds the kernel)."""
    for i in range(source.size):
        target[i] = source[i]


@njit(cache=True, nogil=True)
def _copy_run(run, scratch):  # pragma: no cover (compiled)
    """What an update changes in a run (histories, plan, the estimator's d̂ and held prediction),
    copied into ``scratch`` (which shares the run's profile and corrections)."""
    _copy(scratch.p_hist, run.p_hist)
    _copy(scratch.t_hist, run.t_hist)
    _copy(scratch.p_long, run.p_long)
    _copy(scratch.f_hist, run.f_hist)
    _copy(scratch.plan, run.plan)
    source, target = run.estimator, scratch.estimator
    target.disturbance_m2, target.has_prediction = source.disturbance_m2, source.has_prediction
    target.z_base, target.t_ahead_k, target.correction_m2 = source.z_base, source.t_ahead_k, source.correction_m2


@njit(cache=True, nogil=True)
def _series_variance(planner):  # pragma: no cover (compiled)
    """Whether the feedback takes the variance from the series (no bound tightening, zσ = 0: the
    variance is the diagnostics' only), not from kernel values at the measured T ahead."""
    return planner.z_sigma == 0.0


# ---------------------------------------------------------------------------------------- predict
@njit(cache=True, nogil=True)
def _push_feature(predictor, run, context):  # pragma: no cover (compiled)
    """Push ``p_fill`` copies of the state's power into ``p_long`` (newest first) and ``t_fill``
    copies of its turnaround feature F[k] (the current track's, 0 on a layer's first track and
    beyond the kernel's targets) into ``f_hist`` (oldest first), as :func:`push_history`."""
    since, n_targets = context.since, predictor.feature_kernel.shape[0]
    value = run.track_feature[since] if not context.on_first and 0 <= since < n_targets else 0.0
    push_history(run.p_long, context.p_fill, context.power_w, run.f_hist, context.t_fill, value)


@njit(cache=True, nogil=True)
def _forecast(predictor, run, context, t_ahead_k, ws):  # pragma: no cover (compiled)
    """T ahead over the horizon into ``ws.forecast`` (:func:`gp_model.narx.forecast_into`); with the
    turnaround feature, F[k+1..k+H] into ``ws.feats`` (:func:`_future_sums`, as the remnant terms into
    ``ws.rems``) and its part of the forecast (:func:`gp_model.narx.adjust_forecast`)."""
    out = ws.forecast
    forecast_into(t_ahead_k, context.since, context.on_first, context.to_end, run.profile, context.has_turn_base,
                  context.turn_base_k, predictor.decay, out)
    _future_sums(predictor.remnant_kernel, predictor.remnant_offsets, run.track_remnant, run, context, ws.rems)
    if not predictor.has_feature:
        return
    first = max(predictor.g.size, 1) - 1
    _future_sums(predictor.feature_kernel, predictor.remnant_offsets[:0], run.track_feature, run, context,
                 ws.feats[first:])
    since, n_targets = context.since, predictor.feature_kernel.shape[0]
    f_now = run.track_feature[since] if not context.on_first and 0 <= since < n_targets else 0.0
    adjust_forecast(out, ws.feats[first:], f_now, predictor.feature_mean, predictor.feature_gain, since,
                    context.on_first, context.to_end, predictor.decay)


@njit(cache=True, nogil=True)
def _within_series(predictor, ws, t_ahead_k):  # pragma: no cover (compiled)
    """Every row's shift of the scaled T input from the prepared one (the measured T ahead, then
    the forecast in ``ws``) is inside :data:`SERIES_RADIUS`."""
    forecast, w0 = ws.forecast, ws.w0
    mean0, scale0, w_max = predictor.gp_input_mean[0], predictor.gp_input_scale[0], predictor.w0_max
    for row in range(w0.size):
        t_row = t_ahead_k if row == 0 else forecast[row - 1]
        if not abs(((t_row - mean0) * scale0 - w0[row]) * w_max) <= SERIES_RADIUS:
            return False
    return True


@njit(cache=True, nogil=True)
def _predict(predictor, planner, run, ws, context, disturbance, relinearise):  # pragma: no cover (compiled)
    """x̂ at ū into ``ws`` (the learned correction laid out, the regressors, the GP's kernel values,
    the prediction) and, with ``relinearise``, its Jacobian; without, the kernel values only of the
    variance rows that need them and the prepared correction. True if every x̂ is finite."""
    kern, bits, correction = ws.kern, ws.bits, ws.correction
    if not relinearise:
        kern_rows = 0 if _series_variance(planner) else predictor.n_variance
        _regressors(predictor, run, ws, context, kern_rows)
        exp_into(kern[:kern_rows], bits[:kern_rows * kern.shape[1]])
        return _prediction(predictor, ws, disturbance, kern_rows)
    current = run.current
    if context.learned and current.size:
        correction_into(context.since, context.on_first, context.to_end, current, run.following, correction)
    else:
        correction[:] = 0.0
    _regressors(predictor, run, ws, context, kern.shape[0])
    exp_into(kern, bits)                            # whole arrays: their contiguous type vectorises
    finite = _prediction(predictor, ws, disturbance, kern.shape[0])
    _jacobian(predictor, planner, ws, context.to_end)
    return finite


@njit(cache=True, nogil=True)
def _regressors(predictor, run, ws, context, n_rows):  # pragma: no cover (compiled)
    """The lagged powers, their φ and the temperatures of the rows (into ``powers``, ``mapped``, ``temps``),
    their GP inputs ψ
    (into ``psi``) and, for the first ``n_rows`` rows, the SE kernel's exponents
    ``w·W_a − ‖W_a‖²/2 − ‖w‖²/2`` (into ``kern``, shape (H, N), ``w`` the scaled input)."""
    p_hist, t_hist, forecast, plan = run.p_hist, run.t_hist, ws.forecast, run.plan
    psi, exponents, powers, temps = ws.psi, ws.kern, ws.powers, ws.temps
    gp_points, mean, scale, s_cap = predictor.gp_points, predictor.gp_input_mean, predictor.gp_input_scale, \
        predictor.steps_cap
    since, to_end = context.since, context.to_end
    h, n_p, n_t, n_gp = plan.size, p_hist.size, t_hist.size, gp_points.shape[1]
    for i in range(n_p):                            # p[k−n_p+1 .. k], ū
        powers[i] = p_hist[n_p - 1 - i]
    for i in range(h - 1):
        powers[n_p + i] = plan[i + 1]
    powers[n_p + h - 1] = plan[h - 1]
    mapped, map_scale_w = ws.mapped, predictor.map_scale_w
    for i in range(n_p + h):                        # φ(p) of every power the rows read
        mapped[i] = map_power(powers[i], map_scale_w)
    for i in range(n_t):                            # T[k−n_T+1 .. k], T̂[k+1 .. k+H−1]
        temps[i] = t_hist[i]
    for i in range(h - 1):
        temps[n_t + i] = forecast[i]
    mean_power = 0.0
    for i in range(n_p):
        mean_power += powers[n_p - 1 - i]
    for row in range(h):
        last_p, last_t = n_p + row, n_t - 1 + row   # index of p[k+m] and of T[k+m−1]
        mean_power += powers[last_p] - powers[last_p - n_p]
        s = since + row if to_end < 0 or row <= to_end else row - to_end - 1
        psi[row, 0], psi[row, 1], psi[row, 2] = temps[last_t], math.log1p(min(s, s_cap)), mean_power / n_p
        if row >= n_rows:
            continue
        w0 = (psi[row, 0] - mean[0]) * scale[0]
        w1 = (psi[row, 1] - mean[1]) * scale[1]
        w2 = (psi[row, 2] - mean[2]) * scale[2]
        half_w = 0.5 * (w0 * w0 + w1 * w1 + w2 * w2)
        for a in range(n_gp):
            exponents[row, a] = w0 * gp_points[0, a] + w1 * gp_points[1, a] + w2 * gp_points[2, a] + gp_points[3, a] \
                - half_w
    feats, f_hist = ws.feats, run.f_hist
    for q in range(predictor.g.size - 1):           # F[k−n_F+2 .. k], pushed (F[k+1..] by _forecast)
        feats[q] = f_hist[q + 1]


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _future_sums(kernel, offsets, track_values, run, context, out):  # pragma: no cover (compiled)
    """A plan-driven input of the states k+1 .. k+H into ``out``: the turnaround feature F [K]
    (``offsets`` empty) or the remnant terms R [z] (``offsets`` c_s). Per row the current track's value
    (``track_values``) or, after the turn ahead, ``offsets[s] + Σ_e kernel[s, e] p`` over the current
    track's last powers (the plan ū for the states after k, the state's power and ``p_long`` up to k:
    read before the state's power is pushed); 0 beyond the kernel's states."""
    plan, p_long = run.plan, run.p_long
    h, p_fill, power_w = plan.size, context.p_fill, context.power_w
    n_states, n_sources = kernel.shape
    since, to_end, on_first = context.since, context.to_end, context.on_first
    for i in range(h):
        m = i + 1
        value = 0.0
        if to_end < 0 or m <= to_end:
            s = since + m
            if not on_first and s < n_states:
                value = track_values[s]
        elif m - to_end - 1 < n_states:
            s = m - to_end - 1
            if offsets.size:
                value = offsets[s]
            for e in range(min(to_end, n_sources)):     # planned: p[k + e_k − e] = ū[e_k − 1 − e] = plan[e_k − e]
                value += kernel[s, e] * plan[to_end - e]
            for e in range(to_end, n_sources):          # applied: p[k + e_k − e], the state's p_fill first
                back = e - to_end
                value += kernel[s, e] * (power_w if back < p_fill else p_long[back - p_fill])
        out[i] = value


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _prediction(predictor, ws, disturbance, gp_rows):  # pragma: no cover (compiled)
    """x̂ at ū (into ``ws``: z, x̂, std, the GP's mean-power slope and ``x'(z)``); the GP's kernel
    sums and the variance (of the first ``n_variance`` rows) from ``kern`` for the first ``gp_rows``
    rows, from the prepared moments beyond (:func:`feedback_into`). True if every x̂ is finite."""
    b, q, cc, d, e, g, feats = predictor.b, predictor.q, predictor.cc, predictor.d, predictor.e, predictor.g, ws.feats
    n_p, n_t, n_tq, n_x, n_f = b.size, cc.size, d.size, e.size, g.size
    powers, temps, kern, psi, correction, rems = ws.powers, ws.temps, ws.kern, ws.psi, ws.correction, ws.rems
    mapped = ws.mapped
    h = powers.size - n_p
    n_gp = kern.shape[1]
    beta, moment_weights, var_f = predictor.gp_beta, predictor.gp_slope_weights, predictor.var_factor
    mean0, scale0, mean2, scale2 = predictor.gp_input_mean[0], predictor.gp_input_scale[0], \
        predictor.gp_input_mean[2], predictor.gp_input_scale[2]
    prior_variance, noise_variance = predictor.gp_prior_variance, predictor.gp_noise_variance
    n_variance, log_output, intercept = predictor.n_variance, predictor.log_output, predictor.intercept
    has_feature, gp_points0 = predictor.has_feature, predictor.gp_points[0]
    w0s, mean_moments, slope_moments, variance_moments = ws.w0, ws.mean_moments, ws.slope_moments, \
        ws.variance_moments
    predicted, z, std, gp_slope, slopes = ws.predicted, ws.z, ws.std, ws.gp_slope, ws.slopes
    std[:] = 0.0
    for row in range(n_variance):                   # σ² − ‖σ_f L⁻¹ k‖² of the first rows
        quad = 0.0
        if row < gp_rows:
            for a in range(n_gp):
                projected = 0.0
                for b2 in range(a + 1):
                    projected += var_f[a, b2] * kern[row, b2]
                quad += projected * projected
        else:                                       # the prepared quadratic form, moved by ε
            w0 = w0s[row]
            eps = (psi[row, 0] - mean0) * scale0 - w0
            power = math.exp(-2.0 * w0 * eps - eps * eps)
            for j in range(MOMENTS):
                quad += variance_moments[row, j] * power
                power *= eps / (j + 1)
        std[row] = max(prior_variance - quad, 0.0) + noise_variance
    for row in range(h):
        last_p, last_t = n_p + row, n_t - 1 + row   # index of p[k+m] and of T[k+m−1]
        gp_mean, gp_moment = 0.0, 0.0               # r(ψ_m) and Σ_a k_a W_a2 β_a (its mean-power slope)
        if row < gp_rows:
            for a in range(n_gp):
                gp_mean += kern[row, a] * beta[a]
                gp_moment += kern[row, a] * moment_weights[a]
            if has_feature:                         # ∂r/∂ψ₀ (T ahead): Σ_a k_a β_a W_a0, less w₀ r
                t_moment = 0.0
                for a in range(n_gp):
                    t_moment += kern[row, a] * beta[a] * gp_points0[a]
                ws.gp_t_slope[row] = scale0 * (t_moment - (psi[row, 0] - mean0) * scale0 * gp_mean)
        else:                                       # the prepared sums, moved by ε in the scaled T input
            w0 = w0s[row]
            eps = (psi[row, 0] - mean0) * scale0 - w0
            power = math.exp(-w0 * eps - 0.5 * eps * eps)
            for j in range(MOMENTS):
                gp_mean += mean_moments[row, j] * power
                gp_moment += slope_moments[row, j] * power
                power *= eps / (j + 1)
        w2 = (psi[row, 2] - mean2) * scale2
        gp_slope[row] = scale2 * (gp_moment - w2 * gp_mean) / n_p    # ∂r/∂ū_n through the mean power
        zz = intercept + gp_mean + rems[row]
        for i in range(n_p):
            zz += b[i] * powers[last_p - i] + q[i] * mapped[last_p - i]
        for j in range(n_t):
            t = temps[last_t - j]
            zz += cc[j] * t
            if j < n_tq:
                zz += d[j] * t * t
        for i in range(n_x):
            zz += e[i] * powers[last_p - i] * temps[last_t - i]
        for i in range(n_f):
            zz += g[i] * feats[n_f - 1 + row - i]
        z[row] = zz
    finite = True
    for row in range(h):
        x = math.exp(z[row]) if log_output else z[row]
        slope = x if log_output else 1.0
        slopes[row] = slope
        std[row] = slope * math.sqrt(std[row]) if row < n_variance else 0.0
        predicted[row] = x + disturbance + correction[row]
        finite = finite and math.isfinite(predicted[row])
    return finite


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _jacobian(predictor, planner, ws, to_end):  # pragma: no cover (compiled)
    """Γ = ∂x̂/∂ū · P / x_sp (banded: n_p powers per row, and with the turnaround feature the rows after
    the turn ahead, ``to_end`` states after k, in the powers before it) and ``jac_u`` = (∂x̂/∂ū) ū, by
    row; ``ws.width`` the columns left of the diagonal that may be non-zero."""
    b, q, e = predictor.b, predictor.q, predictor.e
    n_p, n_x, n_t = b.size, e.size, predictor.cc.size
    powers, temps, gp_slope, slopes, jac_u, gamma = ws.powers, ws.temps, ws.gp_slope, ws.slopes, ws.jac_u, ws.gamma
    ratio = planner.power_scale_w / planner.set_point_m2
    h = powers.size - n_p
    gamma[:] = 0.0
    u, mapped_slope, map_scale_w = powers[n_p:], ws.mapped_slope, predictor.map_scale_w
    for col in range(h):                            # φ'(ū)
        mapped_slope[col] = map_power_slope(u[col], map_scale_w)
    for row in range(h):
        slope = slopes[row]
        du = 0.0
        for col in range(max(0, row + 1 - n_p), row + 1):
            lag = row - col
            dz = b[lag] + q[lag] * mapped_slope[col] + gp_slope[row]
            if lag < n_x:
                dz += e[lag] * temps[n_t - 1 + row - min(lag, n_t - 1)]
            jac = slope * dz
            du += jac * u[col]
            gamma[row, col] = jac * ratio
        jac_u[row] = du
    feature_jac = predictor.feature_jac
    n_sources = feature_jac.shape[1]
    ws.width = n_p
    has_remnant = predictor.remnant_kernel.shape[0] > 0
    if (predictor.has_feature or has_remnant) and 1 <= to_end < h:   # F and R after the turn by the planned
        ws.width = h                                  # powers before it: through T̂ (β ∂F), the lagged features
    if predictor.has_feature and 1 <= to_end < h:    # and the remnant terms (M)
        _feature_jacobian(predictor, ratio, ws, to_end)
    if (predictor.g.size or has_remnant) and 1 <= to_end < h:
        for row in range(to_end, h):
            slope, r, du = slopes[row], row - to_end, 0.0
            for col in range(max(0, to_end - n_sources), to_end):
                jac = slope * feature_jac[r, to_end - 1 - col]
                du += jac * u[col]
                gamma[row, col] += jac * ratio
            jac_u[row] += du


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _feature_jacobian(predictor, ratio, ws, to_end):  # pragma: no cover (compiled)
    """Add to Γ (and ``jac_u``) the rows' derivative through the forecast T ahead after the turn
    ahead: ``∂T̂[k+1+q]/∂ū_n = β K[q − e_k, e_k − 1 − n]`` (q ≥ e_k, n < e_k) times each T lag's
    ∂z/∂T (``c_j + 2 d_j T + e_j p`` and, for T[k+m−1], the GP's ∂r/∂ψ₀)."""
    cc, d, e, kernel, gain = predictor.cc, predictor.d, predictor.e, predictor.feature_kernel, predictor.feature_gain
    n_p, n_t, n_tq, n_x = predictor.b.size, cc.size, d.size, e.size
    n_targets, n_sources = kernel.shape
    powers, temps, slopes, gamma, jac_u = ws.powers, ws.temps, ws.slopes, ws.gamma, ws.jac_u
    u, h = powers[n_p:], ws.c.size
    first_col = max(0, to_end - n_sources)
    for row in range(to_end + 1, h):
        last_p, last_t, du = n_p + row, n_t - 1 + row, 0.0
        for lag in range(min(n_t, row - to_end)):   # T[k+m−1−lag] = T̂[k+1+q], q = row − 1 − lag ≥ e_k
            s = row - 1 - lag - to_end
            if s >= n_targets:
                continue
            t = temps[last_t - lag]
            dz = cc[lag]
            if lag < n_tq:
                dz += 2.0 * d[lag] * t
            if lag < n_x:
                dz += e[lag] * powers[last_p - lag]
            if lag == 0:
                dz += ws.gp_t_slope[row]
            w = slopes[row] * gain * dz
            for col in range(first_col, to_end):
                jac = w * kernel[s, to_end - 1 - col]
                du += jac * u[col]
                gamma[row, col] += jac * ratio
        jac_u[row] += du


# ---------------------------------------------------------------------------------------- plan
@njit(cache=True, nogil=True)
def _plan(planner, ws, p_now, blind, n_p, relinearise, status):  # pragma: no cover (compiled)
    """The QP's affine term ``c = (x̂ − ∂x̂/∂ū ū − x_sp) / x_sp``, gradient, (with ``relinearise``)
    Hessian and factor, and unconstrained step, over the tracked rows (from ``blind`` on); the
    status of :meth:`Kernel.update` given the prediction's ``status`` (0, or 2 if not finite)."""
    c, predicted, jac_u, sp = ws.c, ws.predicted, ws.jac_u, planner.set_point_m2
    for row in range(c.size):
        c[row] = (predicted[row] - jac_u[row] - sp) / sp
    width = ws.width
    _gradient(planner, ws, p_now, blind, width)
    if relinearise:
        ws.has_step = _factor(planner, ws, blind, width)
        if not ws.has_step:
            return max(status, 1)
    return max(status, _step(planner, ws, blind, n_p, width))


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _gradient(planner, ws, p_now, blind, width):  # pragma: no cover (compiled)
    """The QP's gradient ``f = 2 Γᵀ W c − 2 r (p[k] / P) e₁`` over the tracked rows (Γ banded:
    ``width`` powers per row)."""
    gamma, c, f, weights = ws.gamma, ws.c, ws.f, planner.weights
    f[:] = 0.0
    for m in range(blind, c.size):
        w = 2.0 * weights[m]
        for a in range(max(0, m + 1 - width), m + 1):
            f[a] += w * gamma[m, a] * c[m]
    f[0] -= 2.0 * planner.move_weight * p_now / planner.power_scale_w


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _factor(planner, ws, blind, width):  # pragma: no cover (compiled)
    """The QP's Hessian ``2 Γᵀ W Γ + 2 r DᵀD`` over the tracked rows and its banded Cholesky factor
    ``L`` (``chol``) with ``1/L_jj`` in ``inv_diag`` (Γ banded: ``width`` powers per row); False if the
    Hessian is not positive definite."""
    gamma, hess, chol, inv_diag, weights = ws.gamma, ws.hess, ws.chol, ws.inv_diag, planner.weights
    h = gamma.shape[0]
    for a in range(h):                              # + 2 Γᵀ W Γ over the tracked rows
        _copy(hess[a], planner.moves[a])
    for m in range(blind, h):                       # Γ is banded (width powers per row), so is the Hessian:
        w, first = 2.0 * weights[m], max(0, m + 1 - width)   # square blocks (equal-length loops vectorise)
        for a in range(first, m + 1):
            wg = w * gamma[m, a]
            for b2 in range(first, m + 1):
                hess[a, b2] += wg * gamma[m, b2]
    band = max(width - 1, 1)                        # the moves' band is 1 (Kernel checks)
    for i in range(h):                              # banded Cholesky, Hessian = L Lᵀ (1/L_jj multiplies:
        first = max(0, i - band)                    # a division's latency would chain the row)
        for j in range(first, i):
            acc = hess[i, j]
            for k in range(first, j):
                acc -= chol[i, k] * chol[j, k]
            chol[i, j] = acc * inv_diag[j]
        acc = hess[i, i]
        for k in range(first, i):
            acc -= chol[i, k] * chol[i, k]
        if not acc > 0.0:
            return False
        chol[i, i] = math.sqrt(acc)
        inv_diag[i] = 1.0 / chol[i, i]
    return True


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _step(planner, ws, blind, n_p, width):  # pragma: no cover (compiled)
    """The unconstrained optimum ``v = −Hessian⁻¹ f`` from the factor of :func:`_factor`, the areas
    x̂ at ``P v`` (linearised) and the status: 0 when no power bound and no (tightened) area bound of
    the tracked rows is active, else 1."""
    gamma, c, chol, inv_diag, f, v, areas = ws.gamma, ws.c, ws.chol, ws.inv_diag, ws.f, ws.v, ws.areas
    predicted, std, u = ws.predicted, ws.std, ws.powers[n_p:]
    h, band = c.size, max(width - 1, 1)
    sp, scale = planner.set_point_m2, planner.power_scale_w
    v_lo, v_hi, e_lo, e_hi, z_sigma = planner.v_lo, planner.v_hi, planner.e_lo, planner.e_hi, planner.z_sigma
    status = 0
    for i in range(h):                              # L y = −f
        acc = -f[i]
        for k in range(max(0, i - band), i):
            acc -= chol[i, k] * v[k]
        v[i] = acc * inv_diag[i]
    for i in range(h - 1, -1, -1):                  # Lᵀ v = y, by columns of Lᵀ
        v[i] *= inv_diag[i]
        for k in range(max(0, i - band), i):
            v[k] -= chol[i, k] * v[i]
        if not (v_lo <= v[i] <= v_hi):
            status = 1
    for row in range(h):                            # e = Γ v + c of the tracked rows, x̂ at P v
        e, dx = 0.0, 0.0
        for col in range(max(0, row + 1 - width), row + 1):
            e += gamma[row, col] * v[col]
            dx += gamma[row, col] * (v[col] - u[col] / scale)
        areas[row] = predicted[row] + dx * sp
        e = e + c[row] if row >= blind else 0.0     # untracked rows: Γ and c are 0 in the QP
        tighten = z_sigma * std[row] / sp
        if e - tighten < e_lo or e + tighten > e_hi:
            status = 1
    return status


# ---------------------------------------------------------------------------------------- apply
@njit(cache=True, nogil=True)
def _apply(run, ws, planner, n_p, status):  # pragma: no cover (compiled)
    """What an update leaves for the next one: x̂[k+1|k] held by the estimator (its z without the
    p[k+1] terms, T ahead and learned correction) unless the prediction is not finite, and, when the
    unconstrained step is the QP's solution (status 0), the plan ``P v`` [W]."""
    estimator, t_hist = run.estimator, run.t_hist
    if status != 2:
        u1, t_now = ws.powers[n_p], t_hist[t_hist.size - 1]
        z_base = ws.z[0] - (estimator.b0 + estimator.e0 * t_now) * u1 - estimator.q0 * ws.mapped[n_p]
        hold_prediction(estimator, z_base, t_now, ws.correction[0])
    if status == 0:
        plan, v, scale = run.plan, ws.v, planner.power_scale_w
        for i in range(plan.size):
            plan[i] = v[i] * scale


class Kernel:
    """The preview MPC's stages for one controller (:mod:`controller_node.preview_stages`): the
    :class:`~controller_node.preview_stages.Predictor` and
    :class:`~controller_node.preview_stages.Planner` of the model and QP, the run (with its
    :class:`~controller_node.preview_stages.Estimator`) and two workspaces, every array allocated
    once (an update allocates nothing). :meth:`prepare` fills the spare workspace; the workspace's
    named arrays (attributes below) follow the one in use (swapped by a successful :meth:`feedback`).

    Parameters
    ----------
    model : gp_model.narx.NarxGPModel
        The delay-aware model.
    qp : controller_node.preview_qp.PreviewQP
        The QP (set point, scales, bounds, weights, move matrix).
    n_variance : int
        Rows whose GP variance is computed (the others' ``std`` is 0).
    uncertainty_z : float
        Bound tightening in standard deviations.
    n_profile, n_correction : int
        Lengths of the turnaround profile and of the learned correction.
    observer_gain : float
        Gain L of the disturbance observer.

    Attributes
    ----------
    predictor, planner, run, estimator, workspace
        The stages' structures (``workspace``: the one in use).
    work : numpy.ndarray
        The block that holds the arrays of the workspace in use.
    p_hist : numpy.ndarray, shape (n_p,)
        ``p[k], p[k−1], …`` [W].
    t_hist : numpy.ndarray, shape (n_T,)
        ``T[k−n_T+1 .. k]`` [K].
    plan : numpy.ndarray, shape (H,)
        The previous plan ``p̄[k .. k+H−1]`` [W] (shifted to ū = p̄[k+1 .. k+H], last held, by the update).
    profile : numpy.ndarray, shape (n_profile,)
        Turnaround profile of the T-ahead forecast [K].
    current, following : numpy.ndarray, shape (n_correction,)
        Learned correction after the current track's turn and after the next turn [m²].
    turn_errors, turn_error_seen : numpy.ndarray, shape (n_correction,)
        The estimator's one-step errors after the current track's turn, by state since it [m²], and
        which were seen.
    gamma, hess : numpy.ndarray, shape (H, H)
        Γ and the QP's Hessian.
    c, predicted, z, std, f, v, areas : numpy.ndarray, shape (H,)
        ``c``; x̂ at ū [m²]; ``z``; ``x'(z) sqrt(σ²_latent + σ_n²)`` for the first ``n_variance``
        rows, else 0 [m²]; the gradient; the unconstrained optimum (meaningful with
        :attr:`has_step`); x̂ at the plan ``P v`` [m²] (linearised).
    psi : numpy.ndarray, shape (H, 3)
        The GP inputs ψ_{k+m−1} (T ahead [K], log1p(min(s, cap)), mean power [W]).
    powers, temps : numpy.ndarray
        The lagged powers ``p[k−n_p+1 .. k]``, ū [W] and temperatures ``T[k−n_T+1 .. k]``,
        ``T̂[k+1 .. k+H−1]`` [K] of the rows.
    forecast, correction : numpy.ndarray, shape (H,)
        ``T̂[k+1 .. k+H]`` [K] and the learned correction of x̂_{k+1..k+H} [m²].
    p_long, f_hist, prev_powers, track_feature, track_remnant : numpy.ndarray
        The turnaround feature's and remnant's power history p[k], p[k−1], … (E,) [W], the feature's values
        F[k−n_F+1 .. k] [K], the previous track's last powers (E,) [W] and the current track's F [K] and
        remnant terms [z] by state since its start (S,), (n_R,) (:meth:`start_track`).
    feats : numpy.ndarray, shape (n_F − 1 + H,)
        F[k−n_F+2 .. k+H] [K] of the rows.
    prepared : bool
        A preparation is waiting for its :meth:`feedback`.
    """

    def __init__(self, model, qp, n_variance: int, uncertainty_z: float, n_profile: int, n_correction: int,
                 observer_gain: float) -> None:
        h = qp.horizon
        if np.any(np.triu(qp.moves, 2)) or np.any(np.tril(qp.moves, -2)):
            raise ValueError("the QP's move penalty must be tridiagonal (the kernel's Cholesky is banded)")
        scalars, points, var_f = self._three_inputs(*model.residual.kernel_terms())
        n_p, n_t, n_gp = model.power_coefficients.size, model.temperature_coefficients.size, points.shape[1]
        e, g = model.power_temperature_coefficients, model.feature_coefficients
        feature_kernel = model.feature_kernel()
        remnant_kernel, remnant_offsets = model.remnant_kernel()
        n_targets = feature_kernel.shape[0]
        n_sources = max(feature_kernel.shape[1], remnant_kernel.shape[1])   # the power history both read
        self.feature_kernel, self.remnant_kernel, self.remnant_offsets = feature_kernel, remnant_kernel, remnant_offsets
        horizon_kernel = self._horizon_kernel(feature_kernel, h)
        feature_jac = self._lag_feature_jacobian(g, horizon_kernel, h, remnant_kernel)
        log_output = bool(model.output == "log")
        const = carve({"b": (n_p,), "q": (n_p,), "cc": (n_t,), "d": model.temperature_square_coefficients.shape,
                       "e": e.shape, "mean": (3,), "scale": (3,), "decay": (h,), "weights": (h,), "moves": (h, h),
                       "gp_points": (4, n_gp), "beta": (n_gp,), "slope_weights": (n_gp,), "var_f": (n_gp, n_gp),
                       "series_weights": (n_gp, 2 * MOMENTS), "g": g.shape, "feature_kernel": horizon_kernel.shape,
                       "feature_jac": feature_jac.shape,
                       "feature_mean": (max(model.feature_profile_k.size, 1),), "remnant_kernel": remnant_kernel.shape,
                       "remnant_offsets": remnant_offsets.shape})
        w0_powers = points[0][:, None] ** np.arange(MOMENTS)          # W_a0ʲ, (N, MOMENTS)
        for name, value in (("b", model.power_coefficients), ("q", model.power_map_coefficients),
                            ("cc", model.temperature_coefficients), ("d", model.temperature_square_coefficients),
                            ("e", e), ("mean", scalars[:3]), ("scale", scalars[3:6]),
                            ("decay", model.forecast_persistence ** np.arange(1.0, h + 1)), ("weights", qp.weights),
                            ("moves", qp.moves), ("gp_points", points[:4]), ("beta", points[4]),
                            ("slope_weights", points[5]), ("var_f", var_f),
                            ("series_weights", np.hstack((points[4][:, None] * w0_powers,
                                                          points[5][:, None] * w0_powers))),
                            ("g", g), ("feature_kernel", horizon_kernel),
                            ("feature_jac", feature_jac),
                            ("feature_mean", model.feature_profile_k if model.turn_feature else np.zeros(1)),
                            ("remnant_kernel", remnant_kernel), ("remnant_offsets", remnant_offsets)):
            const[name][...] = value
        map_scale_w = 0.0 if model.power_map == "square" else LOG_POWER_SCALE_W
        self.predictor = new_predictor(float(model.intercept), const["b"], const["q"], map_scale_w, const["cc"],
                                       const["d"],
                                       const["e"], const["mean"], const["scale"], float(scalars[6]),
                                       float(scalars[7]), float(np.abs(points[0]).max()), const["gp_points"],
                                       const["beta"], const["slope_weights"], const["var_f"],
                                       const["series_weights"], const["decay"], log_output, int(n_variance),
                                       float(STEPS_SINCE_START_CAP), const["g"], const["feature_kernel"],
                                       const["feature_jac"], model.turn_feature is not None,
                                       float(model.feature_temperature_gain), const["feature_mean"],
                                       const["remnant_kernel"], const["remnant_offsets"])
        self.planner = new_planner(float(qp.x_sp), float(qp.scale), float(qp.r), float(qp.v_lo), float(qp.v_hi),
                                   float(qp.e_lo), float(qp.e_hi), float(uncertainty_z), const["weights"],
                                   const["moves"])
        run = carve({"p_hist": (n_p,), "t_hist": (n_t,), "plan": (h,), "profile": (n_profile,),
                     "current": (n_correction,), "following": (n_correction,), "turn_errors": (n_correction,),
                     "p_long": (n_sources,), "f_hist": (max(g.size, 1),), "prev_powers": (n_sources,),
                     "track_feature": (n_targets,), "track_remnant": (max(remnant_kernel.shape[0], 1),)})
        scratch = carve({"p_hist": (n_p,), "t_hist": (n_t,), "plan": (h,), "p_long": (n_sources,),
                         "f_hist": (max(g.size, 1),)})
        self.turn_error_seen = np.zeros(n_correction, dtype=bool)
        estimator_terms = (float(observer_gain), float(model.power_coefficients[0]),
                           float(model.power_map_coefficients[0]), float(e[0]) if e.size else 0.0, map_scale_w,
                           log_output)
        self.estimator = new_estimator(*estimator_terms, run["turn_errors"], self.turn_error_seen)
        self.run = new_run(run["p_hist"], run["t_hist"], run["plan"], run["profile"], run["current"],
                           run["following"], run["p_long"], run["f_hist"], run["prev_powers"], run["track_feature"],
                           run["track_remnant"], self.estimator)
        self._scratch = new_run(scratch["p_hist"], scratch["t_hist"], scratch["plan"], run["profile"],
                                run["current"], run["following"], scratch["p_long"], scratch["f_hist"],
                                run["prev_powers"], run["track_feature"], run["track_remnant"],
                                new_estimator(*estimator_terms, run["turn_errors"], self.turn_error_seen))
        self.p_hist, self.t_hist, self.plan, self.profile = run["p_hist"], run["t_hist"], run["plan"], run["profile"]
        self.current, self.following, self.turn_errors = run["current"], run["following"], run["turn_errors"]
        self.p_long, self.f_hist = run["p_long"], run["f_hist"]
        self.prev_powers, self.track_feature, self.track_remnant = run["prev_powers"], run["track_feature"], \
            run["track_remnant"]
        self.prepared = False
        self._workspaces = (self._workspace(h, n_p, n_t, n_gp, g.size), self._workspace(h, n_p, n_t, n_gp, g.size))
        self.__dict__.update(self._workspaces[0][1])
        self._update, self._prepare, self._feedback = (BoundOnFirstCall(f) for f in (update_into, prepare_into,
                                                                                    feedback_into))

    @staticmethod
    def _three_inputs(scalars: np.ndarray, points: np.ndarray, var_f: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The GP's :meth:`~gp_model.narx.ResidualGP.kernel_terms` as the compiled code reads them, for
        the three inputs of :data:`gp_model.narx.RESIDUAL_INPUTS`: a GP without the mean-power input gets
        it with scale 0 (its scaled input, the points' coordinate and their slope weights 0), so that
        its kernel values and sums are the two-input GP's and its slope in the mean power is 0."""
        d = points.shape[0] - 3
        if d == 3:
            return scalars, points, var_f
        zero = np.zeros(1)
        scalars = np.r_[scalars[:d], zero, scalars[d:2 * d], zero, scalars[2 * d:]]
        points = np.vstack([points[:d], np.zeros((1, points.shape[1])), points[d:d + 2],
                            np.zeros((1, points.shape[1]))])
        return scalars, points, var_f

    @staticmethod
    def _horizon_kernel(kernel: np.ndarray, h: int) -> np.ndarray:
        """The feature kernel's columns (sources) that reach the first ``h`` states after a turn, all rows.

        The compiled code reads ``K[s, e]`` only for s < H (the rows after the turn ahead; the current
        track's feature is :meth:`start_track`'s full product). Sources further back than the last column
        with a term above ``1e-17`` of the largest term of those rows (the heat of a point mm away, far
        below a double's rounding of the sum) are dropped: at least ``h`` columns are kept."""
        rows = np.abs(kernel[:h])
        reach = np.flatnonzero(np.any(rows > 1e-17 * rows.max(), axis=0)) if rows.size and rows.max() > 0 else []
        n = max(h, int(reach[-1]) + 1 if len(reach) else 0)
        return np.ascontiguousarray(kernel[:, :min(n, kernel.shape[1])])

    @staticmethod
    def _lag_feature_jacobian(g: np.ndarray, kernel: np.ndarray, h: int,
                              remnant: np.ndarray | None = None) -> np.ndarray:
        """``M[r, e] = Σ_{l ≤ r, r − l < S} g_l K[r − l, e] + W[r, e]``, shape (H, max(E, E_R)): ∂z of the r-th
        state after a turn by the power e states before it, through the lagged turnaround features and the
        remnant terms ``remnant`` W, shape (n_R, E_R) (W = 0 beyond them)."""
        remnant = np.zeros((0, 1)) if remnant is None else remnant
        out = np.zeros((h, max(kernel.shape[1], remnant.shape[1])))
        for lag, coefficient in enumerate(g):
            rows = np.arange(lag, min(h, lag + kernel.shape[0]))
            out[rows, :kernel.shape[1]] += coefficient * kernel[rows - lag]
        rows = min(h, remnant.shape[0])
        out[:rows, :remnant.shape[1]] += remnant[:rows]
        return out

    def start_track(self, previous: bool) -> None:
        """At a track's first state, before its update: the previous track's last powers (``p_long``,
        with ``previous``; zeros at a layer's start) and the turnaround feature and remnant terms they give
        along this track (``track_feature = K prev_powers``, ``track_remnant = c + W prev_powers``)."""
        self.prev_powers[:] = self.p_long if previous else 0.0
        self.track_feature[:] = self.feature_kernel @ self.prev_powers[:self.feature_kernel.shape[1]] if previous \
            else 0.0
        n_r, n_e = self.remnant_kernel.shape
        self.track_remnant[:n_r] = self.remnant_offsets + self.remnant_kernel @ self.prev_powers[:n_e] if previous \
            else 0.0

    @staticmethod
    def _workspace(h: int, n_p: int, n_t: int, n_gp: int, n_f: int) -> tuple[Workspace, dict]:
        """A workspace and the named arrays of it that are attributes (following the workspace in use)."""
        a = carve({"gamma": (h, h), "hess": (h, h), "chol": (h, h), "c": (h,), "predicted": (h,), "z": (h,),
                   "std": (h,), "f": (h,), "v": (h,), "areas": (h,), "gp_slope": (h,), "inv_diag": (h,),
                   "slopes": (h,), "jac_u": (h,), "psi": (h, 3), "kern": (h, n_gp), "bits": (h * n_gp,),
                   "powers": (n_p + h,), "temps": (n_t + h - 1,), "forecast": (h,), "correction": (h,), "w0": (h,),
                   "mean_moments": (h, MOMENTS), "slope_moments": (h, MOMENTS), "variance_moments": (h, MOMENTS),
                   "powers_of_w0": (n_gp, MOMENTS), "feats": (max(n_f, 1) - 1 + h,), "gp_t_slope": (h,),
                   "rems": (h,), "mapped": (n_p + h,), "mapped_slope": (h,)})
        block = a["gamma"].base                     # the one block of the views
        a["bits"] = a["bits"].view(np.int64)
        ws = new_workspace(*a.values())
        names = ("gamma", "hess", "c", "predicted", "z", "std", "f", "v", "areas", "psi", "kern", "powers", "temps",
                 "forecast", "correction", "feats")
        return ws, dict({name: a[name] for name in names}, workspace=ws, work=block)

    @property
    def has_step(self) -> bool:
        """The last update's Hessian was positive definite: ``v`` is the unconstrained optimum."""
        return self.workspace.has_step

    def update(self, context: StateContext, t_ahead_k: float, area_m2: float) -> int:
        """:func:`update_into` for a state at ``context`` with its measured T ahead [K] and area [m²];
        the status: 0 ``v`` solves the QP (no bound active; ``plan`` is its solution), 1 a bound is
        active or the Hessian is not positive definite (:attr:`has_step`), 2 a prediction is not
        finite. Pass the types of the first call every time. Discards a preparation."""
        self.prepared = False
        return self._update.call(self.predictor, self.planner, self.run, self.workspace, context, t_ahead_k, area_m2)

    def prepare(self, context: StateContext, t_ahead_k: float) -> bool:
        """:func:`prepare_into` in the spare workspace, for a next state at ``context`` with T ahead
        near ``t_ahead_k`` [K]; the run and the workspace in use are not changed. True if the
        prepared step exists (finite prediction, positive definite Hessian), and :meth:`feedback` may
        then be called for that state."""
        self.prepared = self._prepare.call(self.predictor, self.planner, self.run, self._scratch,
                                           self._workspaces[1][0], context, t_ahead_k)
        return self.prepared

    def feedback(self, context: StateContext, t_ahead_k: float, area_m2: float) -> int:
        """:func:`feedback_into` for the state :meth:`prepare` prepared (the caller checks that
        ``context`` is the one it prepared for); on success the prepared workspace becomes the one in
        use. The status of :meth:`update`, or −1 (nothing changed) if the measured T ahead is too
        far from the forecast for the prepared series: call :meth:`update` then."""
        if not self.prepared:
            raise RuntimeError("feedback without a preparation")
        self.prepared = False
        spare, names = self._workspaces[1]
        status = self._feedback.call(self.predictor, self.planner, self.run, spare, context, t_ahead_k, area_m2)
        if status >= 0:
            self._workspaces = self._workspaces[::-1]
            self.__dict__.update(names)
        return status
