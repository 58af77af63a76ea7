"""Material model: temperature-dependent IN625 (or constant properties) in enthalpy form.

The solver's state is the volumetric enthalpy ``H`` [J/m³]; conduction acts on the
Kirchhoff variable ``phi`` [K],

    phi(T) = (1 / k_ref) * integral_0^T k(s) ds,      div(k grad T) = k_ref * lap(phi),

so the stiffness matrix never changes while k depends on T.  ``H(T) = rho * integral_0^T
cp(s) ds + rho * L * f_liq(T)`` with a liquid fraction rising linearly from solidus to
liquidus.  ``H -> T`` and ``H -> phi`` are piecewise-linear look-up tables, uniform in
``H`` so a look-up is an index computation and a gather (no search).  The table is the
constitutive law; energy bookkeeping is done in ``H`` and is exact regardless.

Property set (IN625)
--------------------
Linear set of the Penn State group, as used by Q. Wang, P. Michaleris, A. R. Nassar et al.,
"Model-based feedforward control of laser powder bed fusion additive manufacturing",
Additive Manufacturing 31 (2020) 100985 (the paper's reference [WangAM2020]):
cp = 405 + 0.247 T[°C] J/(kg K), k = 9.5 + 0.0150 T[°C] W/(m K) capped at the solidus,
latent heat L = 2.8e5 J/kg; rho = 8440 kg/m³ and the melting range 1290-1350 °C (solidus
1563 K, liquidus 1623 K) from the Special Metals INCONEL alloy 625 datasheet
(docs/fe.md, "Material data and sources").

Liquid choices (documented assumptions; an effective, optionally anisotropic liquid
conductivity for Marangoni flow is a plant option, see :meth:`Constitutive.mushy_integral`):

* k in the liquid stays at its solidus value, 28.85 W/(m K).  The paper's FE model is
  conduction only with no Marangoni enhancement, and the tabulated set of the open-source
  code mlhpbf gives 31.9 W/(m K) just below and 27 W/(m K) above melting, i.e. no jump.
* cp is held at its liquidus value, 738 J/(kg K), in the liquid (mlhpbf: 769 liquid).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from messages.in625 import (
    CP_0C_J_KGK,
    CP_SLOPE_J_KGK2,
    K_0C_W_MK,
    K_SLOPE_W_MK2,
    LATENT_J_KG,
    RHO_KG_M3,
    T_BOIL_K,
    T_LIQUIDUS_K,
    T_SOLIDUS_K,
)

_C0 = 273.15


@dataclass(frozen=True)
class Material:
    """Thermal properties, linear in temperature and capped (see module docstring).

    Parameters
    ----------
    name : str
        Label.
    rho : float
        Density [kg/m³].
    cp_a, cp_b : float
        ``cp = cp_a + cp_b * (T - 273.15)`` [J/(kg K)], T [K], held constant above
        ``t_liquidus``.
    k_a, k_b : float
        ``k = k_a + k_b * (T - 273.15)`` [W/(m K)], held constant above ``t_solidus``.
    latent : float
        Latent heat of fusion [J/kg], released linearly between solidus and liquidus.
    t_solidus, t_liquidus : float
        [K].
    t_boil : float
        Boiling point [K] (Ni 3186 K; 3190 K is the value commonly used for Ni
        superalloys).  Only caps the temperature used in the surface losses: this
        conduction model has no evaporation, so the spot centre can superheat far above
        boiling (1e4 K), where radiation would otherwise be an artefact of several %.
    """

    name: str = "IN625"
    rho: float = RHO_KG_M3
    cp_a: float = CP_0C_J_KGK
    cp_b: float = CP_SLOPE_J_KGK2
    k_a: float = K_0C_W_MK
    k_b: float = K_SLOPE_W_MK2
    latent: float = LATENT_J_KG
    t_solidus: float = T_SOLIDUS_K
    t_liquidus: float = T_LIQUIDUS_K
    t_boil: float = T_BOIL_K

    def __post_init__(self):
        if not (self.rho > 0 and self.latent >= 0):
            raise ValueError("material: rho must be > 0 and latent heat >= 0")
        if not 0 < self.t_solidus < self.t_liquidus < self.t_boil:
            raise ValueError("material: need 0 < t_solidus < t_liquidus < t_boil")
        for what, f in (("cp", self.cp), ("k", self.k)):
            if min(f(0.0), f(self.t_liquidus)) <= 0:
                raise ValueError(f"material: {what} must stay positive")

    @classmethod
    def in625(cls) -> Material:
        """Temperature-dependent IN625 (Penn State linear set, module docstring)."""
        return cls()

    @classmethod
    def constant(cls, k: float, rho: float, cp: float, latent: float = 0.0,
                 t_solidus: float = T_SOLIDUS_K, t_liquidus: float = T_LIQUIDUS_K) -> Material:
        """Constant k [W/(m K)], rho [kg/m³], cp [J/(kg K)]; optional latent heat [J/kg]."""
        return cls(name="constant", rho=rho, cp_a=cp, cp_b=0.0, k_a=k, k_b=0.0,
                   latent=latent, t_solidus=t_solidus, t_liquidus=t_liquidus)

    def cp(self, t):
        """Specific heat [J/(kg K)] at temperature ``t`` [K] (array-like)."""
        return self.cp_a + self.cp_b * (np.minimum(t, self.t_liquidus) - _C0)

    def k(self, t):
        """Thermal conductivity [W/(m K)] at temperature ``t`` [K] (array-like)."""
        return self.k_a + self.k_b * (np.minimum(t, self.t_solidus) - _C0)

    @property
    def k_ref(self) -> float:
        """Reference conductivity of the Kirchhoff transform, k(solidus) [W/(m K)]."""
        return float(self.k(self.t_solidus))


class Constitutive:
    """Uniform-in-H look-up tables ``H -> T`` and ``H -> phi`` for a :class:`Material`.

    Parameters
    ----------
    material : Material
    n_table : int
        Number of table intervals between 0 K and ``t_liquidus + 50 K``.  Above the table
        both maps are extrapolated linearly, which is exact there (cp, k constant).
    """

    def __init__(self, material: Material, n_table: int = 1 << 15):
        m = material
        self.material = m
        self.k_ref = m.k_ref
        # fine temperature grid containing the property kinks -> trapezoid sums are exact
        t = np.unique(np.concatenate([np.linspace(0.0, m.t_liquidus + 50.0, 400_001),
                                      [m.t_solidus, m.t_liquidus]]))
        cp, k = m.cp(t), m.k(t)
        dt = np.diff(t)
        h = np.concatenate([[0.0], np.cumsum(0.5 * (cp[1:] + cp[:-1]) * dt)]) * m.rho
        h += m.rho * m.latent * np.clip((t - m.t_solidus) / (m.t_liquidus - m.t_solidus), 0, 1)
        phi = np.concatenate([[0.0], np.cumsum(0.5 * (k[1:] + k[:-1]) * dt)]) / self.k_ref
        self._t_grid, self._h_grid, self._phi_grid = t, h, phi
        hn = np.linspace(h[0], h[-1], n_table + 1)
        tn = np.interp(hn, h, t)
        pn = np.interp(hn, h, phi)
        self._h0 = hn[0]
        self._inv_dh = n_table / (hn[-1] - hn[0])
        self._imax = n_table - 1
        sl_t = np.diff(tn) / np.diff(hn)
        sl_p = np.diff(pn) / np.diff(hn)
        self._t_a, self._t_b = tn[:-1] - sl_t * hn[:-1], sl_t
        self._p_a, self._p_b = pn[:-1] - sl_p * hn[:-1], sl_p
        # the last interval is inside the liquid: make it the exact liquid line
        cpl = float(m.cp(m.t_liquidus))
        h_liq = float(np.interp(m.t_liquidus, t, h))
        phi_liq = float(np.interp(m.t_liquidus, t, phi))
        self._t_b[-1] = 1.0 / (m.rho * cpl)
        self._t_a[-1] = m.t_liquidus - h_liq * self._t_b[-1]
        self._p_b[-1] = float(m.k(m.t_liquidus)) / self.k_ref / (m.rho * cpl)
        self._p_a[-1] = phi_liq - h_liq * self._p_b[-1]
        self.max_diffusivity = float(self.k_ref * self._p_b.max())
        """Largest k/(rho cp) [m²/s] of the table (explicit stability)."""
        self.liquid_heat_capacity = m.rho * cpl
        """rho cp above the liquidus [J/(m³ K)]; ``H`` is linear in ``T`` there."""
        self.mushy_floor = float(np.interp(m.t_solidus, t, h)) - 2.0 / self._inv_dh
        """Enthalpy [J/m³] at and below which :meth:`mushy_integral` is 0: two table intervals
        below the solidus (the table's ``T`` is monotone and exact at its nodes)."""

    def _index(self, h):
        """Table interval of each ``h``, clipped to the table."""
        x, i = np.empty(np.shape(h)), np.empty(np.shape(h), dtype=np.intp)
        np.subtract(h, self._h0, out=x)
        x *= self._inv_dh
        i[...] = x                                  # truncation, as ``astype``
        return np.clip(i, 0, self._imax, out=i)

    def temperature(self, h):
        """Temperature [K] from enthalpy ``h`` [J/m³] (any shape; a scalar for a scalar): one
        compiled pass, :func:`fe_node.kernels.piecewise_linear` (a strided ``h`` is copied first)."""
        from fe_node.kernels import piecewise_linear

        h = np.asarray(h, dtype=float)
        out = np.empty(h.shape)
        piecewise_linear(np.ascontiguousarray(h).reshape(-1), self._h0, self._inv_dh, self._imax, self._t_a,
                         self._t_b, out.reshape(-1))
        return out if h.ndim else out[()]

    def temperature_slope(self, h):
        """``dT / dH`` [K m³/J] at enthalpy ``h`` (the table's slope)."""
        return self._t_b[self._index(h)]

    def kirchhoff_slope(self, h):
        """``d phi / d H`` [K m³/J] at enthalpy ``h`` (the table's slope; small in the mushy range)."""
        return self._p_b[self._index(h)]

    def kirchhoff(self, h, out=None):
        """Kirchhoff variable phi [K] from enthalpy ``h`` [J/m³] (any shape).

        ``out`` (C-contiguous, h's shape) receives the result: no array is allocated on the
        explicit stepping path (one compiled pass, :func:`fe_node.kernels.piecewise_linear`).
        """
        from fe_node.kernels import piecewise_linear

        h = np.ascontiguousarray(h, dtype=float)
        out = np.empty_like(h) if out is None else out
        if out.shape != h.shape or not out.flags.c_contiguous:
            raise ValueError(f"kirchhoff: out must be C-contiguous of shape {h.shape}")
        piecewise_linear(h.reshape(-1), self._h0, self._inv_dh, self._imax, self._p_a, self._p_b, out.reshape(-1))
        return out

    @property
    def temperature_table(self) -> tuple[float, float, int, np.ndarray, np.ndarray]:
        """The temperature table for the compiled passes: ``h0``, ``1 / dh``, the last interval, and each
        interval's ``a``, ``b`` (``T = b H + a``; :func:`fe_node.kernels.piecewise_linear`)."""
        return self._h0, self._inv_dh, self._imax, self._t_a, self._t_b

    def kirchhoff_above(self, h: np.ndarray, floor: float, out: np.ndarray, box: np.ndarray) -> bool:
        """:meth:`kirchhoff` of the (ny, nz, nx) C-contiguous ``h`` into ``out`` (the same) and, in the same
        compiled pass (:func:`fe_node.kernels.piecewise_linear_box`), the smallest box of nodes with
        ``h > floor`` [J/m³] into ``box`` (int, 6: first and past-last y, z, x index); False if there is none.
        ValueError unless ``h`` and ``out`` are C-contiguous 3-D float arrays of one shape and ``box`` holds 6 ints
        (the compiled pass does not check its indices)."""
        from fe_node.kernels import piecewise_linear_box

        if not (h.ndim == 3 and h.shape == out.shape and h.flags.c_contiguous and out.flags.c_contiguous
                and h.dtype == out.dtype == np.float64 and box.shape == (6,) and box.dtype == np.intp):
            raise ValueError(f"kirchhoff_above: h {h.shape} and out {out.shape} must be C-contiguous float arrays "
                             f"of one 3-D shape, box {box.shape} 6 ints")
        return piecewise_linear_box(h, self._h0, self._inv_dh, self._imax, self._p_a, self._p_b, floor, out, box)

    def add_mushy_integral(self, h: np.ndarray, box: np.ndarray, in_plane: float, vertical: float,
                           phi: np.ndarray) -> np.ndarray:
        """``phi += in_plane psi`` on the node box ``box`` (as :meth:`kirchhoff_above` gives it) of the
        (ny, nz, nx) arrays ``h``, ``phi``; returns ``vertical psi`` on the box, ``psi`` the
        :meth:`mushy_integral` at ``h`` (one compiled pass, :func:`fe_node.kernels.add_mushy_integral`)."""
        from fe_node.kernels import add_mushy_integral

        m = self.material
        u_box = np.empty((box[1] - box[0], box[3] - box[2], box[5] - box[4]))
        add_mushy_integral(h, box, *self.temperature_table, m.t_solidus, m.t_liquidus, in_plane, vertical, phi, u_box)
        return u_box

    def mushy_integral(self, h):
        """``psi = int_solidus^T f_liq(s) ds`` [K] at enthalpy ``h`` [J/m³] (any shape).

        With a liquid conductivity enhanced by ``f`` (ramping with the liquid fraction
        ``f_liq``), the Kirchhoff variable becomes ``phi + (f - 1) psi`` (k = k_ref above the
        solidus).
        """
        m = self.material
        t = self.temperature(h)
        dt = m.t_liquidus - m.t_solidus
        return np.where(t < m.t_liquidus, np.maximum(t - m.t_solidus, 0.0) ** 2 / (2 * dt),
                        0.5 * dt + (t - m.t_liquidus))

    def enthalpy(self, t):
        """Volumetric enthalpy [J/m³] at temperature ``t`` [K] (setup use, exact)."""
        t = np.asarray(t, dtype=float)
        m = self.material
        hl = np.interp(np.minimum(t, self._t_grid[-1]), self._t_grid, self._h_grid)
        extra = np.maximum(t - self._t_grid[-1], 0.0) * m.rho * float(m.cp(m.t_liquidus))
        return hl + extra
