"""Compiled inner loops of the explicit step and of the melt-pool observation (numba), each one pass
over the nodes.

The numpy forms they replace took about ten passes over the grid each.  The table
(:func:`piecewise_linear`: Kirchhoff variable and temperature), the tensor operator's product
(:func:`tensor_apply`, equal to scipy's sparse product and the x passes) and the powder's consolidation
(:func:`melt_powder`) are bitwise equal to those forms (same IEEE operations in the same order, no
fast-math; ``tests/test_fe_kernels.py``), as are the explicit sub-step's fused passes
(:func:`piecewise_linear_box`, :func:`add_mushy_integral`, :func:`vertical_box`, :func:`forward_euler`);
the operator's element-wise correction,
the evaporation solve, the keyhole's column walk (:func:`drill_columns`) and the melt-pool geometry
(:func:`area_and_extent`, :func:`deepest_line`) agree with the library or numpy results to rounding
(``tests/test_fe_operators.py`` against the scikit-fem forms, the evaporation residual test,
``tests/test_fe_physical.py``, ``tests/test_fe_core.py``).
Imported when a plant is built (:func:`warm`), so a process that builds no plant never loads numba.
"""
from __future__ import annotations

import numba
import numpy as np


@numba.njit(cache=True, nogil=True)
def tensor_apply(a_ptr: np.ndarray, a_idx: np.ndarray, a_val: np.ndarray, b_ptr: np.ndarray, b_idx: np.ndarray,
                 b_val: np.ndarray, u: np.ndarray, kd: np.ndarray, ko: np.ndarray, md: np.ndarray, mo: np.ndarray,
                 out: np.ndarray) -> None:
    """``out = (A U) Kx + (B U) Mx`` for the (y, z) factors ``A``, ``B`` (CSR: row pointers, column
    indices, values), ``U`` and ``out`` of shape (p, nx) and the tridiagonal symmetric ``Kx``, ``Mx``
    (diagonals ``kd``, ``md``, off-diagonals ``ko``, ``mo``): the product of
    :class:`~fe_node.operators.TensorOperator`, one row of ``out`` at a time, without the (2p, nx)
    intermediate of ``[A; B] @ U`` (the same operations in the same order as scipy's sparse product
    followed by the x passes)."""
    p, nx = u.shape
    v = np.empty(nx)
    w = np.empty(nx)
    for r in range(p):
        v[:] = 0.0
        w[:] = 0.0
        for q in range(a_ptr[r], a_ptr[r + 1]):
            c, s = a_idx[q], a_val[q]
            for i in range(nx):
                v[i] += s * u[c, i]
        for q in range(b_ptr[r], b_ptr[r + 1]):
            c, s = b_idx[q], b_val[q]
            for i in range(nx):
                w[i] += s * u[c, i]
        for i in range(nx):
            s = v[i] * kd[i] + w[i] * md[i]
            if i > 0:
                s += v[i - 1] * ko[i - 1] + w[i - 1] * mo[i - 1]
            if i < nx - 1:
                s += v[i + 1] * ko[i] + w[i + 1] * mo[i]
            out[r, i] = s


@numba.njit(cache=True, nogil=True)
def _table(h: float, h0: float, inv_dh: float, imax: int, a: np.ndarray, b: np.ndarray) -> float:
    """``b[i] h + a[i]`` with ``i = clip(trunc((h - h0) inv_dh), 0, imax)``: one value of a table of
    :class:`~fe_node.material.Constitutive`."""
    x = (h - h0) * inv_dh
    i = int(x) if x > 0.0 else 0
    if i > imax:
        i = imax
    return b[i] * h + a[i]


@numba.njit(cache=True, nogil=True)
def piecewise_linear(h: np.ndarray, h0: float, inv_dh: float, imax: int, a: np.ndarray, b: np.ndarray,
                     out: np.ndarray) -> None:
    """``out = b[i] h + a[i]`` with ``i = clip(trunc((h - h0) inv_dh), 0, imax)``, element-wise over
    the flat arrays ``h`` and ``out``: a table of :class:`~fe_node.material.Constitutive`."""
    for n in range(h.size):
        out[n] = _table(h[n], h0, inv_dh, imax, a, b)


