"""The preview MPC's hot path, compiled: prediction, Jacobian and unconstrained QP step.

:class:`controller_node.preview.PreviewMPC` makes one call per update, :meth:`Kernel.update`
(compiled :func:`update_into`): it updates the disturbance observer with the state's area
(:func:`_observe`), pushes the state's power and T ahead into the histories,
forecasts T ahead over the horizon (:func:`gp_trainer.narx.forecast_into`), lays out the learned
turnaround correction (:func:`correction_into`), and, for the planned powers ū (the previous plan,
shifted), evaluates for m = 1..H (model of :mod:`gp_trainer.narx`, rows indexed ``i = m − 1``)::

    z_m = c₀ + Σ_i (b_i p_i + q_i p_i²) + Σ_j c_j T_j + Σ_{j<n_Tq} d_j T_j² + Σ_{i<n_x} e_i p_i T_i + r(ψ_{k+m−1})
    x̂_m = exp(z_m) (log output) + d̂ + κ-learned correction_m
    ∂x̂_m/∂ū_n = x'(z_m) (b_l + 2 q_l ū_n + e_l T[k+m−1−l] + ∂r/∂ψ₂ / n_p),  l = m − 1 − n ∈ [0, n_p)

with ``p_i = p[k+m−i]``, ``T_j = T[k+m−1−j]`` (the forecast beyond k), the SE-ARD residual GP
``r(ψ) = Σ_a k(ψ, ψ_a) β_a`` at ψ = (T ahead, log1p(min(s, 100)), mean of the p_i), its slope in
the mean power and its latent variance ``σ² − ‖L⁻¹ k‖²`` for the first ``n_variance`` rows. Then
the condensed QP of :mod:`controller_node.preview_qp` in ``v = u / P``, ``e = Γ v + c``::

    Γ = ∂x̂/∂ū · P / x_sp,   c = (x̂ − ∂x̂/∂ū ū − x_sp) / x_sp
    Hessian = 2 Γᵀ W Γ + 2 r DᵀD,   gradient f = 2 Γᵀ W c − 2 r (p[k] / P) e₁

and its unconstrained optimum ``v* = −Hessian⁻¹ f`` by Cholesky. When ``v*`` is inside the power
bounds and ``e = Γ v* + c`` (± the bound tightening) inside the area bounds, it is the QP's
solution (the fast path, as :meth:`controller_node.preview_qp.PreviewQP.finish` decides) and
becomes the plan; else the caller hands Γ, c to :meth:`~controller_node.preview_qp.PreviewQP.finish`.

Why one compiled call over flat arrays: between FE steps or plant frames the controller's caches
are cold, and each call from Python into compiled code or numpy then costs microseconds of
dispatch, each argument more, each fresh allocation and each small BLAS call a cache miss
(``docs/controller.md``, "Speed"). So the model's constants, the run's histories and plan, and
every result live in three flat arrays allocated once (:class:`Kernel`, named views into them),
the GP kernel's exponential is a vectorisable loop (:func:`exp_into`, within 1 ulp of numpy's),
and the Hessian and its Cholesky factor are formed by loops over their band (n_p powers
per row of Γ). The real-time iteration splits an update in two (:class:`controller_node.preview.PreviewMPC`):
:func:`prepare_into` runs :func:`update_into` for the state expected next into a spare workspace
before it arrives; :func:`feedback_into` then recomputes only what the measurement changes (observer,
histories, forecast, prediction, gradient, step) on the prepared Γ and Cholesky factor.
The numpy formulation stays
the reference: ``tests/test_preview_kernel.py`` checks this kernel against the model's own
prediction (:meth:`gp_trainer.narx.NarxGPModel.predict_run`), its Jacobian against finite
differences, and the QP terms against :meth:`PreviewQP.hessian` / :meth:`PreviewQP.gradient`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from gp_trainer.compiled import BoundOnFirstCall
from gp_trainer.narx import STEPS_SINCE_START_CAP, forecast_into

__all__ = ["Kernel", "correction_into", "exp_into", "feedback_into", "prepare_into", "push_history", "update_into"]

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


@njit(cache=True, nogil=True)
def _regressors(p_hist, t_hist, forecast, plan, since, to_end, s_cap, gp, gp_points, psi, exponents, powers,
                temps, n_rows):  # pragma: no cover (compiled)
    """The lagged powers and temperatures of the rows (into ``powers``, ``temps``), their GP inputs ψ
    (into ``psi``) and, for the first ``n_rows`` rows, the SE kernel's exponents
    ``w·W_a − ‖W_a‖²/2 − ‖w‖²/2`` (into ``exponents``, shape (H, N), ``w`` the scaled input)."""
    h, n_p, n_t, n_gp = plan.size, p_hist.size, t_hist.size, gp_points.shape[1]
    for i in range(n_p):                            # p[k−n_p+1 .. k], ū
        powers[i] = p_hist[n_p - 1 - i]
    for i in range(h - 1):
        powers[n_p + i] = plan[i + 1]
    powers[n_p + h - 1] = plan[h - 1]
    temps[:n_t] = t_hist                            # T[k−n_T+1 .. k], T̂[k+1 .. k+H−1]
    temps[n_t:] = forecast[:h - 1]
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
        w0 = (psi[row, 0] - gp[0]) * gp[3]
        w1 = (psi[row, 1] - gp[1]) * gp[4]
        w2 = (psi[row, 2] - gp[2]) * gp[5]
        half_w = 0.5 * (w0 * w0 + w1 * w1 + w2 * w2)
        for a in range(n_gp):
            exponents[row, a] = w0 * gp_points[0, a] + w1 * gp_points[1, a] + w2 * gp_points[2, a] + gp_points[3, a] \
                - half_w


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


MOMENTS = 12
"""Terms of the series in which :func:`feedback_into` moves the GP's kernel sums (and, without bound
tightening, the variance) to the measured T ahead."""
SERIES_RADIUS = 0.5
"""Largest ``|ε W_a0|`` of those series: their truncation is then below ``0.5¹²/12! e^0.5`` ≈ 5e-13 of
``Σ_a |k_a β_a|`` (the mean) and ``1/12! e`` ≈ 6e-9 of ``Σ_ab |k_a A_ab k_b|`` (the variance's
quadratic form, whose variable ``ε (W_a0 + W_b0)`` reaches twice the radius); beyond it the state
gets the full update."""
_MEAN, _SLOPE, _W0, _VARIANCE = 0, MOMENTS, 2 * MOMENTS, 2 * MOMENTS + 1
"""Where a row of the prepared ``moments`` keeps the mean's and the mean-power slope's moments, the
row's scaled T input and the variance's moments."""

N_SIZES = 11
"""Leading entries of :class:`Kernel`'s ``dims``: n_p, n_T, n_Tq, n_x, N, H, profile and correction
lengths, n_variance, log output, steps-since-start cap; :func:`_layout`'s ends follow."""


