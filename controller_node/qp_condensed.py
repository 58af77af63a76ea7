"""The one-step MPC's condensed QP and its unconstrained optimum, compiled (one call per update).

Condensing the prediction ``e[i+1] = a e[i] + a⁻ e[i−1] + β u[i] + g`` (:mod:`controller_node.qp`)
gives ``e[1..H] = c + Γ u`` with ::

    Γ[j, i] = β h[j−i]  (i <= j, rows j = 0..H−1 for e[j+1]),
    h[0] = 1, h[1] = a, h[n] = a h[n−1] + a⁻ h[n−2]   (impulse response),
    c       = the free response from e[0], e[−1] with the constant input g,

so the QP in ``u`` has Hessian ``2(ΓᵀWΓ) + R_u`` (``W = diag(Q, …, Q, Q_f)``) and gradient
``2ΓᵀWc`` (``− 2R u_prev`` on ``u[0]`` for the move penalty). :func:`condense_into` forms them and
the unconstrained optimum ``u* = −Hessian⁻¹ gradient`` (Cholesky). When ``u*`` keeps every bound
(power, rate and the soft area bounds with zero slack) it is the QP's solution, since the QP is
strictly convex; else :class:`controller_node.qp_daqp.DaqpBackend` hands the terms to DAQP.

Why compiled: the numpy formulation is about twenty small calls, each costing microseconds of
dispatch on the cold caches a controller has between plant frames (``docs/realtime.md``).
``tests/test_controller_mpc.py`` checks the result against the OSQP backend and the cvxpy reference.
"""

from __future__ import annotations

import math

from numba import njit

__all__ = ["condense_into"]


@njit(cache=True, nogil=True)
def condense_into(a, a_prev, beta, g, e0, e_prev, u_prev, weights, r_u, move_r, bounds, gamma, c, hess, grad,
                  u, e):  # pragma: no cover (compiled)
    """Form the condensed QP of one step and try its unconstrained optimum.

    Parameters
    ----------
    a, a_prev, beta, g : float
        Prediction model (normalised, :class:`controller_node.qp.QPData`).
    e0, e_prev : float
        ``e[0]``, ``e[−1]``.
    u_prev : float
        ``u[−1]`` (rate bound and move penalty).
    weights : numpy.ndarray
        ``diag(W)``, shape (H,).
    r_u : numpy.ndarray
        Input weight of the Hessian (``2R·I`` or ``2R·DᵀD``), shape (H, H).
    move_r : float
        ``R`` for the move penalty's ``u[−1]`` term, 0 for the steady-state penalty.
    bounds : numpy.ndarray
        ``(u_lo, u_hi, du_lo, du_hi, e_lo, e_hi)``, shape (6,).
    gamma, hess : numpy.ndarray
        Out: Γ and the Hessian, shape (H, H).
    c, grad : numpy.ndarray
        Out: free response and gradient, shape (H,).
    u, e : numpy.ndarray
        Out: the unconstrained optimum and its predicted errors ``c + Γ u``, shape (H,).

    Returns
    -------
    bool
        True when ``u`` keeps every bound (then it solves the QP).
    """
    h = c.size
    impulse_prev, impulse = 0.0, beta
    older, old = e_prev, e0
    for n in range(h):
        if n == 1:
            impulse_prev, impulse = impulse, a * impulse
        elif n >= 2:
            impulse_prev, impulse = impulse, a * impulse + a_prev * impulse_prev
        for i in range(h - n):
            gamma[i + n, i] = impulse
            if n > 0:
                gamma[i, i + n] = 0.0
        older, old = old, a * old + a_prev * older + g
        c[n] = old
    for i in range(h):
        s = 0.0
        for j in range(i, h):
            s += weights[j] * gamma[j, i] * c[j]
        grad[i] = 2.0 * s
        for k in range(i, h):
            s = 0.0
            for j in range(k, h):
                s += weights[j] * gamma[j, i] * gamma[j, k]
            hess[i, k] = 2.0 * s + r_u[i, k]
            hess[k, i] = hess[i, k]
    grad[0] -= 2.0 * move_r * u_prev
    # u* = −H⁻¹ grad by the Cholesky factor H = L Lᵀ
    lower = hess.copy()
    for j in range(h):
        d = lower[j, j]
        for k in range(j):
            d -= lower[j, k] * lower[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        lower[j, j] = d
        for i in range(j + 1, h):
            s = lower[i, j]
            for k in range(j):
                s -= lower[i, k] * lower[j, k]
            lower[i, j] = s / d
    for i in range(h):                      # L y = −grad
        s = -grad[i]
        for k in range(i):
            s -= lower[i, k] * u[k]
        u[i] = s / lower[i, i]
    for i in range(h - 1, -1, -1):          # Lᵀ u = y
        s = u[i]
        for k in range(i + 1, h):
            s -= lower[k, i] * u[k]
        u[i] = s / lower[i, i]
    feasible = True
    previous = u_prev
    for i in range(h):
        s = c[i]
        for k in range(i + 1):
            s += gamma[i, k] * u[k]
        e[i] = s
        move = u[i] - previous
        previous = u[i]
        if not (bounds[0] <= u[i] <= bounds[1] and bounds[2] <= move <= bounds[3] and bounds[4] <= s <= bounds[5]):
            feasible = False
    return feasible
