"""Graded tensor-product hexahedral grid and 1-D linear-element matrices.

On a tensor-product grid of boxes with trilinear hexahedra (ElementHex1) the stiffness and
consistent mass factor into 1-D linear-element matrices (:func:`fe1d`); the fast operator of
:mod:`fe_node.operators` applies them.  :meth:`Grid.skfem_mesh` gives the same grid as a
scikit-fem mesh, :meth:`Grid.top_areas` the lumped top-face areas (the ``facet_area`` form of
:mod:`fe_node.forms` on boxes).

Array convention: the solver stores nodal fields as ``(ny, nz, nx)`` arrays (C order, x
fastest), so the (y, z)-plane product needs no transposes and the top surface (z = 0,
z ascending) ``[:, -1, :]`` is contiguous.  ``Grid.to_xyz`` gives the ``(nx, ny, nz)``
view used in the public API.
"""
from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np


def graded_axis(lo: float, hi: float, fine_lo: float, fine_hi: float, h: float,
                growth: float, h_max: float) -> np.ndarray:
    """Node coordinates of a 1-D graded grid [m].

    Uniform spacing ``<= h`` on ``[fine_lo, fine_hi]``, element sizes growing
    geometrically by ``growth`` (capped at ``h_max``) towards ``lo`` and ``hi``; each
    outer sequence is scaled to end exactly on its bound.

    Returns
    -------
    ndarray, shape (n,)
        Strictly increasing coordinates from ``lo`` to ``hi``.
    """
    if not lo <= fine_lo < fine_hi <= hi:
        raise ValueError("mesh: fine region must lie inside the domain")
    n = max(1, int(np.ceil((fine_hi - fine_lo) / h - 1e-9)))
    fine = np.linspace(fine_lo, fine_hi, n + 1)
    hf = (fine_hi - fine_lo) / n

    def outer(length):
        sizes, s, total = [], hf, 0.0
        while total < length - 1e-12 * max(length, 1e-3):
            s = min(s * growth, h_max)
            sizes.append(s)
            total += s
        sizes = np.asarray(sizes)
        return np.cumsum(sizes * (length / sizes.sum())) if len(sizes) else sizes

    left = fine_lo - outer(fine_lo - lo)[::-1]
    right = fine_hi + outer(hi - fine_hi)
    x = np.concatenate([left, fine, right])
    x[0], x[-1] = lo, hi
    return x


def graded_axis_size(lo: float, hi: float, fine_lo: float, fine_hi: float, h: float,
                     growth: float, h_max: float) -> int:
    """Number of nodes of :func:`graded_axis` with the same arguments, counted without placing
    them (a plan too large to mesh is refused before anything is allocated); its outer sequences
    are counted geometrically up to ``h_max`` and in closed form beyond (within one node of
    :func:`graded_axis` where rounding differs)."""
    if not lo <= fine_lo < fine_hi <= hi:
        raise ValueError("mesh: fine region must lie inside the domain")
    n = max(1, math.ceil((fine_hi - fine_lo) / h - 1e-9))
    hf = (fine_hi - fine_lo) / n

    def outer(length):
        goal = length - 1e-12 * max(length, 1e-3)
        count, s, total = 0, hf, 0.0
        while total < goal and s < h_max:
            s = min(s * growth, h_max)
            total += s
            count += 1
        return count + (max(0, math.ceil((goal - total) / h_max)) if total < goal else 0)

    return outer(fine_lo - lo) + n + 1 + outer(hi - fine_hi)


def fe1d(x: np.ndarray, w: np.ndarray | None = None):
    """1-D linear-element matrices on nodes ``x``, optionally weighted per element, as their bands.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Increasing node coordinates [m].
    w : ndarray, shape (n - 1,), optional
        Element weights [-] (default 1).

    Returns
    -------
    kd, ko, md, mo : ndarray, shapes (n,), (n - 1,), (n,), (n - 1,)
        Diagonal and off-diagonal of the stiffness ``int w N_i' N_j'`` [1/m] and of the consistent
        mass ``int w N_i N_j`` [m] (both symmetric tridiagonal).
    """
    h = np.diff(x)
    w = np.ones_like(h) if w is None else np.asarray(w, dtype=float)
    z = np.zeros(1)
    kd = np.concatenate([w / h, z]) + np.concatenate([z, w / h])
    md = np.concatenate([w * h / 3, z]) + np.concatenate([z, w * h / 3])
    return kd, -w / h, md, w * h / 6


