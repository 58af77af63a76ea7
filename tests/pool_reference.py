"""The numpy form of the melt-pool geometry (``fe_node.observe.pool_geometry`` before it was compiled):
the reference the compiled kernels are tested against."""
import numpy as np

from fe_node.observe import interp_matrix, refine


def segments_above(values: np.ndarray, coords: np.ndarray, level: float):
    """Exact measure and extent of ``{u : f(u) > level}`` for piecewise-linear rows.

    Parameters
    ----------
    values : ndarray, shape (m, n)
        Nodal values of m piecewise-linear functions on ``coords``.
    coords : ndarray, shape (n,)
    level : float

    Returns
    -------
    length : ndarray, shape (m,)
        Measure of the super-level set of each row.
    lo, hi : ndarray, shape (m,)
        Its smallest and largest coordinate (NaN if empty).
    """
    length = np.zeros(len(values))
    lo = np.full(len(values), np.nan)
    hi = np.full(len(values), np.nan)
    above = values > level
    rows = np.flatnonzero(above.any(axis=1))      # the others have nothing above: 0, NaN, NaN
    if not len(rows):
        return length, lo, hi
    v, above = values[rows], above[rows]
    a, b = v[:, :-1], v[:, 1:]
    h = np.diff(coords)
    above_a, above_b = above[:, :-1], above[:, 1:]
    with np.errstate(divide="ignore", invalid="ignore"):
        cross = (level - a) / (b - a)              # crossing fraction in the interval
    frac = np.where(above_a & above_b, 1.0,
                    np.where(above_a, cross, np.where(above_b, 1.0 - cross, 0.0)))
    length[rows] = (frac * h).sum(axis=1)
    any_ = frac > 0
    first = np.argmax(any_, axis=1)
    last = any_.shape[1] - 1 - np.argmax(any_[:, ::-1], axis=1)
    r = np.arange(len(rows))
    fa = np.where(above_a[r, first], 0.0, cross[r, first])
    lo[rows] = coords[first] + fa * h[first]
    fb = np.where(above_b[r, last], 1.0, cross[r, last])
    hi[rows] = coords[last] + fb * h[last]
    return length, lo, hi


def area_above(field: np.ndarray, u: np.ndarray, v: np.ndarray, level: float,
               n_refine: int = 16) -> float:
    """Area of ``{f > level}`` for a bilinear field on the tensor grid ``u x v``.

    ``field`` has shape (len(u), len(v)).  Exact along u; trapezoid rule in v on
    ``n_refine`` samples per interval.
    """
    return _area_and_extent(field, u, v, level, n_refine)[0]


def _area_and_extent(field: np.ndarray, u: np.ndarray, v: np.ndarray, level: float, n_refine: int
                     ) -> tuple[float, float]:
    """:func:`area_above` and the extent along u of ``{f > level}`` (max over rows of constant v; 0 if
    empty), from the same refined rows."""
    vf = refine(v, n_refine)
    rows = interp_matrix(v, vf) @ field.T                 # (len(vf), len(u))
    length, lo, hi = segments_above(rows, u, level)
    span = 0.0 if np.all(np.isnan(lo)) else float(np.nanmax(hi) - np.nanmin(lo))
    return float(np.trapezoid(length, vf)), span


def lowest_crossing(values: np.ndarray, coords: np.ndarray, level: float) -> tuple[int, float]:
    """The piecewise-linear row (of ``values``, shape (m, n), on increasing ``coords``) whose set
    ``{f > level}`` reaches lowest, and that lowest coordinate (:func:`segments_above`'s ``lo``;
    the first such row on a tie).  At least one value must exceed ``level``.

    A row's set starts in the interval below its first node above ``level`` (at ``coords[0]`` if
    that is node 0), so only the rows whose first node above is the lowest can hold the minimum.
    """
    above = values > level
    first = np.where(above.any(axis=1), np.argmax(above, axis=1), len(coords))
    i = int(first.min())
    rows = np.flatnonzero(first == i)
    if i == 0:
        return int(rows[0]), float(coords[0])
    a, b = values[rows, i - 1], values[rows, i]
    lo = coords[i - 1] + (level - a) / (b - a) * (coords[i] - coords[i - 1])
    k = int(np.argmin(lo))
    return int(rows[k]), float(lo[k])


def pool_geometry(t3: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray,
                  level: float, n_refine: int = 16) -> dict:
    """The numpy form of :func:`fe_node.observe.pool_geometry` (same arguments and result)."""
    top = t3[:, :, -1]
    if not np.any(top > level):
        return dict(area_m2=0.0, width_m=0.0, length_m=0.0, depth_m=0.0, cross_section_m2=0.0)
    area, length = _area_and_extent(top, xs, ys, level, n_refine)
    width = _area_and_extent(top.T, ys, xs, level, n_refine)[1]
    # depth: exact along z on a refined (x, y) raster of vertical lines
    r = max(2, n_refine // 4)
    xf, yf = refine(xs, r), refine(ys, r)
    k0 = max(int(np.argmax((t3 > level).any(axis=(0, 1)))) - 1, 0)   # liquid-free below
    t3, zs = t3[:, :, k0:], zs[k0:]
    cols = interp_matrix(ys, yf) @ np.tensordot(interp_matrix(xs, xf), t3, axes=1)
    k, zlo = lowest_crossing(cols.reshape(-1, len(zs)), zs, level)
    depth = float(zs[-1] - zlo)
    # transverse section through the deepest point
    x_deep = xf[k // len(yf)]
    t_yz = np.tensordot(interp_matrix(xs, np.array([x_deep]))[0], t3, axes=1)   # (ny, nz)
    cross = area_above(t_yz, ys, zs, level, n_refine)
    return dict(area_m2=area, width_m=width, length_m=length, depth_m=depth,
                cross_section_m2=cross)