@numba.njit(cache=True, nogil=True)
def piecewise_linear_box(h: np.ndarray, h0: float, inv_dh: float, imax: int, a: np.ndarray, b: np.ndarray,
                         floor: float, out: np.ndarray, box: np.ndarray) -> bool:
    """:func:`piecewise_linear` over the (ny, nz, nx) arrays ``h`` and ``out``, and in the same pass the
    smallest box of nodes with ``h > floor`` into ``box`` (int, 6: first and past-last y, z, x index);
    False if no node is above ``floor`` (``box`` then unchanged)."""
    ny, nz, nx = h.shape
    j0, k0, i0, j1, k1, i1 = ny, nz, nx, -1, -1, -1
    for j in range(ny):
        for k in range(nz):
            for i in range(nx):
                v = h[j, k, i]
                out[j, k, i] = _table(v, h0, inv_dh, imax, a, b)
                if v > floor:
                    j0, k0, i0 = min(j0, j), min(k0, k), min(i0, i)
                    j1, k1, i1 = max(j1, j), max(k1, k), max(i1, i)
    if j1 < 0:
        return False
    box[0], box[1], box[2], box[3], box[4], box[5] = j0, j1 + 1, k0, k1 + 1, i0, i1 + 1
    return True


@numba.njit(cache=True, nogil=True)
def add_mushy_integral(h: np.ndarray, box: np.ndarray, h0: float, inv_dh: float, imax: int, t_a: np.ndarray,
                       t_b: np.ndarray, t_solidus: float, t_liquidus: float, in_plane: float, vertical: float,
                       phi: np.ndarray, u_box: np.ndarray) -> None:
    """On the node box ``box`` (as :func:`piecewise_linear_box` gives it) of the (ny, nz, nx) arrays:
    ``phi += in_plane psi`` and ``u_box = vertical psi`` (``u_box`` the box's shape), ``psi`` the
    mushy integral at ``h`` (:meth:`fe_node.material.Constitutive.mushy_integral`, through the
    temperature table ``t_a``, ``t_b``; the same operations in the same order)."""
    two_dt, half_dt = 2 * (t_liquidus - t_solidus), 0.5 * (t_liquidus - t_solidus)
    j0, k0, i0 = box[0], box[2], box[4]
    for j in range(j0, box[1]):
        for k in range(k0, box[3]):
            for i in range(i0, box[5]):
                t = _table(h[j, k, i], h0, inv_dh, imax, t_a, t_b)
                if t < t_liquidus:
                    d = max(t - t_solidus, 0.0)
                    psi = d * d / two_dt
                else:
                    psi = half_dt + (t - t_liquidus)
                phi[j, k, i] += in_plane * psi
                u_box[j - j0, k - k0, i - i0] = vertical * psi


@numba.njit(cache=True, nogil=True)
def forward_euler(h: np.ndarray, kphi: np.ndarray, c: np.ndarray, top_w: np.ndarray, c_top: np.ndarray) -> None:
    """``h -= c kphi`` over the (ny, nz, nx) arrays, then ``h[:, -1, :] += top_w c_top`` ((ny, nx) arrays):
    the forward-Euler update of :func:`fe_node.solver.explicit_update`."""
    ny, nz, nx = h.shape
    for j in range(ny):
        for k in range(nz):
            for i in range(nx):
                h[j, k, i] -= kphi[j, k, i] * c[j, k, i]
    for j in range(ny):
        for i in range(nx):
            h[j, nz - 1, i] += top_w[j, i] * c_top[j, i]


@numba.njit(cache=True, nogil=True)
def element_apply(corners: np.ndarray, ke: np.ndarray, u: np.ndarray, out: np.ndarray) -> None:
    """``out += sum_e K_e u`` for element matrices ``ke`` (n, 8, 8) on the flat node indices
    ``corners`` (n, 8) of the flat arrays ``u`` and ``out``."""
    for e in range(corners.shape[0]):
        for a in range(8):
            s = 0.0
            for b in range(8):
                s += ke[e, a, b] * u[corners[e, b]]
            out[corners[e, a]] += s


