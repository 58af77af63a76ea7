"""Two implementations of the forms of :mod:`fe_node.forms`: weighted stiffness ``K_w`` and lumped mass ``m``.

* :class:`CsrOperator` — any scikit-fem mesh: ``conduction`` and ``mass`` assembled element by
  element once with unit weights; the weighted CSR matrix is a scatter of weighted element
  entries, so re-weighting elements updates it in place.
* :class:`TensorOperator` — graded tensor-product box grids (:class:`fe_node.mesh.Grid`): with
  weights constant per z layer, exactly ``Kx (x) My (x) Mz_w + Mx (x) Ky (x) Mz_w + Mx (x) My (x) Kz_w``
  (``Kd, Md`` 1-D linear-element matrices, ``Mz_w, Kz_w`` weighted by layer); elements whose
  weights differ from their layer's are added as a sparse correction ``sum_e dw_e K_e``.

Both give the same ``K_w u``, ``m`` and, with ``vertical=True``, ``K_z u`` of ``conduction_z``
(``tests/test_fe_operators.py``: 1e-12 on random weights) and the explicit stability bound
:meth:`stability_eigenvalue`, recomputed whenever weights change:
``lambda_max(M_L^-1 K_w) <= max_e (kw_e / rho_w_e) lambda_e`` with ``lambda_e`` the largest
eigenvalue of the element pair (``K_e``, lumped ``M_e``) (Fried's element bound; ``4 / h_min²``
for a box).

Node order: flat indices of the solver's ``(ny, nz, nx)`` arrays for the tensor grid; the CSR
operator uses the mesh's order unless given ``order``.  Element order of the tensor grid:
``(ny - 1, nz - 1, nx - 1)``, C order.
"""
from __future__ import annotations

import numpy as np
import scipy.sparse as sp

from fe_node.forms import conduction, conduction_z, facet_area, mass
from fe_node.mesh import Grid, fe1d


def _weights(w, n: int, what: str) -> np.ndarray:
    """Per-element weights as a float array of length ``n`` (``None``: ones)."""
    w = np.ones(n) if w is None else np.asarray(w, dtype=float).ravel()
    if w.shape != (n,):
        raise ValueError(f"operator: {what} needs {n} element weights, got {w.size}")
    return w


def _check_positive(kw: np.ndarray, rho_w: np.ndarray) -> None:
    if not (np.all(kw >= 0) and np.all(rho_w > 0) and np.all(np.isfinite(kw / rho_w))):
        raise ValueError("operator: conductivity weights must be >= 0 and density weights > 0")


