"""Melt-pool geometry from the nodal temperature field, with sub-element accuracy.

The FE temperature is trilinear in each hexahedron, i.e. piecewise linear along any grid
line.  On a line of constant y (top face) or constant (x, y) (vertical) the set above the
liquidus is therefore found exactly from nodal values; the remaining direction is
sampled finely (``refine`` samples per element) by exact linear interpolation.  Nothing
is counted per element.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Observation:
    """Plant output after one step (SI units).

    Attributes
    ----------
    step : int
        Number of steps done (0 = initial state).
    time_s : float
    x_m, y_m : float
        Laser position at the end of the step [m].
    direction : tuple of float
        Scan direction unit vector (dx, dy).
    track : int
        Index of the track the laser is on.
    power_w, speed_m_s : float
        Commands applied during the step that produced this observation.
    area_m2 : float
        Melt-pool top-surface (plan-view) area above liquidus [m²] - the paper's x.
    width_m, length_m, depth_m : float
        Extents of the liquid region along y, along x and below the top surface [m] (across and
        along the scan on a track along x).
    cross_section_m2 : float
        Liquid area in the y-z plane through the deepest point [m²] (transverse on a track along x).
    t_ahead_k : float
        Top-surface temperature at ``position + (v dt + r_s) * direction`` [K] (paper
        footnote 1: next laser spot plus one beam radius).
    t_peak_k : float
        Maximum nodal temperature [K].
    energy_absorbed_j, energy_stored_j, energy_lost_j : float
        Cumulative absorbed laser energy, change of stored enthalpy, and surface losses
        (convection + radiation) since the start [J].
    energy_error_pct : float
        ``100 (absorbed - stored - lost) / absorbed`` (0 before any absorption).
    track_travelled_m, track_remaining_m : float
        Scan-plan preview: distance scanned on the current path and left to its end [m]
        (a path: a hatch line, or a contour's tracks, joined end to start).
    next_track : bool
        Another path follows the current one.
    layer : int
        Layer of the build (0 first).
    z_top_m : float
        Height of the current top surface above the plate's top [m].
    thermal_gradient_k_m : float
        Temperature gradient G [K/m] across the mushy zone at the pool's trailing edge on the
        scan line (top surface; :func:`trailing_edge`); 0 without a pool.
    solidification_rate_m_s : float
        Solidification rate R [m/s] there: the boundary's speed along its normal, the scan speed
        in the quasi-steady pool (the normal is the scan direction on the scan line).
    cooling_rate_k_s : float
        Cooling rate G R [K/s] there.
    """

    step: int
    time_s: float
    x_m: float
    y_m: float
    direction: tuple
    track: int
    power_w: float
    speed_m_s: float
    area_m2: float
    width_m: float
    length_m: float
    depth_m: float
    cross_section_m2: float
    t_ahead_k: float
    t_peak_k: float
    energy_absorbed_j: float
    energy_stored_j: float
    energy_lost_j: float
    energy_error_pct: float
    track_travelled_m: float = 0.0
    track_remaining_m: float = 0.0
    next_track: bool = False
    layer: int = 0
    z_top_m: float = 0.0
    thermal_gradient_k_m: float = 0.0
    solidification_rate_m_s: float = 0.0
    cooling_rate_k_s: float = 0.0


def interp_weights(nodes: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interval ``i`` and weight ``w`` of each point: its value is ``(1 - w) f[i] + w f[i + 1]``.

    Points outside ``[nodes[0], nodes[-1]]`` are clamped to the end values.
    """
    points = np.clip(points, nodes[0], nodes[-1])
    i = np.clip(np.searchsorted(nodes, points, side="right") - 1, 0, len(nodes) - 2)
    return i, (points - nodes[i]) / (nodes[i + 1] - nodes[i])


def interpolate_points(grid, h: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of ``h`` (solver order (ny, nz, nx) on ``grid``, a
    :class:`fe_node.mesh.Grid`) at scattered ``points`` (shape (n, 3), x, y, z [m]), shape (n,);
    points outside ``grid`` take the nearest boundary value."""
    (ix, wx), (iy, wy), (iz, wz) = (interp_weights(c, points[:, k]) for k, c in enumerate((grid.xs, grid.ys, grid.zs)))
    out = np.zeros(len(points))
    for dy, fy in ((0, 1 - wy), (1, wy)):
        for dz, fz in ((0, 1 - wz), (1, wz)):
            for dx, fx in ((0, 1 - wx), (1, wx)):
                out += fy * fz * fx * h[iy + dy, iz + dz, ix + dx]
    return out


def interp_matrix(nodes: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Dense linear-interpolation matrix, shape (len(points), len(nodes)) (:func:`interp_weights`)."""
    i, w = interp_weights(nodes, points)
    out = np.zeros((len(points), len(nodes)))
    r = np.arange(len(points))
    out[r, i] = 1 - w
    out[r, i + 1] = w
    return out


def refine(nodes: np.ndarray, n: int) -> np.ndarray:
    """``nodes`` with ``n - 1`` evenly spaced points inserted in every interval."""
    fine = (nodes[:-1, None] + np.diff(nodes)[:, None] * _fractions(n)).ravel()
    return np.concatenate([fine, nodes[-1:]])


def area_above(field: np.ndarray, u: np.ndarray, v: np.ndarray, level: float,
               n_refine: int = 16) -> float:
    """Area of ``{f > level}`` for a bilinear field on the tensor grid ``u x v``.

    ``field`` has shape (len(u), len(v)).  Exact along u; trapezoid rule in v on
    ``n_refine`` samples per interval (compiled, :func:`fe_node.kernels.area_and_extent`).
    """
    from fe_node.kernels import area_and_extent

    return area_and_extent(np.ascontiguousarray(field, dtype=float), np.asarray(u, dtype=float),
                           np.asarray(v, dtype=float), float(level), _fractions(n_refine))[0]


def _fractions(n: int) -> np.ndarray:
    """The ``n`` sample fractions of an interval of :func:`refine`."""
    return np.linspace(0, 1, n + 1)[:-1]


def pool_geometry(t3: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray,
                  level: float, n_refine: int = 16) -> dict:
    """Melt-pool geometry of a trilinear field on a grid block.

    Area and extents: the top face's rows of constant y (for the width: of constant x), exact along
    them, ``n_refine`` rows per element across; depth: exact along z on the vertical lines of a
    raster of ``n_refine // 4`` (at least 2) lines per element in x and y; cross-section: the area
    above ``level`` in the y-z plane through the deepest line.  Compiled
    (:func:`fe_node.kernels.area_and_extent`, :func:`fe_node.kernels.deepest_line`).

    Parameters
    ----------
    t3 : ndarray, shape (nx, ny, nz)
        Nodal temperatures [K] of a block whose border nodes are below ``level``
        (except possibly the top layer ``[:, :, -1]``, which is the free surface).
    xs, ys, zs : ndarray
        Block coordinates [m]; ``zs[-1]`` is the top surface.
    level : float
        Liquidus [K].

    Returns
    -------
    dict with area_m2, width_m, length_m, depth_m, cross_section_m2 [m², m].
    """
    from fe_node.kernels import area_and_extent, deepest_line

    top = t3[:, :, -1]
    if not np.any(top > level):
        return dict(area_m2=0.0, width_m=0.0, length_m=0.0, depth_m=0.0, cross_section_m2=0.0)
    xs, ys, zs = (np.asarray(c, dtype=float) for c in (xs, ys, zs))
    t = _fractions(n_refine)
    area, length = area_and_extent(np.ascontiguousarray(top), xs, ys, level, t)
    width = area_and_extent(np.ascontiguousarray(top.T), ys, xs, level, t)[1]
    k0 = max(int(np.argmax((t3 > level).any(axis=(0, 1)))) - 1, 0)   # liquid-free below
    t3, zs = np.ascontiguousarray(t3[:, :, k0:], dtype=float), zs[k0:]
    line, zlo = deepest_line(t3, xs, ys, zs, level, _fractions(max(2, n_refine // 4)))
    x_deep = refine(xs, max(2, n_refine // 4))[line]
    (i,), (w,) = interp_weights(xs, np.array([x_deep]))
    cross = area_above((1.0 - w) * t3[i] + w * t3[i + 1], ys, zs, level, n_refine)
    return dict(area_m2=area, width_m=width, length_m=length, depth_m=float(zs[-1] - zlo),
                cross_section_m2=cross)


def bilinear(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, x: float, y: float) -> float:
    """Bilinear interpolation of nodal ``field`` (nx, ny) at (x, y) (clamped to the grid)."""
    wx = interp_matrix(xs, np.array([x]))[0]
    wy = interp_matrix(ys, np.array([y]))[0]
    return float(wx @ field @ wy)


def bilinear_at(field: np.ndarray, xs: np.ndarray, ys: np.ndarray, px: np.ndarray, py: np.ndarray) -> np.ndarray:
    """Bilinear interpolant of nodal ``field`` (nx, ny) at points ``(px, py)`` [m] (clamped to the grid)."""
    (i, wx), (j, wy) = interp_weights(xs, px), interp_weights(ys, py)
    return ((1 - wx) * ((1 - wy) * field[i, j] + wy * field[i, j + 1])
            + wx * ((1 - wy) * field[i + 1, j] + wy * field[i + 1, j + 1]))


def trailing_edge(t_top: np.ndarray, xs: np.ndarray, ys: np.ndarray, position: np.ndarray, direction: np.ndarray,
                  t_liquidus: float, t_solidus: float, reach_m: float, step_m: float) -> float:
    """Temperature gradient G [K/m] across the mushy zone at the pool's trailing edge on the scan line.

    Samples the bilinear top-surface field behind the laser, ``position - s * direction`` for
    ``0 <= s <= reach_m`` every ``step_m``, finds where it first falls below the liquidus and
    below the solidus (linear between samples) and returns ``(T_liquidus - T_solidus) / (s_solidus -
    s_liquidus)``: the mean gradient over the solidification range.  0 if the surface under the
    laser is not liquid or the solidus is not reached within ``reach_m``.

    Parameters
    ----------
    t_top : ndarray, shape (nx, ny)
        Top-surface nodal temperatures [K].
    xs, ys : ndarray
        Node coordinates [m].
    position, direction : ndarray, shape (2,)
        Laser position [m] and scan direction (unit vector).
    t_liquidus, t_solidus : float
        [K].
    reach_m, step_m : float
        Length of the sampled line and its spacing [m].
    """
    s = np.arange(0.0, reach_m + 0.5 * step_m, step_m)
    px, py = position[0] - s * direction[0], position[1] - s * direction[1]
    t = bilinear_at(t_top, xs, ys, px, py)
    if t[0] <= t_liquidus:
        return 0.0

    def crossing(level):
        below = np.nonzero(t <= level)[0]
        if not len(below):
            return None
        k = below[0]
        return s[k - 1] + (t[k - 1] - level) / (t[k - 1] - t[k]) * step_m

    s_liq, s_sol = crossing(t_liquidus), crossing(t_solidus)
    if s_liq is None or s_sol is None or not s_sol > s_liq:
        return 0.0
    return float((t_liquidus - t_solidus) / (s_sol - s_liq))
