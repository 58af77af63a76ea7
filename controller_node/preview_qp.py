"""The preview MPC's quadratic program, condensed, with a fast path and a cvxpy reference.

The predicted areas are affine in the planned powers, ``x̂ = G u + w`` (``G`` the FIR
power coefficients as a lower-triangular Toeplitz matrix, constant), so in normalised units
``e = (x̂ − x_sp)/x_sp``, ``v = u / P`` the problem of :class:`controller_node.preview.PreviewMPC`
is ::

    min_v,s   Σ_m q_m e_m² + r Σ_m (v_m − v_{m−1})² + ρ₁ s + ρ₂ s²
    s.t.      p_l/P <= v_m <= p_u/P                       (hard power bounds, Table 3)
              e_l − s <= e_m − z σ_m,  e_m + z σ_m <= e_u + s,  s >= 0   (soft area bounds)

with ``q_m = q`` and ``q_H = q_f``. The Hessian of the part without slack is constant: its
inverse is precomputed, and when the unconstrained optimum is inside the power bounds and the
area bounds hold it *is* the solution (the fast path, a few matrix-vector products).
Otherwise DAQP solves the box-constrained problem, and, only if the area bounds are violated,
the problem with the slack (exact: a solution that meets the bounds with ``s = 0`` is optimal
for the slack problem too). :func:`solve_reference` solves the full problem with cvxpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import daqp
import numpy as np

__all__ = ["PreviewQP", "QPResult", "solve_reference"]

_INF = 1e30


@dataclass(frozen=True, slots=True)
class QPResult:
    """Planned powers ``u`` [W], shape (H,), and how they were found (``"fast"``, ``"box"``,
    ``"soft"``) or why not (``"failed:<code>"``)."""

    power_w: np.ndarray
    path: str


class PreviewQP:
    """Condensed QP of fixed structure (module docstring).

    Parameters
    ----------
    gain : numpy.ndarray, shape (H, H)
        ``G`` [m²/W].
    set_point_m2 : float
        ``x_sp``.
    q, q_f, r : float
        Stage, terminal and move weights (normalised).
    power_scale_w : float
        ``P`` [W].
    power_min_w, power_max_w : float
        Hard power bounds [W].
    area_min_m2, area_max_m2 : float
        Soft area bounds [m²].
    slack_linear, slack_quadratic : float
        ``ρ₁, ρ₂``.
    """

    def __init__(self, gain: np.ndarray, set_point_m2: float, *, q: float, q_f: float, r: float,
                 power_scale_w: float, power_min_w: float, power_max_w: float, area_min_m2: float,
                 area_max_m2: float, slack_linear: float, slack_quadratic: float) -> None:
        h = gain.shape[0]
        self.horizon = h
        self.x_sp = set_point_m2
        self.scale = power_scale_w
        self.weights = np.full(h, q)
        self.weights[-1] = q_f
        self.gamma = gain * (power_scale_w / set_point_m2)  # e = Γ v + c
        diff = np.eye(h) - np.eye(h, k=-1)
        self.r = r
        self.hessian = 2.0 * (self.gamma.T * self.weights) @ self.gamma + 2.0 * r * diff.T @ diff
        self.hessian_inv = np.linalg.inv(self.hessian)
        self._gw = np.ascontiguousarray(2.0 * self.gamma.T * self.weights)  # ∇ = G_w c − 2 r v_prev e₁
        self.v_lo, self.v_hi = power_min_w / power_scale_w, power_max_w / power_scale_w
        self.e_lo, self.e_hi = area_min_m2 / set_point_m2 - 1.0, area_max_m2 / set_point_m2 - 1.0
        self.rho1, self.rho2 = slack_linear, slack_quadratic
        self._A_empty = np.zeros((0, h))
        self._lo = np.full(h, self.v_lo)
        self._hi = np.full(h, self.v_hi)
        hs = np.zeros((h + 1, h + 1))
        hs[:h, :h] = self.hessian
        hs[h, h] = 2.0 * slack_quadratic
        self._hessian_soft = hs
        self._A_soft = np.zeros((2 * h, h + 1))
        self._A_soft[:h, :h] = self.gamma
        self._A_soft[:h, h] = 1.0   # e + s >= e_l + zσ
        self._A_soft[h:, :h] = self.gamma
        self._A_soft[h:, h] = -1.0  # e − s <= e_u − zσ

    def free_error(self, w_m2: np.ndarray) -> np.ndarray:
        """``c = (w − x_sp)/x_sp``: the normalised error with zero planned power, shape (H,)."""
        return (w_m2 - self.x_sp) / self.x_sp

    def gradient(self, c: np.ndarray, previous_power_w: float) -> np.ndarray:
        """Linear term of the QP in ``v`` for free error ``c`` and the last applied power."""
        f = self._gw @ c
        f[0] -= 2.0 * self.r * previous_power_w / self.scale
        return f

    def solve(self, w_m2: np.ndarray, previous_power_w: float, margin: np.ndarray | None = None) -> QPResult:
        """Plan ``u`` for the known part ``w`` [m²] of the prediction (module docstring).

        Parameters
        ----------
        w_m2 : numpy.ndarray, shape (H,)
            Predicted areas with zero planned power.
        previous_power_w : float
            ``p[k]``, the power applied in the step that produced the current state.
        margin : numpy.ndarray, shape (H,), optional
            ``z σ_m`` in normalised units (bound tightening); zeros by default.
        """
        c = self.free_error(w_m2)
        f = self.gradient(c, previous_power_w)
        margin = np.zeros(self.horizon) if margin is None else margin
        v = -(self.hessian_inv @ f)
        path = "fast"
        if v.min() < self.v_lo or v.max() > self.v_hi:
            v, _, flag, _ = daqp.solve(self.hessian, f, self._A_empty, self._hi, self._lo)
            if flag < 1:
                return QPResult(np.full(self.horizon, np.nan), f"failed:{flag}")
            path = "box"
        e = self.gamma @ v + c
        if np.any(e - margin < self.e_lo) or np.any(e + margin > self.e_hi):
            fs = np.r_[f, self.rho1]
            upper = np.r_[self._hi, _INF, np.full(self.horizon, _INF), self.e_hi - margin - c]
            lower = np.r_[self._lo, 0.0, self.e_lo + margin - c, np.full(self.horizon, -_INF)]
            x, _, flag, _ = daqp.solve(self._hessian_soft, fs, self._A_soft, upper, lower)
            if flag < 1:
                return QPResult(np.full(self.horizon, np.nan), f"failed:{flag}")
            v, path = x[:self.horizon], "soft"
        return QPResult(np.asarray(v) * self.scale, path)


def solve_reference(qp: PreviewQP, w_m2: np.ndarray, previous_power_w: float,
                    margin: np.ndarray | None = None) -> np.ndarray:
    """The same problem written plainly in cvxpy (Clarabel): planned powers [W], shape (H,)."""
    import cvxpy as cp

    h = qp.horizon
    margin = np.zeros(h) if margin is None else margin
    v, s = cp.Variable(h), cp.Variable(nonneg=True)
    e = qp.gamma @ v + qp.free_error(w_m2)
    moves = cp.hstack([v[0] - previous_power_w / qp.scale, v[1:] - v[:-1]])
    cost = (cp.sum(cp.multiply(qp.weights, cp.square(e))) + qp.r * cp.sum_squares(moves)
            + qp.rho1 * s + qp.rho2 * cp.square(s))
    constraints = [v >= qp.v_lo, v <= qp.v_hi, e - margin >= qp.e_lo - s, e + margin <= qp.e_hi + s]
    cp.Problem(cp.Minimize(cost), constraints).solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12,
                                                     tol_feas=1e-12)
    return np.asarray(v.value) * qp.scale
