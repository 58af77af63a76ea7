"""The preview MPC's hot path, compiled: prediction, Jacobian and unconstrained QP step.

:class:`controller_node.preview.PreviewMPC` calls :func:`linearise` once per update (two compiled
passes around numpy's vectorised ``exp`` of the GP kernel's exponents, into a :class:`Workspace`),
after :func:`push_history` and :func:`correction_into`. For the
planned powers ū (the previous plan, shifted) it evaluates, for m = 1..H (model of
:mod:`gp_trainer.narx`, rows indexed ``i = m − 1``)::

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
solution (the fast path, as :meth:`controller_node.preview_qp.PreviewQP.finish` decides); else
the caller hands Γ, c to :meth:`~controller_node.preview_qp.PreviewQP.finish`.

Why compiled: the same computation in numpy is ~60 array operations on (40, 150)-sized data.
Between FE steps or plant frames the controller's caches are cold, and each operation then costs
several µs of dispatch; so does each fresh allocation and each small BLAS call, hence the
workspace and the loops over Γ's triangular structure (``docs/controller.md``, "Speed"). The numpy formulation stays the
reference: ``tests/test_preview_kernel.py`` checks this kernel against the model's own
prediction (:meth:`gp_trainer.narx.NarxGPModel.predict_run`), its Jacobian against finite
differences, and the QP terms against :meth:`PreviewQP.hessian` / :meth:`PreviewQP.gradient`.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["Workspace", "correction_into", "linearise", "push_history"]

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
                temps):  # pragma: no cover (compiled)
    """The lagged powers and temperatures of the rows (into ``powers``, ``temps``), their GP inputs ψ
    (into ``psi``) and the SE kernel's exponents ``w·W_a − ‖W_a‖²/2 − ‖w‖²/2`` (into ``exponents``,
    shape (H, N))."""
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
        w0 = (psi[row, 0] - gp[0]) * gp[3]
        w1 = (psi[row, 1] - gp[1]) * gp[4]
        w2 = (psi[row, 2] - gp[2]) * gp[5]
        half_w = 0.5 * (w0 * w0 + w1 * w1 + w2 * w2)
        for a in range(n_gp):
            exponents[row, a] = w0 * gp_points[0, a] + w1 * gp_points[1, a] + w2 * gp_points[2, a] + gp_points[3, a] \
                - half_w


class Workspace:
    """The arrays one :func:`linearise` call fills, allocated once per controller (an update then
    allocates nothing: between plant steps every fresh allocation is a cache miss).

    Parameters
    ----------
    horizon : int
        ``H``.
    n_powers, n_temperatures : int
        ``n_p`` and ``n_T`` of the model.
    n_points : int
        ``N``, the residual GP's training points.

    Attributes
    ----------
    gamma, hess : numpy.ndarray, shape (H, H)
        Γ and the QP's Hessian.
    c, predicted, z, std, f, v, areas : numpy.ndarray, shape (H,)
        ``c``; x̂ at ū [m²]; ``z``; ``x'(z) sqrt(σ²_latent + σ_n²)`` for the first ``n_variance``
        rows, else 0 [m²]; the gradient; the unconstrained optimum (NaN if the Hessian is not
        positive definite); x̂ at the plan ``P v`` [m²] (linearised).
    psi : numpy.ndarray, shape (H, 3)
        The GP inputs ψ_{k+m−1} (T ahead [K], log1p(min(s, cap)), mean power [W]).
    """

    def __init__(self, horizon: int, n_powers: int, n_temperatures: int, n_points: int) -> None:
        h = horizon
        self.matrices = np.zeros((3, h, h))         # Γ, Hessian, Cholesky factor
        self.vectors = np.zeros((8, h))             # c, x̂, z, std, f, v, areas, ∂r/∂ψ₂
        self.gamma, self.hess, _ = self.matrices
        self.c, self.predicted, self.z, self.std, self.f, self.v, self.areas, _ = self.vectors
        self.psi = np.zeros((h, 3))
        self.kern = np.zeros((h, n_points))
        self.powers = np.zeros(n_powers + h)        # p[k−n_p+1 .. k], ū
        self.temps = np.zeros(n_temperatures + h - 1)   # T[k−n_T+1 .. k], T̂[k+1 .. k+H−1]


def linearise(p_hist, t_hist, forecast, plan, since, to_end, s_cap, log_output, coef, gp, gp_points, var_f,
              n_variance, correction, disturbance, qp_terms, moves, blind, work):
    """Prediction, Jacobian and unconstrained QP step at the shifted plan (module docstring).

    Two compiled passes around numpy's vectorised ``exp`` of the H × N kernel exponents (about
    4 µs; a compiled loop of scalar exponentials took about 30 µs).

    Parameters
    ----------
    p_hist : numpy.ndarray, shape (n_p,)
        ``p[k], p[k−1], …`` [W].
    t_hist : numpy.ndarray, shape (n_T,)
        ``T[k−n_T+1 .. k]`` [K].
    forecast : numpy.ndarray, shape (H,)
        ``T̂[k+1 .. k+H]`` [K].
    plan : numpy.ndarray, shape (H,)
        The previous plan ``p̄[k .. k+H−1]`` [W]; shifted here to ū = p̄[k+1 .. k+H] (last held).
    since : int
        States since the current track's first state.
    to_end : int
        States until the current track's last state, −1 if no turn is ahead in the plan.
    s_cap : float
        Cap of the steps-since-start input.
    log_output : bool
        ``x = exp(z)`` (else ``x = z``).
    coef : tuple of numpy.ndarray
        ``(c₀ as shape (1,), b, q, c, d, e)`` of the model.
    gp : numpy.ndarray, shape (8,)
        ``(μ₀, μ₁, μ₂, g₀, g₁, g₂, σ², σ_n²)`` of the residual GP (input mean, inverse scaled
        length-scales, prior and noise variance).
    gp_points : numpy.ndarray, shape (6, N)
        Per training point (columns): scaled input ``W_a`` (3 rows), ``−‖W_a‖²/2``, weight ``β_a``
        and ``W_a2 β_a``.
    var_f : numpy.ndarray, shape (N, N)
        ``σ_f L⁻¹`` (lower triangular) in target units.
    n_variance : int
        Rows whose latent variance is computed (the others are 0).
    correction : numpy.ndarray, shape (H,)
        Learned turnaround correction of x̂_m [m²].
    disturbance : float
        ``d̂`` [m²].
    qp_terms : numpy.ndarray, shape (H + 9,)
        ``(x_sp [m²], P [W], r, p[k] [W], v_l, v_u, e_l, e_u, z, W_1 .. W_H)``: set point, power
        scale, move weight, applied power, normalised power and area bounds, bound tightening in
        standard deviations, stage weights.
    moves : numpy.ndarray, shape (H, H)
        ``2 r DᵀD``.
    blind : int
        Leading rows not tracked (pool build-up): weight 0 in the Hessian and gradient (Γ and c
        are returned for all rows).
    work : Workspace
        Filled with the results (:class:`Workspace`), overwritten by the next call.

    Returns
    -------
    status : int
        0: ``v`` solves the QP (no bound active); 1: a bound is active or the Hessian is not
        positive definite; 2: a prediction is not finite.
    """
    _regressors(p_hist, t_hist, forecast, plan, since, to_end, s_cap, gp, gp_points, work.psi, work.kern,
                work.powers, work.temps)
    np.exp(work.kern, out=work.kern)
    return _linearised_qp(work.powers, work.temps, work.kern, log_output, coef, gp, gp_points, var_f, n_variance,
                          correction, disturbance, qp_terms, moves, blind, work.psi, work.vectors, work.matrices)


@njit(cache=True, nogil=True, fastmath=_REORDER)
def _linearised_qp(powers, temps, kern, log_output, coef, gp, gp_points, var_f, n_variance, correction,
                   disturbance, qp_terms, moves, blind, psi, vectors, matrices):  # pragma: no cover (compiled)
    """:func:`linearise` from the kernel values ``kern`` = k(ψ_m, ψ_a), shape (H, N), into the
    :class:`Workspace`'s ``vectors`` and ``matrices``."""
    intercept, b, q, cc, d, e = coef
    n_p, n_t, n_tq, n_x = b.size, cc.size, d.size, e.size
    h = powers.size - n_p
    sp, scale, r, p_now = qp_terms[0], qp_terms[1], qp_terms[2], qp_terms[3]
    v_lo, v_hi, e_lo, e_hi, z_sigma = qp_terms[4], qp_terms[5], qp_terms[6], qp_terms[7], qp_terms[8]
    n_gp = kern.shape[1]
    beta, moment_weights = gp_points[4], gp_points[5]
    c, predicted, z, std, f, v, areas, gp_slope = vectors
    gamma, hess, chol = matrices
    std[:] = 0.0
    for row in range(n_variance):                   # σ² − ‖σ_f L⁻¹ k‖² of the first rows
        quad = 0.0
        for a in range(n_gp):
            projected = 0.0
            for b2 in range(a + 1):
                projected += var_f[a, b2] * kern[row, b2]
            quad += projected * projected
        std[row] = max(gp[6] - quad, 0.0) + gp[7]
    for row in range(h):
        last_p, last_t = n_p + row, n_t - 1 + row   # index of p[k+m] and of T[k+m−1]
        gp_mean, gp_moment = 0.0, 0.0               # r(ψ_m) and Σ_a k_a W_a2 β_a (its mean-power slope)
        for a in range(n_gp):
            gp_mean += kern[row, a] * beta[a]
            gp_moment += kern[row, a] * moment_weights[a]
        w2 = (psi[row, 2] - gp[2]) * gp[5]
        gp_slope[row] = gp[5] * (gp_moment - w2 * gp_mean) / n_p    # ∂r/∂ū_n through the mean power
        zz = intercept[0] + gp_mean
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
    gamma[:] = 0.0
    u = powers[n_p:]
    for row in range(h):
        x = math.exp(z[row]) if log_output else z[row]
        slope = x if log_output else 1.0
        std[row] = slope * math.sqrt(std[row]) if row < n_variance else 0.0
        predicted[row] = x + disturbance + correction[row]
        du = 0.0
        for col in range(max(0, row + 1 - n_p), row + 1):
            lag = row - col
            dz = b[lag] + 2.0 * q[lag] * u[col] + gp_slope[row]
            if lag < n_x:
                dz += e[lag] * temps[n_t - 1 + row - min(lag, n_t - 1)]
            jac = slope * dz
            du += jac * u[col]
            gamma[row, col] = jac * (scale / sp)
        c[row] = (predicted[row] - du - sp) / sp
    finite = True
    for row in range(h):
        finite = finite and math.isfinite(predicted[row])
    hess[:] = moves                                 # + 2 Γᵀ W Γ over the tracked rows (Γ lower triangular)
    f[:] = 0.0
    for m in range(blind, h):
        w = 2.0 * qp_terms[9 + m]
        for a in range(m + 1):
            wg = w * gamma[m, a]
            f[a] += wg * c[m]
            for b2 in range(m + 1):
                hess[a, b2] += wg * gamma[m, b2]
    f[0] -= 2.0 * r * p_now / scale
    status = 0 if finite else 2
    for i in range(h):                              # Cholesky, Hessian = L Lᵀ
        for j in range(i + 1):
            acc = hess[i, j]
            for k in range(j):
                acc -= chol[i, k] * chol[j, k]
            if i == j:
                if not acc > 0.0:
                    v[:] = np.nan
                    areas[:] = np.nan
                    return max(status, 1)
                chol[i, i] = math.sqrt(acc)
            else:
                chol[i, j] = acc / chol[j, j]
    for i in range(h):                              # L y = −f
        acc = -f[i]
        for k in range(i):
            acc -= chol[i, k] * v[k]
        v[i] = acc / chol[i, i]
    for i in range(h - 1, -1, -1):                  # Lᵀ v = y, by columns of Lᵀ
        v[i] /= chol[i, i]
        for k in range(i):
            v[k] -= chol[i, k] * v[i]
        if not (v_lo <= v[i] <= v_hi):
            status = max(status, 1)
    for row in range(h):                            # e = Γ v + c of the tracked rows, x̂ at P v
        e, dx = 0.0, 0.0
        for col in range(row + 1):
            e += gamma[row, col] * v[col]
            dx += gamma[row, col] * (v[col] - u[col] / scale)
        areas[row] = predicted[row] + dx * sp
        e = e + c[row] if row >= blind else 0.0     # untracked rows: Γ and c are 0 in the QP
        tighten = z_sigma * std[row] / sp
        if e - tighten < e_lo or e + tighten > e_hi:
            status = max(status, 1)
    return status
