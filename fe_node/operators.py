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

import copy

import numpy as np
import scipy.sparse as sp

from fe_node.mesh import Grid, fe1d, lumped1d


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
        from skfem import Basis  # scikit-fem here, not at the top: the tensor operator's nodes start without it

        from fe_node.forms import conduction, conduction_z, mass

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

        from fe_node.forms import facet_area

        areas = facet_area.assemble(FacetBasis(self.mesh, self.mesh.elem(), facets=facets, intorder=2))
        out = np.empty_like(areas)
        out[self._inv] = areas
        return out

    def vertical(self, u: np.ndarray) -> np.ndarray:
        """``K_z u`` with the shape of ``u`` (needs ``vertical=True``)."""
        return (self.matrix_z @ np.ravel(u)).reshape(np.shape(u))

    def add_vertical(self, u_box: np.ndarray, box: tuple[slice, slice, slice], out: np.ndarray) -> None:
        """``out += K_z u`` for ``u`` zero outside the node box ``box`` (slices of the solver's
        ``(ny, nz, nx)`` arrays; this operator's ``order`` must be that order), ``u_box`` its values there."""
        u = np.zeros(out.shape)
        u[box] = u_box
        out += self.vertical(u)

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


def box_stiffness(hx, hy, hz, vertical_only: bool = False, nodal: bool = False) -> np.ndarray:
    """Unit ``conduction`` (or ``conduction_z``) element matrices of axis-aligned boxes [m].

    Parameters
    ----------
    hx, hy, hz : ndarray, shape (n,)
        Box edge lengths [m].
    vertical_only : bool
        Only the ``z`` term (``conduction_z``).
    nodal : bool
        Integrate at the 8 corners (nodal quadrature) instead of exactly: the 1-D masses in each
        term are lumped, so a node couples to its axis neighbours only, with negative entries.

    Returns
    -------
    ndarray, shape (n, 8, 8)
        Local node ``4 b_y + 2 b_z + b_x`` (corner bits along y, z, x).
    """
    hx, hy, hz = (np.asarray(h, dtype=float) for h in (hx, hy, hz))
    terms = _UNIT_BOX_TERMS[nodal]
    z = (hx * hy / hz)[:, None] * terms[2]
    if not vertical_only:      # K_x, K_y, K_z scale as hy hz / hx, hx hz / hy, hx hy / hz
        z = z + (hy * hz / hx)[:, None] * terms[0] + (hx * hz / hy)[:, None] * terms[1]
    return z.reshape(-1, 8, 8)


def _unit_box_terms(nodal: bool) -> np.ndarray:
    """The x, y and z terms of the unit cube's ``conduction`` matrix, shape (3, 64) (local node
    ``4 b_y + 2 b_z + b_x``): ``kron(M, M, K)``, ``kron(K, M, M)``, ``kron(M, K, M)`` over (y, z, x),
    ``K``, ``M`` the 1-D unit stiffness and (``nodal``: lumped) mass."""
    k, m = np.array([[1.0, -1.0], [-1.0, 1.0]]), _mass1(np.ones(1), nodal)[0]
    return np.stack([np.kron(np.kron(m, m), k), np.kron(np.kron(k, m), m), np.kron(np.kron(m, k), m)]).reshape(3, 64)