@numba.njit(cache=True, nogil=True)
def csr_box_rows(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, nz: int, j_rows: int, k_rows: int,
                 j0: int, k0: int, sj: int, sk: int, u_box: np.ndarray, i0: int, out: np.ndarray) -> None:
    """``out += A u`` on the rows of a (y, z) node box of ``A`` (CSR, rows and columns ``j nz + k``), for
    ``u`` zero outside the node box that starts at (``sj``, ``sk``), ``u_box`` (nj, nk, n) its values
    there: ``out[(j - j0) k_rows + (k - k0), i0:i0 + n]`` for the ``j_rows`` × ``k_rows`` rows from
    (``j0``, ``k0``)."""
    nj, nk = u_box.shape[0], u_box.shape[1]
    for a in range(j_rows):
        for b in range(k_rows):
            r, o = (j0 + a) * nz + k0 + b, a * k_rows + b
            for q in range(indptr[r], indptr[r + 1]):
                c = indices[q]
                jc, kc = c // nz - sj, c % nz - sk
                if 0 <= jc < nj and 0 <= kc < nk:
                    v = data[q]
                    for i in range(u_box.shape[2]):
                        out[o, i0 + i] += v * u_box[jc, kc, i]


@numba.njit(cache=True, nogil=True)
def vertical_box(indptr: np.ndarray, indices: np.ndarray, data: np.ndarray, nz: int, rows: np.ndarray,
                 sj: int, sk: int, si: int, u_box: np.ndarray, md: np.ndarray, mo: np.ndarray, out: np.ndarray) -> None:
    """``out += (Mx (x) C) u`` for ``u`` zero outside the node box from (``sj``, ``sk``, ``si``),
    ``u_box`` its values, on the node rows ``rows`` (int, 6: first and past-last y, z, x index; the box
    and its neighbours): :func:`csr_box_rows` with the (y, z) factor ``C`` (CSR), then the tridiagonal x
    factor (diagonal ``md``, off-diagonal ``mo``); ``out`` the grid's (ny, nz, nx) array."""
    j0, j1, k0, k1, i0, i1 = rows[0], rows[1], rows[2], rows[3], rows[4], rows[5]
    k_rows, n = k1 - k0, i1 - i0
    w = np.zeros(((j1 - j0) * k_rows, n))
    csr_box_rows(indptr, indices, data, nz, j1 - j0, k_rows, j0, k0, sj, sk, u_box, si - i0, w)
    for a in range(j1 - j0):
        for b in range(k_rows):
            o = a * k_rows + b
            for i in range(n):
                s = w[o, i] * md[i0 + i]
                if i > 0:
                    s += w[o, i - 1] * mo[i0 + i - 1]
                if i < n - 1:
                    s += w[o, i + 1] * mo[i0 + i]
                out[j0 + a, k0 + b, i0 + i] += s


@numba.njit(cache=True, nogil=True)
def element_apply_box(first: np.ndarray, ke: np.ndarray, u_box: np.ndarray, j0: int, k0: int, i0: int,
                      out: np.ndarray) -> None:
    """``out += sum_e K_e u`` as :func:`element_apply`, for ``u`` zero outside a box of nodes that
    starts at node (``j0``, ``k0``, ``i0``), ``u_box`` (its shape) its values there; ``first`` (n, 3)
    the (y, z, x) node of each element's first corner (its local node ``4 b_y + 2 b_z + b_x`` is that
    node plus (b_y, b_z, b_x)) and ``out`` of the grid's node shape (ny, nz, nx). Elements with no
    corner in the box are skipped."""
    ny_b, nz_b, nx_b = u_box.shape
    vals = np.empty(8)
    for e in range(first.shape[0]):
        j, k, i = first[e, 0] - j0, first[e, 1] - k0, first[e, 2] - i0
        if not (-1 <= j < ny_b and -1 <= k < nz_b and -1 <= i < nx_b):
            continue
        for b in range(8):
            jb, kb, ib = j + (b >> 2), k + ((b >> 1) & 1), i + (b & 1)
            if 0 <= jb < ny_b and 0 <= kb < nz_b and 0 <= ib < nx_b:
                vals[b] = u_box[jb, kb, ib]
            else:
                vals[b] = 0.0
        for a in range(8):
            s = 0.0
            for b in range(8):
                s += ke[e, a, b] * vals[b]
            out[first[e, 0] + (a >> 2), first[e, 1] + ((a >> 1) & 1), first[e, 2] + (a & 1)] += s


