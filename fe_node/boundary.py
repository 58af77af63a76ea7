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


def loss_flux(t: np.ndarray, settings: Settings) -> np.ndarray:
    """Convection + radiation flux [W/m²] at surface temperatures ``t`` [K] (any shape)."""
    s = settings
    t = np.minimum(t, s.material.t_boil)
    return s.h_conv_w_m2k * (t - s.t_amb_k) + s.emissivity * SIGMA_SB * (t**4 - s.t_amb_k**4)
