"""Coarser levels of the multi-level plant and the energy-conserving transfers between levels.

With ``Settings.mesh = "multilevel"`` (:mod:`fe_node.multilevel`) the plant is three nested grids:
the fine level (the full physics of :class:`fe_node.solver.ThermalModel`) on a box around the
laser, an intermediate level of ``mid_h_m`` on a box of ``mid_box_m`` around the fine one, and the
part at ``coarse_h_m``.  A coarser level here (:class:`ConductionLevel`) solves the same
enthalpy equation with the same forms (:func:`fe_node.solver.explicit_update`) but only with
conduction and the top-face losses, at its own stable time step; near the laser its field is
overwritten by its finer level's (:class:`Restriction`), and the heat the finer level sends out of
those nodes is handed to the nodes around them (:meth:`ConductionLevel.advance`).

Transfers.  A box's side and bottom nodes take their coarser level's field (Dirichlet, held
between the coarser level's steps).  :class:`Restriction` takes the fine field's values at the
coarse nodes' x and y, averaged in z under each coarse hat function; :func:`prolong` interpolates
linearly; then one enthalpy shift of the transferred nodes (:func:`shift_to`) makes their energy
that of the source field over the same region: the lumped (row-sum) energy of a nodal field
inside a box counts each node's dual cell (half-way to its neighbours) clipped to the box
(:func:`region_energy`).
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.boundary import loss_flux
from fe_node.dwell import cool, implicit_cooling_step
from fe_node.material import Constitutive
from fe_node.mesh import Grid, graded_axis
from fe_node.observe import interp_matrix, interp_weights
from fe_node.operators import TensorOperator
from fe_node.settings import Settings

STABILITY_SAFETY = 0.9
"""Fraction of the explicit stability limit a coarser level's sub-step takes (as the fine level)."""


def dual_cells(coords: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Lower and upper ends [m] of each node's dual cell (half-way to its neighbours; the row-sum
    lumped 1-D mass is its length), shapes (n,)."""
    half = 0.5 * np.diff(coords)
    return np.concatenate([coords[:1], coords[1:] - half]), np.concatenate([coords[:-1] + half, coords[-1:]])


def dual_lengths(coords: np.ndarray, lo: float, hi: float) -> np.ndarray:
    """Length [m] of each node's dual cell (:func:`dual_cells`) inside ``[lo, hi]``, shape (n,)."""
    left, right = dual_cells(coords)
    return np.clip(np.minimum(right, hi) - np.maximum(left, lo), 0.0, None)


def region_energy(grid: Grid, h: np.ndarray, box: tuple[tuple[float, float], ...]) -> float:
    """Lumped energy [J] of nodal enthalpy ``h`` (J/m³, solver order (ny, nz, nx)) inside the box
    ``((x0, x1), (y0, y1), (z0, z1))`` [m]: the sum of ``h`` times each node's dual volume inside it
    (every element's heat-capacity weight is 1, :data:`fe_node.powder.RHO_W`)."""
    wx, wy, wz = (dual_lengths(c, *b) for c, b in zip((grid.xs, grid.ys, grid.zs), box))
    return separable_sum(wy, wz, wx, h)


def separable_sum(wy: np.ndarray, wz: np.ndarray, wx: np.ndarray, h: np.ndarray) -> float:
    """``sum_jki wy_j wz_k wx_i h_jki`` for ``h`` of shape (ny, nz, nx), as three vector products (the
    four-operand ``einsum`` multiplies all four operands in every term)."""
    ny, nz, nx = h.shape
    return float(wz @ (wy @ h.reshape(ny, nz * nx)).reshape(nz, nx) @ wx)


