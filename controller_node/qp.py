"""The MPC quadratic programme of eq. (7), in normalised deviation variables.

Scaling (chosen so that Table 3's ``Q = 1, R = 0.1, Q_f = 20`` are meaningful):

* state  ``e = (x − x_sp) / x_sp``       — relative melt-pool area error [-];
* input  ``u = (p − p_ref) / P`` — power as a fraction of ``P`` = ``mpc.power_scale_w``
  (default 4 W; when set to None, ``p_u − p_l``, the power range) [-].

With the affine linearisation (eq. 8 plus the offset ``f0``) held over the horizon and
the temperature held at ``T[k]``, the prediction model is ::

    e[i+1] = a·e[i] + a⁻·e[i−1] + β·u[i] + g,   β = b·P/x_sp,
    g = (f0 − a·x0 − a⁻·x0⁻ − b·p0 + d̂ + (a + a⁻)·x_sp + b·p_ref − x_sp) / x_sp

(``d̂`` is the optional output-disturbance estimate; ``a⁻ = ∂f/∂x[k−1]`` of a history model,
0 for the paper's model, and ``e[−1]`` the previous area's error).  ``p_ref`` is the model's
steady-state power ``p_ss`` for the set point, clamped to the bounds; then ``g = 0``
unless ``p_ss`` is out of reach.  The QP, solved by :mod:`controller_node.qp_daqp` (DAQP,
the default), :mod:`controller_node.qp_osqp` (OSQP) and :mod:`controller_node.mpc_reference`
(cvxpy) — chosen by ``mpc.solver`` in :func:`controller_node.mpc.make_backend` — is ::

    min  Σ_{i=1}^{H-1} Q e[i]² + Q_f e[H]² + R Σ_{i=0}^{H-1} w[i]² + Σ_{i=1}^{H} (ρ₁ s[i] + ρ₂ s[i]²)
    s.t. e[i+1] = a e[i] + a⁻ e[i−1] + β u[i] + g,   e[0], e[−1] given
         e_l − s[i] <= e[i] <= e_u + s[i],   s[i] >= 0        (soft area bounds)
         u_l <= u[i] <= u_u                                  (power bounds)
         δ_l <= u[i] − u[i−1] <= δ_u,         u[−1] = u_prev   (rate bounds)

with ``w[i] = u[i]`` (``input_penalty="steady_state"``) or ``w[i] = u[i] − u[i−1]``
(``"move"``).  ``e[0]`` is fixed, so its stage cost is dropped.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import numpy as np

from .model import Linearisation
from .settings import ControllerSettings

__all__ = ["QPData", "QPSolution", "QPBackend", "build_qp_data", "power_scale_w", "qp_constants"]

_MIN_GAIN_M2_PER_W = 1e-16  # b below this (1e-10 mm²/W) means power has no usable effect
_MAX_NORMALISED = 1e6  # larger normalised coefficients mean a broken model/measurement
_MAX_STATE_GAIN = 1.5  # spectral radius above this: explosive linearised pool dynamics, untrustworthy model


@dataclass(frozen=True, slots=True)
class QPData:
    """Numbers that change from step to step (all normalised, dimensionless).

    Attributes
    ----------
    a, beta, g : float
        Prediction model ``e[i+1] = a e[i] + a_prev e[i−1] + β u[i] + g``.
    e0 : float
        Current relative area error.
    u_lo, u_hi : float
        Power bounds in ``u``.
    u_prev : float
        Last applied power in ``u`` (rate bound and ``"move"`` penalty).
    p_ref_w : float
        ``p_ref`` [W] of the input scaling.
    a_prev : float
        Gain on the previous error ``e[i−1]`` (0 for the paper's one-state model).
    e_prev : float
        Previous relative area error ``e[−1]``.
    """

    a: float
    beta: float
    g: float
    e0: float
    u_lo: float
    u_hi: float
    u_prev: float
    p_ref_w: float
    a_prev: float = 0.0
    e_prev: float = 0.0


@dataclass(frozen=True, slots=True)
class QPSolution:
    """Result of a backend solve.

    Attributes
    ----------
    status : str
        ``"solved"`` on success, else the solver's status.
    u : numpy.ndarray
        Planned normalised inputs ``u[0..H-1]``, shape (H,) (NaN when not solved).
    e : numpy.ndarray
        Predicted normalised errors ``e[1..H]``, shape (H,).
    iterations : int
        Solver iterations.
    """

    status: str
    u: np.ndarray
    e: np.ndarray
    iterations: int


class QPBackend(Protocol):
    """A solver of the QP above, built for fixed settings.

    Parameters
    ----------
    settings : ControllerSettings
        Weights, horizon, bounds and solver tolerances (``settings.mpc``).
    """

    def solve(self, data: QPData) -> QPSolution:
        """Solve the QP of one step.

        Parameters
        ----------
        data : QPData
            Normalised step data.

        Returns
        -------
        QPSolution
            ``u`` shape (H,), ``e`` shape (H,).
        """
        ...


def power_scale_w(settings: ControllerSettings) -> float:
    """Power normalisation [W]: ``mpc.power_scale_w`` (default 4 W), or ``p_u − p_l`` when it is None."""
    scale = settings.mpc.power_scale_w
    return settings.power_max_w - settings.power_min_w if scale is None else scale


def build_qp_data(
    lin: Linearisation,
    area_m2: float,
    applied_power_w: float,
    disturbance_m2: float,
    settings: ControllerSettings,
    power_offset_w: float = 0.0,
) -> QPData | None:
    """Normalise one step's linearisation into :class:`QPData`.

    Parameters
    ----------
    lin : Linearisation
        GP mean linearised at ``z0 = (x[k], T[k], p0, v)``.
    area_m2 : float
        Measured ``x[k]`` [m²].
    applied_power_w : float
        ``p[k−1]`` [W], the rate-bound anchor (clamped to the power bounds).
    disturbance_m2 : float
        Output-disturbance estimate ``d̂`` added to every prediction [m²].
    settings : ControllerSettings
        Set point, power bounds.
    power_offset_w : float
        Power added to the planned power outside the QP (the temperature
        feed-forward ``Δp_ff``): the QP plans ``p̃ = p − Δp_ff`` within
        ``[p_l − Δp_ff, p_u − Δp_ff]``; ``applied_power_w`` and ``lin.z0[2]`` are in
        the same (compensated) units.

    Returns
    -------
    QPData or None
        None when the numbers are not finite, absurdly large (|·| > 1e6), or the
        linearised pool dynamics are explosive (spectral radius > 1.5; its H-th power
        would dominate the condensed QP).
    """
    x_sp = settings.set_point_m2
    p_lo, p_hi = settings.power_min_w - power_offset_w, settings.power_max_w - power_offset_w
    p_scale = power_scale_w(settings)
    x0, p0, x0_prev = float(lin.z0[0]), float(lin.z0[2]), lin.previous_area_m2
    gain = lin.a + lin.a_prev
    c = lin.f0 - lin.a * x0 - lin.a_prev * x0_prev - lin.b * p0 + disturbance_m2
    if lin.b > _MIN_GAIN_M2_PER_W:
        p_ref = min(max((x_sp * (1.0 - gain) - c) / lin.b, p_lo), p_hi)
    else:
        p_ref = min(max(p0, p_lo), p_hi)
    g = (c + gain * x_sp + lin.b * p_ref - x_sp) / x_sp
    p_prev = min(max(applied_power_w, p_lo), p_hi)
    data = QPData(
        a=lin.a,
        beta=lin.b * p_scale / x_sp,
        g=g,
        e0=(area_m2 - x_sp) / x_sp,
        u_lo=(p_lo - p_ref) / p_scale,
        u_hi=(p_hi - p_ref) / p_scale,
        u_prev=(p_prev - p_ref) / p_scale,
        p_ref_w=p_ref,
        a_prev=lin.a_prev,
        e_prev=(x0_prev - x_sp) / x_sp,
    )
    for value in (data.a, data.a_prev, data.beta, data.g, data.e0, data.e_prev, data.u_prev):
        if not abs(value) <= _MAX_NORMALISED:  # also rejects NaN
            return None
    return data if lin.spectral_radius() <= _MAX_STATE_GAIN else None


def qp_constants(settings: ControllerSettings) -> dict[str, float]:
    """Step-independent normalised bounds of the QP.

    Returns
    -------
    dict
        ``e_lo, e_hi`` (soft area bounds in ``e``), ``du_lo, du_hi`` (rate bounds in ``u``).
    """
    x_sp = settings.set_point_m2
    p_scale = power_scale_w(settings)
    m = settings.mpc
    return {
        "e_lo": (m.area_min_m2 - x_sp) / x_sp,
        "e_hi": (m.area_max_m2 - x_sp) / x_sp,
        "du_lo": m.rate_min_w / p_scale,
        "du_hi": m.rate_max_w / p_scale,
    }
