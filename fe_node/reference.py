"""IN625 reference: a 1-D melting column solved implicitly with scikit-fem vs the plant's scheme.

Case: a 1.5 mm IN625 column at 300 K, insulated below, absorbs a uniform 4e8 W/m² on top for
5 ms (surface 2814 K, liquidus 105 µm deep); no losses.  Two solutions of this case:

* :func:`implicit_column` — the reference.  IN625 properties written out here from their
  sources (the Penn State linear set as used by Wang et al., Additive Manufacturing 31 (2020)
  100985, and the Special Metals INCONEL alloy 625 datasheet; docs/fe.md, "Material data and
  sources"), independent of :mod:`fe_node.material`, so a change there shows:
  ``rho = 8440 kg/m³``, ``cp = 405 + 0.247 T[°C]`` (held above the liquidus),
  ``k = 9.5 + 0.015 T[°C]`` (held above the solidus), ``L = 2.8e5 J/kg`` released linearly over
  1563-1623 K.  Linear elements (``conduction`` and ``mass`` of
  :mod:`fe_node.forms` assembled on a ``MeshLine`` of 2 µm), backward Euler with 2 µs steps,
  Newton on ``m (H(T) - H_n) / dt + K Psi(T) = f`` with ``Psi = int k dT`` (exact, no tables).
  Halving ``h`` and ``dt`` to 4 µm changes the nodal temperatures by 0.03 % of the rise.
* :func:`plant_column` — the plant's discretisation: its z axis, operator, look-up tables and
  explicit sub-steps (:func:`fe_node.solver.explicit_update`) on a one-element-wide column.

:func:`in625_reference` compares them node by node: the largest nodal temperature difference
as a percentage of the reference surface temperature rise.
"""
from __future__ import annotations

import math

import numpy as np
from scipy.linalg import solve_banded

from fe_node.material import Constitutive
from fe_node.mesh import Grid, graded_axis
from fe_node.operators import TensorOperator
from fe_node.settings import Settings
from messages import in625

C0 = 273.15
RHO, LATENT, T_SOL, T_LIQ = in625.RHO_KG_M3, in625.LATENT_J_KG, in625.T_SOLIDUS_K, in625.T_LIQUIDUS_K
CP0, CP1, K0, K1 = in625.CP_0C_J_KGK, in625.CP_SLOPE_J_KGK2, in625.K_0C_W_MK, in625.K_SLOPE_W_MK2
FLUX_W_M2, T_ON_S, T0_K, DEPTH_M = 4e8, 5e-3, 300.0, 1.5e-3


def _cp(t):
    return CP0 + CP1 * (np.minimum(t, T_LIQ) - C0)


def _k(t):
    return K0 + K1 * (np.minimum(t, T_SOL) - C0)


def enthalpy(t):
    """IN625 volumetric enthalpy [J/m³] at ``t`` [K] (closed form of the literal properties)."""
    tc = np.minimum(t, T_LIQ)
    sensible = (CP0 - CP1 * C0) * tc + 0.5 * CP1 * tc**2 + np.maximum(t - T_LIQ, 0.0) * _cp(T_LIQ)
    return RHO * (sensible + LATENT * np.clip((t - T_SOL) / (T_LIQ - T_SOL), 0.0, 1.0))


def _d_enthalpy(t):
    return RHO * (_cp(t) + np.where((t > T_SOL) & (t < T_LIQ), LATENT / (T_LIQ - T_SOL), 0.0))


def _psi(t):
    """``int_0^T k`` [W/m]."""
    tc = np.minimum(t, T_SOL)
    return (K0 - K1 * C0) * tc + 0.5 * K1 * tc**2 + np.maximum(t - T_SOL, 0.0) * _k(T_SOL)


