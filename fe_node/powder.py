"""The powder bed of the plant: element weights of powder and consolidated metal, consolidation.

The layers above the plate are meshed in mass coordinates: a layer of thickness
``powder_layer_m`` (the platform drop per layer, i.e. the height of the dense metal the layer
becomes) holds the mass of the powder spread over it, ``powder_layer_m / packing`` thick at
packing density ``packing``.  So powder elements carry the dense heat capacity (``rho_w = 1``)
and the vertical conductance of the spread powder: ``k_powder / (t / packing)`` over a mesh
thickness ``t`` gives ``kw = packing * k_powder / k_dense`` (IN625 powder: 1.01 W/(m K) at
500 °C, ASME J. Manuf. Sci. Eng. 140(11):111008).  An element whose mean nodal temperature passes
the liquidus consolidates to dense metal (``kw = rho_w = 1``): the layer shrinks to the height
its mass gives, which is the mesh's height, with no mass or energy moved.
"""
from __future__ import annotations

import numpy as np

from fe_node.settings import Settings

T_POWDER_K = 773.15
"""Temperature of the powder conductivity value [K] (500 °C)."""
KW_DENSE = 1.0
"""Conductivity weight of dense (plate or consolidated) metal [-]."""
RHO_W = 1.0
"""Heat-capacity weight of every element [-]: in mass coordinates powder holds the dense mass."""


class PowderBed:
    """Which elements are powder and which consolidated.

    Parameters
    ----------
    settings : Settings
        ``powder_layer_m > 0``, ``powder_k_w_mk``, ``powder_packing``.
    zs : ndarray, shape (nz,)
        Node heights [m]; elements above z = 0 are powder.
    plan_shape : (int, int)
        Element counts along y and x.

    Attributes
    ----------
    k0 : int
        First powder element layer.
    consolidated : ndarray of bool, shape (ny - 1, n_powder_layers, nx - 1)
        Consolidated powder elements.
    """

    def __init__(self, settings: Settings, zs: np.ndarray, plan_shape: tuple[int, int]):
        s = settings
        self.k0 = int(np.argmax(0.5 * (zs[1:] + zs[:-1]) > 0))
        self.consolidated = np.zeros((plan_shape[0], len(zs) - 1 - self.k0, plan_shape[1]), dtype=bool)
        self.kw_powder = s.powder_packing * s.powder_k_w_mk / float(s.material.k(T_POWDER_K))
        self.t_liquidus = s.material.t_liquidus

    def layer_weights(self, n_layers: int) -> tuple[np.ndarray, np.ndarray]:
        """(kw, rho_w) [-] of the ``n_layers`` z element layers before consolidation, shape (n_layers,)."""
        powder = np.arange(n_layers) >= self.k0
        return np.where(powder, self.kw_powder, KW_DENSE), np.full(n_layers, RHO_W)

    def grow(self, n_layers: int) -> None:
        """``n_layers`` new element layers of powder on top."""
        ny, _, nx = self.consolidated.shape
        self.consolidated = np.concatenate([self.consolidated, np.zeros((ny, n_layers, nx), dtype=bool)], axis=1)

    def surface_fraction(self) -> np.ndarray:
        """Consolidated share [-] of the top element layer around each top node, shape (ny, nx):
        the mean of the (up to four) top elements that share the node."""
        top = np.pad(self.consolidated[:, -1, :].astype(float), 1, mode="edge")
        return 0.25 * (top[:-1, :-1] + top[:-1, 1:] + top[1:, :-1] + top[1:, 1:])

    def consolidate(self, t: np.ndarray) -> np.ndarray:
        """Mark the powder elements that melted (mean nodal temperature above the liquidus; compiled,
        :func:`fe_node.kernels.melt_powder`); returns their flat indices in the full element order.

        Parameters
        ----------
        t : ndarray, shape (ny, nz - k0, nx)
            Nodal temperatures [K] of the powder layers (from the plate's top nodes up).
        """
        from fe_node.kernels import melt_powder

        self.consolidated = np.ascontiguousarray(self.consolidated)
        out = np.empty(self.consolidated.size, dtype=np.intp)
        n = melt_powder(np.ascontiguousarray(t, dtype=float), float(self.t_liquidus), self.consolidated, self.k0, out)
        return out[:n]
