"""Condensed dense backend of the MPC QP (:mod:`controller_node.qp`) solved by DAQP.

Condensing the prediction ``e[i+1] = a e[i] + a⁻ e[i−1] + β u[i] + g`` gives
``e[1..H] = c + Γ u`` with ::

    Γ[j, i] = β h[j−i]  (i <= j, 0-based rows j = 0..H−1 for e[j+1]),
    h[0] = 1, h[1] = a, h[n] = a h[n−1] + a⁻ h[n−2]   (impulse response; a^n when a⁻ = 0),
    c       = the free response from e[0], e[−1] with the constant input g,

so the QP in ``u`` has Hessian ``2(ΓᵀWΓ + R_u)`` (``W = diag(Q, …, Q, Q_f)``,
``R_u = R·I`` or ``R·DᵀD`` for moves) and gradient ``2ΓᵀWc`` (``− 2R u_prev`` on
``u[0]`` for moves).  DAQP (dual active set, exact) solves it in two phases:

1. without the area rows and slacks (H variables, power bounds as simple bounds,
   rate rows) — a few µs;
2. only if the resulting ``e`` leaves ``[e_l, e_u]``: the full problem with slacks
   ``s`` (2H variables).  When phase 1 satisfies the area bounds, ``s = 0`` is
   optimal for the full problem, so both phases return the same optimum as the
   sparse OSQP backend and the cvxpy reference.
"""

from __future__ import annotations

import daqp
import numpy as np

from .qp import QPData, QPSolution, qp_constants
from .settings import ControllerSettings

__all__ = ["DaqpBackend"]

_INF = 1e30  # DAQP's infinity


def _condense(h: int, data: QPData) -> tuple[np.ndarray, np.ndarray]:
    """``β h[0..H−1]`` (scaled impulse response) and the free response ``c``, both shape (H,).

    Plain float recursions: 20 steps cost ~3 µs, less than building them with array calls.
    """
    a, a_prev, g = data.a, data.a_prev, data.g
    impulse = [data.beta] * h
    free = [0.0] * h
    older, old = data.e_prev, data.e0
    for n in range(h):
        if n == 1:
            impulse[1] = a * impulse[0]
        elif n >= 2:
            impulse[n] = a * impulse[n - 1] + a_prev * impulse[n - 2]
        older, old = old, a * old + a_prev * older + g
        free[n] = old
    return np.array(impulse), np.array(free)


class DaqpBackend:
    """Exact dense solver of the MPC QP (condensed, DAQP), fixed settings.

    Parameters
    ----------
    settings : ControllerSettings
        Weights, horizon, bounds (``settings.mpc``).
    """

    def __init__(self, settings: ControllerSettings) -> None:
        m = settings.mpc
        h = self._h = m.horizon
        k = qp_constants(settings)
        self._e_lo, self._e_hi = k["e_lo"], k["e_hi"]
        self._du = (k["du_lo"], k["du_hi"])
        self._move = m.input_penalty == "move"
        self._r = m.r
        rows = np.arange(h)[:, None]
        cols = np.arange(h)[None, :]
        self._lag = np.where(cols <= rows, rows - cols, 0)
        self._lower = (cols <= rows).astype(float)
        self._w = np.full(h, m.q)
        self._w[-1] = m.q_f
        diff = np.eye(h) - np.eye(h, k=-1)  # rows: u[i] − u[i−1] (u[−1] in the bounds)
        self._r_u = 2.0 * m.r * (diff.T @ diff if self._move else np.eye(h))
        self._rate = np.ascontiguousarray(diff)
        # phase 1: simple bounds on u (h), rate rows (h)
        self._bu1 = np.concatenate([np.zeros(h), np.full(h, self._du[1])])
        self._bl1 = np.concatenate([np.zeros(h), np.full(h, self._du[0])])
        self._sense1 = np.zeros(2 * h, dtype=np.int32)
        # phase 2: variables (u, s); simple bounds u (h), s (h); rows: rate, e + s >= e_l, e − s <= e_u
        self._a2 = np.zeros((3 * h, 2 * h))
        self._a2[:h, :h] = diff
        self._a2[h : 2 * h, h:] = np.eye(h)
        self._a2[2 * h :, h:] = -np.eye(h)
        self._h2 = np.zeros((2 * h, 2 * h))
        self._h2[h:, h:] = 2.0 * m.slack_quadratic * np.eye(h)
        self._f2 = np.concatenate([np.zeros(h), np.full(h, m.slack_linear)])
        self._bu2 = np.concatenate([np.zeros(h), np.full(h, _INF), np.full(h, self._du[1]), np.full(h, _INF),
                                    np.zeros(h)])
        self._bl2 = np.concatenate([np.zeros(h), np.zeros(h), np.full(h, self._du[0]), np.zeros(h), np.full(h, -_INF)])
        self._sense2 = np.zeros(5 * h, dtype=np.int32)

    def solve(self, data: QPData) -> QPSolution:
        """Condense one step's QP and solve it (phase 2 only if the area bounds bind).

        Parameters
        ----------
        data : QPData
            Normalised step data.

        Returns
        -------
        QPSolution
            ``u`` shape (H,), ``e`` shape (H,); ``iterations`` sums both phases.
        """
        h = self._h
        gamma, c = _condense(h, data)
        gamma = gamma[self._lag] * self._lower
        wg = self._w[:, None] * gamma
        hess = 2.0 * (gamma.T @ wg) + self._r_u
        grad = 2.0 * (wg.T @ c)
        if self._move:
            grad[0] -= 2.0 * self._r * data.u_prev
        bu, bl = self._bu1, self._bl1
        bu[:h] = data.u_hi
        bl[:h] = data.u_lo
        bu[h] = data.u_prev + self._du[1]
        bl[h] = data.u_prev + self._du[0]
        u, _, flag, info = daqp.solve(hess, grad, self._rate, bu, bl, self._sense1)
        if flag != 1:
            return QPSolution(f"daqp_exitflag_{flag}", np.full(h, np.nan), np.full(h, np.nan), int(info["iterations"]))
        e = c + gamma @ u
        if e.min() >= self._e_lo and e.max() <= self._e_hi:
            return QPSolution("solved", u, e, int(info["iterations"]))
        iterations = int(info["iterations"])

        self._h2[:h, :h] = hess
        self._f2[:h] = grad
        self._a2[h : 2 * h, :h] = gamma
        self._a2[2 * h :, :h] = gamma
        bu, bl = self._bu2, self._bl2
        bu[:h] = data.u_hi
        bl[:h] = data.u_lo
        bu[2 * h] = data.u_prev + self._du[1]
        bl[2 * h] = data.u_prev + self._du[0]
        bl[3 * h : 4 * h] = self._e_lo - c
        bu[4 * h :] = self._e_hi - c
        x, _, flag, info = daqp.solve(self._h2, self._f2, self._a2, bu, bl, self._sense2)
        iterations += int(info["iterations"])
        if flag != 1:
            return QPSolution(f"daqp_exitflag_{flag}", np.full(h, np.nan), np.full(h, np.nan), iterations)
        u = x[:h]
        return QPSolution("solved", u, c + gamma @ u, iterations)
