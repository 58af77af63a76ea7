"""The IN625 alloy's thermal properties (SI, temperatures in K), defined once.

The plant's material (:class:`fe_node.material.Material`, whose docstring gives the sources),
the model's turnaround feature (:mod:`gp_model.plan_feature`) and the analytic stand-in plants
build from these. Specific heat and conductivity are linear in the temperature in °C,
``cp = CP_0C + CP_SLOPE · T[°C]`` (held above the liquidus) and ``k = K_0C + K_SLOPE · T[°C]``
(held above the solidus).
"""

RHO_KG_M3 = 8440.0
"""Density [kg/m³]."""
CP_0C_J_KGK = 405.0
"""Specific heat at 0 °C [J/(kg K)]."""
CP_SLOPE_J_KGK2 = 0.247
"""Slope of the specific heat [J/(kg K²)]."""
K_0C_W_MK = 9.5
"""Conductivity at 0 °C [W/(m K)]."""
K_SLOPE_W_MK2 = 0.0150
"""Slope of the conductivity [W/(m K²)]."""
LATENT_J_KG = 2.8e5
"""Latent heat of fusion [J/kg]."""
T_SOLIDUS_K = 1563.0
"""Solidus [K]."""
T_LIQUIDUS_K = 1623.0
"""Liquidus [K]."""
T_BOIL_K = 3190.0
"""Boiling point [K]."""
