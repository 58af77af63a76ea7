"""Condensed dense backend of the MPC QP (:mod:`controller_node.qp`) solved by DAQP.

The condensed terms ``e[1..H] = c + Γ u``, Hessian ``2(ΓᵀWΓ + R_u)`` and gradient ``2ΓᵀWc`` come
from :func:`controller_node.qp_condensed.condense_into`, with the optimum within the power bounds
(an active set in the same compiled call). When that optimum also keeps the rate and area bounds it
is the solution and DAQP is not called (``iterations`` are then the active set's). Else DAQP (dual
active set, exact) solves the QP in two phases:

1. without the area rows and slacks (H variables, power bounds as simple bounds,
   rate rows);
2. only if the resulting ``e`` leaves ``[e_l, e_u]``: the full problem with slacks
   ``s`` (2H variables).  When phase 1 satisfies the area bounds, ``s = 0`` is
   optimal for the full problem, so both phases return the same optimum as the
   sparse OSQP backend and the cvxpy reference.
"""

from __future__ import annotations

import daqp
import numpy as np

from gp_model.compiled import BoundOnFirstCall, compile_lock

from .qp import QPData, QPSolution, qp_constants
from .qp_condensed import condense_into
from .settings import ControllerSettings

__all__ = ["DaqpBackend"]

_INF = 1e30  # DAQP's infinity


class DaqpBackend:
    """Exact dense solver of the MPC QP (condensed, DAQP), fixed settings (a :class:`~controller_node.qp.QPBackend`)."""

    def __init__(self, settings: ControllerSettings) -> None:
        m = settings.mpc
        h = self._h = m.horizon
        k = qp_constants(settings)
        self._e_lo, self._e_hi = k["e_lo"], k["e_hi"]
        self._du = (k["du_lo"], k["du_hi"])
        self._move = m.input_penalty == "move"
        self._r = m.r
        self._gamma, self._hess = np.zeros((h, h)), np.zeros((h, h))
        self._c, self._grad = np.zeros(h), np.zeros(h)
        self._bounds = np.array([0.0, 0.0, *self._du, self._e_lo, self._e_hi])
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
        # compiled (or loaded from numba's cache) and bound to its argument types now, not at a run's first state
        self._condense = BoundOnFirstCall(condense_into)
        with compile_lock(__file__):        # one process compiles on a fresh install, the others load
            self.solve(QPData(a=0.5, beta=1.0, g=0.0, e0=0.0, u_lo=-1.0, u_hi=1.0, u_prev=0.0, p_ref_w=0.0))

    def solve(self, data: QPData) -> QPSolution:
        """Condense one step's QP and solve it (:meth:`~controller_node.qp.QPBackend.solve`; DAQP only if
        a rate or area bound binds, phase 2 only if an area bound does); ``iterations``: the compiled
        active set's when it solves the QP (0: the unconstrained optimum), else the sum of DAQP's two phases."""
        h = self._h
        gamma, c, hess, grad, bounds = self._gamma, self._c, self._hess, self._grad, self._bounds
        bounds[0], bounds[1] = data.u_lo, data.u_hi
        u, e = np.empty(h), np.empty(h)
        iterations = self._condense.call(data.a, data.a_prev, data.beta, data.g, data.e0, data.e_prev, data.u_prev,
                                         self._w, self._r_u, self._r if self._move else 0.0, bounds, gamma, c, hess,
                                         grad, u, e)
        if iterations >= 0:
            return QPSolution("solved", u, e, iterations)
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