class Interpolation:
    """Trilinear interpolation from ``grid`` to the tensor points (xs, ys, zs), its weights computed
    once (:func:`fe_node.observe.interp_weights`): applied to a field by :meth:`of`, axis by axis, each
    a weighted sum of two slices, the axis that shrinks the field most first.  Points outside
    ``grid`` take the nearest boundary value."""

    def __init__(self, grid: Grid, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray):
        weights = [interp_weights(c, p) for c, p in ((grid.ys, ys), (grid.zs, zs), (grid.xs, xs))]
        shape = grid.solver_shape
        self._passes = []
        for axis in sorted(range(3), key=lambda a: len(weights[a][0]) / shape[a]):
            i, w = weights[axis]
            bshape = [1, 1, 1]
            bshape[axis] = len(i)
            self._passes.append((axis, i, i + 1, w.reshape(bshape), (1.0 - w).reshape(bshape)))

    def of(self, h: np.ndarray) -> np.ndarray:
        """The interpolated field, shape (len(ys), len(zs), len(xs)), of ``h`` (solver order on the grid)."""
        out = h
        for axis, lo, hi, w, w0 in self._passes:
            out = np.take(out, lo, axis=axis) * w0 + np.take(out, hi, axis=axis) * w
        return np.ascontiguousarray(out)


def interpolate(grid: Grid, h: np.ndarray, xs: np.ndarray, ys: np.ndarray, zs: np.ndarray) -> np.ndarray:
    """Trilinear interpolation of ``h`` (solver order on ``grid``) at the tensor points (xs, ys, zs),
    shape (len(ys), len(zs), len(xs)) (:class:`Interpolation`, once)."""
    return Interpolation(grid, xs, ys, zs).of(h)


def inside_grid(grid: Grid, points: np.ndarray) -> np.ndarray:
    """True for the ``points`` (shape (n, 3) x, y, z, or (n, 2) x, y only, [m]) inside ``grid``'s box."""
    return np.all([(points[:, k] >= lo) & (points[:, k] <= hi)
                   for k, (lo, hi) in enumerate(extent(grid)[:points.shape[1]])], axis=0)


def extent(grid: Grid) -> tuple[tuple[float, float], ...]:
    """The grid's box ``((x0, x1), (y0, y1), (z0, z1))`` [m]."""
    return tuple((float(c[0]), float(c[-1])) for c in (grid.xs, grid.ys, grid.zs))


def inside(coords: np.ndarray, lo: float, hi: float) -> slice:
    """The nodes of ``coords`` whose dual cells lie inside ``[lo, hi]``, as a slice (may be empty)."""
    left, right = dual_cells(coords)
    tol = 1e-9 * max(abs(hi - lo), 1e-9)
    idx = np.flatnonzero((left >= lo - tol) & (right <= hi + tol))
    return slice(0, 0) if not len(idx) else slice(int(idx[0]), int(idx[-1]) + 1)


def dual_box(coords: np.ndarray, sl: slice) -> tuple[float, float]:
    """The union [m] of the dual cells of nodes ``coords[sl]``."""
    left, right = dual_cells(coords)
    return float(left[sl.start]), float(right[sl.stop - 1])