@njit(cache=True, nogil=True)
def _layout(dims):  # pragma: no cover (compiled)
    """Where each named array ends in the flat ``consts``, ``state`` and ``work`` of :class:`Kernel`
    (cumulative lengths; the last of each is the flat array's length): the one definition of their layout."""
    n_p, n_t, n_tq, n_x, n_gp, h, n_profile, n_corr = dims[0], dims[1], dims[2], dims[3], dims[4], dims[5], \
        dims[6], dims[7]
    return (np.cumsum(np.array([1, n_p, n_p, n_t, n_tq, n_x, 9, h, h + 9, h * h, 6 * n_gp, n_gp * n_gp,
                                2 * MOMENTS * n_gp])),
            np.cumsum(np.array([n_p, n_t, h, n_profile, n_corr, n_corr, n_corr, 4])),
            np.cumsum(np.array([3 * h * h, 11 * h, 3 * h, h * n_gp, h * n_gp, n_p + h, n_t + h - 1, h, h,
                                h * (3 * MOMENTS + 1), MOMENTS * n_gp])))


@njit(cache=True, nogil=True)
def _views(dims, consts, state, work):  # pragma: no cover (compiled)
    """The named arrays inside the three flat ones, at the ends of :func:`_layout` that ``dims`` carries
    from index ``N_SIZES`` on (:class:`Kernel`; nothing allocated per update)."""
    h, n_gp = dims[5], dims[4]
    ends, state_ends, work_ends = dims[N_SIZES:N_SIZES + 13], dims[N_SIZES + 13:N_SIZES + 21], dims[N_SIZES + 21:]
    intercept, b, q, cc = consts[0:ends[0]], consts[ends[0]:ends[1]], consts[ends[1]:ends[2]], consts[ends[2]:ends[3]]
    d, e, gp, decay = consts[ends[3]:ends[4]], consts[ends[4]:ends[5]], consts[ends[5]:ends[6]], consts[ends[6]:ends[7]]
    qp_terms, moves = consts[ends[7]:ends[8]], consts[ends[8]:ends[9]].reshape((h, h))
    gp_points = consts[ends[9]:ends[10]].reshape((6, n_gp))
    var_f = consts[ends[10]:ends[11]].reshape((n_gp, n_gp))
    series_weights = consts[ends[11]:ends[12]].reshape((n_gp, 2 * MOMENTS))
    ends = state_ends
    p_hist, t_hist, plan = state[0:ends[0]], state[ends[0]:ends[1]], state[ends[1]:ends[2]]
    profile, current, following = state[ends[2]:ends[3]], state[ends[3]:ends[4]], state[ends[4]:ends[5]]
    turn_errors, observer = state[ends[5]:ends[6]], state[ends[6]:ends[7]]
    ends = work_ends
    matrices, vectors = work[0:ends[0]].reshape((3, h, h)), work[ends[0]:ends[1]].reshape((11, h))
    psi, kern = work[ends[1]:ends[2]].reshape((h, 3)), work[ends[2]:ends[3]].reshape((h, n_gp))
    bits, powers, temps = work[ends[3]:ends[4]].view(np.int64), work[ends[4]:ends[5]], work[ends[5]:ends[6]]
    forecast, correction = work[ends[6]:ends[7]], work[ends[7]:ends[8]]
    moments = work[ends[8]:ends[9]].reshape((h, 3 * MOMENTS + 1))
    powers_of_w0 = work[ends[9]:ends[10]].reshape((n_gp, MOMENTS))
    return (intercept, b, q, cc, d, e, gp, decay, qp_terms, moves, gp_points, var_f,
            p_hist, t_hist, plan, profile, current, following, turn_errors, observer,
            matrices, vectors, psi, kern, bits, powers, temps, forecast, correction, moments, powers_of_w0,
            series_weights)