class _Correction:
    """``sum_e dk_e K_e`` (and ``K_z``) over some elements, kept element by element: adding some
    copies their matrices, a product costs 64 products per element held (compiled loops,
    :func:`fe_node.kernels.element_apply`).

    Parameters
    ----------
    shape : (int, int, int)
        Node shape ``(ny, nz, nx)`` of the grid.
    vertical : bool
        Also hold the ``K_z`` correction.
    """

    def __init__(self, shape: tuple[int, int, int], vertical: bool):
        self.shape, self._vertical = shape, vertical
        self._corners = np.empty((0, 8), dtype=np.intp)
        self._ke = np.empty((0, 8, 8))
        self._kze = np.empty((0, 8, 8))
        self.n_elements = 0
        """Element matrices added so far (an element added twice counts twice)."""
        self._first = np.empty((0, 3), dtype=np.intp)

    def add(self, corners: np.ndarray, ke: np.ndarray, kze: np.ndarray | None) -> None:
        """Add element matrices ``ke`` (and ``kze``), shape (n, 8, 8), on nodes ``corners`` (n, 8)."""
        n, m = self.n_elements, len(corners)
        if n + m > len(self._corners):                 # capacity doubles: adding is amortised O(m)
            cap = max(2 * len(self._corners), n + m, 64)
            grow = [(np.empty((cap, 8), dtype=np.intp), self._corners), (np.empty((cap, 8, 8)), self._ke)]
            if self._vertical:
                grow.append((np.empty((cap, 8, 8)), self._kze))
            for new, old in grow:
                new[:n] = old[:n]
            self._corners, self._ke = grow[0][0], grow[1][0]
            if self._vertical:
                self._kze = grow[2][0]
        self._corners[n:n + m], self._ke[n:n + m] = corners, ke
        if self._vertical:
            self._kze[n:n + m] = kze
        self.n_elements = n + m

    def copy(self) -> _Correction:
        """An independent copy."""
        new = copy.copy(self)
        n = self.n_elements
        new._corners, new._ke, new._kze = self._corners[:n].copy(), self._ke[:n].copy(), self._kze[:n].copy()
        return new

    def apply(self, u: np.ndarray, out: np.ndarray) -> None:
        """``out += K u`` (flat arrays of the grid's size)."""
        from fe_node.kernels import element_apply

        n = self.n_elements
        if n:
            element_apply(self._corners[:n], self._ke[:n], u, out)

    def apply_vertical(self, u_box: np.ndarray, box: tuple[slice, slice, slice], out: np.ndarray) -> None:
        """``out += K_z u`` (``out`` flat) for ``u`` zero outside the node box ``box``, ``u_box`` its values there."""
        from fe_node.kernels import element_apply_box

        if self.n_elements:
            element_apply_box(self._first_corners(), self._kze, np.ascontiguousarray(u_box, dtype=float),
                              box[0].start, box[1].start, box[2].start, out.reshape(self.shape))

    def _first_corners(self) -> np.ndarray:
        """The (y, z, x) node of each element's first corner, shape (n_elements, 3) (kept until elements are added)."""
        if len(self._first) != self.n_elements:
            self._first = np.stack(np.unravel_index(self._corners[:self.n_elements, 0], self.shape), axis=1)
        return self._first

    def matrix(self, n_nodes: int) -> sp.csr_matrix:
        """``K`` on all ``n_nodes`` nodes."""
        c = self._corners[:self.n_elements]
        rows, cols = np.repeat(c, 8, axis=1).ravel(), np.tile(c, (1, 8)).ravel()
        return sp.csr_matrix((self._ke[:self.n_elements].ravel(), (rows, cols)), shape=(n_nodes, n_nodes))


def _mass1(h: np.ndarray, nodal: bool) -> np.ndarray:
    """1-D linear-element masses [m] of edges ``h`` (shape (n,)), consistent or (``nodal``) lumped, shape (n, 2, 2)."""
    local = np.eye(2) / 2.0 if nodal else np.array([[2.0, 1.0], [1.0, 2.0]]) / 6.0
    return local[None] * h[:, None, None]


_UNIT_BOX_TERMS = {nodal: _unit_box_terms(nodal) for nodal in (False, True)}


def _assemble_yz(hy: np.ndarray, hz: np.ndarray, w: np.ndarray, y: str, z: str, nodal: bool = False) -> sp.csr_matrix:
    """Sum over the (y, z) elements of ``w[j, k] Y_j (x) Z_k`` [m or 1/m], ``Y, Z`` the 1-D element
    stiffness (``"k"``) or mass (``"m"``, lumped if ``nodal``) of edges ``hy``, ``hz``; node ``j nz + k``."""
    def element(h, which):
        if which == "k":
            return np.array([[1.0, -1.0], [-1.0, 1.0]])[None] / h[:, None, None]
        return _mass1(h, nodal)

    ny, nz = len(hy) + 1, len(hz) + 1
    local = np.einsum("jab,kcd,jk->jkacbd", element(hy, y), element(hz, z), w).reshape(-1, 4, 4)
    j, k = np.meshgrid(np.arange(ny - 1), np.arange(nz - 1), indexing="ij")
    c = ((j.ravel()[:, None] + np.array([0, 0, 1, 1])) * nz + k.ravel()[:, None] + np.array([0, 1, 0, 1]))
    rows, cols = np.repeat(c, 4, axis=1).ravel(), np.tile(c, (1, 4)).ravel()
    return sp.csr_matrix((local.ravel(), (rows, cols)), shape=(ny * nz, ny * nz))


