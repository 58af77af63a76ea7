"""Keyhole onset: the surface temperature limit of the plant, where the beam's excess energy goes,
and the keyhole's absorptivity.

Above the boiling point the vapour's recoil pressure, ``p_r = 0.54 p_sat(T)`` (Anisimov, Sov.
Phys. JETP 27 (1968) 182), pushes the melt surface down once it beats the ambient pressure plus
the capillary pressure of a depression of the beam's size:

    0.54 p_sat(T_kh) = p_amb + 2 gamma / w,

``p_sat`` the Clausius-Clapeyron vapour pressure of :mod:`fe_node.boundary`, ``gamma`` the
surface tension of the melt and ``w`` the beam's 1/e² radius.  A hotter surface is no longer
where the beam is absorbed: the keyhole opens and the beam drills down.  The plant models this
without moving its surface: the enthalpy that would heat a top node above ``T_kh`` is carried
down its vertical column and deposited in the first nodes below ``T_kh`` (the keyhole's
bottom), so the absorbed energy is conserved and the surface never exceeds ``T_kh``.

The keyhole is a cavity: the beam is reflected several times inside before it leaves, so the
molten metal under it absorbs more, the deeper the keyhole (the rise of absorptance with keyhole
depth measured by Trapp et al., "In situ absorptivity measurements of metallic powders and
substrates exposed to a laser beam", Appl. Mater. Today 9 (2017) 341).  The plant takes the
cavity absorptance of Gouffé (Rev. Opt. 24 (1945) 1) without its second-order correction, for a
cylinder of the beam's radius ``w`` and depth ``d`` with walls of absorptivity ``a``:

    a_cav = a / (a (1 - s/S) + s/S),    s/S = w / (w + 2 d),

``s`` the opening and ``S`` the cavity's inner surface (``a_cav = a`` without a keyhole, -> 1
for a deep one).  The depth follows from the energy balance of the drilled field, not from a node
count: ``d = V / (pi w²)``, ``V`` the vapour volume, each node counting with the share of its
enthalpy between boiling and ``T_kh`` (:func:`vapour_volume_m3`).  One absorptivity for the
whole beam, set once per step: a per-node switch to the keyhole's absorptivity at the opening's
nodes made the absorbed power follow the mesh (docs/fe.md, "Measured").
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.boundary import L_VAP_J_KG, MOLAR_MASS_KG_MOL, P_AMBIENT_PA, R_GAS

RECOIL_FRACTION = 0.54
"""Recoil pressure over saturation pressure of strong evaporation [-] (Anisimov 1968)."""
SURFACE_TENSION_N_M = 1.78
"""Surface tension of the melt [N/m]: nickel at its melting point (Keene, Int. Mater. Rev. 38
(1993) 157), for the Ni-base IN625."""


def beam_1e2_radius_m(beam_radius_m: float) -> float:
    """1/e² radius [m] of the eq. 6 Gaussian ``exp(-3 rho² / r_s²)``: ``w = 2 r_s / sqrt(6)``."""
    return 2.0 * beam_radius_m / math.sqrt(6.0)


def keyhole_temperature_k(beam_radius_m: float, t_boil_k: float,
                          surface_tension_n_m: float = SURFACE_TENSION_N_M) -> float:
    """Keyhole-onset surface temperature [K] (module docstring) for a beam of eq. 6 radius
    ``beam_radius_m`` [m] and a melt boiling at ``t_boil_k`` [K] at ambient pressure."""
    p = (P_AMBIENT_PA + 2.0 * surface_tension_n_m / beam_1e2_radius_m(beam_radius_m)) / RECOIL_FRACTION
    b = L_VAP_J_KG * MOLAR_MASS_KG_MOL / R_GAS
    return 1.0 / (1.0 / t_boil_k - math.log(p / P_AMBIENT_PA) / b)


def drill(h: np.ndarray, m: np.ndarray, h_cap: float, n_heated: int = 1) -> np.ndarray:
    """Carry the enthalpy above ``h_cap`` down each column, in place.

    From the top down, a node above ``h_cap`` is set to it and its excess passed to the node
    below, which takes what it can up to ``h_cap``; what no node of the column can take stays in
    its bottom node.  A column is walked down while in its ``n_heated`` top nodes or carrying an
    excess (compiled, :func:`fe_node.kernels.drill_columns`).

    Parameters
    ----------
    h : ndarray, shape (ny, nz, nx)
        Nodal enthalpy [J/m³]; ``h[:, -1, :]`` is the top surface.
    m : ndarray, shape (ny, nz, nx)
        Lumped nodal volumes [m³].
    h_cap : float
        Enthalpy at the keyhole-onset temperature [J/m³].
    n_heated : int
        Top node layers the laser heats directly (the depth of its load); below them only the
        excess carried down can exceed ``h_cap``.

    Returns
    -------
    ndarray of bool, shape (ny, nx)
        The columns drilled (the keyhole's opening).  The sum of ``m * h`` is unchanged.
    """
    from fe_node.kernels import drill_columns

    n_heated = min(max(n_heated, 1), h.shape[1])
    opening = np.empty((h.shape[0], h.shape[2]), dtype=bool)
    drill_columns(h, m, float(h_cap), n_heated, opening)
    return opening


def cavity_absorptivity(a, depth_m: float, radius_m: float):
    """Gouffé's absorptance [-] of a cylindrical keyhole (module docstring) with walls of
    absorptivity ``a`` [-] (any shape), depth ``depth_m`` >= 0 and radius ``radius_m`` > 0 [m]."""
    opening = radius_m / (radius_m + 2.0 * depth_m)
    return a / (a * (1.0 - opening) + opening)


def vapour_depth_m(h: np.ndarray, m: np.ndarray, a_top: np.ndarray, h_boil: float, h_cap: float,
                   weights: np.ndarray) -> float:
    """Depth [m] of the keyhole's vapour under the beam: each column's vapour volume over its top
    area, averaged with ``weights``.

    A node counts with the share of its enthalpy between ``h_boil`` (boiling) and ``h_cap``
    (keyhole onset), clipped to [0, 1].

    Parameters
    ----------
    h : ndarray, shape (ny, nz, nx)
        Nodal enthalpy [J/m³] of a block of whole columns.
    m : ndarray, shape (ny, nz, nx)
        Lumped nodal volumes [m³] (heat-capacity weight 1).
    a_top : ndarray, shape (ny, nx)
        Lumped top areas of the columns [m²].
    h_boil, h_cap : float
        Enthalpies [J/m³] at boiling and at keyhole onset.
    weights : ndarray, shape (ny, nx)
        Weight of each column [-] (the beam's relative intensity).
    """
    share = np.clip((h - h_boil) / (h_cap - h_boil), 0.0, 1.0)
    return float(np.sum(weights * np.einsum("ikj,ikj->ij", m, share)) / np.sum(weights * a_top))