@njit(cache=True, nogil=True)
def update_into(dims, consts, state, work, p_fill, power_w, t_fill, t_ahead_k, area_m2, observe, since, on_first,
                to_end, t_base, learned, blind):  # pragma: no cover (compiled)
    """One update's numerics (module docstring) in place; the status of :func:`_linearised_qp`.

    ``observe``: the state follows the last one and the pool is built up, so the disturbance
    observer compares ``area_m2`` [m²] with x̂[k|k−1] (:func:`_observe`). ``p_fill``/``t_fill``
    copies of ``power_w`` [W] / ``t_ahead_k`` [K] enter the histories (:func:`push_history`);
    ``since``, ``on_first``, ``to_end`` (−1: no turn ahead), ``t_base`` [K] (NaN: none) place the
    state on the scan plan (:func:`gp_trainer.narx.forecast_into`); ``learned``: the learned
    turnaround correction applies (:func:`correction_into`, else 0); ``blind`` leading rows not
    tracked. With no bound active the plan becomes the QP's solution here."""
    (intercept, b, q, cc, d, e, gp, decay, qp_terms, moves, gp_points, var_f, p_hist, t_hist, plan, profile,
     current, following, turn_errors, observer, matrices, vectors, psi, kern, bits, powers, temps, forecast,
     correction, moments, powers_of_w0, series_weights) = _views(dims, consts, state, work)
    log_output, e0 = dims[9] != 0, e[0] if e.size else 0.0
    if observe:
        _observe(observer, b[0], q[0], e0, log_output, qp_terms[3], power_w, area_m2,
                 since if t_base == t_base else -1, turn_errors)
    observer[1] = math.nan                          # no x̂[k+1|k] until this update gives one
    push_history(p_hist, p_fill, power_w, t_hist, t_fill, t_ahead_k)
    forecast_into(t_ahead_k, since, on_first, to_end, profile, t_base, decay, forecast)
    if learned and current.size:
        correction_into(since, on_first, to_end, current, following, correction)
    else:
        correction[:] = 0.0
    _regressors(p_hist, t_hist, forecast, plan, since, to_end, float(dims[10]), gp, gp_points, psi, kern, powers,
                temps, plan.size)
    exp_into(kern, bits)
    status = _linearised_qp(powers, temps, kern, log_output, intercept[0], b, q, cc, d, e, gp, gp_points, var_f,
                            dims[8], correction, observer[0], qp_terms, p_hist[0], moves, blind, psi, vectors,
                            matrices, moments)
    _finish(status, observer, b[0], q[0], e0, powers[p_hist.size], t_hist[t_hist.size - 1], vectors, correction[0],
            qp_terms[1], plan)
    return status


@njit(cache=True, nogil=True)
def _finish(status, observer, b0, q0, e0, u1, t_now, vectors, correction0, scale, plan):  # pragma: no cover
    """What an update leaves for the next one: the z of x̂[k+1|k] without its p[k+1] terms, its T ahead
    ``t_now`` [K] and learned correction [m²] for the observer (unless the prediction is not finite),
    and, when the unconstrained step is the QP's solution (status 0), the plan ``P v`` [W]."""
    if status != 2:
        observer[1] = vectors[2, 0] - (b0 + q0 * u1 + e0 * t_now) * u1
        observer[2], observer[3] = t_now, correction0
    if status == 0:
        for i in range(plan.size):
            plan[i] = vectors[5, i] * scale


