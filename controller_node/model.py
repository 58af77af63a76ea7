"""Model interface the controllers use, and its affine linearisation (eq. 8).

Any one-step model of eq. (1), ``x[k+1] = f(x[k], T[k], p[k], v[k])``, works if it
provides ``predict`` and ``mean_and_jacobian`` on ``z = (x [m²], T [K], p [W], v [m/s])``,
e.g. ``gp_trainer.model.GPModel`` or :class:`controller_node.synthetic.AnalyticMeltPoolModel`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["DynamicsModel", "Linearisation", "guard", "linearise"]


@runtime_checkable
class DynamicsModel(Protocol):
    """One-step melt-pool model ``x[k+1] = f(z)``, ``z = (area_m2, t_ahead_k, power_w, speed_m_s)``."""

    def predict(self, z: np.ndarray) -> tuple[float, float]:
        """Return the mean [m²] and variance [m⁴] of ``x[k+1]`` at ``z``, shape (4,)."""
        ...

    def mean_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Return the mean [m²] of ``x[k+1]`` and its gradient w.r.t. ``z``, shape (4,)."""
        ...


@dataclass(frozen=True, slots=True)
class Linearisation:
    """Affine model around ``z0``: ``x⁺ ≈ f0 + a(x − x0) + b(p − p0) + e(T − T0)`` (eq. 8 plus offset).

    Attributes
    ----------
    z0 : numpy.ndarray
        Operating point ``(x0 [m²], T0 [K], p0 [W], v0 [m/s])``, shape (4,).
    f0 : float
        ``f(z0)`` [m²].
    a : float
        ``A_d = ∂f/∂x`` [-].
    b : float
        ``B_d = ∂f/∂p`` [m²/W].
    e : float
        ``∂f/∂T`` [m²/K].
    """

    z0: np.ndarray
    f0: float
    a: float
    b: float
    e: float

    def temperature_gain_w_per_k(self) -> float:
        """Power change per kelvin that keeps the area: ``K_T = −e / b`` [W/K] (0 if ``b`` ≈ 0)."""
        if abs(self.b) < 1e-30:
            return 0.0
        return -self.e / self.b


def linearise(model: DynamicsModel, z0: np.ndarray) -> Linearisation | None:
    """Linearise the model mean at ``z0`` (eq. 8), keeping the affine term.

    Parameters
    ----------
    model : DynamicsModel
        One-step model.
    z0 : numpy.ndarray
        Operating point, shape (4,), SI units.

    Returns
    -------
    Linearisation or None
        None when the model returns non-finite values.
    """
    f0, jac = model.mean_and_jacobian(z0)
    f0 = float(f0)
    a, e, b = float(jac[0]), float(jac[1]), float(jac[2])
    if not (math.isfinite(f0) and math.isfinite(a) and math.isfinite(b) and math.isfinite(e)):
        return None
    return Linearisation(z0=z0, f0=f0, a=a, b=b, e=e)


def guard(lin: Linearisation, a_max: float, b_min: float) -> Linearisation:
    """Clip a linearisation to the physical prior: ``a <= a_max``, ``b >= b_min``.

    The affine term ``f0`` and the operating point are kept, so the guarded model
    still passes through the model's own one-step prediction at ``z0``.

    Parameters
    ----------
    lin : Linearisation
        Raw linearisation.
    a_max : float
        Upper bound of ``∂f/∂x`` (an open-loop stable pool: < 1).
    b_min : float
        Lower bound of ``∂f/∂p`` [m²/W] (more power, larger pool: > 0).

    Returns
    -------
    Linearisation
        ``lin`` itself when nothing is clipped.
    """
    a, b = min(lin.a, a_max), max(lin.b, b_min)
    if a == lin.a and b == lin.b:
        return lin
    return Linearisation(z0=lin.z0, f0=lin.f0, a=a, b=b, e=lin.e)