class Restriction:
    """The transfer from a finer grid to the coarse nodes whose dual cells lie inside it
    (:func:`slaved`), its geometry (interpolation and hat weights, dual volumes) computed once for
    the pair of grids.

    :meth:`apply` overwrites those nodes with the fine field: each takes the fine field's value at
    the node's x and y (bilinear; exact where fine nodes lie there) averaged in z under its hat
    function (weighted by the fine nodes' heights; interpolated where the hat holds no fine node),
    then all are shifted alike (:func:`shift_to`) so that their lumped energy equals the fine
    field's over their dual cells.  Values in x and y, not averages under the whole hat: a fresh
    track's edge in the powder layer (consolidated metal beside insulating powder) is steep
    sideways, and an average over a coarse element's width, prolonged back into the fine box,
    brought that heat to the next track's line cooler than on the uniform mesh.

    Parameters
    ----------
    fine, coarse : Grid
        The finer grid and the coarser one it lies in.

    Attributes
    ----------
    held : tuple of slice or None
        The coarse nodes the fine field overwrites, slices along y, z, x (``None``: none).
    """

    def __init__(self, fine: Grid, coarse: Grid):
        self.fine, self.coarse = fine, coarse
        self.held = slaved(fine, coarse)
        self._m_fine = lumped_volumes(fine)
        if self.held is None:
            return
        sy, sz, sx = self.held
        box = (dual_box(coarse.xs, sx), dual_box(coarse.ys, sy), dual_box(coarse.zs, sz))
        self._wx, self._wy, self._wz = (dual_lengths(c, *b) for c, b in zip((fine.xs, fine.ys, fine.zs), box))
        self._lateral = Interpolation(fine, coarse.xs[sx], coarse.ys[sy], fine.zs)
        self._az = hat_weights(coarse.zs, fine.zs, sz)
        height = self._az.sum(axis=1)
        self._height = height[None, :, None]
        self._gap = np.flatnonzero(height <= 0)       # hats holding no fine node
        self._gap_values = (Interpolation(fine, coarse.xs[sx], coarse.ys[sy], coarse.zs[sz][self._gap])
                            if len(self._gap) else None)
        self._m_coarse = lumped_volumes(coarse)[sy, sz, sx]
        self._m_total = float(np.sum(self._m_coarse))

    def held_energy(self, h_fine: np.ndarray) -> float:
        """Lumped energy [J] of the fine field ``h_fine`` over the dual cells of the held nodes."""
        return 0.0 if self.held is None else separable_sum(self._wy, self._wz, self._wx, h_fine)

    def outside(self, h_fine: np.ndarray) -> float:
        """Lumped energy [J] of the fine field outside the dual cells of the held nodes: the part of
        the fine level the coarse one holds in its own free nodes."""
        return float(np.sum(self._m_fine * h_fine)) - self.held_energy(h_fine)

    def apply(self, h_fine: np.ndarray, h_coarse: np.ndarray) -> float:
        """Overwrite the held nodes of ``h_coarse`` (solver order on ``coarse``) with the fine field
        ``h_fine``, in place; returns their energy [J] (0: no node)."""
        if self.held is None:
            return 0.0
        target = self.held_energy(h_fine)
        view = h_coarse[self.held]
        np.divide(np.einsum("kf,jfi->jki", self._az, self._lateral.of(h_fine)), self._height, out=view,
                  where=self._height > 0)
        if self._gap_values is not None:
            view[:, self._gap, :] = self._gap_values.of(h_fine)
        view += (target - float(np.sum(self._m_coarse * view))) / self._m_total
        return target


def slaved(fine: Grid, coarse: Grid) -> tuple[slice, slice, slice] | None:
    """The coarse nodes whose dual cells lie inside the fine grid (those :class:`Restriction` sets), as
    slices along y, z, x (``None``: none)."""
    (x0, x1), (y0, y1), (z0, z1) = extent(fine)
    box = (inside(coarse.ys, y0, y1), inside(coarse.zs, z0, z1), inside(coarse.xs, x0, x1))
    return None if any(s.stop <= s.start for s in box) else box


def hat_weights(coarse: np.ndarray, fine: np.ndarray, sl: slice) -> np.ndarray:
    """``A[i, f]`` = coarse hat function ``sl``'s ``i``-th at fine node ``f`` times the fine node's
    dual length [m], shape (len(coarse[sl]), len(fine)): the 1-D weights of an average under a hat."""
    return (interp_matrix(coarse, fine) * dual_lengths(fine, fine[0], fine[-1])[:, None]).T[sl]


def shift_to(h: np.ndarray, mass: np.ndarray, moved: np.ndarray, energy_j: float) -> float:
    """Add one enthalpy [J/m³] to the ``moved`` nodes so that ``sum(mass * h)`` is ``energy_j``, in
    place; returns the shift (bounded by the transfer's own error, unlike a scaling of the excess
    enthalpy, which diverges where the field is near its reference)."""
    m = float(np.sum(mass[moved]))
    dh = (energy_j - float(np.sum(mass * h))) / m if m > 0 else 0.0
    h[moved] += dh
    return dh