@njit(cache=True, nogil=True)
def prepare_into(dims, consts, state, scratch, work, p_fill, power_w, t_fill, t_ahead_k, since, on_first, to_end,
                 t_base, learned, blind):  # pragma: no cover (compiled)
    """Preparation phase of a real-time iteration: :func:`update_into` for the state expected next
    (its arguments, with T ahead ``t_ahead_k`` [K] forecast; the area is not known yet, so the
    observer is not run) on a copy of ``state`` in ``scratch`` (``state`` is not changed), into
    ``work``; then, per row m, the moments of the GP's kernel sums in the scaled T input,
    ``Σ_a k_ma β_a W_a0ʲ`` and ``Σ_a k_ma β_a W_a2 W_a0ʲ``, j < :data:`MOMENTS`, the row's scaled
    T input w_m0 and, for the variance rows when the feedback takes the variance from the series
    (:func:`_series_variance`), the moments of its quadratic form ``Σ_ab k_a A_ab k_b (W_a0 + W_b0)ʲ``,
    ``A = (σ_f L⁻¹)ᵀ σ_f L⁻¹`` (``moments``, for :func:`feedback_into`). Returns the update's status."""
    scratch[:] = state
    area = math.nan                                 # not measured yet: no observer (a typed, not a literal, False)
    status = update_into(dims, consts, scratch, work, p_fill, power_w, t_fill, t_ahead_k, area, not math.isnan(area),
                         since, on_first, to_end, t_base, learned, blind)
    (intercept, b, q, cc, d, e, gp, decay, qp_terms, moves, gp_points, var_f, p_hist, t_hist, plan, profile,
     current, following, turn_errors, observer, matrices, vectors, psi, kern, bits, powers, temps, forecast,
     correction, moments, powers_of_w0, series_weights) = _views(dims, consts, scratch, work)
    h = plan.size
    sums = np.dot(kern, series_weights)             # (H, 2 MOMENTS): Σ_a k_ma β_a W_a0ʲ, Σ_a k_ma β_a W_a2 W_a0ʲ
    for row in range(h):
        for j in range(2 * MOMENTS):
            moments[row, _MEAN + j] = sums[row, j]
        moments[row, _W0] = (psi[row, 0] - gp[0]) * gp[3]
    for row in range(0 if _series_variance(qp_terms) else dims[8], dims[8]):
        for a in range(kern.shape[1]):              # k ∘ W_0ⁱ, i < MOMENTS, as columns
            weighted = kern[row, a]
            for i in range(MOMENTS):
                powers_of_w0[a, i] = weighted
                weighted *= gp_points[0, a]
        projected = np.dot(var_f, powers_of_w0)     # y_i = σ_f L⁻¹ (k ∘ W_0ⁱ)
        gram = np.dot(projected.T, projected)
        for j in range(MOMENTS):                    # Q_j = Σ_i C(j, i) y_iᵀ y_{j−i} = kᵀA(W_a0 + W_b0)ʲk
            binomial, total = 1.0, 0.0
            for i in range(j + 1):
                total += binomial * gram[i, j - i]
                binomial = binomial * (j - i) / (i + 1)
            moments[row, _VARIANCE + j] = total
    return status


@njit(cache=True, nogil=True)
def _series_variance(qp_terms):  # pragma: no cover (compiled)
    """Whether the feedback takes the variance from the series (no bound tightening, zσ = 0: the
    variance is the diagnostics' only), not from kernel values at the measured T ahead."""
    return qp_terms[8] == 0.0