@numba.njit(cache=True, nogil=True)
def _evaporated(t_star: float, k: float, heat_capacity: float, t_boil: float, t_low: float, a: float, b: float,
                c: float, n_iter: int) -> float:
    """Temperature [K] of a liquid surface node after the implicit evaporation step: bracketed Newton on
    ``C (T - T*) + k q_evap(T) = 0`` in ``[t_low, T*]`` until the step is below 1e-10 T, with
    ``q_evap(T) = a exp(b (1/T_boil - 1/T)) sqrt(c / T)`` (:func:`fe_node.boundary.evaporation_flux`;
    Newton steps that leave the bracket are replaced by bisection: ``q_evap`` is convex near boiling but
    concave above ~2e4 K, where a plain Newton step overshoots)."""
    lo, hi, t = t_low, t_star, t_star
    for _ in range(n_iter):
        q = a * np.exp(b * (1.0 / t_boil - 1.0 / t)) * np.sqrt(c / t)
        f = heat_capacity * (t - t_star) + k * q
        if f > 0:
            hi = t
        else:
            lo = t
        new = t - f / (heat_capacity + k * q * (b / t**2 - 0.5 / t))
        if not (lo <= new <= hi):
            new = 0.5 * (lo + hi)
        done = abs(new - t) < 1e-10 * t
        t = new
        if done:
            break
    return t


@numba.njit(cache=True, nogil=True)
def evaporate_top(h: np.ndarray, m: np.ndarray, h0: float, inv_dh: float, imax: int, t_a: np.ndarray,
                  t_b: np.ndarray, k: np.ndarray, heat_capacity: float, t_boil: float, t_low: float, a: float,
                  b: float, c: float, n_iter: int, lost: np.ndarray) -> int:
    """:func:`_evaporated` on the top nodes of the (ny, nz, nx) enthalpy ``h`` [J/m³] whose temperature
    (the table ``t_a``, ``t_b``) is above ``t_low``, in place: ``H -= C (T* - T)``; ``k`` (ny, nx) as
    there. Returns their number n, with ``lost[:n]`` their energies ``C (T* - T) m`` [J] (``m`` the lumped
    masses, ``h``'s shape), in C order."""
    ny, nz, nx = h.shape
    n = 0
    for j in range(ny):
        for i in range(nx):
            v = h[j, nz - 1, i]
            t = _table(v, h0, inv_dh, imax, t_a, t_b)
            if t > t_low:
                dh = heat_capacity * (t - _evaporated(t, k[j, i], heat_capacity, t_boil, t_low, a, b, c, n_iter))
                h[j, nz - 1, i] = v - dh
                lost[n] = dh * m[j, nz - 1, i]
                n += 1
    return n


@numba.njit(cache=True, nogil=True)
def drill_columns(h: np.ndarray, m: np.ndarray, h_cap: float, n_heated: int, opening: np.ndarray) -> None:
    """:func:`fe_node.keyhole.drill` column by column: ``h``, ``m`` of shape (ny, nz, nx), top at
    ``[:, -1, :]``; ``opening`` (ny, nx) receives the drilled columns.  A column is walked down from
    its top while in its ``n_heated`` top nodes or while it carries an excess."""
    ny, nz, nx = h.shape
    for j in range(ny):
        for i in range(nx):
            hot = False
            for k in range(nz - n_heated, nz):
                if h[j, k, i] > h_cap:
                    hot = True
            opening[j, i] = hot
            if not hot:
                continue
            excess = 0.0
            for k in range(nz - 1, -1, -1):
                total = excess + (h[j, k, i] - h_cap) * m[j, k, i]
                if total > 0:
                    h[j, k, i] = h_cap
                    excess = total
                else:
                    h[j, k, i] = h_cap + total / m[j, k, i]
                    excess = 0.0
                if k <= nz - n_heated and excess <= 0.0:
                    break
            h[j, 0, i] += excess / m[j, 0, i]