def lumped_volumes(grid: Grid) -> np.ndarray:
    """Row-sum lumped nodal volumes [m³] of ``grid``, solver order (ny, nz, nx)."""
    wx, wy, wz = (dual_lengths(c, c[0], c[-1]) for c in (grid.xs, grid.ys, grid.zs))
    return wy[:, None, None] * wz[None, :, None] * wx[None, None, :]


def prolong(coarse: Grid, h_coarse: np.ndarray, old: Grid | None, h_old: np.ndarray | None, new: Grid
            ) -> np.ndarray:
    """The field on ``new`` for a level that moved from ``old`` (``None``: a new level): nodes inside
    the old grid interpolated from the old field (exact at shared nodes), the others from the
    coarser level, those shifted alike (:func:`shift_to`) so that the new field's energy is
    the old field's over the overlap plus the coarser field's over the rest of the new box."""
    h = interpolate(coarse, h_coarse, new.xs, new.ys, new.zs)
    box_new = extent(new)
    target = region_energy(coarse, h_coarse, box_new)
    interpolated = np.ones(h.shape, dtype=bool)
    if old is not None:
        box_old = extent(old)
        lap = tuple((max(a[0], b[0]), min(a[1], b[1])) for a, b in zip(box_new, box_old))
        if all(hi > lo for lo, hi in lap):
            tol = 1e-9
            in_x = (new.xs >= lap[0][0] - tol) & (new.xs <= lap[0][1] + tol)
            in_y = (new.ys >= lap[1][0] - tol) & (new.ys <= lap[1][1] + tol)
            in_z = (new.zs >= lap[2][0] - tol) & (new.zs <= lap[2][1] + tol)
            ix, iy, iz = np.flatnonzero(in_x), np.flatnonzero(in_y), np.flatnonzero(in_z)
            block = (slice(iy[0], iy[-1] + 1), slice(iz[0], iz[-1] + 1), slice(ix[0], ix[-1] + 1))
            h[block] = interpolate(old, h_old, new.xs[block[2]], new.ys[block[0]], new.zs[block[1]])
            (ky, jy), (kz, jz), (kx, jx) = (_on(o, c[b]) for o, c, b in ((old.ys, new.ys, block[0]),
                                                                      (old.zs, new.zs, block[1]),
                                                                      (old.xs, new.xs, block[2])))
            sub = h[block]
            sub[np.ix_(ky, kz, kx)] = h_old[np.ix_(jy, jz, jx)]     # shared nodes: their values exactly
            shared = np.zeros(sub.shape, dtype=bool)
            shared[np.ix_(ky, kz, kx)] = True
            interpolated[block] = ~shared
            target += region_energy(old, h_old, lap) - region_energy(coarse, h_coarse, lap)
    shift_to(h, lumped_volumes(new), interpolated, target)
    return h


