"""The preview MPC's quadratic program, condensed, with a fast path and a cvxpy reference.

The controller linearises its prediction around the previous plan, so the normalised error
``e = (x̂ − x_sp)/x_sp`` is affine in the normalised planned powers ``v = u / P``,
``e = Γ v + c`` (``Γ`` lower triangular), and the problem of
:class:`controller_node.preview.PreviewMPC` is ::

    min_v,s   Σ_m q_m e_m² + r Σ_m (v_m − v_{m−1})² + ρ₁ s + ρ₂ s²
    s.t.      p_l/P <= v_m <= p_u/P                       (hard power bounds, Table 3)
              e_l − s <= e_m − z σ_m,  e_m + z σ_m <= e_u + s,  s >= 0   (soft area bounds)

with ``q_m = q`` and ``q_H = q_f``. When the unconstrained optimum (one dense solve) is inside
the power bounds and the area bounds hold it *is* the solution (the fast path).
Otherwise DAQP solves the box-constrained problem, and, only if the area bounds are violated,
the problem with the slack (exact: a solution that meets the bounds with ``s = 0`` is optimal
for the slack problem too). :func:`solve_reference` solves the full problem with cvxpy.
"""

from __future__ import annotations

from dataclasses import dataclass

import daqp
import numpy as np
from scipy.linalg.lapack import dposv

__all__ = ["PreviewQP", "QPResult", "solve_reference"]

_INF = 1e30


@dataclass(frozen=True, slots=True)
class QPResult:
    """Planned powers ``u`` [W], shape (H,), and how they were found (``"fast"``, ``"box"``,
    ``"soft"``) or why not (``"failed:<code>"``)."""

    power_w: np.ndarray
    path: str


