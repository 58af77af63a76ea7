"""Nonlinear top-surface heat loss ``q_loss(T)`` [W/m²], applied on the lumped facet areas.

``q_loss = h (T - T_amb) + eps sigma (T^4 - T_amb^4)`` with ``T`` capped at the boiling point
(:class:`fe_node.material.Material`).  The semi-discrete boundary term is ``A_i q_loss(T_i)``,
``A`` the lumped areas of the ``facet_area`` form (:mod:`fe_node.forms`).
"""
from __future__ import annotations

import numpy as np

from fe_node.settings import Settings

SIGMA_SB = 5.670374419e-8
"""Stefan-Boltzmann constant [W/(m² K^4)]."""


def loss_flux_slope(t: np.ndarray, settings: Settings) -> np.ndarray:
    """``d q_loss / dT`` [W/(m² K)] at ``t`` [K] (0 above the boiling cap)."""
    s = settings
    return np.where(t < s.material.t_boil, s.h_conv_w_m2k + 4.0 * s.emissivity * SIGMA_SB * t**3, 0.0)


def loss_flux(t: np.ndarray, settings: Settings) -> np.ndarray:
    """Convection + radiation flux [W/m²] at surface temperatures ``t`` [K] (any shape)."""
    s = settings
    t = np.minimum(t, s.material.t_boil)
    return s.h_conv_w_m2k * (t - s.t_amb_k) + s.emissivity * SIGMA_SB * (t**4 - s.t_amb_k**4)


L_VAP_J_KG = 6.43e6
"""Latent heat of vaporisation [J/kg]: nickel, 377.5 kJ/mol / 58.69 g/mol (CRC Handbook)."""
MOLAR_MASS_KG_MOL = 58.69e-3
"""Molar mass of the vapour [kg/mol] (nickel)."""
R_GAS = 8.314462618
"""Gas constant [J/(mol K)]."""
P_AMBIENT_PA = 101325.0
"""Ambient pressure [Pa]: the vapour pressure equals it at the boiling point."""
RECONDENSATION = 0.18
"""Fraction of the evaporated flux that recondenses (Anisimov 1968; Klassen et al. 2014)."""


def evaporation_flux(t, t_boil: float):
    """Evaporative heat flux [W/m²] at surface temperatures ``t`` [K] (Hertz-Knudsen-Langmuir).

    ``q = L_v (1 - beta) p_sat(T) sqrt(M / (2 pi R T))`` with the Clausius-Clapeyron vapour
    pressure ``p_sat = p_amb exp(L_v M / R (1 / T_boil - 1 / T))``: 480 W/m² at the IN625
    liquidus (radiation there: 1.6e5 W/m²), 3.2e8 W/m² at boiling, 5e9 W/m² at 4000 K.
    """
    t = np.asarray(t, dtype=float)
    p_sat = P_AMBIENT_PA * np.exp(L_VAP_J_KG * MOLAR_MASS_KG_MOL / R_GAS * (1.0 / t_boil - 1.0 / t))
    return L_VAP_J_KG * (1.0 - RECONDENSATION) * p_sat * np.sqrt(MOLAR_MASS_KG_MOL / (2.0 * np.pi * R_GAS * t))


def evaporate_top(h: np.ndarray, m: np.ndarray, law, k: np.ndarray, lost: np.ndarray) -> float:
    """Backward-Euler evaporative cooling of the liquid top nodes of the (ny, nz, nx) enthalpy ``h``
    [J/m³], in place.

    Solves ``C (T - T*) + k q_evap(T) = 0`` per node above the liquidus (:func:`evaporation_flux`,
    ``C`` the liquid volumetric heat capacity, ``H`` linear in ``T`` there), then ``H -= C (T* - T)``.
    Implicit because the flux is stiff: ``dq/dT`` reaches 1e7 W/(m² K) at 4000 K, 10x the explicit
    limit at 50 µs. One compiled pass (:func:`fe_node.kernels.evaporate_top`).

    Parameters
    ----------
    h, m : ndarray, shape (ny, nz, nx)
        Nodal enthalpy [J/m³] (updated) and lumped masses [m³].
    law : Constitutive
        The material's tables (:class:`fe_node.material.Constitutive`).
    k : ndarray, shape (ny, nx)
        ``dt A / m`` of the top nodes [s/m].
    lost : ndarray
        Scratch of at least ny nx values.

    Returns
    -------
    float
        The energy evaporated [J].
    """
    from fe_node.kernels import evaporate_top as evaporate_nodes_on_top

    if not (h.ndim == 3 and m.shape == h.shape and k.shape == (h.shape[0], h.shape[2]) and lost.size >= k.size):
        raise ValueError(f"evaporate_top: h {h.shape}, m {m.shape}, k {k.shape} (ny, nx) and lost of at least ny nx "
                         f"values ({lost.size})")
    mat = law.material
    n = evaporate_nodes_on_top(h, m, *law.temperature_table, k, float(law.liquid_heat_capacity), float(mat.t_boil),
                               float(mat.t_liquidus), L_VAP_J_KG * (1.0 - RECONDENSATION) * P_AMBIENT_PA,
                               L_VAP_J_KG * MOLAR_MASS_KG_MOL / R_GAS, MOLAR_MASS_KG_MOL / (2.0 * np.pi * R_GAS), 100,
                               lost)
    return float(np.sum(lost[:n]))