def _on(old: np.ndarray, new: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The indices into ``new`` of its coordinates that are nodes of ``old`` (to 1e-6 of the
    spacing), and those nodes' indices into ``old``."""
    i = np.clip(np.searchsorted(old, new), 1, len(old) - 1)
    i = np.where(np.abs(old[i - 1] - new) < np.abs(old[i] - new), i - 1, i)
    hit = np.flatnonzero(np.abs(old[i] - new) <= 1e-6 * float(np.min(np.diff(old))))
    return hit, i[hit]


def level_axis(lo: float, hi: float, centre: float, side: float | None, h: float) -> np.ndarray:
    """Uniform node coordinates [m] of spacing ``<= h`` over ``[lo, hi]`` (``side`` None) or over the
    box of ``side`` around ``centre`` clipped to ``[lo, hi]``, its ends on the lattice ``lo + i h``."""
    if side is not None:
        a = max(lo, lo + math.floor((centre - 0.5 * side - lo) / h) * h)
        b = min(hi, lo + math.ceil((centre + 0.5 * side - lo) / h) * h)
        lo, hi = a, b
    n = max(1, math.ceil((hi - lo) / h - 1e-9))
    return np.linspace(lo, hi, n + 1)


def level_depth_axis(settings: Settings, h: float, depth_m: float, top: float) -> np.ndarray:
    """Node heights [m] of a coarser level: from ``-depth_m`` to the powder surface ``top``, the two
    top elements ``h`` thick but at most ``mid_h_m`` (holding the powder layers), graded downwards
    (``growth``, ``h_max_m``).

    The part level's top elements are as thin as the intermediate level's: the heat of the tracks
    lies within about 100 µm of the surface, and a ``coarse_h_m`` element spread it that deep, so
    that prolonged back to the intermediate level it left the surface cooler."""
    s = settings
    top_h = min(h, s.mid_h_m)
    return graded_axis(-depth_m, top, max(-depth_m, top - 2 * top_h), top, top_h, s.growth, max(s.h_max_m, h))


FACE_SLICES = {"x0": (slice(None), slice(None), slice(0, 1)), "x1": (slice(None), slice(None), slice(-1, None)),
               "y0": (slice(0, 1), slice(None), slice(None)), "y1": (slice(-1, None), slice(None), slice(None)),
               "z0": (slice(None), slice(0, 1), slice(None))}
"""Solver-order slices (y, z, x) of a box's faces that can be held."""


def held_faces(grid: Grid, coarse: Grid) -> tuple[str, ...]:
    """The faces of ``grid`` strictly inside ``coarse`` (held to its field); the others lie on the
    domain's boundary and keep its boundary condition."""
    (x0, x1), (y0, y1), (z0, z1) = extent(grid)
    (cx0, cx1), (cy0, cy1), (cz0, _) = extent(coarse)
    tol = 1e-9
    candidates = {"x0": x0 > cx0 + tol, "x1": x1 < cx1 - tol, "y0": y0 > cy0 + tol, "y1": y1 < cy1 - tol,
                  "z0": z0 > cz0 + tol}
    return tuple(face for face, held in candidates.items() if held)


class HeldFaces:
    """The side and bottom faces of a box that take a coarser level's field (Dirichlet), the values
    interpolated when the coarser level changes (:meth:`hold`) and set after every sub-step
    (:meth:`apply`)."""

    def __init__(self, grid: Grid, coarse: Grid):
        self.grid, self.faces = grid, held_faces(grid, coarse)
        self._values: dict[str, np.ndarray] = {}
        self._coarse: Grid | None = None
        self._interpolations: dict[str, Interpolation] = {}

    def hold(self, coarse: Grid, h_coarse: np.ndarray) -> None:
        """Interpolate the held faces' values from the coarser field ``h_coarse`` on ``coarse``."""
        if coarse is not self._coarse:
            g = self.grid
            points = {"x0": (g.xs[:1], g.ys, g.zs), "x1": (g.xs[-1:], g.ys, g.zs), "y0": (g.xs, g.ys[:1], g.zs),
                      "y1": (g.xs, g.ys[-1:], g.zs), "z0": (g.xs, g.ys, g.zs[:1])}
            self._interpolations = {f: Interpolation(coarse, *points[f]) for f in self.faces}
            self._coarse = coarse
        self._values = {f: i.of(h_coarse) for f, i in self._interpolations.items()}

    def apply(self, h: np.ndarray, m: np.ndarray) -> float:
        """Set the held faces of ``h`` in place (``m`` the lumped volumes [m³]); returns the energy [J]
        that left the box through them (what resetting them removed)."""
        out = 0.0
        for face, values in self._values.items():
            sl = FACE_SLICES[face]
            out += float(np.sum(m[sl] * (h[sl] - values)))
            h[sl] = values
        return out


class ConductionLevel:
    """A coarser level (module docstring): conduction, top and plate losses and a given surface heat input.

    Parameters
    ----------
    settings : Settings
    law : Constitutive
    grid : Grid
        The level's grid.
    h : ndarray, shape grid.solver_shape
        Initial nodal enthalpy [J/m³].
    weights : tuple of ndarray, each shape (ny - 1, nz - 1, nx - 1)
        Per-element conductivity weights [-], in plane and vertical (:func:`column_weights`).
    coarse : Grid, optional
        The next coarser level's grid, whose field this level's faces inside it take (none: the part
        level, whose operator integrates at the corners, ``TensorOperator(nodal=True)``: its flat top
        elements under a track's heat would otherwise undershoot their neighbours by 100 K).

    Attributes
    ----------
    lost_j, outflow_j : float
        Energy [J] lost through the top face and to the plate, and left through the held faces, so far.
    """

    def __init__(self, settings: Settings, law: Constitutive, grid: Grid, h: np.ndarray,
                 weights: tuple[np.ndarray, np.ndarray], coarse: Grid | None = None):
        self.settings, self.law, self.grid = settings, law, grid
        self.h = np.ascontiguousarray(h, dtype=float)
        kw, kw_z = weights
        self.operator = TensorOperator(grid, kw.ravel(), None, kw_z=kw_z.ravel(), nodal=coarse is None)
        self.m = np.reshape(self.operator.lumped_mass, grid.solver_shape)
        self.a_top = grid.top_areas()         # the bottom face's too: a level spans the domain's depth
        self.dt_stable = STABILITY_SAFETY * 2.0 / (law.max_diffusivity * self.operator.stability_eigenvalue())
        self.faces = HeldFaces(grid, coarse) if coarse is not None else None
        self.lost_j = 0.0
        self.outflow_j = 0.0

    def energy(self) -> float:
        """Lumped energy [J] of the level."""
        return float(np.einsum("ijk,ijk->", self.m, self.h))

    def set_weights(self, weights: tuple[np.ndarray, np.ndarray]) -> None:
        """Element conductivity weights [-], in plane and vertical, each shape (ny - 1, nz - 1, nx - 1);
        only changed ones are touched."""
        kw, kw_z = (w.ravel() for w in weights)
        changed = np.flatnonzero((kw != self.operator.kw.ravel()) | (kw_z != self.operator.kw_z.ravel()))
        if len(changed):
            self.operator.reweight(changed, kw[changed], 1.0, kw_z[changed])

    def take(self, restriction: Restriction, h_fine: np.ndarray) -> None:
        """Take the finer field ``h_fine`` now (``restriction`` from its grid to this level's) with
        the level's energy unchanged, the difference spread over the free nodes around the
        overwritten ones: after a finer grid changes, when no time has passed."""
        if restriction.held is None:
            return
        before = self.energy()
        restriction.apply(h_fine, self.h)
        shift_to(self.h, self.m, ring_around(restriction.held, self.h.shape), before)

    def advance(self, duration_s: float, held: tuple[slice, slice, slice] | None = None,
                inflow_j: float = 0.0) -> None:
        """Step ``duration_s`` [s] explicitly; ``held`` (slices along y, z, x) are the nodes a finer
        level overwrites (:func:`slaved`), which lose no heat through the top or to the plate (the
        finer level counts its own losses).  What conduction carried out of them is then replaced by
        ``inflow_j`` [J], the heat the finer level sent out through its held faces meanwhile,
        spread over the free nodes around them (:func:`shift_to`): the coupling conserves energy."""
        from fe_node.solver import StepWork, explicit_update

        n = max(1, math.ceil(duration_s / self.dt_stable))
        dt = duration_s / n
        c = (dt * self.law.k_ref) / self.m
        c_top = dt / self.m[:, -1, :]
        work = StepWork(self.h.shape)
        top_free, bottom_free = np.ones(self.a_top.shape), np.ones(self.a_top.shape)
        if held is not None and held[1].stop == self.h.shape[1]:
            top_free[held[0], held[2]] = 0.0
        if held is not None and held[1].start == 0:
            bottom_free[held[0], held[2]] = 0.0
        plate = self.settings.plate_h_w_m2k * self.a_top * bottom_free
        c_bottom = dt / self.m[:, 0, :]
        before = 0.0 if held is None else float(np.sum(self.m[held] * self.h[held]))
        for _ in range(n):
            if self.settings.plate_h_w_m2k > 0:
                q_plate = plate * (self.law.temperature(self.h[:, 0, :]) - self.settings.t0_k)
                self.h[:, 0, :] -= q_plate * c_bottom
                self.lost_j += float(q_plate.sum()) * dt
            q_loss = self.a_top * top_free * loss_flux(self.law.temperature(self.h[:, -1, :]), self.settings)
            explicit_update(self.h, self.operator, self.law, c, -q_loss, c_top, (1.0, 1.0), work)
            self.lost_j += float(q_loss.sum()) * dt
            if self.faces is not None:
                self.outflow_j += self.faces.apply(self.h, self.m)
        if held is None:
            return
        conducted = before - float(np.sum(self.m[held] * self.h[held]))
        shift_to(self.h, self.m, ring_around(held, self.h.shape), self.energy() + inflow_j - conducted)


    def dwell(self, duration_s: float) -> None:
        """Cool the whole level for ``duration_s`` [s] with no heat input and no finer level: its own
        stable steps, then implicit ones (:func:`fe_node.dwell.cool`); losses counted."""
        s = self.settings
        for lost in cool(self.h, duration_s, self.dt_stable, lambda: self.advance(self.dt_stable),
                         lambda dt: implicit_cooling_step(self.h, self.operator, self.law, self.m, self.a_top,
                                                          self.a_top, s, dt),
                         s.dwell_step_s, self.law.temperature, s.t_amb_k):
            self.lost_j += lost


def ring_around(held: tuple[slice, slice, slice], shape: tuple[int, int, int]) -> np.ndarray:
    """The nodes next to the box of nodes ``held`` (slices along y, z, x) but not in it, a mask of ``shape``."""
    ring = np.zeros(shape, dtype=bool)
    ring[tuple(slice(max(sl.start - 1, 0), sl.stop + 1) for sl in held)] = True
    ring[held] = False
    return ring


def column_weights(zs: np.ndarray, plan_shape: tuple[int, int], row_m: float, kw_powder: float,
                   share: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
    """Per-element conductivity weights [-] in plane and vertical, each shape (ny - 1, nz - 1, nx - 1)
    (``plan_shape`` the element counts (ny - 1, nx - 1)), of a grid with node heights ``zs`` [m]
    over the powder's element rows: dense metal below z = 0; row ``r`` of thickness ``row_m`` [m]
    (from ``r row_m`` up) conducts as powder (``kw_powder``) plus its consolidated
    ``share[:, r, :]`` (shape (ny - 1, n_rows, nx - 1), from
    :class:`fe_node.window.ConsolidationLattice`; ``None``: no powder, all dense) of dense metal,
    the two side by side (their mean weighted by the share).

    An element spanning several rows (a coarser level's, a buried layer's) conducts in plane as its
    rows side by side (their thickness-weighted mean) and vertically as its rows in series (their
    thickness-weighted harmonic mean): an insulating powder row over dense metal keeps its
    surface's heat on a coarse element as on the rows it stands for.  An element within one row
    has the row's weight in both."""
    dz = np.diff(zs)
    if share is None:
        dense = np.ones((plan_shape[0], len(dz), plan_shape[1]))
        return dense, dense
    edges = np.arange(share.shape[1] + 1) * row_m
    overlap = np.clip(np.minimum(zs[1:, None], edges[None, 1:]) - np.maximum(zs[:-1, None], edges[None, :-1]), 0.0,
                      None) / dz[:, None]
    dense = np.clip(np.minimum(zs[1:], 0.0) - zs[:-1], 0.0, None) / dz
    row_kw = kw_powder + share * (1.0 - kw_powder)
    in_plane = dense[None, :, None] + np.einsum("kr,jri->jki", overlap, row_kw)
    one_row = (np.count_nonzero(overlap, axis=1) + (dense > 0)) == 1
    series = 1.0 / (dense[None, :, None] + np.einsum("kr,jri->jki", overlap, 1.0 / row_kw))
    return in_plane, np.where(one_row[None, :, None], in_plane, series)