class PreviewQP:
    """The QP of the module docstring for a given linearisation ``e = Γ v + c``.

    Parameters
    ----------
    horizon : int
        ``H``.
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

    def __init__(self, horizon: int, set_point_m2: float, *, q: float, q_f: float, r: float,
                 power_scale_w: float, power_min_w: float, power_max_w: float, area_min_m2: float,
                 area_max_m2: float, slack_linear: float, slack_quadratic: float) -> None:
        h = self.horizon = horizon
        self.x_sp = set_point_m2
        self.scale = power_scale_w
        self.weights = np.full(h, q)
        self.weights[-1] = q_f
        diff = np.eye(h) - np.eye(h, k=-1)
        self.r = r
        self.moves = 2.0 * r * diff.T @ diff
        self.v_lo, self.v_hi = power_min_w / power_scale_w, power_max_w / power_scale_w
        self.e_lo, self.e_hi = area_min_m2 / set_point_m2 - 1.0, area_max_m2 / set_point_m2 - 1.0
        self.rho1, self.rho2 = slack_linear, slack_quadratic
        self._A_empty = np.zeros((0, h))
        self._lo = np.full(h, self.v_lo)
        self._hi = np.full(h, self.v_hi)

    def hessian(self, gamma: np.ndarray) -> np.ndarray:
        """``2 (Γᵀ W Γ + r DᵀD)``, shape (H, H)."""
        return 2.0 * (gamma.T * self.weights) @ gamma + self.moves

    def gradient(self, gamma: np.ndarray, c: np.ndarray, previous_power_w: float) -> np.ndarray:
        """Linear term ``2 Γᵀ W c − 2 r v_prev e₁``, shape (H,)."""
        f = 2.0 * (gamma.T * self.weights) @ c
        f[0] -= 2.0 * self.r * previous_power_w / self.scale
        return f

    def solve(self, gamma: np.ndarray, c: np.ndarray, previous_power_w: float,
              margin: np.ndarray | None = None) -> QPResult:
        """Plan the powers for the prediction ``e = Γ v + c`` (module docstring).

        Parameters
        ----------
        gamma : numpy.ndarray, shape (H, H)
            ``∂e/∂v``.
        c : numpy.ndarray, shape (H,)
            ``e`` at ``v = 0``.
        previous_power_w : float
            ``p[k]``, the power applied in the step that produced the current state.
        margin : numpy.ndarray, shape (H,), optional
            ``z σ_m`` in normalised units (bound tightening); zeros by default.
        """
        gw = 2.0 * gamma.T * self.weights
        f = gw @ c
        f[0] -= 2.0 * self.r * previous_power_w / self.scale
        hess = gw @ gamma + self.moves
        _, v, info = dposv(hess, -f)  # LAPACK Cholesky solve: the Hessian is positive definite (r > 0)
        return self.finish(gamma, c, hess, f, v if info == 0 else None, margin)

    def finish(self, gamma: np.ndarray, c: np.ndarray, hess: np.ndarray, f: np.ndarray, v: np.ndarray | None,
               margin: np.ndarray | None = None) -> QPResult:
        """:meth:`solve` from its :meth:`hessian`, :meth:`gradient` and unconstrained optimum ``v``
        (None or NaN: the Hessian was not positive definite): ``v`` itself when no bound is active
        (the fast path), else DAQP."""
        h = self.horizon
        path = "fast"
        if v is None or not (v.min() >= self.v_lo and v.max() <= self.v_hi):
            v, _, flag, _ = daqp.solve(hess, f, self._A_empty, self._hi, self._lo)
            if flag < 1:
                return QPResult(np.full(h, np.nan), f"failed:{flag}")
            path = "box"
        e = gamma @ v + c
        if margin is None:
            violated = e.min() < self.e_lo or e.max() > self.e_hi
        else:
            violated = (e - margin).min() < self.e_lo or (e + margin).max() > self.e_hi
        if violated:
            margin = np.zeros(h) if margin is None else margin
            hs = np.zeros((h + 1, h + 1))
            hs[:h, :h] = hess
            hs[h, h] = 2.0 * self.rho2
            A = np.zeros((2 * h, h + 1))
            A[:h, :h], A[:h, h] = gamma, 1.0     # e + s >= e_l + zσ
            A[h:, :h], A[h:, h] = gamma, -1.0    # e − s <= e_u − zσ
            upper = np.r_[self._hi, _INF, np.full(h, _INF), self.e_hi - margin - c]
            lower = np.r_[self._lo, 0.0, self.e_lo + margin - c, np.full(h, -_INF)]
            x, _, flag, _ = daqp.solve(hs, np.r_[f, self.rho1], A, upper, lower)
            if flag < 1:
                return QPResult(np.full(h, np.nan), f"failed:{flag}")
            v, path = x[:h], "soft"
        return QPResult(np.asarray(v) * self.scale, path)


def solve_reference(qp: PreviewQP, gamma: np.ndarray, c: np.ndarray, previous_power_w: float,
                    margin: np.ndarray | None = None) -> np.ndarray:
    """The same problem written plainly in cvxpy (Clarabel): planned powers [W], shape (H,)."""
    import cvxpy as cp

    h = qp.horizon
    margin = np.zeros(h) if margin is None else margin
    v, s = cp.Variable(h), cp.Variable(nonneg=True)
    e = gamma @ v + c
    moves = cp.hstack([v[0] - previous_power_w / qp.scale, v[1:] - v[:-1]])
    cost = (cp.sum(cp.multiply(qp.weights, cp.square(e))) + qp.r * cp.sum_squares(moves)
            + qp.rho1 * s + qp.rho2 * cp.square(s))
    constraints = [v >= qp.v_lo, v <= qp.v_hi, e - margin >= qp.e_lo - s, e + margin <= qp.e_hi + s]
    cp.Problem(cp.Minimize(cost), constraints).solve(solver=cp.CLARABEL, tol_gap_abs=1e-12, tol_gap_rel=1e-12,
                                                     tol_feas=1e-12)
    return np.asarray(v.value) * qp.scale