class TensorOperator:
    """Weighted stiffness and lumped mass of a graded box grid through its tensor structure.

    The Kronecker factors hold weights constant along x in each (y, z) row of elements (the
    row's median: the tracks run along x); the elements that differ from their row's weight are
    a sparse correction (:class:`_Correction`).  When re-weighting has grown the correction
    beyond twice its size at the last factoring plus one row, the factors are rebuilt.  With vertical
    weights ``kw_z``, ``K_w = sum_e kw_e (K_e - K_z,e) + kw_z,e K_z,e``: the vertical factor takes
    the rows' medians of ``kw_z``, and an element off either median is in the correction.

    Parameters
    ----------
    grid : Grid
    kw, rho_w : array_like, shape (n_elements,), optional
        Per-element weights [-] in element order ``(ny - 1, nz - 1, nx - 1)`` (default 1).
    kw_z : array_like, shape (n_elements,), optional
        Per-element weights [-] of the vertical term (default ``kw``: isotropic elements).
    vertical : bool
        Also provide ``K_z`` (``conduction_z``) for :meth:`vertical` and :meth:`add_vertical`.
    nodal : bool
        Integrate the stiffness at the elements' corners (:func:`box_stiffness`): an M-matrix on any
        box, so an explicit or implicit step never cools a node below its neighbours (the exact
        trilinear stiffness couples the in-plane neighbours of a flat element positively and
        undershoots next to a hot spot); its stability bound is ``4 (1/hx² + 1/hy² + 1/hz²)``.

    Attributes
    ----------
    lumped_mass : ndarray, shape (ny, nz, nx)
        ``m`` [m³].
    """

    def __init__(self, grid: Grid, kw=None, rho_w=None, vertical: bool = False, kw_z=None, nodal: bool = False):
        self.grid, self._vertical, self.nodal = grid, vertical, nodal
        self.shape = grid.solver_shape
        ny, nz, nx = self.shape
        self.elem_shape = (ny - 1, nz - 1, nx - 1)
        self.n_nodes, self.n_elements = grid.n_nodes, int(np.prod(self.elem_shape))
        self.kw = _weights(kw, self.n_elements, "kw").reshape(self.elem_shape)
        self.rho_w = _weights(rho_w, self.n_elements, "rho_w").reshape(self.elem_shape)
        self.kw_z = self.kw.copy() if kw_z is None else _weights(kw_z, self.n_elements, "kw_z").reshape(self.elem_shape)
        _check_positive(self.kw, self.rho_w)
        _check_positive(self.kw_z, self.rho_w)
        self._h = [np.diff(a) for a in (grid.ys, grid.zs, grid.xs)]
        if nodal:
            inv2 = [1.0 / h**2 for h in self._h]
            self._lam_e = 4.0 * (np.add.outer(inv2[0], inv2[1])[:, :, None] + inv2[2][None, None, :])
        else:
            hmin = np.minimum(np.minimum.outer(self._h[0], self._h[1])[:, :, None], self._h[2][None, None, :])
            self._lam_e = 4.0 / hmin**2
        self._ratio = np.maximum(self.kw, self.kw_z) / self.rho_w * self._lam_e
        self._kd, self._ko, self._md, self._mo = fe1d(grid.xs)
        if nodal:
            self._md, self._mo = lumped1d(grid.xs), np.zeros(len(grid.xs) - 1)
        rz = self.rho_w[0, :, 0]
        sx, sy, sz = (lumped1d(c, w) for c, w in ((grid.xs, None), (grid.ys, None), (grid.zs, rz)))
        self.lumped_mass = sy[:, None, None] * sz[None, :, None] * sx[None, None, :]
        dr = (self.rho_w - rz[None, :, None]).ravel()
        self._add_mass(np.flatnonzero(dr), dr[np.flatnonzero(dr)])
        self._factor()

    def _factor(self) -> None:
        """Kronecker factors for the row medians of ``kw`` (the vertical term: of ``kw_z``) and the
        correction of the other elements."""
        mid = self.elem_shape[2] // 2
        w = np.partition(self.kw, mid, axis=2)[:, :, mid]
        wz = np.partition(self.kw_z, mid, axis=2)[:, :, mid]
        hy, hz = self._h[0], self._h[1]
        a = _assemble_yz(hy, hz, w, "m", "m", self.nodal)
        cz = _assemble_yz(hy, hz, wz, "m", "k", self.nodal)
        self._a, self._b = a.tocsr(), (_assemble_yz(hy, hz, w, "k", "m", self.nodal) + cz).tocsr()
        self._cz = cz if self._vertical else None
        self._p = a.shape[0]
        self._corr = _Correction(self.shape, self._vertical)
        dk = self.kw - w[:, :, None]
        el = np.flatnonzero(dk)
        self._add_stiffness(el, dk.ravel()[el])
        dz = (self.kw_z - wz[:, :, None] - dk).ravel()       # K_z,e's weight beyond what dk_e K_e holds
        el = np.flatnonzero(dz)
        self._add_stiffness(el, dz[el], vertical_only=True)
        self._n_factored = self._corr.n_elements

    def _corners(self, el: np.ndarray) -> np.ndarray:
        """Flat node indices of the 8 corners of elements ``el``, shape (n, 8), local order of :func:`box_stiffness`."""
        j, k, i = np.unravel_index(el, self.elem_shape)
        b = np.array([(by, bz, bx) for by in (0, 1) for bz in (0, 1) for bx in (0, 1)])
        return np.ravel_multi_index((j[:, None] + b[:, 0], k[:, None] + b[:, 1], i[:, None] + b[:, 2]), self.shape)

    def _add_stiffness(self, el: np.ndarray, dk: np.ndarray, vertical_only: bool = False) -> None:
        """Add ``dk_e K_e`` (``vertical_only``: ``dk_e K_z,e``), and ``dk_e K_z,e`` to the ``K_z``
        correction, of elements ``el`` to the correction."""
        if len(el):
            j, k, i = np.unravel_index(el, self.elem_shape)
            h = (self._h[2][i], self._h[0][j], self._h[1][k])
            kze = (box_stiffness(*h, vertical_only=True, nodal=self.nodal) * dk[:, None, None]
                   if self._vertical or vertical_only else None)
            ke = kze if vertical_only else box_stiffness(*h, nodal=self.nodal) * dk[:, None, None]
            self._corr.add(self._corners(el), ke, kze if self._vertical else None)

    def _add_mass(self, el: np.ndarray, dr: np.ndarray) -> None:
        """Add ``dr_e V_e / 8`` to the masses of the corners of elements ``el``."""
        if len(el):
            j, k, i = np.unravel_index(el, self.elem_shape)
            v8 = self._h[0][j] * self._h[1][k] * self._h[2][i] / 8.0 * dr
            np.add.at(self.lumped_mass.reshape(-1), self._corners(el).ravel(), np.repeat(v8, 8))

    def __call__(self, u: np.ndarray, out: np.ndarray | None = None) -> np.ndarray:
        """Return ``K_w u`` with the shape of ``u`` (solver order, flat or (ny, nz, nx)).

        ``out`` (contiguous, ``u``'s size) receives the result, so that a step allocates nothing
        (the product is one compiled pass, :func:`fe_node.kernels.tensor_apply`).
        """
        from fe_node.kernels import tensor_apply

        p, nx = self._p, self.shape[2]
        a, b = self._a, self._b
        res = np.empty((p, nx)) if out is None else np.reshape(out, (p, nx))
        tensor_apply(a.indptr, a.indices, a.data, b.indptr, b.indices, b.data,
                     np.ascontiguousarray(np.reshape(u, (p, nx)), dtype=float), self._kd, self._ko, self._md, self._mo,
                     res)
        self._corr.apply(np.ravel(u), res.reshape(-1))
        return res.reshape(np.shape(u)) if out is None else out

    def vertical(self, u: np.ndarray) -> np.ndarray:
        """``K_z u`` = ``Mx (x) My (x) Kz_w`` u (+ correction) with the shape of ``u`` (needs ``vertical=True``)."""
        v = self._cz @ np.reshape(u, (self._p, self.shape[2]))
        out = v * self._md
        out[:, 1:] += v[:, :-1] * self._mo
        out[:, :-1] += v[:, 1:] * self._mo
        self._corr.apply_vertical(np.reshape(u, self.shape), tuple(slice(0, n) for n in self.shape),
                                  out.reshape(-1))
        return out.reshape(np.shape(u))

    def add_vertical(self, u_box: np.ndarray, box: tuple[slice, slice, slice], out: np.ndarray) -> None:
        """``out += K_z u`` for ``u`` zero outside the node box ``box`` (slices along y, z, x with
        explicit bounds), ``u_box`` its values there; only ``box`` and its neighbours are touched."""
        from fe_node.kernels import vertical_box

        rows = np.array([v for s, n in zip(box, self.shape) for v in (max(s.start - 1, 0), min(s.stop + 1, n))])
        cz = self._cz
        vertical_box(cz.indptr, cz.indices, cz.data, self.shape[1], rows, box[0].start, box[1].start, box[2].start,
                     np.ascontiguousarray(u_box, dtype=float), self._md, self._mo, out)
        self._corr.apply_vertical(u_box, box, out.reshape(-1))

    def reweight(self, elements, kw, rho_w, kw_z=None) -> None:
        """Set the weights of ``elements`` (flat indices) to ``kw``, ``rho_w`` and ``kw_z`` (default
        ``kw``) [-]; updates K_w and m."""
        el = np.asarray(elements, dtype=np.intp).ravel()
        kw = np.broadcast_to(np.asarray(kw, dtype=float), el.shape)
        kw_z = kw if kw_z is None else np.broadcast_to(np.asarray(kw_z, dtype=float), el.shape)
        rho_w = np.broadcast_to(np.asarray(rho_w, dtype=float), el.shape)
        _check_positive(kw, rho_w)
        _check_positive(kw_z, rho_w)
        flat_k, flat_z, flat_r = self.kw.reshape(-1), self.kw_z.reshape(-1), self.rho_w.reshape(-1)
        dk, dr = kw - flat_k[el], rho_w - flat_r[el]
        dz = (kw_z - kw) - (flat_z[el] - flat_k[el])
        flat_k[el], flat_z[el], flat_r[el] = kw, kw_z, rho_w
        self._ratio.reshape(-1)[el] = np.maximum(kw, kw_z) / rho_w * self._lam_e.reshape(-1)[el]
        self._add_mass(el[dr != 0], dr[dr != 0])
        added = np.count_nonzero(dk) + np.count_nonzero(dz)
        if self._corr.n_elements + added > 2 * self._n_factored + self.elem_shape[2]:
            self._factor()
        else:
            self._add_stiffness(el[dk != 0], dk[dk != 0])
            self._add_stiffness(el[dz != 0], dz[dz != 0], vertical_only=True)

    def moved(self, grid: Grid, kw=None, rho_w=None) -> TensorOperator | None:
        """This operator on ``grid``, a translate of its grid, with element weights ``kw`` and
        ``rho_w`` (as in the constructor; vertical weights equal to ``kw``), or ``None`` if ``grid``
        is no translate (other spacings along x, y or other heights).

        The factors, the element bounds and the correction are reused; only the elements whose
        weights differ from this operator's at the same place are re-weighted (:meth:`reweight`):
        a box that moves along the tracks keeps most of its weights.
        """
        same = (np.array_equal(grid.zs, self.grid.zs)
                and all(len(a) == len(b) and np.allclose(np.diff(a), np.diff(b), rtol=1e-9, atol=0.0)
                        for a, b in ((grid.xs, self.grid.xs), (grid.ys, self.grid.ys))))
        if not same:
            return None
        kw = _weights(kw, self.n_elements, "kw")
        rho_w = _weights(rho_w, self.n_elements, "rho_w")
        _check_positive(kw, rho_w)
        new = copy.copy(self)
        new.grid = grid
        new.kw, new.kw_z, new.rho_w = self.kw.copy(), self.kw_z.copy(), self.rho_w.copy()
        new._ratio, new.lumped_mass = self._ratio.copy(), self.lumped_mass.copy()
        new._corr = self._corr.copy()
        changed = np.flatnonzero((kw != self.kw.ravel()) | (kw != self.kw_z.ravel()) | (rho_w != self.rho_w.ravel()))
        if len(changed):
            new.reweight(changed, kw[changed], rho_w[changed])
        return new

    def stability_eigenvalue(self) -> float:
        """Upper bound of ``lambda_max(M_L^-1 K_w)`` [1/m²] (element bound, module docstring)."""
        return float(np.max(self._ratio))

    def assembled(self) -> sp.csr_matrix:
        """The full sparse ``K_w`` in solver order (for tests)."""
        kx = sp.diags([self._kd, self._ko, self._ko], [0, -1, 1])
        mx = sp.diags([self._md, self._mo, self._mo], [0, -1, 1])
        k = sp.kron(self._a, kx) + sp.kron(self._b, mx)
        return (k + self._corr.matrix(self.n_nodes)).tocsr()
