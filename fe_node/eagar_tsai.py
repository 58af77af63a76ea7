"""Eagar-Tsai reference: quasi-steady moving Gaussian surface source on a semi-infinite body.

Constant properties, no latent heat, no surface losses.  The source is the c -> 0 limit
of paper eq. 6, a surface Gaussian of standard deviation ``s = r_s / sqrt(6)`` carrying
``a P``.  In the frame of the beam (moving in +x at speed v, ``xi = x - x_beam``, z <= 0
into the body), superposing instantaneous Gaussian surface sources (doubled for the
insulated surface) gives

    T - T0 = 2 a P / (rho c) * int_0^inf exp(-((xi + v t)² + y²) / (2 (s² + 2 alpha t))
             - z² / (4 alpha t)) / (2 pi (s² + 2 alpha t) sqrt(4 pi alpha t)) dt

(T. W. Eagar, N.-S. Tsai, Welding J. 62 (1983) 346).  With ``t = u²`` the integrand is
smooth; it is integrated by composite Gauss-Legendre quadrature.  Boundaries of the
liquid region are found by vectorised bisection; the top-surface area is
``int 2 w(xi) dxi`` with the substitution ``xi = c + h cos(theta)`` that removes the
square-root end behaviour.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from fe_node.material import Material

_IN625 = Material.in625()


@dataclass(frozen=True)
class EagarTsaiCase:
    """Inputs (SI units): by default the plant's process on IN625's density and liquidus, with
    constant conductivity and specific heat."""

    power_w: float = 250.0
    absorptivity: float = 0.4
    beam_radius_m: float = 50e-6
    k: float = 20.0
    rho: float = _IN625.rho
    cp: float = 600.0
    speed_m_s: float = 0.8
    t_liquidus_k: float = _IN625.t_liquidus
    t0_k: float = 300.0

    def as_dict(self) -> dict:
        return asdict(self)


class EagarTsai:
    """Temperature field and melt-pool geometry of an :class:`EagarTsaiCase`.

    Parameters
    ----------
    case : EagarTsaiCase
    n_panels, n_gauss : int
        Composite Gauss-Legendre rule in ``u = sqrt(t)``.
    """

    def __init__(self, case: EagarTsaiCase, n_panels: int = 400, n_gauss: int = 8):
        self.case = c = case
        self.alpha = c.k / (c.rho * c.cp)
        self.s2 = c.beam_radius_m**2 / 6.0
        # source history that matters: 5x the passage over the 20 r_s search range,
        # plus 50 diffusion times 4 alpha / v² (the integrand then is < e^-50)
        self.search_m = 20 * c.beam_radius_m
        t_max = 5 * self.search_m / c.speed_m_s + 200 * self.alpha / c.speed_m_s**2
        x, w = np.polynomial.legendre.leggauss(n_gauss)
        edges = np.linspace(0.0, np.sqrt(t_max), n_panels + 1)
        half = np.diff(edges)[:, None] / 2
        self._u = ((edges[:-1, None] + half) + half * x).ravel()
        self._w = (half * w).ravel()

    def temperature(self, xi, y, z):
        """Temperature [K] at beam-frame points (broadcastable arrays, m; z <= 0)."""
        c = self.case
        xi, y, z = np.broadcast_arrays(*(np.asarray(a, dtype=float)[..., None] for a in (xi, y, z)))
        t = self._u**2
        var = self.s2 + 2 * self.alpha * t
        g = (np.exp(-((xi + c.speed_m_s * t) ** 2 + y**2) / (2 * var)
                    - z**2 / (4 * self.alpha * np.maximum(t, 1e-300)))
             / (2 * np.pi * var))
        # dt / sqrt(4 pi alpha t) = 2 u du / (sqrt(4 pi alpha) u) = 2 du / sqrt(4 pi alpha)
        integral = (g * self._w).sum(axis=-1) * 2 / np.sqrt(4 * np.pi * self.alpha)
        return c.t0_k + 2 * c.absorptivity * c.power_w / (c.rho * c.cp) * integral

    def _bisect(self, f, lo, hi, n=60):
        """Vectorised bisection for f(x) = T_liquidus with f(lo) > T_l > f(hi)."""
        lo, hi = np.array(lo, dtype=float), np.array(hi, dtype=float)
        tl = self.case.t_liquidus_k
        for _ in range(n):
            mid = 0.5 * (lo + hi)
            hot = f(mid) > tl
            lo, hi = np.where(hot, mid, lo), np.where(hot, hi, mid)
        return 0.5 * (lo + hi)

    def geometry(self, n_theta: int = 48) -> dict:
        """Quasi-steady melt pool: area_m2 (top surface), length_m, width_m, depth_m.

        Raises
        ------
        ValueError
            If the surface never reaches the liquidus.
        """
        tl = self.case.t_liquidus_k
        xi = np.linspace(-self.search_m, self.search_m / 4, 2001)
        tc = self.temperature(xi, 0.0, 0.0)
        i = int(np.argmax(tc))
        if tc[i] <= tl:
            raise ValueError("Eagar-Tsai: no melting for this case")
        far = 100 * self.case.beam_radius_m
        front = self._bisect(lambda x: self.temperature(x, 0.0, 0.0), xi[i], xi[i] + far)
        if tc[0] > tl:
            raise ValueError("Eagar-Tsai: pool longer than the search range")
        rear = self._bisect(lambda x: self.temperature(x, 0.0, 0.0), xi[i], xi[0])
        centre, half = 0.5 * (front + rear), 0.5 * (front - rear)
        theta, wts = np.polynomial.legendre.leggauss(n_theta)
        theta = 0.5 * np.pi * (theta + 1)
        wts = 0.5 * np.pi * wts
        xq = centre + half * np.cos(theta)
        w = self._bisect(lambda y: self.temperature(xq, y, 0.0), np.zeros_like(xq), np.full_like(xq, far))
        area = float(np.sum(2 * w * half * np.sin(theta) * wts))
        xs = np.linspace(rear, front, 401)[1:-1]
        wy = self._bisect(lambda y: self.temperature(xs, y, 0.0), np.zeros_like(xs), np.full_like(xs, far))
        dz = self._bisect(lambda z: self.temperature(xs, 0.0, -z), np.zeros_like(xs), np.full_like(xs, far))
        return dict(area_m2=area, length_m=float(front - rear), width_m=float(2 * wy.max()),
                    depth_m=float(dz.max()))
