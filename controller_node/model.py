"""Model interface the controllers use, and its affine linearisation (eq. 8).

Any one-step model of eq. (1), ``x[k+1] = f(x[k], T[k], p[k], v[k])``, works if it
provides ``predict`` and ``mean_and_jacobian`` on ``z = (x [m²], T [K], p [W], v [m/s])``,
e.g. ``gp_model.model.GPModel`` or :class:`controller_node.synthetic.AnalyticMeltPoolModel`.
A *history model* (``n_inputs == 5``, the shipped GP) takes the last area change
``x[k] − x[k−1]`` [m²] as a fifth input; its linearisation then has a second state gain
``a_prev = ∂f/∂x[k−1]`` and the MPC predicts with ``x[k+1] = f0 + a(x − x0) + a_prev(x⁻ − x0⁻) + …``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

__all__ = ["DynamicsModel", "Linearisation", "guard", "linearise", "operating_point"]


@runtime_checkable
class DynamicsModel(Protocol):
    """One-step melt-pool model ``x[k+1] = f(z)``, ``z = (area_m2, t_ahead_k, power_w, speed_m_s)``."""

    def predict(self, z: np.ndarray) -> tuple[float, float]:
        """Return the mean [m²] and variance [m⁴] of ``x[k+1]`` at ``z``, shape (4,)."""
        ...

    def mean_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Return the mean [m²] of ``x[k+1]`` and its gradient w.r.t. ``z``, shape (4,)."""
        ...


def operating_point(model: DynamicsModel, area_m2: float, t_ahead_k: float, power_w: float, speed_m_s: float,
                    previous_area_m2: float | None = None) -> np.ndarray:
    """The model input ``z`` for these values: shape (4,), or (5,) for a history model.

    Parameters
    ----------
    model : DynamicsModel
        ``getattr(model, "n_inputs", 4)`` decides the shape.
    area_m2, t_ahead_k, power_w, speed_m_s : float
        ``x[k]`` [m²], ``T[k]`` [K], ``p[k]`` [W], ``v[k]`` [m/s].
    previous_area_m2 : float or None
        ``x[k−1]`` [m²]; ``None`` (unknown, e.g. the first sample of a track) means no change.

    Returns
    -------
    numpy.ndarray
        ``(x, T, p, v)`` or ``(x, T, p, v, x − x⁻)``.
    """
    if getattr(model, "n_inputs", 4) == 5:
        change = 0.0 if previous_area_m2 is None else area_m2 - previous_area_m2
        return np.array([area_m2, t_ahead_k, power_w, speed_m_s, change])
    return np.array([area_m2, t_ahead_k, power_w, speed_m_s])


@dataclass(frozen=True, slots=True)
class Linearisation:
    """Affine model around ``z0``: ``x⁺ ≈ f0 + a(x − x0) + a_prev(x⁻ − x0⁻) + b(p − p0) + e(T − T0)``
    (eq. 8 plus offset; ``x⁻`` the previous area, ``a_prev = 0`` for the paper's model).

    Attributes
    ----------
    z0 : numpy.ndarray
        Operating point ``(x0 [m²], T0 [K], p0 [W], v0 [m/s][, x0 − x0⁻ [m²]])``, shape (4,) or (5,).
    f0 : float
        ``f(z0)`` [m²].
    a : float
        ``A_d = ∂f/∂x`` [-].
    b : float
        ``B_d = ∂f/∂p`` [m²/W].
    e : float
        ``∂f/∂T`` [m²/K].
    a_prev : float
        ``∂f/∂x[k−1]`` [-] (0 unless the model has the area-change input).
    variance_m4 : float or None
        The model's predictive variance of ``f(z0)`` [m⁴], when asked for (:func:`linearise`).
    """

    z0: np.ndarray
    f0: float
    a: float
    b: float
    e: float
    a_prev: float = 0.0
    variance_m4: float | None = None

    @property
    def previous_area_m2(self) -> float:
        """``x0⁻`` [m²], the previous area of the operating point (``x0`` for a 4-input model)."""
        return float(self.z0[0] - self.z0[4]) if self.z0.shape[0] == 5 else float(self.z0[0])

    def spectral_radius(self) -> float:
        """Largest |root| of ``λ² − aλ − a_prev`` (the companion matrix of the area dynamics)."""
        disc = self.a * self.a + 4.0 * self.a_prev
        if disc >= 0.0:
            root = math.sqrt(disc)
            return max(abs(self.a + root), abs(self.a - root)) / 2.0
        return math.sqrt(-self.a_prev)  # complex pair: |λ|² = −a_prev

    def temperature_gain_w_per_k(self) -> float:
        """Power change per kelvin that keeps the area: ``K_T = −e / b`` [W/K] (0 if ``b`` ≈ 0)."""
        if abs(self.b) < 1e-30:
            return 0.0
        return -self.e / self.b