@njit(cache=True, nogil=True)
def feedback_into(dims, consts, state, work, p_fill, power_w, t_fill, t_ahead_k, area_m2, observe, since, on_first,
                  to_end, t_base, blind):  # pragma: no cover (compiled)
    """Feedback phase of a real-time iteration: the update of the state that :func:`prepare_into`
    prepared ``work`` for (same arguments), with its measured T ahead ``t_ahead_k`` [K] and area
    ``area_m2`` [m²]. The prediction x̂ at ū is the model's own at the measured T ahead, as in
    :func:`update_into`, except that the GP's kernel sums come from the prepared moments: with ``ε``
    the row's shift of the scaled T input, ``k_a(w + ε e₀) = k_a(w) exp(ε W_a0 − w₀ ε − ε²/2)``, so
    ``Σ_a k_a β_a`` moves to ``exp(−w₀ ε − ε²/2) Σ_j εʲ/j! Σ_a k_a β_a W_a0ʲ`` (the mean-power
    moment likewise, and the variance's quadratic form with ``exp(−2 w₀ ε − ε²)`` and
    ``(W_a0 + W_b0)ʲ``); with bound tightening the variance rows are computed from their kernel
    values instead (:func:`_series_variance`). The
    Jacobian Γ, the Hessian and its factor stay those of the forecast T ahead (the real-time
    iteration's linearisation); ``c``, the gradient, the step and the bound checks are those of the
    new prediction. Returns :func:`update_into`'s status, or −1, changing nothing in ``state``, when a
    shift is outside :data:`SERIES_RADIUS` (the caller then runs the full update)."""
    (intercept, b, q, cc, d, e, gp, decay, qp_terms, moves, gp_points, var_f, p_hist, t_hist, plan, profile,
     current, following, turn_errors, observer, matrices, vectors, psi, kern, bits, powers, temps, forecast,
     correction, moments, powers_of_w0, series_weights) = _views(dims, consts, state, work)
    h, n_gp, n_variance, log_output = plan.size, gp_points.shape[1], dims[8], dims[9] != 0
    forecast_into(t_ahead_k, since, on_first, to_end, profile, t_base, decay, forecast)
    w_max = gp[8]
    for row in range(h):
        t_row = t_ahead_k if row == 0 else forecast[row - 1]
        if not abs(((t_row - gp[0]) * gp[3] - moments[row, _W0]) * w_max) <= SERIES_RADIUS:
            return -1
    e0, n_p = e[0] if e.size else 0.0, b.size
    if observe:
        _observe(observer, b[0], q[0], e0, log_output, qp_terms[3], power_w, area_m2,
                 since if t_base == t_base else -1, turn_errors)
    observer[1] = math.nan
    push_history(p_hist, p_fill, power_w, t_hist, t_fill, t_ahead_k)
    kern_rows = 0 if _series_variance(qp_terms) else n_variance
    _regressors(p_hist, t_hist, forecast, plan, since, to_end, float(dims[10]), gp, gp_points, psi, kern, powers,
                temps, kern_rows)
    exp_into(kern[:kern_rows], bits[:kern_rows * n_gp])
    finite = _prediction(powers, temps, kern, log_output, intercept[0], b, q, cc, d, e, gp, gp_points, var_f,
                         n_variance, correction, observer[0], psi, vectors, kern_rows, moments)
    sp = qp_terms[0]
    c, predicted, jac_u = vectors[0], vectors[1], vectors[10]
    for row in range(h):
        c[row] = (predicted[row] - jac_u[row] - sp) / sp
    gamma, chol = matrices[0], matrices[2]
    _gradient(gamma, c, qp_terms, p_hist[0], blind, n_p, vectors[4])
    status = max(0 if finite else 2, _step(gamma, c, chol, vectors[8], qp_terms, blind, n_p, predicted, vectors[3],
                                            powers[n_p:], vectors[4], vectors[5], vectors[6]))
    _finish(status, observer, b[0], q[0], e0, powers[n_p], t_hist[t_hist.size - 1], vectors, correction[0],
            qp_terms[1], plan)
    return status


@njit(cache=True, nogil=True)
def _observe(observer, b0, q0, e0, log_output, gain, power_w, area_m2, since, turn_errors):  # pragma: no cover
    """The disturbance observer ``d̂ ← d̂ + L (x[k] − x̂[k|k−1] − d̂)`` (``observer`` = d̂ [m²], the
    z of x̂[k|k−1] without its p[k] terms (NaN: none), the T ahead in them [K], its learned
    correction [m²]); x̂[k|k−1] completed with the applied ``power_w`` [W]. The one-step error is
    kept in ``turn_errors[since]`` when ``0 <= since`` < its length (after a turn)."""
    base = observer[1]
    if base != base:
        return
    z = base + (b0 + q0 * power_w + e0 * observer[2]) * power_w
    predicted = (math.exp(z) if log_output else z) + observer[3]
    error = area_m2 - predicted - observer[0]
    if 0 <= since < turn_errors.size:
        turn_errors[since] = error
    observer[0] += gain * error


