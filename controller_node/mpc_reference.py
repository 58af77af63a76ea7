"""Readable cvxpy formulation (DPP parameters) of the same MPC QP as :mod:`controller_node.mpc`.

The QP is written exactly as documented in :mod:`controller_node.qp`; only the
per-step numbers are ``cvxpy.Parameter`` objects, so cvxpy compiles the problem
once.  It is solved with Clarabel (interior point, independent of OSQP and DAQP)
at tight tolerances (1e-11): with active slacks the cost is ~1e4 and the plan's
tail is nearly flat in the cost, so default tolerances move the plan by ~1 W.  Use it as
the reference (tests, benchmark) or via ``MPCSettings(solver="cvxpy")``;
cvxpy's per-solve overhead makes it far slower than the DAQP backend
(``benchmarks/bench_controller.py`` prints the ratio), too slow for the loop.
"""

from __future__ import annotations

import cvxpy as cp
import numpy as np

from .qp import QPData, QPSolution, qp_constants
from .settings import ControllerSettings

__all__ = ["CvxpyBackend"]


class CvxpyBackend:
    """cvxpy/Clarabel solver of the MPC QP (a :class:`~controller_node.qp.QPBackend`)."""

    def __init__(self, settings: ControllerSettings) -> None:
        m = settings.mpc
        h = m.horizon
        k = qp_constants(settings)
        self.a = cp.Parameter(name="a")
        self.a_prev = cp.Parameter(name="a_prev")
        self.e_prev = cp.Parameter(name="e_prev")
        self.beta = cp.Parameter(name="beta")
        self.g = cp.Parameter(name="g")
        self.e0 = cp.Parameter(name="e0")
        self.u_lo = cp.Parameter(name="u_lo")
        self.u_hi = cp.Parameter(name="u_hi")
        self.u_prev = cp.Parameter(name="u_prev")

        e = cp.Variable(h + 2, name="e")  # e[-1..H]
        u = cp.Variable(h, name="u")  # u[0..H-1]
        s = cp.Variable(h, nonneg=True, name="slack")  # s[1..H]
        u_ext = cp.hstack([cp.reshape(self.u_prev, (1,), order="F"), u])  # u[-1..H-1]
        moves = u_ext[1:] - u_ext[:-1]
        penalised = moves if m.input_penalty == "move" else u
        cost = (
            m.q * cp.sum_squares(e[2 : h + 1])
            + m.q_f * cp.square(e[h + 1])
            + m.r * cp.sum_squares(penalised)
            + m.slack_linear * cp.sum(s)
            + m.slack_quadratic * cp.sum_squares(s)
        )
        constraints = [
            e[0] == self.e_prev,
            e[1] == self.e0,
            e[2:] == self.a * e[1:-1] + self.a_prev * e[:-2] + self.beta * u + self.g,
            e[2:] >= k["e_lo"] - s,
            e[2:] <= k["e_hi"] + s,
            u >= self.u_lo,
            u <= self.u_hi,
            moves >= k["du_lo"],
            moves <= k["du_hi"],
        ]
        self.problem = cp.Problem(cp.Minimize(cost), constraints)
        if not self.problem.is_dpp():  # pragma: no cover - guards edits of the formulation
            raise RuntimeError("MPC reference problem is not DPP")
        self._e, self._u = e, u

    def solve(self, data: QPData) -> QPSolution:
        """Set the parameters from ``data`` and solve (:meth:`~controller_node.qp.QPBackend.solve`);
        ``status`` is ``"solved"`` when cvxpy reports an optimal solution."""
        for name in ("a", "a_prev", "beta", "g", "e0", "e_prev", "u_lo", "u_hi", "u_prev"):
            getattr(self, name).value = getattr(data, name)
        h = self._u.shape[0]
        try:
            self.problem.solve(solver=cp.CLARABEL, tol_gap_abs=1e-11, tol_gap_rel=1e-11, tol_feas=1e-11)
        except cp.error.SolverError:
            return QPSolution("solver_error", np.full(h, np.nan), np.full(h, np.nan), 0)
        if self.problem.status != cp.OPTIMAL:
            return QPSolution(str(self.problem.status), np.full(h, np.nan), np.full(h, np.nan), 0)
        iterations = int(self.problem.solver_stats.num_iters or 0)
        return QPSolution("solved", np.array(self._u.value, dtype=float), np.array(self._e.value[2:], dtype=float),
                          iterations)
