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

import numpy as np
from scipy.sparse.linalg import LinearOperator, cg


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
