"""Graded tensor-product hexahedral mesh and its exact fast stiffness operator.

On a tensor-product grid with trilinear hexahedra (ElementHex1), the unit-conductivity
stiffness and consistent mass matrices are exactly

    K = Kx (x) My (x) Mz + Mx (x) Ky (x) Mz + Mx (x) My (x) Kz,     M = Mx (x) My (x) Mz,

with ``Kd, Md`` the 1-D linear-element stiffness and mass matrices.  :class:`Stiffness`
applies ``K`` as one sparse product on the (y, z) planes followed by one along x, which
is exact and avoids assembling the 27-point matrix.  ``tests/test_fe_mesh.py`` checks it
against scikit-fem assembly (``Basis(m, ElementHex1(), intorder=2)``).

Array convention: the solver stores nodal fields as ``(ny, nz, nx)`` arrays (C order, x
fastest), so the (y, z)-plane product needs no transposes and the top surface (z = 0,
z ascending) ``[:, -1, :]`` is contiguous.  ``Grid.to_xyz`` gives the ``(nx, ny, nz)``
view used in the public API.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import scipy.sparse as sp


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
        sizes, s = [], hf
        while sum(sizes) < length - 1e-12 * max(length, 1e-3):
            s = min(s * growth, h_max)
            sizes.append(s)
        sizes = np.asarray(sizes)
        return np.cumsum(sizes * (length / sizes.sum())) if len(sizes) else sizes

    left = fine_lo - outer(fine_lo - lo)[::-1]
    right = fine_hi + outer(hi - fine_hi)
    x = np.concatenate([left, fine, right])
    x[0], x[-1] = lo, hi
    return x


def fe1d(x: np.ndarray):
    """1-D linear-element matrices on nodes ``x``.

    Returns
    -------
    K, M : scipy.sparse.csr_matrix, shape (n, n)
        Stiffness ``int N_i' N_j'`` [1/m] and consistent mass ``int N_i N_j`` [m].
    """
    h = np.diff(x)
    z = np.zeros(1)
    kd = np.concatenate([1 / h, z]) + np.concatenate([z, 1 / h])
    md = np.concatenate([h / 3, z]) + np.concatenate([z, h / 3])
    K = sp.diags([kd, -1 / h, -1 / h], [0, -1, 1], format="csr")
    M = sp.diags([md, h / 6, h / 6], [0, -1, 1], format="csr")
    return K, M


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

    def lumped_mass(self) -> np.ndarray:
        """Row-sum lumped nodal volumes [m³], solver shape ``(ny, nz, nx)``."""
        mx, my, mz = (np.asarray(fe1d(a)[1].sum(axis=1)).ravel() for a in (self.xs, self.ys, self.zs))
        return my[:, None, None] * mz[None, :, None] * mx[None, None, :]

    def top_areas(self) -> np.ndarray:
        """Row-sum lumped nodal areas of the top face [m²], shape ``(ny, nx)``."""
        mx, my = (np.asarray(fe1d(a)[1].sum(axis=1)).ravel() for a in (self.xs, self.ys))
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


def _nearest(a, v, i):
    i = np.clip(i, 1, len(a) - 1)
    return np.where(np.abs(a[i - 1] - v) < np.abs(a[i] - v), i - 1, i)


class Stiffness:
    """Exact action of the unit-conductivity trilinear stiffness matrix ``K`` [m].

    ``K u`` for a solver field ``u`` of shape ``(ny, nz, nx)`` (or flat) is computed as
    ``(A u) Kx + (B u) Mx`` with ``A = My (x) Mz`` and ``B = Ky (x) Mz + My (x) Kz``
    acting on the (y, z) index (one sparse product, no copy), then the symmetric
    tridiagonal ``Kx``, ``Mx`` along the contiguous x axis by array slicing.
    """

    def __init__(self, grid: Grid):
        self.shape = grid.solver_shape
        kx, mx = fe1d(grid.xs)
        ky, my = fe1d(grid.ys)
        kz, mz = fe1d(grid.zs)
        a = sp.kron(my, mz)
        b = sp.kron(ky, mz) + sp.kron(my, kz)
        self._ab = sp.vstack([a, b]).tocsr()
        self._p = a.shape[0]
        self._kd, self._ko = kx.diagonal(), kx.diagonal(1)
        self._md, self._mo = mx.diagonal(), mx.diagonal(1)

    def __call__(self, u: np.ndarray) -> np.ndarray:
        """Return ``K u`` with the shape of ``u``."""
        nx = self.shape[2]
        vw = self._ab @ np.reshape(u, (self._p, nx))
        v, w = vw[: self._p], vw[self._p:]
        out = v * self._kd
        out += w * self._md
        up = v[:, :-1] * self._ko          # couplings (i, i+1): contributions to row i+1
        up += w[:, :-1] * self._mo
        out[:, 1:] += up
        dn = v[:, 1:] * self._ko           # contributions to row i
        dn += w[:, 1:] * self._mo
        out[:, :-1] += dn
        return out.reshape(np.shape(u))

    def assembled(self) -> sp.csr_matrix:
        """The full sparse ``K`` in solver order (for tests only)."""
        kx = sp.diags([self._kd, self._ko, self._ko], [0, -1, 1])
        mx = sp.diags([self._md, self._mo, self._mo], [0, -1, 1])
        return (sp.kron(self._ab[: self._p], kx) + sp.kron(self._ab[self._p:], mx)).tocsr()