@numba.njit(cache=True, nogil=True)
def melt_powder(t: np.ndarray, t_liquidus: float, consolidated: np.ndarray, k0: int, out: np.ndarray) -> int:
    """:meth:`fe_node.powder.PowderBed.consolidate`: mark the elements of ``consolidated`` (ny, n, nx)
    whose mean corner temperature of ``t`` (ny + 1, n + 1, nx + 1) [K] passes ``t_liquidus``; their
    flat indices in the element order of a grid with ``k0`` element layers below them go to ``out``
    (C order, as ``np.nonzero``); returns how many."""
    ny, n, nx = consolidated.shape
    count = 0
    for j in range(ny):
        for k in range(n):
            for i in range(nx):
                if consolidated[j, k, i]:
                    continue
                mean = 0.125 * (t[j, k, i] + t[j, k, i + 1] + t[j, k + 1, i] + t[j, k + 1, i + 1]
                                + t[j + 1, k, i] + t[j + 1, k, i + 1] + t[j + 1, k + 1, i] + t[j + 1, k + 1, i + 1])
                if mean > t_liquidus:
                    consolidated[j, k, i] = True
                    out[count] = (j * (n + k0) + k + k0) * nx + i
                    count += 1
    return count


@numba.njit(cache=True, nogil=True)
def _row_above(field: np.ndarray, m: int, w: float, u: np.ndarray, level: float) -> tuple[float, float, float]:
    """Measure, lowest and highest coordinate of ``{f > level}`` on the row ``(1 - w) field[:, m] + w
    field[:, m + 1]``, piecewise linear on ``u`` (0, NaN, NaN if empty)."""
    length, lo, hi = 0.0, np.nan, np.nan
    a = (1.0 - w) * field[0, m] + w * field[0, m + 1]
    for c in range(u.size - 1):
        b = (1.0 - w) * field[c + 1, m] + w * field[c + 1, m + 1]
        above_a, above_b = a > level, b > level
        if above_a or above_b:
            h = u[c + 1] - u[c]
            cross = (level - a) / (b - a) if not (above_a and above_b) else 0.0
            length += (1.0 if above_a and above_b else cross if above_a else 1.0 - cross) * h   # > 0
            if np.isnan(lo):
                lo = u[c] + (0.0 if above_a else cross) * h
            hi = u[c] + (1.0 if above_b else cross) * h
        a = b
    return length, lo, hi


@numba.njit(cache=True, nogil=True)
def area_and_extent(field: np.ndarray, u: np.ndarray, v: np.ndarray, level: float, t: np.ndarray
                    ) -> tuple[float, float]:
    """Area of ``{f > level}`` for the bilinear ``field`` (len(u), len(v)) on ``u x v``, exact along
    ``u``, trapezoid rule in ``v`` on the rows at ``v[m] + (v[m + 1] - v[m]) t`` and at ``v[-1]``; and
    its extent along ``u`` over those rows (0 if empty) (:func:`fe_node.observe.pool_geometry`)."""
    area, lo_min, hi_max = 0.0, np.inf, -np.inf
    v_prev, len_prev = 0.0, 0.0
    n = v.size - 1
    for m in range(n):
        d = v[m + 1] - v[m]
        for r in range(t.size + (1 if m == n - 1 else 0)):
            vr = v[m] + d * t[r] if r < t.size else v[n]
            length, lo, hi = _row_above(field, m, (vr - v[m]) / d, u, level)
            if m > 0 or r > 0:
                area += (vr - v_prev) * (length + len_prev) / 2.0
            v_prev, len_prev = vr, length
            if not np.isnan(lo):
                lo_min, hi_max = min(lo_min, lo), max(hi_max, hi)
    return area, (hi_max - lo_min) if hi_max >= lo_min else 0.0