def linearise(model: DynamicsModel, z0: np.ndarray, variance: bool = False) -> Linearisation | None:
    """Linearise the model mean at ``z0`` (eq. 8), keeping the affine term.

    Parameters
    ----------
    model : DynamicsModel
        One-step model.
    z0 : numpy.ndarray
        Operating point, shape (4,) or (5,) (:func:`operating_point`), SI units.
    variance : bool
        Also give the predictive variance at ``z0`` (``variance_m4``): from the same evaluation
        when the model has ``mean_jacobian_and_variance`` (:class:`gp_model.model.GPModel`), else
        from ``predict``.

    Returns
    -------
    Linearisation or None
        None when the model returns non-finite values.

    Notes
    -----
    For a history model ``f(x, T, p, v, Δ)`` with ``Δ = x − x⁻``: ``a = ∂f/∂x + ∂f/∂Δ`` and
    ``a_prev = −∂f/∂Δ``.
    """
    var = None
    if not variance:
        f0, jac = model.mean_and_jacobian(z0)
    elif hasattr(model, "mean_jacobian_and_variance"):
        f0, jac, var = model.mean_jacobian_and_variance(z0)
    else:
        f0, jac = model.mean_and_jacobian(z0)
        var = float(model.predict(z0)[1])
    f0 = float(f0)
    a, e, b = float(jac[0]), float(jac[1]), float(jac[2])
    a_prev = 0.0
    if len(jac) == 5:
        a, a_prev = a + float(jac[4]), -float(jac[4])
    if not (math.isfinite(f0) and math.isfinite(a) and math.isfinite(b) and math.isfinite(e)
            and math.isfinite(a_prev)):
        return None
    return Linearisation(z0=z0, f0=f0, a=a, b=b, e=e, a_prev=a_prev, variance_m4=var)


def guard(lin: Linearisation, a_max: float, b_min: float) -> Linearisation:
    """Clip a linearisation to the physical prior: ``a + a_prev <= a_max``, ``b >= b_min``.

    The affine term ``f0`` and the operating point are kept, so the guarded model
    still passes through the model's own one-step prediction at ``z0``.

    Parameters
    ----------
    lin : Linearisation
        Raw linearisation.
    a_max : float
        Upper bound of the DC state gain ``a + a_prev`` (an open-loop stable pool: < 1); ``a``
        is lowered to meet it.
    b_min : float
        Lower bound of ``∂f/∂p`` [m²/W] (more power, larger pool: > 0).

    Returns
    -------
    Linearisation
        ``lin`` itself when nothing is clipped.
    """
    a, b = min(lin.a, a_max - lin.a_prev), max(lin.b, b_min)
    if a == lin.a and b == lin.b:
        return lin
    return Linearisation(z0=lin.z0, f0=lin.f0, a=a, b=b, e=lin.e, a_prev=lin.a_prev, variance_m4=lin.variance_m4)