def lumped1d(x: np.ndarray, w: np.ndarray | None = None) -> np.ndarray:
    """Row sums [m] of :func:`fe1d`'s mass on nodes ``x`` (element weights ``w``), shape (n,)."""
    _, _, md, mo = fe1d(x, w)
    out = md.copy()
    out[:-1] += mo
    out[1:] += mo
    return out


@dataclass(frozen=True)
class Grid:
    """Tensor-product node coordinates [m]; top surface at ``zs[-1] = 0``."""

    xs: np.ndarray
    ys: np.ndarray
    zs: np.ndarray

    @property
    def shape(self) -> tuple[int, int, int]:
        return (len(self.xs), len(self.ys), len(self.zs))

    @property
    def n_nodes(self) -> int:
        return int(np.prod(self.shape))

    @property
    def solver_shape(self) -> tuple[int, int, int]:
        """Storage shape (ny, nz, nx) of solver fields."""
        return (len(self.ys), len(self.zs), len(self.xs))

    @staticmethod
    def to_xyz(u: np.ndarray) -> np.ndarray:
        """View of a solver field (ny, nz, nx) as (nx, ny, nz)."""
        return np.transpose(u, (2, 0, 1))

    def top_areas(self) -> np.ndarray:
        """Row-sum lumped nodal areas of the top face [m²], shape ``(ny, nx)``."""
        mx, my = (lumped1d(a) for a in (self.xs, self.ys))
        return my[:, None] * mx[None, :]

    def skfem_mesh(self):
        """The same grid as a :class:`skfem.MeshHex` plus the map to our node order.

        Returns
        -------
        mesh : skfem.MeshHex
        perm : ndarray of int, shape (n_nodes,)
            ``perm[solver_flat_index] = skfem node index`` (solver order (ny, nz, nx)).
        """
        from skfem import MeshHex

        mesh = MeshHex.init_tensor(self.xs, self.ys, self.zs)
        ix = np.searchsorted(self.xs, mesh.p[0])
        iy = np.searchsorted(self.ys, mesh.p[1])
        iz = np.searchsorted(self.zs, mesh.p[2])
        # snap in case of round-off in the stored coordinates
        ix = _nearest(self.xs, mesh.p[0], ix)
        iy = _nearest(self.ys, mesh.p[1], iy)
        iz = _nearest(self.zs, mesh.p[2], iz)
        ours = np.ravel_multi_index((iy, iz, ix), self.solver_shape)
        perm = np.empty(self.n_nodes, dtype=np.intp)
        perm[ours] = np.arange(self.n_nodes)
        return mesh, perm

    def element_order(self, mesh) -> np.ndarray:
        """``order[solver_element] = mesh element`` for :meth:`skfem_mesh`'s mesh.

        Solver elements are numbered in C order of ``(ny - 1, nz - 1, nx - 1)``.
        """
        c = mesh.p[:, mesh.t].mean(axis=1)              # element centroids, (3, n_elements)
        mids = [0.5 * (a[1:] + a[:-1]) for a in (self.xs, self.ys, self.zs)]
        ix, iy, iz = (_nearest(m, ci, np.searchsorted(m, ci)) for m, ci in zip(mids, c))
        ours = np.ravel_multi_index((iy, iz, ix), (len(self.ys) - 1, len(self.zs) - 1, len(self.xs) - 1))
        order = np.empty(len(ours), dtype=np.intp)
        order[ours] = np.arange(len(ours))
        return order


def _nearest(a, v, i):
    i = np.clip(i, 1, len(a) - 1)
    return np.where(np.abs(a[i - 1] - v) < np.abs(a[i] - v), i - 1, i)