@numba.njit(cache=True, nogil=True)
def deepest_line(t3: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray, level: float, t: np.ndarray
                 ) -> tuple[int, float]:
    """Of the vertical lines of the bilinear-in-(x, y) ``t3`` (nx, ny, nz) on the raster ``refine(xs) x
    refine(ys)`` (``t`` the fractions of an interval, the last node added), in x-major order: the
    index along the refined x of the line whose set ``{f > level}`` reaches lowest (the first on a
    tie) and that lowest height, linear between nodes along z."""
    nx, ny, nz = t3.shape
    best_first, best_lo, best_p = nz, np.inf, -1
    p = 0
    for i in range(nx - 1):
        dx = xs[i + 1] - xs[i]
        for a in range(t.size + (1 if i == nx - 2 else 0)):
            wx = ((xs[i] + dx * t[a]) - xs[i]) / dx if a < t.size else 1.0
            for j in range(ny - 1):
                dy = ys[j + 1] - ys[j]
                for b in range(t.size + (1 if j == ny - 2 else 0)):
                    wy = ((ys[j] + dy * t[b]) - ys[j]) / dy if b < t.size else 1.0
                    below = 0.0
                    for k in range(nz):
                        val = ((1.0 - wy) * ((1.0 - wx) * t3[i, j, k] + wx * t3[i + 1, j, k])
                               + wy * ((1.0 - wx) * t3[i, j + 1, k] + wx * t3[i + 1, j + 1, k]))
                        if val > level:
                            if k < best_first or k == best_first and k > 0:
                                lo = zs[0] if k == 0 else (zs[k - 1] + (level - below) / (val - below)
                                                           * (zs[k] - zs[k - 1]))
                                if k < best_first or lo < best_lo:
                                    best_first, best_lo, best_p = k, lo, p
                            break
                        below = val
            p += 1
    return best_p, best_lo


def warm() -> None:
    """Compile (or load from numba's cache) every kernel here with the argument types the plant
    passes, on tiny arrays: a plant calls it when it is built, so its first step runs at speed
    (a fresh install compiles them once, in one process of those that start together:
    :func:`gp_model.compiled.compile_lock`)."""
    from gp_model.compiled import compile_lock

    with compile_lock(__file__):
        _warm()


def _warm() -> None:
    """:func:`warm`'s calls."""
    one, two = np.ones(2), np.ones((2, 2))
    ptr, idx = np.array([0, 1, 2], dtype=np.int32), np.array([0, 1], dtype=np.int32)
    tensor_apply(ptr, idx, one, ptr, idx, one, two, one, one[:1], one, one[:1], np.empty((2, 2)))
    piecewise_linear(one, 0.0, 1.0, 1, one, one, np.empty(2))
    cube, box = np.ones((2, 2, 2)), np.array([0, 1, 0, 1, 0, 1])
    piecewise_linear_box(cube, 0.0, 1.0, 1, one, one, 0.5, np.empty((2, 2, 2)), box)
    add_mushy_integral(cube, box, 0.0, 1.0, 1, one, one, 1.0, 2.0, 1.0, 1.0, np.zeros((2, 2, 2)), np.empty((2, 2, 2)))
    forward_euler(cube.copy(), cube, cube, two, two)
    corners = np.zeros((1, 8), dtype=np.intp)
    element_apply(corners, np.zeros((1, 8, 8)), one, np.zeros(2))
    csr_box_rows(np.array([0, 1], dtype=np.int32), np.zeros(1, dtype=np.int32), one[:1], 1, 1, 1, 0, 0, 0, 0,
                 np.ones((1, 1, 2)), 0, np.zeros((1, 2)))
    vertical_box(np.array([0, 1], dtype=np.int32), np.zeros(1, dtype=np.int32), one[:1], 1,
                 np.array([0, 1, 0, 1, 0, 2]), 0, 0, 0, np.ones((1, 1, 1)), one, one[:1], np.zeros((2, 2, 2)))
    element_apply_box(np.zeros((1, 3), dtype=np.intp), np.zeros((1, 8, 8)), np.ones((1, 1, 1)), 0, 0, 0,
                      np.zeros((2, 2, 2)))
    evaporate_top(cube.copy(), cube, 0.0, 1.0, 1, one, one, two, 1.0, 3.0, 0.5, 1.0, 1.0, 1.0, 2, np.empty(4))
    drill_columns(np.ones((1, 2, 1)), np.ones((1, 2, 1)), 2.0, 1, np.empty((1, 1), dtype=np.bool_))
    melt_powder(np.ones((2, 2, 2)), 2.0, np.zeros((1, 1, 1), dtype=np.bool_), 1, np.empty(1, dtype=np.intp))
    axis = np.array([0.0, 1.0])
    area_and_extent(two, axis, axis, 0.5, np.zeros(1))
    deepest_line(np.ones((2, 2, 2)), axis, axis, axis, 0.5, np.zeros(1))
