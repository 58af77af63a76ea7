"""Cooling between layers (recoating dwell): implicit steps of the plant's semi-discrete system.

Seconds of dwell are 1e5 explicit 50 µs sub-steps; instead each dwell step ``dt`` is backward
Euler linearised in the Kirchhoff variable, ``phi(H + dH) ~ phi + D dH`` (``D`` the table's
slope), with the boundary losses linearised too, ``b(T + dT) ~ b + B dphi`` (``B = db/dT dT/dphi``
>= 0, diagonal): an SPD system for ``dphi = D dH``,

    (M D^-1 + dt k_ref K_w + dt B) dphi = -dt (k_ref K_w phi + b),

solved by conjugate gradients (Jacobi preconditioner).  The enthalpy is then updated with the
fluxes of the new state, ``m dH = -dt (k_ref K_w (phi + dphi) + b + B dphi)``, which is also the
energy counted as lost: energy is conserved whatever the linearisation error.
"""
from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from fe_node.boundary import loss_flux, loss_flux_slope
from fe_node.settings import Settings

EXPLICIT_S = 2e-3
"""Explicit part of a dwell [s] (:func:`cool`)."""


def implicit_step(h: np.ndarray, operator, law, m: np.ndarray, dt: float, b: np.ndarray, db_dt: np.ndarray,
                  rtol: float = 1e-8) -> float:
    """One backward-Euler dwell step, in place; returns the energy lost through the boundary [J].

    Parameters
    ----------
    h : ndarray, shape (ny, nz, nx)
        Nodal enthalpy [J/m³].
    operator : TensorOperator or CsrOperator
        ``K_w`` in solver node order.
    law : Constitutive
    m : ndarray, shape (ny, nz, nx)
        Lumped nodal volumes [m³].
    dt : float
        Step [s].
    b : ndarray, shape (ny, nz, nx)
        Boundary loss power per node at the start [W] (positive = heat leaving).
    db_dt : ndarray, shape (ny, nz, nx)
        Its temperature derivative [W/K] (>= 0).
    rtol : float
        CG relative tolerance.
    """
    from scipy.sparse.linalg import LinearOperator, cg  # here: only a dwell needs it, not every node's start

    shape, n = h.shape, h.size
    k_ref = law.k_ref
    phi = law.kirchhoff(h)
    slope = law.kirchhoff_slope(h)
    diag = (m / slope + dt * db_dt * law.temperature_slope(h) / slope).ravel()
    rhs = -dt * (k_ref * operator(phi) + b).ravel()
    a = LinearOperator((n, n), matvec=lambda x: diag * x + dt * k_ref * np.ravel(operator(x.reshape(shape))))
    dphi, info = cg(a, rhs, rtol=rtol, maxiter=2000, M=LinearOperator((n, n), matvec=lambda x: x / diag))
    if info != 0:
        raise RuntimeError(f"dwell: CG did not converge ({info})")
    dphi = dphi.reshape(shape)
    lost = b + db_dt * law.temperature_slope(h) / slope * dphi
    h -= dt * (k_ref * operator(phi + dphi) + lost) / m
    return float(lost.sum()) * dt


def cool(h: np.ndarray, duration_s: float, dt_explicit: float, explicit_step: Callable[[], None],
         implicit: Callable[[float], float], max_step_s: float, temperature: Callable, t_amb_k: float,
         fallback: Callable[[float], float] | None = None) -> list[float]:
    """Cool ``h`` (nodal enthalpy [J/m³], in place) for ``duration_s`` [s] with no heat input.

    The first :data:`EXPLICIT_S` in explicit steps of ``dt_explicit`` [s] (``explicit_step()``, which
    counts its own losses), then implicit steps (``implicit(dt)``, e.g. :func:`implicit_step`:
    in place, returns the energy lost [J] or raises ``RuntimeError``) doubling from
    :data:`EXPLICIT_S` up to ``max_step_s``.  The trilinear stiffness is no M-matrix, so a long
    implicit step over the steep gradients of a fresh track can undershoot: a step that cools any
    node below the coldest temperature before it (``temperature(h)`` [K], floored at ``t_amb_k``)
    or whose CG fails is undone and retried at an eighth of its length.  On graded elements a step
    can undershoot even at ``dt_explicit``; from there the dwell goes on with ``fallback`` (the same
    step on an operator that is an M-matrix, e.g. :class:`~fe_node.operators.TensorOperator` with
    ``nodal=True``), or raises ``RuntimeError`` without one.  Returns the energies [J] lost in the
    accepted implicit steps, in order, as a list.
    """
    n_explicit = min(math.ceil(EXPLICIT_S / dt_explicit), math.floor(duration_s / dt_explicit))
    for _ in range(n_explicit):
        explicit_step()
    lost_j = []
    left, dt = duration_s - n_explicit * dt_explicit, EXPLICIT_S / 2
    while left > 1e-12 * duration_s:
        dt = min(2 * dt, max_step_s, left)
        before = h.copy()
        t_floor = min(t_amb_k, float(temperature(before.min()))) - 1e-3
        try:
            lost = implicit(dt)
        except RuntimeError:
            lost = None
        if lost is None or float(temperature(h.min())) < t_floor:
            h[...] = before
            if dt <= dt_explicit:
                if fallback is None or implicit is fallback:
                    raise RuntimeError("dwell: implicit step failed at the explicit step size")
                implicit, dt = fallback, dt / 2           # the same step again, on the fallback
            else:
                dt /= 8
            continue
        lost_j.append(lost)
        left -= dt
    return lost_j


def implicit_cooling_step(h: np.ndarray, operator, law, m: np.ndarray, a_top: np.ndarray, a_bottom: np.ndarray,
                          settings: Settings, dt: float) -> float:
    """One :func:`implicit_step` of ``dt`` [s] with the top-face losses (lumped areas ``a_top`` [m²],
    shape (ny, nx)) and the plate's (``plate_h_w_m2k`` on ``a_bottom``) at the start temperature,
    linearised; returns the energy lost [J]."""
    s = settings
    b, db = np.zeros_like(h), np.zeros_like(h)
    t_top = law.temperature(h[:, -1, :])
    b[:, -1, :] = a_top * loss_flux(t_top, s)
    db[:, -1, :] = a_top * loss_flux_slope(t_top, s)
    if s.plate_h_w_m2k > 0:
        b[:, 0, :] += a_bottom * s.plate_h_w_m2k * (law.temperature(h[:, 0, :]) - s.t0_k)
        db[:, 0, :] += a_bottom * s.plate_h_w_m2k
    return implicit_step(h, operator, law, m, dt, b, db)
