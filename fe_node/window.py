"""A fine window that follows the laser: a node count bounded as the part grows (``window_m``).

:func:`fe_node.solver.build_grid` puts its ``h_fine_m`` band over the whole scan plan, so the
node count grows with the part's plan area.  With ``Settings.window_m > 0`` the band in x and y
covers only a square of that side around the laser; outside it the elements grow to ``h_max_m``
as before.  The plant remeshes (:meth:`fe_node.solver.ThermalModel.step`) when the laser comes
within ``window_m / 4`` of the window's edge (:func:`needs_move`); the new window is centred
``window_m / 4`` ahead of the laser (:func:`ahead`).

Transfer (:func:`transfer`): the window's edges lie on the lattice of the whole-plan band,
so nodes that stay fine keep their coordinates and values; elsewhere the enthalpy is
interpolated linearly along x and y (z is unchanged), and the enthalpy above the preheat state
at those interpolated nodes is scaled so that the energy is unchanged (:func:`conserve`;
interpolation onto coarser elements overestimates the convex profile around the tracks).  The
powder's consolidation is kept on the band's lattice (:class:`ConsolidationLattice`): each new
powder element gets the conductivity of its consolidated share; other elements take the weights
of the old element containing their centre.
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.mesh import graded_axis
from fe_node.observe import interp_matrix

EDGE_FRACTION = 0.25
"""Remesh when the laser is closer than this fraction of ``window_m`` to the window's edge; the
new window's centre lies this fraction of ``window_m`` ahead of the laser."""


def window_axis(lo: float, hi: float, band_lo: float, band_hi: float, centre: float, width: float, h: float,
                growth: float, h_max: float) -> np.ndarray:
    """Node coordinates [m] along one axis with the fine band cut to ``width`` around ``centre``.

    ``band_lo``, ``band_hi`` bound the whole-plan fine band, whose spacing ``hf <= h`` (as
    :func:`graded_axis` makes it) is the lattice the window's edges snap to.
    """
    n = max(1, math.ceil((band_hi - band_lo) / h - 1e-9))
    hf = (band_hi - band_lo) / n
    i0 = min(max(math.floor((centre - 0.5 * width - band_lo) / hf), 0), n - 1)
    i1 = max(min(math.ceil((centre + 0.5 * width - band_lo) / hf), n), i0 + 1)
    return graded_axis(lo, hi, band_lo + i0 * hf, band_lo + i1 * hf, hf * (1 + 1e-9), growth, h_max)


def fine_extent(coords: np.ndarray, h_fine: float) -> tuple[float, float]:
    """First and last coordinate [m] of the run of elements of size ``<= h_fine`` on an axis."""
    fine = np.flatnonzero(np.diff(coords) <= h_fine * (1 + 1e-6))
    return float(coords[fine[0]]), float(coords[fine[-1] + 1])


def needs_move(axes: tuple[np.ndarray, np.ndarray], bands: tuple[tuple[float, float], ...], h_fine: float,
               points: np.ndarray, width: float) -> bool:
    """True if the window no longer holds ``EDGE_FRACTION * width`` of fine mesh around one of
    ``points`` (shape (n, 2), [m]) on x or y, where the whole-plan band (``bands``) has it.

    Parameters
    ----------
    axes : (ndarray, ndarray)
        Node coordinates along x and y [m].
    bands : ((float, float), (float, float))
        The whole-plan fine band along x and y [m].
    """
    margin = EDGE_FRACTION * width
    for coords, (band_lo, band_hi), axis in zip(axes, bands, (0, 1)):
        lo, hi = fine_extent(coords, h_fine)
        for p in points[:, axis]:
            if max(band_lo, p - margin) < lo - 1e-3 * h_fine or min(band_hi, p + margin) > hi + 1e-3 * h_fine:
                return True
    return False


def ahead(xy: np.ndarray, direction: np.ndarray, width: float) -> np.ndarray:
    """The new window's centre [m]: ``EDGE_FRACTION * width`` ahead of the laser."""
    return np.asarray(xy, dtype=float) + EDGE_FRACTION * width * np.asarray(direction, dtype=float)


def element_map(old: np.ndarray, new: np.ndarray) -> np.ndarray:
    """For each element of axis ``new``, the element of axis ``old`` containing its centre."""
    centres = 0.5 * (new[1:] + new[:-1])
    return np.clip(np.searchsorted(old, centres, side="right") - 1, 0, len(old) - 2)


def transfer(h: np.ndarray, old_xs: np.ndarray, old_ys: np.ndarray, new_xs: np.ndarray,
             new_ys: np.ndarray) -> np.ndarray:
    """Nodal field of shape (ny, nz, nx) on the old x, y axes → the new ones (linear in x and y)."""
    iy, ix = interp_matrix(old_ys, new_ys), interp_matrix(old_xs, new_xs)
    return np.einsum("ab,bkc,dc->akd", iy, h, ix, optimize=True)


def kept(old: np.ndarray, new: np.ndarray, tol: float) -> np.ndarray:
    """True for the coordinates of axis ``new`` that are also nodes of axis ``old`` (within ``tol``)."""
    i = np.clip(np.searchsorted(old, new), 1, len(old) - 1)
    return np.minimum(np.abs(old[i] - new), np.abs(old[i - 1] - new)) <= tol