class CsrOperator:
    """Weighted stiffness and lumped mass of any scikit-fem mesh as a CSR matrix.

    Parameters
    ----------
    mesh : skfem.Mesh
        Any mesh with a first-order Lagrange element (``mesh.elem()``).
    kw, rho_w : array_like, shape (n_elements,), optional
        Per-element conductivity and density weights [-] (default 1).
    order : ndarray of int, shape (n_nodes,), optional
        ``order[i]`` = mesh node of the operator's node ``i`` (default identity).
    intorder : int
        Quadrature order (2 integrates trilinear boxes exactly).
    vertical : bool
        Also assemble ``K_z`` (``conduction_z``) for :meth:`vertical`.

    Attributes
    ----------
    mesh : skfem.Mesh
        The mesh.
    matrix : scipy.sparse.csr_matrix, shape (n_nodes, n_nodes)
        ``K_w`` [m].
    matrix_z : scipy.sparse.csr_matrix or None
        ``K_z`` [m] (with ``vertical=True``).
    lumped_mass : ndarray, shape (n_nodes,)
        ``m`` [m³].
    """

    def __init__(self, mesh, kw=None, rho_w=None, order=None, intorder: int = 2, vertical: bool = False):
        from skfem import Basis

        basis = Basis(mesh, mesh.elem(), intorder=intorder)
        n, nt, nb = basis.N, basis.nelems, basis.Nbfun
        inv = np.arange(n) if order is None else np.argsort(np.asarray(order))
        coo = conduction.elemental(basis, kw=1.0)
        self._unit = coo.data.reshape(nb * nb, nt)                 # (local entry, element)
        self._unit_z = conduction_z.elemental(basis, kw=1.0).data.reshape(nb * nb, nt) if vertical else None
        rows, cols = (inv[i].reshape(nb * nb, nt) for i in coo.indices)
        pattern = sp.csr_matrix((np.ones(rows.size), (rows.ravel(), cols.ravel())), shape=(n, n))
        pattern.sum_duplicates()
        keys = np.repeat(np.arange(n, dtype=np.int64), np.diff(pattern.indptr)) * n + pattern.indices
        self._slot = np.searchsorted(keys, rows.astype(np.int64) * n + cols)
        self._dofs = inv[basis.element_dofs]                        # (nb, nt)
        self._me = mass.elemental(basis, rho_w=1.0).data.reshape(nb, nb, nt).sum(axis=0)
        self._lam_e = self._element_eigenvalues(nb, nt)
        self.kw, self.rho_w = _weights(kw, nt, "kw"), _weights(rho_w, nt, "rho_w")
        _check_positive(self.kw, self.rho_w)
        self.matrix = pattern
        self.matrix.data = np.bincount(self._slot.ravel(), (self._unit * self.kw).ravel(), minlength=keys.size)
        self.lumped_mass = np.bincount(self._dofs.ravel(), (self._me * self.rho_w).ravel(), minlength=n)
        self.n_nodes, self.n_elements = n, nt
        self.mesh, self._inv = mesh, inv
        self.matrix_z = None
        if vertical:        # same element dof pairs as K_w: same slots
            self.matrix_z = pattern.copy()
            self.matrix_z.data = np.bincount(self._slot.ravel(), (self._unit_z * self.kw).ravel(), minlength=keys.size)

    def _element_eigenvalues(self, nb: int, nt: int, chunk: int = 1 << 15) -> np.ndarray:
        """Largest eigenvalue of each element pair (K_e, diag(m_e)) [1/m²], shape (nt,)."""
        lam = np.empty(nt)
        for s in range(0, nt, chunk):
            ke = np.moveaxis(self._unit[:, s:s + chunk].reshape(nb, nb, -1), -1, 0)
            d = 1.0 / np.sqrt(self._me[:, s:s + chunk].T)
            lam[s:s + chunk] = np.linalg.eigvalsh(d[:, :, None] * ke * d[:, None, :])[:, -1]
        return lam

    def __call__(self, u: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """``K_w u`` with the shape of ``u`` (flat size n_nodes); into ``out`` if given."""
        r = (self.matrix @ np.ravel(u)).reshape(np.shape(u))
        if out is None:
            return r
        out[...] = r
        return out

    def facet_areas(self, facets: np.ndarray) -> np.ndarray:
        """Lumped areas [m²] of boundary ``facets`` (``facet_area`` on a ``FacetBasis``), shape (n_nodes,)."""
        from skfem import FacetBasis

        areas = facet_area.assemble(FacetBasis(self.mesh, self.mesh.elem(), facets=facets, intorder=2))
        out = np.empty_like(areas)
        out[self._inv] = areas
        return out

    def vertical(self, u: np.ndarray) -> np.ndarray:
        """``K_z u`` with the shape of ``u`` (needs ``vertical=True``)."""
        return (self.matrix_z @ np.ravel(u)).reshape(np.shape(u))

    def reweight(self, elements, kw, rho_w) -> None:
        """Set the weights of ``elements`` (flat indices) to ``kw``, ``rho_w`` [-]; updates K_w and m."""
        el = np.asarray(elements, dtype=np.intp).ravel()
        kw = np.broadcast_to(np.asarray(kw, dtype=float), el.shape)
        rho_w = np.broadcast_to(np.asarray(rho_w, dtype=float), el.shape)
        _check_positive(kw, rho_w)
        np.add.at(self.matrix.data, self._slot[:, el].ravel(), (self._unit[:, el] * (kw - self.kw[el])).ravel())
        if self.matrix_z is not None:
            np.add.at(self.matrix_z.data, self._slot[:, el].ravel(),
                      (self._unit_z[:, el] * (kw - self.kw[el])).ravel())
        np.add.at(self.lumped_mass, self._dofs[:, el].ravel(), (self._me[:, el] * (rho_w - self.rho_w[el])).ravel())
        self.kw[el], self.rho_w[el] = kw, rho_w

    def stability_eigenvalue(self) -> float:
        """Upper bound of ``lambda_max(M_L^-1 K_w)`` [1/m²] (element bound, module docstring)."""
        return float(np.max(self.kw / self.rho_w * self._lam_e))


def box_stiffness(hx, hy, hz, vertical_only: bool = False) -> np.ndarray:
    """Unit ``conduction`` (or ``conduction_z``) element matrices of axis-aligned boxes [m].

    Parameters
    ----------
    hx, hy, hz : ndarray, shape (n,)
        Box edge lengths [m].
    vertical_only : bool
        Only the ``z`` term (``conduction_z``).

    Returns
    -------
    ndarray, shape (n, 8, 8)
        Local node ``4 b_y + 2 b_z + b_x`` (corner bits along y, z, x).
    """
    def k1(h):
        return np.array([[1.0, -1.0], [-1.0, 1.0]])[None] / h[:, None, None]

    def m1(h):
        return np.array([[2.0, 1.0], [1.0, 2.0]])[None] * (h / 6.0)[:, None, None]

    def kron3(a, b, c):   # kron(a, b, c) per box: rows (y, z, x), columns (y, z, x)
        return np.einsum("nab,ncd,nef->nacebdf", a, b, c).reshape(-1, 8, 8)

    z = kron3(m1(hy), k1(hz), m1(hx))
    return z if vertical_only else kron3(m1(hy), m1(hz), k1(hx)) + kron3(k1(hy), m1(hz), m1(hx)) + z


class TensorOperator:
    """Weighted stiffness and lumped mass of a graded box grid through its tensor structure.

    Parameters
    ----------
    grid : Grid
    kw, rho_w : array_like, shape (n_elements,), optional
        Per-element weights [-] in element order ``(ny - 1, nz - 1, nx - 1)`` (default 1).
    vertical : bool
        Also provide ``K_z`` (``conduction_z``) for :meth:`vertical`.

    Attributes
    ----------
    lumped_mass : ndarray, shape (ny, nz, nx)
        ``m`` [m³].
    """

    def __init__(self, grid: Grid, kw=None, rho_w=None, vertical: bool = False):
        self.grid, self._vertical = grid, vertical
        self.shape = grid.solver_shape
        ny, nz, nx = self.shape
        self.elem_shape = (ny - 1, nz - 1, nx - 1)
        self.n_nodes, self.n_elements = grid.n_nodes, int(np.prod(self.elem_shape))
        self.kw = _weights(kw, self.n_elements, "kw").reshape(self.elem_shape)
        self.rho_w = _weights(rho_w, self.n_elements, "rho_w").reshape(self.elem_shape)
        _check_positive(self.kw, self.rho_w)
        self._h = [np.diff(a) for a in (grid.ys, grid.zs, grid.xs)]
        hmin = np.minimum(np.minimum.outer(self._h[0], self._h[1])[:, :, None], self._h[2][None, None, :])
        self._lam_e = 4.0 / hmin**2
        self._scratch = None
        self._layered(self.kw[0, :, 0], self.rho_w[0, :, 0])

    def _layered(self, kz, rz) -> None:
        """Kronecker factors for layer weights ``kz``, ``rz`` (nz - 1,) and the correction of the rest."""
        kx, mx = fe1d(self.grid.xs)
        ky, my = fe1d(self.grid.ys)
        kz_w, mz_w = fe1d(self.grid.zs, kz)
        a = sp.kron(my, mz_w)
        b = sp.kron(ky, mz_w) + sp.kron(my, kz_w)
        self._ab = sp.vstack([a, b]).tocsr()
        self._cz = sp.kron(my, kz_w).tocsr() if self._vertical else None
        self._p = a.shape[0]
        self._kd, self._ko = kx.diagonal(), kx.diagonal(1)
        self._md, self._mo = mx.diagonal(), mx.diagonal(1)
        sx, sy, sz = (np.asarray(fe1d(c, w)[1].sum(axis=1)).ravel()
                      for c, w in ((self.grid.xs, None), (self.grid.ys, None), (self.grid.zs, rz)))
        self.lumped_mass = sy[:, None, None] * sz[None, :, None] * sx[None, None, :]
        dk = self.kw - kz[None, :, None]
        dr = self.rho_w - rz[None, :, None]
        self._corr = self._corr_z = None
        self._add(np.flatnonzero(dk), dk.ravel()[np.flatnonzero(dk)], np.flatnonzero(dr),
                  dr.ravel()[np.flatnonzero(dr)])

    def _corners(self, el: np.ndarray) -> np.ndarray:
        """Flat node indices of the 8 corners of elements ``el``, shape (n, 8), local order of :func:`box_stiffness`."""
        j, k, i = np.unravel_index(el, self.elem_shape)
        b = np.array([(by, bz, bx) for by in (0, 1) for bz in (0, 1) for bx in (0, 1)])
        return np.ravel_multi_index((j[:, None] + b[:, 0], k[:, None] + b[:, 1], i[:, None] + b[:, 2]), self.shape)

    def _add(self, el_k, dk, el_r, dr) -> None:
        """Add ``dk_e K_e`` to the correction and ``dr_e V_e / 8`` to the corners' masses."""
        if len(el_k):
            j, k, i = np.unravel_index(el_k, self.elem_shape)
            ke = box_stiffness(self._h[2][i], self._h[0][j], self._h[1][k]) * dk[:, None, None]
            c = self._corners(el_k)
            rows, cols, n = np.repeat(c, 8, axis=1).ravel(), np.tile(c, (1, 8)).ravel(), self.n_nodes
            delta = sp.csr_matrix((ke.ravel(), (rows, cols)), shape=(n, n))
            self._corr = delta if self._corr is None else self._corr + delta
            if self._vertical:
                kz = box_stiffness(self._h[2][i], self._h[0][j], self._h[1][k], vertical_only=True)
                delta = sp.csr_matrix(((kz * dk[:, None, None]).ravel(), (rows, cols)), shape=(n, n))
                self._corr_z = delta if self._corr_z is None else self._corr_z + delta
        if len(el_r):
            j, k, i = np.unravel_index(el_r, self.elem_shape)
            v8 = self._h[0][j] * self._h[1][k] * self._h[2][i] / 8.0 * dr
            np.add.at(self.lumped_mass.reshape(-1), self._corners(el_r).ravel(), np.repeat(v8, 8))

    def __call__(self, u: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Return ``K_w u`` with the shape of ``u`` (solver order, flat or (ny, nz, nx)).

        ``out`` (contiguous, ``u``'s size) receives the result; the x pass then runs in the
        operator's own scratch arrays, so a step allocates only the (y, z) product.
        """
        p, nx = self._p, self.shape[2]
        if self._scratch is None:
            self._scratch = (np.empty((p, nx)), np.empty((p, nx - 1)), np.empty((p, nx - 1)))
        full, e1, e2 = self._scratch
        vw = self._ab @ np.reshape(u, (p, nx))
        v, w = vw[:p], vw[p:]
        res = np.multiply(v, self._kd, out=None if out is None else np.reshape(out, (p, nx)))
        res += np.multiply(w, self._md, out=full)
        up = np.multiply(v[:, :-1], self._ko, out=e1)     # couplings (i, i+1): contributions to row i+1
        up += np.multiply(w[:, :-1], self._mo, out=e2)
        res[:, 1:] += up
        dn = np.multiply(v[:, 1:], self._ko, out=e1)      # contributions to row i
        dn += np.multiply(w[:, 1:], self._mo, out=e2)
        res[:, :-1] += dn
        if self._corr is not None:
            res.reshape(-1)[:] += self._corr @ np.ravel(u)
        return res.reshape(np.shape(u)) if out is None else out

    def vertical(self, u: np.ndarray) -> np.ndarray:
        """``K_z u`` = ``Mx (x) My (x) Kz_w`` u (+ correction) with the shape of ``u`` (needs ``vertical=True``)."""
        v = self._cz @ np.reshape(u, (self._p, self.shape[2]))
        out = v * self._md
        out[:, 1:] += v[:, :-1] * self._mo
        out[:, :-1] += v[:, 1:] * self._mo
        if self._corr_z is not None:
            out.reshape(-1)[:] += self._corr_z @ np.ravel(u)
        return out.reshape(np.shape(u))

    def reweight(self, elements, kw, rho_w) -> None:
        """Set the weights of ``elements`` (flat indices) to ``kw``, ``rho_w`` [-]; updates K_w and m."""
        el = np.asarray(elements, dtype=np.intp).ravel()
        kw = np.broadcast_to(np.asarray(kw, dtype=float), el.shape)
        rho_w = np.broadcast_to(np.asarray(rho_w, dtype=float), el.shape)
        _check_positive(kw, rho_w)
        flat_k, flat_r = self.kw.reshape(-1), self.rho_w.reshape(-1)
        self._add(el, kw - flat_k[el], el, rho_w - flat_r[el])
        flat_k[el], flat_r[el] = kw, rho_w

    def stability_eigenvalue(self) -> float:
        """Upper bound of ``lambda_max(M_L^-1 K_w)`` [1/m²] (element bound, module docstring)."""
        return float(np.max(self.kw / self.rho_w * self._lam_e))

    def assembled(self) -> sp.csr_matrix:
        """The full sparse ``K_w`` in solver order (for tests)."""
        kx = sp.diags([self._kd, self._ko, self._ko], [0, -1, 1])
        mx = sp.diags([self._md, self._mo, self._mo], [0, -1, 1])
        k = sp.kron(self._ab[: self._p], kx) + sp.kron(self._ab[self._p:], mx)
        return (k if self._corr is None else k + self._corr).tocsr()