def implicit_column(h_m: float = 2e-6, dt_s: float = 2e-6, flux_w_m2: float = FLUX_W_M2,
                    t_on_s: float = T_ON_S) -> tuple[np.ndarray, np.ndarray]:
    """Reference solution (module docstring).

    Returns
    -------
    z : ndarray, shape (n,)
        Node heights [m], ascending to the top at 0.
    t : ndarray, shape (n,)
        Temperatures [K] at ``t_on_s``.
    """
    from skfem import Basis, ElementLineP1, MeshLine

    from fe_node.forms import conduction, mass

    z = np.linspace(-DEPTH_M, 0.0, int(round(DEPTH_M / h_m)) + 1)
    basis = Basis(MeshLine(z), ElementLineP1(), intorder=2)
    stiff = conduction.assemble(basis, kw=1.0)
    m = np.asarray(mass.assemble(basis, rho_w=1.0).sum(axis=1)).ravel()
    kd, ko = stiff.diagonal(0), stiff.diagonal(1)
    f = np.zeros(len(z))
    f[np.argmax(z)] = flux_w_m2
    t = np.full(len(z), T0_K)
    band = np.zeros((3, len(z)))
    for _ in range(int(round(t_on_s / dt_s))):
        h_old, new = enthalpy(t), t.copy()
        for _ in range(50):
            p = _psi(new)
            kp = kd * p
            kp[:-1] += ko * p[1:]
            kp[1:] += ko * p[:-1]
            k = _k(new)
            band[1] = m * _d_enthalpy(new) / dt_s + kd * k
            band[0, 1:] = ko * k[1:]
            band[2, :-1] = ko * k[:-1]
            step = solve_banded((1, 1), band, f - kp - m * (enthalpy(new) - h_old) / dt_s)
            new += step
            if np.abs(step).max() < 1e-7:
                break
        else:
            raise RuntimeError("reference: Newton did not converge")
        t = new
    return z, t


def plant_column(settings: Settings, flux_w_m2: float = FLUX_W_M2,
                 t_on_s: float = T_ON_S) -> tuple[np.ndarray, np.ndarray, int]:
    """The plant's scheme on the reference case: z axis, operator, tables and sub-steps of ``settings``.

    Returns
    -------
    z : ndarray, shape (nz,)
        Node heights [m].
    t : ndarray, shape (nz,)
        Temperatures [K] at ``t_on_s``.
    n_substeps : int
        Explicit sub-steps per ``settings.dt_s``.
    """
    from fe_node.solver import explicit_update

    s, h = settings, settings.h_fine_m
    zs = graded_axis(-DEPTH_M, 0.0, -s.fine_depth_m, 0.0, h=h, growth=s.growth, h_max=s.h_max_m)
    grid = Grid(np.array([0.0, h]), np.array([0.0, h]), zs)
    op = TensorOperator(grid)
    law = Constitutive(s.material)
    dt_stable = 0.9 * 2.0 / (law.max_diffusivity * op.stability_eigenvalue())
    n_sub = max(s.min_substeps, math.ceil(s.dt_s / dt_stable))
    dt_sub = s.dt_s / n_sub
    c, c_top = dt_sub * law.k_ref / op.lumped_mass, dt_sub / op.lumped_mass[:, -1, :]
    top = flux_w_m2 * grid.top_areas()
    hh = np.full(grid.solver_shape, float(law.enthalpy(T0_K)))
    for _ in range(int(round(t_on_s / s.dt_s)) * n_sub):
        explicit_update(hh, op, law, c, top, c_top)
    return zs, law.temperature(hh[0, :, 0]), n_sub


def liquidus_depth(z: np.ndarray, t: np.ndarray) -> float:
    """Depth [m] of the liquidus isotherm (linear between nodes; 0 if the top is solid)."""
    below = np.flatnonzero(t < T_LIQ)
    if t[-1] < T_LIQ or len(below) == 0:
        return 0.0
    j = below[-1]
    return float(-(z[j] + (T_LIQ - t[j]) / (t[j + 1] - t[j]) * (z[j + 1] - z[j])))


def in625_reference(settings: Settings, reference: tuple[np.ndarray, np.ndarray] | None = None) -> dict:
    """Plant scheme vs reference on the IN625 column.

    Parameters
    ----------
    settings : Settings
        Plant settings (material, ``h_fine_m``, z grading, ``dt_s``, ``min_substeps``).
    reference : (z, t), optional
        A precomputed :func:`implicit_column` (default: computed here, ~1.5 s).

    Returns
    -------
    dict
        ``error_pct`` (largest nodal |T - T_ref| in % of the reference surface rise),
        ``surface_k`` and ``reference_surface_k`` [K], ``liquidus_depth_um`` and
        ``reference_liquidus_depth_um``.
    """
    zr, tr = implicit_column() if reference is None else reference
    z, t, _ = plant_column(settings)
    err = np.abs(t - np.interp(z, zr, tr)).max() / (tr[-1] - T0_K)
    return dict(error_pct=float(100 * err), surface_k=float(t[-1]), reference_surface_k=float(tr[-1]),
                liquidus_depth_um=liquidus_depth(z, t) * 1e6, reference_liquidus_depth_um=liquidus_depth(zr, tr) * 1e6)