def conserve(h: np.ndarray, mass: np.ndarray, interpolated: np.ndarray, energy_j: float, h_ref: float) -> float:
    """Scale the enthalpy above ``h_ref`` at the ``interpolated`` nodes so that ``sum(mass * h)``
    equals ``energy_j`` again (in place); returns the factor.  Linear interpolation onto coarser
    elements overestimates a convex profile (the heat around the tracks) and so creates energy.
    """
    excess = float(np.sum(mass[interpolated] * (h[interpolated] - h_ref)))
    deficit = energy_j - float(np.sum(mass * h))
    factor = 1.0 + deficit / excess if excess > 0 else 1.0
    h[interpolated] = h_ref + factor * (h[interpolated] - h_ref)
    return factor


SHARES_KEPT = 6
"""Grids whose :meth:`ConsolidationLattice.fraction` is kept (the three levels, and the boxes a move compares)."""


class ConsolidationLattice:
    """Which powder has consolidated, on the cells of the whole-plan band's lattice.

    The window's elements change at every remesh; consolidation is a property of the material,
    so it is kept here, independent of the mesh: a cell is consolidated once an element covering
    it consolidated.  An element's consolidated fraction is the share of its cells that are.

    Parameters
    ----------
    band_x, band_y : (float, float)
        The whole-plan fine band along x and y [m].
    h : float
        ``h_fine_m`` [m] (the lattice spacing is the band's, ``<= h``).
    n_layers : int
        Powder element layers.
    """

    def __init__(self, band_x: tuple[float, float], band_y: tuple[float, float], h: float, n_layers: int):
        self.edges = [np.linspace(lo, hi, max(1, math.ceil((hi - lo) / h - 1e-9)) + 1) for lo, hi in (band_x, band_y)]
        self.melted = np.zeros((len(self.edges[1]) - 1, n_layers, len(self.edges[0]) - 1), dtype=bool)
        # (changed through mark() and grow() only: they keep the versions fraction() relies on)
        self._versions = np.zeros(n_layers, dtype=np.int64)   # per layer: changes marked so far
        self._shares: dict[tuple, tuple[np.ndarray, np.ndarray]] = {}   # fraction()'s last results, by grid

    def grow(self, n_layers: int) -> None:
        """``n_layers`` new powder element layers on top."""
        ny, _, nx = self.melted.shape
        self.melted = np.concatenate([self.melted, np.zeros((ny, n_layers, nx), dtype=bool)], axis=1)
        self._versions = np.concatenate([self._versions, np.zeros(n_layers, dtype=np.int64)])

    def _cells(self, axis: int, coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Per element of ``coords``: the lattice cells ``a <= c < b`` whose centres it contains."""
        e = self.edges[axis]
        centres = 0.5 * (e[1:] + e[:-1])
        return np.searchsorted(centres, coords[:-1]), np.searchsorted(centres, coords[1:])

    def mark(self, xs: np.ndarray, ys: np.ndarray, elements: np.ndarray) -> None:
        """Mark the cells of consolidated ``elements`` (indices (j, k, i) into the powder layers)."""
        (ax, bx), (ay, by) = self._cells(0, xs), self._cells(1, ys)
        for j, k, i in zip(*elements):
            self.melted[ay[j]:by[j], k, ax[i]:bx[i]] = True
        self._versions[np.unique(elements[1])] += 1

    def fraction(self, xs: np.ndarray, ys: np.ndarray) -> np.ndarray:
        """Consolidated share [-] of every powder element of the grid (xs, ys), shape (ny - 1, n_layers, nx - 1);
        0 for elements that hold no lattice cell (outside the band). Read-only: the result is kept per grid,
        and a later call for that grid computes again only the layers :meth:`mark` or :meth:`grow` changed
        since (a layer's shares depend on its cells alone; buried layers no longer change)."""
        key = (xs.size, xs.tobytes(), ys.tobytes())
        kept = self._shares.pop(key, None)
        n = self._versions.size
        if kept is None:
            share, stale = np.empty((len(ys) - 1, n, len(xs) - 1)), np.arange(n)
        else:
            share, versions = kept
            stale = np.flatnonzero(self._versions[:versions.size] != versions)
            if versions.size < n:                                   # layers grown since
                share = np.concatenate([share, np.empty((share.shape[0], n - versions.size, share.shape[2]))], axis=1)
                stale = np.concatenate([stale, np.arange(versions.size, n)])
        if stale.size:
            share.flags.writeable = True
            share[:, stale, :] = self._layer_shares(xs, ys, stale)
            share.flags.writeable = False
        self._shares[key] = (share, self._versions.copy())
        while len(self._shares) > SHARES_KEPT:                      # the oldest grid first
            del self._shares[next(iter(self._shares))]
        return share

    def _layer_shares(self, xs: np.ndarray, ys: np.ndarray, layers: np.ndarray) -> np.ndarray:
        """:meth:`fraction` of the powder layers ``layers`` only, shape (ny - 1, len(layers), nx - 1)."""
        (ax, bx), (ay, by) = self._cells(0, xs), self._cells(1, ys)
        x0, y0 = int(ax.min()), int(ay.min())                     # the cells under the grid only
        ax, bx, ay, by = ax - x0, bx - x0, ay - y0, by - y0
        cells = self.melted[y0:y0 + int(by.max()), layers, x0:x0 + int(bx.max())]
        s = np.zeros((cells.shape[0] + 1, cells.shape[1], cells.shape[2] + 1))
        s[1:, :, 1:] = cells.cumsum(axis=0).cumsum(axis=2)        # summed-area table (integer counts)
        total = s[by][:, :, bx] - s[ay][:, :, bx] - s[by][:, :, ax] + s[ay][:, :, ax]
        count = ((by - ay)[:, None] * (bx - ax)[None, :])[:, None, :]
        return np.divide(total, count, out=np.zeros_like(total), where=count > 0)