class Kernel:
    """The model's constants, the run's histories and plan, and the workspace of one controller, as
    the three flat arrays :func:`update_into` reads and fills (allocated once: an update allocates
    nothing), with named views into them. A second workspace takes :meth:`prepare`'s results; the
    workspace's named views follow the one in use (swapped by a successful :meth:`feedback`).

    Parameters
    ----------
    model : gp_trainer.narx.NarxGPModel
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
    dims : numpy.ndarray of int64
        The sizes (``N_SIZES`` of them) and the layout's ends (:func:`_layout`).
    consts, state, work : numpy.ndarray
        The flat arrays: the model's and QP's constants, the run's (histories, plan, profile,
        corrections), the results.
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
    turn_errors : numpy.ndarray, shape (n_correction,)
        The observer's one-step errors after the current track's turn, by state since it (NaN: not seen) [m²].
    observer : numpy.ndarray, shape (4,)
        d̂ [m²]; z of x̂[k+1|k] without its p[k+1] terms (NaN: none); the T ahead [K] and the learned
        correction [m²] in it.
    gamma, hess : numpy.ndarray, shape (H, H)
        Γ and the QP's Hessian.
    c, predicted, z, std, f, v, areas : numpy.ndarray, shape (H,)
        ``c``; x̂ at ū [m²]; ``z``; ``x'(z) sqrt(σ²_latent + σ_n²)`` for the first ``n_variance``
        rows, else 0 [m²]; the gradient; the unconstrained optimum (NaN if the Hessian is not
        positive definite); x̂ at the plan ``P v`` [m²] (linearised).
    psi : numpy.ndarray, shape (H, 3)
        The GP inputs ψ_{k+m−1} (T ahead [K], log1p(min(s, cap)), mean power [W]).
    forecast, correction : numpy.ndarray, shape (H,)
        ``T̂[k+1 .. k+H]`` [K] and the learned correction of x̂_{k+1..k+H} [m²].
    prepared : bool
        A preparation is waiting for its :meth:`feedback`.
    """

    def __init__(self, model, qp, n_variance: int, uncertainty_z: float, n_profile: int, n_correction: int,
                 observer_gain: float) -> None:
        h = qp.horizon
        if np.any(np.triu(qp.moves, 2)) or np.any(np.tril(qp.moves, -2)):
            raise ValueError("the QP's move penalty must be tridiagonal (the kernel's Cholesky is banded)")
        scalars, points, var_f = model.residual.kernel_terms()
        b, cc = model.power_coefficients, model.temperature_coefficients
        sizes = np.array([b.size, cc.size, model.temperature_square_coefficients.size,
                              model.power_temperature_coefficients.size, points.shape[1], h, n_profile, n_correction,
                              n_variance, model.output == "log", STEPS_SINCE_START_CAP], dtype=np.int64)
        layout = _layout(sizes)
        self.dims = np.concatenate((sizes, *layout))
        self.consts, self.state, self.work = (np.zeros(int(ends[-1])) for ends in layout)
        (intercept, b_, q, cc_, d, e, gp, decay, qp_terms, moves, gp_points, var_f_, self.p_hist, self.t_hist,
         self.plan, self.profile, self.current, self.following, self.turn_errors, self.observer,
         *_, series_weights) = _views(self.dims, self.consts, self.state, self.work)
        w0_powers = points[0][:, None] ** np.arange(MOMENTS)          # W_a0ʲ, (N, MOMENTS)
        series_weights[...] = np.hstack((points[4][:, None] * w0_powers, points[5][:, None] * w0_powers))
        intercept[0] = model.intercept
        # qp_terms: x_sp, P, r, observer gain L, v_lo, v_hi, e_lo, e_hi, zσ, then the H row weights;
        # gp: the GP's (μ, g, σ², σ_n²) of kernel_terms and max |W_a0| (feedback_into's series radius)
        for view, value in ((b_, b), (q, model.power_square_coefficients), (cc_, cc),
                            (d, model.temperature_square_coefficients), (e, model.power_temperature_coefficients),
                            (gp, np.r_[scalars, np.abs(points[0]).max()]),
                            (decay, model.forecast_persistence ** np.arange(1.0, h + 1)),
                            (moves, qp.moves), (gp_points, points), (var_f_, var_f),
                            (qp_terms, np.r_[qp.x_sp, qp.scale, qp.r, observer_gain, qp.v_lo, qp.v_hi, qp.e_lo, qp.e_hi,
                                             uncertainty_z, qp.weights])):
            view[...] = value
        self.observer[:] = (0.0, math.nan, 0.0, 0.0)   # d̂ = 0, no x̂[k+1|k] yet
        self._scratch = np.zeros_like(self.state)
        self.prepared = False
        self._workspaces = (self._named(self.work), self._named(np.zeros_like(self.work)))
        self.__dict__.update(self._workspaces[0])
        self._update, self._prepare, self._feedback = (BoundOnFirstCall(f) for f in (update_into, prepare_into,
                                                                                    feedback_into))

    def _named(self, work: np.ndarray) -> dict:
        """The named views of one workspace (the attributes that follow the workspace in use)."""
        matrices, vectors, psi, kern, _, powers, temps, forecast, correction = _views(self.dims, self.consts,
                                                                                      self.state, work)[20:29]
        c, predicted, z, std, f, v, areas, *_ = vectors
        return dict(work=work, matrices=matrices, vectors=vectors, psi=psi, kern=kern, powers=powers, temps=temps,
                    forecast=forecast, correction=correction, gamma=matrices[0], hess=matrices[1], c=c,
                    predicted=predicted, z=z, std=std, f=f, v=v, areas=areas)

    def update(self, p_fill: int, power_w: float, t_fill: int, t_ahead_k: float, area_m2: float, observe: bool,
               since: int, on_first: bool, to_end: int, t_base_k: float, learned: bool, blind: int) -> int:
        """:func:`update_into` on this kernel's arrays (its parameters); the status: 0 ``v`` solves the
        QP (no bound active; ``plan`` is its solution), 1 a bound is active or the Hessian is not
        positive definite, 2 a prediction is not finite. Pass the types of the first call (int, float,
        bool as annotated) every time. Discards a preparation."""
        self.prepared = False
        return self._update.call(self.dims, self.consts, self.state, self.work, p_fill, power_w, t_fill, t_ahead_k,
                                 area_m2, observe, since, on_first, to_end, t_base_k, learned, blind)

    def prepare(self, p_fill: int, power_w: float, t_fill: int, t_ahead_k: float, since: int, on_first: bool,
                to_end: int, t_base_k: float, learned: bool, blind: int) -> bool:
        """:func:`prepare_into` in the spare workspace, for a next state with these arguments of
        :meth:`update` and T ahead near ``t_ahead_k`` [K]; the state and the workspace in use are not
        changed. True if the prepared step exists (finite prediction, positive definite Hessian), and
        :meth:`feedback` may then be called for that state."""
        spare = self._workspaces[1]
        status = self._prepare.call(self.dims, self.consts, self.state, self._scratch, spare["work"], p_fill, power_w,
                                    t_fill, t_ahead_k, since, on_first, to_end, t_base_k, learned, blind)
        self.prepared = status != 2 and not math.isnan(spare["v"][0])
        return self.prepared

    def feedback(self, p_fill: int, power_w: float, t_fill: int, t_ahead_k: float, area_m2: float, observe: bool,
                 since: int, on_first: bool, to_end: int, t_base_k: float, blind: int) -> int:
        """:func:`feedback_into` for the state :meth:`prepare` prepared (the caller checks that the
        arguments are those it prepared for); on success the prepared workspace becomes the one in use.
        The status of :meth:`update`, or −1 (nothing changed) if the measured T ahead is too far from
        the forecast for the prepared series: call :meth:`update` then."""
        if not self.prepared:
            raise RuntimeError("feedback without a preparation")
        self.prepared = False
        spare = self._workspaces[1]
        status = self._feedback.call(self.dims, self.consts, self.state, spare["work"], p_fill, power_w, t_fill,
                                     t_ahead_k, area_m2, observe, since, on_first, to_end, t_base_k, blind)
        if status >= 0:
            self._workspaces = self._workspaces[::-1]
            self.__dict__.update(spare)
        return status


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _linearised_qp(powers, temps, kern, log_output, intercept, b, q, cc, d, e, gp, gp_points, var_f, n_variance,
                   correction, disturbance, qp_terms, p_now, moves, blind, psi, vectors, matrices,
                   moments):  # pragma: no cover
    """Prediction, Jacobian and unconstrained QP step (module docstring) from the regressors and the
    kernel values ``kern`` = k(ψ_m, ψ_a), shape (H, N), into :class:`Kernel`'s ``vectors`` and
    ``matrices``; its status (:meth:`Kernel.update`)."""
    n_p, n_t, n_x = b.size, cc.size, e.size
    h = powers.size - n_p
    sp, scale = qp_terms[0], qp_terms[1]
    # rows by index, not by unpacking: an unpacked row's layout is unknown to the compiler (no vector code)
    c, predicted, std, f, v = vectors[0], vectors[1], vectors[3], vectors[4], vectors[5]
    areas, gp_slope, inv_diag, slopes, jac_u = vectors[6], vectors[7], vectors[8], vectors[9], vectors[10]
    gamma, hess, chol = matrices[0], matrices[1], matrices[2]
    finite = _prediction(powers, temps, kern, log_output, intercept, b, q, cc, d, e, gp, gp_points, var_f, n_variance,
                         correction, disturbance, psi, vectors, h, moments)
    gamma[:] = 0.0
    u = powers[n_p:]
    for row in range(h):
        slope = slopes[row]
        du = 0.0
        for col in range(max(0, row + 1 - n_p), row + 1):
            lag = row - col
            dz = b[lag] + 2.0 * q[lag] * u[col] + gp_slope[row]
            if lag < n_x:
                dz += e[lag] * temps[n_t - 1 + row - min(lag, n_t - 1)]
            jac = slope * dz
            du += jac * u[col]
            gamma[row, col] = jac * (scale / sp)
        jac_u[row] = du
        c[row] = (predicted[row] - du - sp) / sp
    status = 0 if finite else 2
    _gradient(gamma, c, qp_terms, p_now, blind, n_p, f)
    if not _factor(gamma, moves, qp_terms, blind, n_p, hess, chol, inv_diag):
        v[:] = np.nan
        areas[:] = np.nan
        return max(status, 1)
    return max(status, _step(gamma, c, chol, inv_diag, qp_terms, blind, n_p, predicted, std, u, f, v, areas))


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _prediction(powers, temps, kern, log_output, intercept, b, q, cc, d, e, gp, gp_points, var_f, n_variance,
                correction, disturbance, psi, vectors, gp_rows, moments):  # pragma: no cover (compiled)
    """x̂ at ū (into ``vectors``: z, x̂, std, the GP's mean-power slope and ``x'(z)``); the GP's kernel
    sums and the variance (of the first ``n_variance`` rows) from ``kern`` for the first ``gp_rows``
    rows, from the prepared ``moments`` beyond (:func:`feedback_into`). True if every x̂ is finite."""
    n_p, n_t, n_tq, n_x = b.size, cc.size, d.size, e.size
    h = powers.size - n_p
    n_gp = kern.shape[1]
    beta, moment_weights = gp_points[4], gp_points[5]
    predicted, z, std, gp_slope, slopes = vectors[1], vectors[2], vectors[3], vectors[7], vectors[9]
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
            w0 = moments[row, _W0]
            eps = (psi[row, 0] - gp[0]) * gp[3] - w0
            power = math.exp(-2.0 * w0 * eps - eps * eps)
            for j in range(MOMENTS):
                quad += moments[row, _VARIANCE + j] * power
                power *= eps / (j + 1)
        std[row] = max(gp[6] - quad, 0.0) + gp[7]
    for row in range(h):
        last_p, last_t = n_p + row, n_t - 1 + row   # index of p[k+m] and of T[k+m−1]
        gp_mean, gp_moment = 0.0, 0.0               # r(ψ_m) and Σ_a k_a W_a2 β_a (its mean-power slope)
        if row < gp_rows:
            for a in range(n_gp):
                gp_mean += kern[row, a] * beta[a]
                gp_moment += kern[row, a] * moment_weights[a]
        else:                                       # the prepared sums, moved by ε in the scaled T input
            w0 = moments[row, _W0]
            eps = (psi[row, 0] - gp[0]) * gp[3] - w0
            power = math.exp(-w0 * eps - 0.5 * eps * eps)
            for j in range(MOMENTS):
                gp_mean += moments[row, _MEAN + j] * power
                gp_moment += moments[row, _SLOPE + j] * power
                power *= eps / (j + 1)
        w2 = (psi[row, 2] - gp[2]) * gp[5]
        gp_slope[row] = gp[5] * (gp_moment - w2 * gp_mean) / n_p    # ∂r/∂ū_n through the mean power
        zz = intercept + gp_mean
        for i in range(n_p):
            p = powers[last_p - i]
            zz += (b[i] + q[i] * p) * p
        for j in range(n_t):
            t = temps[last_t - j]
            zz += cc[j] * t
            if j < n_tq:
                zz += d[j] * t * t
        for i in range(n_x):
            zz += e[i] * powers[last_p - i] * temps[last_t - i]
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
def _gradient(gamma, c, qp_terms, p_now, blind, n_p, f):  # pragma: no cover (compiled)
    """The QP's gradient ``f = 2 Γᵀ W c − 2 r (p[k] / P) e₁`` over the tracked rows (Γ banded: n_p
    powers per row)."""
    f[:] = 0.0
    for m in range(blind, c.size):
        w = 2.0 * qp_terms[9 + m]
        for a in range(max(0, m + 1 - n_p), m + 1):
            f[a] += w * gamma[m, a] * c[m]
    f[0] -= 2.0 * qp_terms[2] * p_now / qp_terms[1]


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _factor(gamma, moves, qp_terms, blind, n_p, hess, chol, inv_diag):  # pragma: no cover (compiled)
    """The QP's Hessian ``2 Γᵀ W Γ + 2 r DᵀD`` over the tracked rows and its banded Cholesky factor
    ``L`` (``chol``) with ``1/L_jj`` in ``inv_diag``; False if the Hessian is not positive definite."""
    h = gamma.shape[0]
    hess[:] = moves                                 # + 2 Γᵀ W Γ over the tracked rows
    for m in range(blind, h):                       # Γ is banded (n_p powers per row), so is the Hessian:
        w, first = 2.0 * qp_terms[9 + m], max(0, m + 1 - n_p)   # square blocks (equal-length loops vectorise)
        for a in range(first, m + 1):
            wg = w * gamma[m, a]
            for b2 in range(first, m + 1):
                hess[a, b2] += wg * gamma[m, b2]
    band = max(n_p - 1, 1)                          # the moves' band is 1 (Kernel checks)
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
def _step(gamma, c, chol, inv_diag, qp_terms, blind, n_p, predicted, std, u, f, v, areas):  # pragma: no cover
    """The unconstrained optimum ``v = −Hessian⁻¹ f`` from the factor of :func:`_factor`, the areas
    x̂ at ``P v`` (linearised) and the status: 0 when no power bound and no (tightened) area bound of
    the tracked rows is active, else 1."""
    h, band = c.size, max(n_p - 1, 1)
    sp, scale = qp_terms[0], qp_terms[1]
    v_lo, v_hi, e_lo, e_hi, z_sigma = qp_terms[4], qp_terms[5], qp_terms[6], qp_terms[7], qp_terms[8]
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
        for col in range(max(0, row + 1 - n_p), row + 1):
            e += gamma[row, col] * v[col]
            dx += gamma[row, col] * (v[col] - u[col] / scale)
        areas[row] = predicted[row] + dx * sp
        e = e + c[row] if row >= blind else 0.0     # untracked rows: Γ and c are 0 in the QP
        tighten = z_sigma * std[row] / sp
        if e - tighten < e_lo or e + tighten > e_hi:
            status = 1
    return status
