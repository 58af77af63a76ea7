"""GP-MPC of eq. (7)-(8): linearise the GP mean each step, solve the QP with OSQP.

:class:`OSQPBackend` builds the sparse QP of :mod:`controller_node.qp` once and, per
step, only updates the changing matrix values (``a``, ``β``) and the bound vectors,
then warm-starts OSQP.  :class:`MPCController` wraps linearisation, QP, the optional
temperature feed-forward and output-disturbance estimate.
"""

from __future__ import annotations

import math

import numpy as np
import osqp
import scipy.sparse as sp

from .base import Controller, Proposal
from .feedforward import temperature_feedforward_w
from .model import DynamicsModel, Linearisation, linearise
from .qp import QPBackend, QPData, QPSolution, build_qp_data
from .settings import ControllerSettings
from .types import Measurement

__all__ = ["OSQPBackend", "MPCController", "qp_constants"]


def qp_constants(settings: ControllerSettings) -> dict[str, float]:
    """Step-independent normalised bounds of the QP.

    Returns
    -------
    dict
        ``e_lo, e_hi`` (soft area bounds in ``e``), ``du_lo, du_hi`` (rate bounds in ``u``).
    """
    x_sp = settings.set_point_m2
    p_scale = settings.power_max_w - settings.power_min_w
    m = settings.mpc
    return {
        "e_lo": (m.area_min_m2 - x_sp) / x_sp,
        "e_hi": (m.area_max_m2 - x_sp) / x_sp,
        "du_lo": m.rate_min_w / p_scale,
        "du_hi": m.rate_max_w / p_scale,
    }


class OSQPBackend:
    """Sparse OSQP solver of the MPC QP, built once, updated in place each step.

    Variables ``z = (e[1..H], u[0..H-1], s[1..H])``; constraint rows: dynamics (H),
    soft lower (H), soft upper (H), power bounds (H), rate bounds (H), ``s >= 0`` (H).

    Parameters
    ----------
    settings : ControllerSettings
        Weights, horizon, bounds and OSQP tolerances (``settings.mpc``).
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
        self._b_idx = np.array([where[entry[(i, u_col + i)]] for i in range(h)], dtype=np.int64)
        self._ax_idx = np.concatenate([self._a_idx, self._b_idx])
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
        """Update the QP with one step's data and solve it.

        Parameters
        ----------
        data : QPData
            Normalised step data.

        Returns
        -------
        QPSolution
            ``u`` shape (H,), ``e`` shape (H,).
        """
        h = self._h
        self._ax[: h - 1] = -data.a
        self._ax[h - 1 :] = -data.beta
        lo, hi = self._l, self._u
        lo[:h] = data.g
        lo[0] += data.a * data.e0
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


class MPCController(Controller):
    """Linear time-varying GP-MPC (paper eq. 7-8) with soft area bounds.

    Each update linearises the model mean at ``z0 = (x[k], T[k], p[k−1], v)`` with
    the affine term, builds the normalised QP (:func:`controller_node.qp.build_qp_data`),
    solves it, applies the first planned power plus the optional temperature
    feed-forward and keeps the plan for the fallback.

    Parameters
    ----------
    settings : ControllerSettings
        ``settings.mpc`` configures the MPC.
    model : DynamicsModel
        One-step model with ``predict`` and ``mean_and_jacobian``.
    backend : {"osqp", "cvxpy"} or QPBackend
        QP solver: the fast OSQP backend or the cvxpy reference
        (:class:`controller_node.mpc_reference.CvxpyBackend`).
    """

    name = "mpc"

    def __init__(self, settings: ControllerSettings, model: DynamicsModel, backend: str | QPBackend = "osqp") -> None:
        if not isinstance(model, DynamicsModel):
            raise ValueError("model must provide predict(z) and mean_and_jacobian(z)")
        self.model = model
        if backend == "osqp":
            self.backend: QPBackend = OSQPBackend(settings)
        elif backend == "cvxpy":
            from .mpc_reference import CvxpyBackend

            self.backend = CvxpyBackend(settings)
        elif isinstance(backend, str):
            raise ValueError(f"backend must be 'osqp', 'cvxpy' or a QPBackend, got {backend!r}")
        else:
            self.backend = backend
        super().__init__(settings)

    def reset(self) -> None:
        """Forget history, including the disturbance estimate and the last linearisation."""
        super().reset()
        self._previous: tuple[Measurement, Linearisation] | None = None
        self.disturbance_m2 = 0.0

    def _propose(self, m: Measurement) -> Proposal:
        s = self.settings
        mpc = s.mpc
        p0 = min(max(m.power_w, s.power_min_w), s.power_max_w)
        z0 = np.array([m.area_m2, m.t_ahead_k, p0, m.speed_m_s])
        lin = linearise(self.model, z0)
        if lin is None:
            return Proposal(math.nan, status="model_error")
        previous = self._previous if self._previous is not None and self._previous[0].step == m.step - 1 else None
        if previous is not None and mpc.disturbance_gain > 0.0:
            prev_lin = previous[1]
            predicted = prev_lin.f0 + prev_lin.b * (m.power_w - prev_lin.z0[2])
            self.disturbance_m2 += mpc.disturbance_gain * (m.area_m2 - predicted - self.disturbance_m2)
        self._previous = (m, lin)

        data = build_qp_data(lin, m.area_m2, m.power_w, self.disturbance_m2, s)
        if data is None:
            return Proposal(math.nan, status="model_error")
        sol = self.backend.solve(data)
        if sol.status != "solved":
            return Proposal(math.nan, status=f"solver_failed:{sol.status}")

        feedforward = 0.0
        ff = mpc.feedforward
        if ff.enabled:
            t_prev = previous[0].t_ahead_k if previous is not None else m.t_ahead_k
            gain = ff.gain_w_per_k if ff.gain_w_per_k is not None else lin.temperature_gain_w_per_k()
            feedforward = temperature_feedforward_w(ff, gain, m.t_ahead_k, t_prev)
        p_scale = s.power_max_w - s.power_min_w
        plan = data.p_ref_w + p_scale * sol.u + feedforward
        areas = s.set_point_m2 * (1.0 + sol.e)
        std = None
        if mpc.report_model_std:
            var = float(self.model.predict(z0)[1])
            std = math.sqrt(var) if math.isfinite(var) and var >= 0.0 else None
        return Proposal(
            power_w=float(plan[0]),
            plan_w=tuple(plan.tolist()),
            predicted_area_m2=tuple(areas.tolist()),
            model_std_m2=std,
            feedforward_w=feedforward,
            reference_power_w=data.p_ref_w,
            iterations=sol.iterations,
        )
