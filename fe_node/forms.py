"""The plant's physics as scikit-fem forms: the single definition both operators implement.

Transient heat conduction of the powder bed in enthalpy form with the Kirchhoff variable
(paper Sec. II.D; :mod:`fe_node.material`):

    rho_w H_t = div(k_ref kw grad phi(H))          in the body,
    k_ref kw d(phi)/dn = q_laser - q_loss(T)        on the top face,    insulated elsewhere,

``H`` the volumetric enthalpy of the dense metal [J/m³], ``phi`` the Kirchhoff variable [K]
(so ``k_ref grad phi = k(T) grad T``), ``rho_w`` [-] the relative density of the material
(1 dense, the packing density in powder) and ``kw`` [-] a conductivity weight (1 dense,
``k_powder / k`` in powder), both constant per element.  The Galerkin forms:

* :data:`conduction` ``kw grad u . grad v`` — the stiffness ``K_w`` [m] (``k_ref`` factored out);
* :data:`conduction_z` ``kw du/dz dv/dz`` — its vertical part ``K_z``: with an effective
  anisotropic liquid conductivity (Marangoni flow) the horizontal and vertical fluxes act on
  their own Kirchhoff variables, ``K_w phi_xy + K_z (phi_z - phi_xy)`` (:mod:`fe_node.material`);
* :data:`mass` ``rho_w u v`` — the mass, lumped by row sums to nodal volumes ``m`` [m³];
* :data:`laser` — eq. 6 in its c -> 0 limit, a surface Gaussian per unit absorbed power [1/m²];
* :data:`facet_area` ``v`` on the top facets — lumped facet areas ``A`` [m²] carrying the
  nonlinear boundary flux ``q_loss(T)`` (:func:`fe_node.boundary.loss_flux`).

The semi-discrete system is ``m dH/dt = -k_ref K_w phi(H) + a P f_laser - A q_loss(T)``.
:mod:`fe_node.operators` implements ``K_w`` and ``m`` twice (a CSR matrix for any mesh and a
tensor-product specialisation for graded box grids), tested equal to these forms.
"""
from __future__ import annotations

import numpy as np
from skfem import BilinearForm, LinearForm
from skfem.helpers import dot, grad


@BilinearForm
def conduction(u, v, w):
    """``kw grad u . grad v`` [1/m² per m³]; ``w.kw`` per-element conductivity weight [-]."""
    return w.kw * dot(grad(u), grad(v))


@BilinearForm
def conduction_z(u, v, w):
    """``kw du/dz dv/dz``: the vertical part of :data:`conduction`."""
    return w.kw * grad(u)[2] * grad(v)[2]


@BilinearForm
def mass(u, v, w):
    """``rho_w u v``; ``w.rho_w`` per-element relative density [-] (lump by row sums)."""
    return w.rho_w * u * v


@LinearForm
def laser(v, w):
    """Eq. 6 (c -> 0) per unit absorbed power: ``3 / (pi r²) exp(-3 rho² / r²) v`` [1/m²].

    ``w.xl``, ``w.yl``: beam centre [m]; ``w.r``: beam radius r_s [m].  Integrates to 1 over
    the plane, so the nodal load of an absorbed power ``a P`` is ``a P`` times this vector.
    """
    rho2 = (w.x[0] - w.xl) ** 2 + (w.x[1] - w.yl) ** 2
    return 3.0 / (np.pi * w.r**2) * np.exp(-3.0 * rho2 / w.r**2) * v


@LinearForm
def facet_area(v, _):
    """``v`` on boundary facets: lumped facet areas [m²] (row sums of the facet mass)."""
    return v
