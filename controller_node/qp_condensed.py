"""The one-step MPC's condensed QP, solved in one compiled call when only power bounds bind.

Condensing the prediction ``e[i+1] = a e[i] + a⁻ e[i−1] + β u[i] + g`` (:mod:`controller_node.qp`)
gives ``e[1..H] = c + Γ u`` with ::

    Γ[j, i] = β h[j−i]  (i <= j, rows j = 0..H−1 for e[j+1]),
    h[0] = 1, h[1] = a, h[n] = a h[n−1] + a⁻ h[n−2]   (impulse response),
    c       = the free response from e[0], e[−1] with the constant input g,

so the QP in ``u`` has Hessian ``2(ΓᵀWΓ) + R_u`` (``W = diag(Q, …, Q, Q_f)``) and gradient
``2ΓᵀWc`` (``− 2R u_prev`` on ``u[0]`` for the move penalty). :func:`condense_into` forms them,
then solves the QP with the power bounds only (``u_l <= u <= u_u``) by a primal active-set method
(Nocedal & Wright, *Numerical Optimization*, Algorithm 16.3) started from the unconstrained optimum
clipped into the bounds: each iteration solves the equality-constrained problem on the free
inputs by Cholesky, steps to the first bound it meets, or frees the bound whose multiplier has the
wrong sign. When that solution also keeps the rate bounds and the soft area bounds with zero slack,
it is the QP's solution (the QP is strictly convex and its feasible set lies inside the box); else
:class:`controller_node.qp_daqp.DaqpBackend` hands the terms to DAQP.

Why compiled: the numpy formulation is about twenty small calls, and DAQP's one more, each costing
microseconds of dispatch on the cold caches a controller has between plant frames
(``docs/controller.md``, "Speed of the one-step update"). ``tests/test_qp_condensed.py`` checks
the terms against numpy and the solutions against DAQP; ``tests/test_controller_mpc.py`` the
backend against OSQP and cvxpy.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["condense_into"]

MULTIPLIER_TOL = 1e-12
"""A bound is freed only if its multiplier has the wrong sign by more than this times (1 + the
gradient's largest entry): rounding must not make the active set cycle."""


@njit(cache=True, nogil=True)
def _solve_free(hess, grad, x, state, factor, rhs, y):  # pragma: no cover (compiled)
    """Minimise over the free inputs (``state == 0``) with the others fixed at ``x``: their optimum into
    ``y`` (free entries; the rest copied from ``x``). False if the free block is not positive definite."""
    h = x.size
    free = np.empty(h, dtype=np.int64)
    nf = 0
    for i in range(h):
        y[i] = x[i]
        if state[i] == 0:
            free[nf] = i
            nf += 1
    for p in range(nf):
        i = free[p]
        s = -grad[i]
        for j in range(h):
            if state[j] != 0:
                s -= hess[i, j] * x[j]
        rhs[p] = s
        for q in range(p + 1):
            factor[p, q] = hess[i, free[q]]
    for j in range(nf):                     # Cholesky of the free block, in place (lower triangle)
        d = factor[j, j]
        for k in range(j):
            d -= factor[j, k] * factor[j, k]
        if not d > 0.0:
            return False
        d = math.sqrt(d)
        factor[j, j] = d
        for i in range(j + 1, nf):
            s = factor[i, j]
            for k in range(j):
                s -= factor[i, k] * factor[j, k]
            factor[i, j] = s / d
    for i in range(nf):                     # L z = rhs, then Lᵀ y_F = z
        s = rhs[i]
        for k in range(i):
            s -= factor[i, k] * rhs[k]
        rhs[i] = s / factor[i, i]
    for i in range(nf - 1, -1, -1):
        s = rhs[i]
        for k in range(i + 1, nf):
            s -= factor[k, i] * rhs[k]
        rhs[i] = s / factor[i, i]
    for p in range(nf):
        y[free[p]] = rhs[p]
    return True


@njit(cache=True, nogil=True)
def _box_qp(hess, grad, lo, hi, x):  # pragma: no cover (compiled)
    """``min ½ xᵀ H x + gradᵀ x`` subject to ``lo <= x <= hi`` by the primal active-set method, from
    ``x`` (overwritten by the solution). Its iterations, or −1 if it did not finish (a block not
    positive definite, or more than 4H + 10 iterations)."""
    h = x.size
    state = np.zeros(h, dtype=np.int64)     # −1 at the lower bound, +1 at the upper, 0 free
    for i in range(h):
        if not x[i] > lo:
            x[i], state[i] = lo, -1
        elif not x[i] < hi:
            x[i], state[i] = hi, 1
    factor, rhs, y = np.empty((h, h)), np.empty(h), np.empty(h)
    scale = 0.0
    for i in range(h):
        scale = max(scale, abs(grad[i]))
    tol = MULTIPLIER_TOL * (1.0 + scale)
    for iteration in range(4 * h + 10):
        if not _solve_free(hess, grad, x, state, factor, rhs, y):
            return -1
        step, blocking, side = 1.0, -1, 0      # the longest step towards y that keeps the bounds
        for i in range(h):
            p = y[i] - x[i]
            if state[i] != 0 or p == 0.0:
                continue
            limit = max((lo - x[i]) / p if p < 0.0 else (hi - x[i]) / p, 0.0)
            if limit < step:
                step, blocking, side = limit, i, -1 if p < 0.0 else 1
        for i in range(h):
            if state[i] == 0:                  # (rounding must not carry an input past a bound)
                x[i] = min(max(x[i] + step * (y[i] - x[i]), lo), hi)
        if blocking >= 0:                      # a bound met on the way: it joins the working set
            x[blocking], state[blocking] = lo if side == -1 else hi, side
            continue
        worst, release = tol, -1               # optimal on this working set: check the multipliers
        for i in range(h):
            if state[i] == 0:
                continue
            r = grad[i]
            for j in range(h):
                r += hess[i, j] * x[j]
            wrong = -r if state[i] == -1 else r    # at the lower bound r >= 0 is right, at the upper r <= 0
            if wrong > worst:
                worst, release = wrong, i
        if release < 0:
            return iteration + 1
        state[release] = 0
    return -1


@njit(cache=True, nogil=True)
def condense_into(a, a_prev, beta, g, e0, e_prev, u_prev, weights, r_u, move_r, bounds, gamma, c, hess, grad,
                  u, e):  # pragma: no cover (compiled)
    """Form the condensed QP of one step and solve it with the power bounds only.

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
        Out: the optimum within the power bounds and its predicted errors ``c + Γ u``, shape (H,).

    Returns
    -------
    int
        The active-set iterations (0: the unconstrained optimum keeps the power bounds) when ``u``
        also keeps the rate and area bounds, and so solves the QP; −1 when it does not (or the
        active set did not finish): the QP needs DAQP.
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
    state = np.zeros(h, dtype=np.int64)
    if not _solve_free(hess, grad, u, state, np.empty((h, h)), np.empty(h), u):   # u* = −H⁻¹ grad
        return -1
    iterations = 0
    for i in range(h):
        if not bounds[0] <= u[i] <= bounds[1]:
            iterations = _box_qp(hess, grad, bounds[0], bounds[1], u)
            if iterations < 0:
                return -1
            break
    solved = True
    previous = u_prev
    for i in range(h):
        s = c[i]
        for k in range(i + 1):
            s += gamma[i, k] * u[k]
        e[i] = s
        move = u[i] - previous
        previous = u[i]
        if not (bounds[2] <= move <= bounds[3] and bounds[4] <= s <= bounds[5]):
            solved = False
    return iterations if solved else -1
