"""Sparse OSQP backend of the MPC QP (:mod:`controller_node.qp`), built once, updated in place.

Variables ``z = (e[1..H], u[0..H-1], s[1..H])``; each step only the ``a``/``a⁻``/``β``
entries of the constraint matrix and the bound vectors change (OSQP ``update`` plus
warm start, tolerances ``settings.mpc.eps_abs/eps_rel``).
:class:`controller_node.qp_daqp.DaqpBackend` is faster (``benchmarks/bench_controller.py``)
and exact, so this is the alternative backend (``MPCSettings(solver="osqp")``).
Known weakness (ADMM): when soft area bounds and binding rate limits are active
together (e.g. area bounds close to the set point and rate limits of ±20 W/step)
OSQP needs thousands of iterations and may stop at ``max_iter`` (then the
controller falls back); with Table 3's bounds this does not occur.
"""

from __future__ import annotations

import numpy as np
import osqp
import scipy.sparse as sp

from .qp import QPData, QPSolution, qp_constants
from .settings import ControllerSettings

__all__ = ["OSQPBackend"]


class OSQPBackend:
    """Sparse OSQP solver of the MPC QP, built once, updated in place each step.

    Variables ``z = (e[1..H], u[0..H-1], s[1..H])``; constraint rows: dynamics (H),
    soft lower (H), soft upper (H), power bounds (H), rate bounds (H), ``s >= 0`` (H). A
    :class:`~controller_node.qp.QPBackend`.
    """

    def __init__(self, settings: ControllerSettings) -> None:
        m = settings.mpc
        h = self._h = m.horizon
        k = qp_constants(settings)
        self._du = (k["du_lo"], k["du_hi"])
        self._move = m.input_penalty == "move"
        self._r = m.r

        # Cost 0.5 z'Pz + q'z (OSQP form, hence the factors 2).
        w_e = np.full(h, 2.0 * m.q)
        w_e[-1] = 2.0 * m.q_f
        if self._move:  # R Σ (u[i] − u[i−1])², u[−1] fixed: tridiagonal 2R·DᵀD
            main = np.full(h, 4.0 * m.r)
            main[-1] = 2.0 * m.r
            p_uu = sp.diags([main, np.full(h - 1, -2.0 * m.r)], [0, 1], shape=(h, h))
        else:
            p_uu = sp.diags(np.full(h, 2.0 * m.r))
        p_mat = sp.block_diag(
            [sp.diags(w_e), p_uu, sp.diags(np.full(h, 2.0 * m.slack_quadratic))], format="csc"
        )
        self._q = np.concatenate([np.zeros(2 * h), np.full(h, m.slack_linear)])

        rows, cols, vals = [], [], []

        def add(r: int, c: int, v: float) -> None:
            rows.append(r)
            cols.append(c)
            vals.append(v)

        e_col, u_col, s_col = 0, h, 2 * h
        for i in range(h):
            add(i, e_col + i, 1.0)  # e[i+1]
            if i > 0:
                add(i, e_col + i - 1, -1.0)  # −a·e[i] (placeholder value)
            if i > 1:
                add(i, e_col + i - 2, -1.0)  # −a⁻·e[i−1] (placeholder value)
            add(i, u_col + i, -1.0)  # −β·u[i] (placeholder value)
            add(h + i, e_col + i, 1.0)
            add(h + i, s_col + i, 1.0)
            add(2 * h + i, e_col + i, 1.0)
            add(2 * h + i, s_col + i, -1.0)
            add(3 * h + i, u_col + i, 1.0)
            add(4 * h + i, u_col + i, 1.0)
            if i > 0:
                add(4 * h + i, u_col + i - 1, -1.0)
            add(5 * h + i, s_col + i, 1.0)
        n_rows = 6 * h
        # Tag each entry to find where the a/β entries land in CSC data order.
        tags = sp.coo_matrix((np.arange(1, len(vals) + 1, dtype=float), (rows, cols)), shape=(n_rows, 3 * h)).tocsc()
        order = tags.data.astype(int) - 1
        a_mat = tags.copy()
        a_mat.data = np.asarray(vals)[order]
        entry = {(rows[j], cols[j]): j for j in range(len(vals))}
        where = np.empty(len(vals), dtype=np.int64)
        where[order] = np.arange(len(order))
        self._a_idx = np.array([where[entry[(i, e_col + i - 1)]] for i in range(1, h)], dtype=np.int64)
        a_prev_idx = np.array([where[entry[(i, e_col + i - 2)]] for i in range(2, h)], dtype=np.int64)
        self._b_idx = np.array([where[entry[(i, u_col + i)]] for i in range(h)], dtype=np.int64)
        self._ax_idx = np.concatenate([self._a_idx, a_prev_idx, self._b_idx])
        self._ax = np.empty(len(self._ax_idx))

        inf = np.inf
        self._l = np.concatenate(
            [np.zeros(h), np.full(h, k["e_lo"]), np.full(h, -inf), np.zeros(h), np.full(h, k["du_lo"]), np.zeros(h)]
        )
        self._u = np.concatenate(
            [np.zeros(h), np.full(h, inf), np.full(h, k["e_hi"]), np.zeros(h), np.full(h, k["du_hi"]), np.full(h, inf)]
        )
        self._solver = osqp.OSQP()
        self._solver.setup(
            p_mat, self._q.copy(), a_mat, self._l.copy(), self._u.copy(),
            eps_abs=m.eps_abs, eps_rel=m.eps_rel, max_iter=m.max_iter,
            polishing=False, warm_starting=True, verbose=False,
        )

    def solve(self, data: QPData) -> QPSolution:
        """Update the QP with one step's data and solve it (:meth:`~controller_node.qp.QPBackend.solve`)."""
        h = self._h
        self._ax[: h - 1] = -data.a
        self._ax[h - 1 : 2 * h - 3] = -data.a_prev
        self._ax[2 * h - 3 :] = -data.beta
        lo, hi = self._l, self._u
        lo[:h] = data.g
        lo[0] += data.a * data.e0 + data.a_prev * data.e_prev
        if h > 1:
            lo[1] += data.a_prev * data.e0
        hi[:h] = lo[:h]
        lo[3 * h : 4 * h] = data.u_lo
        hi[3 * h : 4 * h] = data.u_hi
        lo[4 * h] = data.u_prev + self._du[0]
        hi[4 * h] = data.u_prev + self._du[1]
        if self._move:
            self._q[h] = -2.0 * self._r * data.u_prev
            self._solver.update(q=self._q, l=lo, u=hi, Ax=self._ax, Ax_idx=self._ax_idx)
        else:
            self._solver.update(l=lo, u=hi, Ax=self._ax, Ax_idx=self._ax_idx)
        res = self._solver.solve(raise_error=False)
        status = res.info.status
        x = res.x
        return QPSolution(status=status, u=x[h : 2 * h], e=x[:h], iterations=int(res.info.iter))
