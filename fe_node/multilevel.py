"""The multi-level plant (``Settings.mesh = "multilevel"``): a fine box that moves with the laser.

Three nested grids, after the moving-level scheme of GO-MELT (Leonor et al., Addit. Manuf. 2024):

* the fine level, :class:`MultiLevelModel` itself: the full physics of
  :class:`~fe_node.solver.ThermalModel` (powder, keyhole, evaporation, liquid conductivity,
  observation) on a box of side ``fine_box_m`` around the laser and ``fine_box_depth_m`` deep,
  ``h_fine_m`` inside the whole-plan band and graded outside it;
* the intermediate level: conduction and top losses on a box of ``mid_box_m`` at ``mid_h_m``
  (:class:`~fe_node.levels.ConductionLevel`);
* the part level: the same over the whole domain at ``coarse_h_m``.

Each level steps at its own stable time step (the intermediate level every ``mid_every`` fine
steps, the part level every ``part_every``; :meth:`MultiLevelModel.sync` brings them up to now);
a box's side and bottom faces take its coarser level's field (held between that level's steps),
and after a coarser level's step its nodes inside the finer box take the finer field
(:class:`~fe_node.levels.Restriction`) and the heat the finer level sent out of them meanwhile
(energy exact without losses, ``tests/test_fe_multilevel.py``).  The cost of a step depends
on the fine box, not on the part.  The fine box moves when less than ``MIN_FRONT`` of its side
lies ahead of the laser or ``MIN_SIDE`` to a side (the new box has ``FRONT_ROOM`` ahead); the
intermediate box moves when the fine one nears its edge.  A box whose side holds the whole-plan band
(every layer's tracks plus ``fine_pad_m``, a small part or wall) is centred on it and never moves: the
earlier layers' heat stays on the fine level.  Moves carry the state over with the
energy-conserving :func:`~fe_node.levels.prolong`, and the powder's consolidation through the
:class:`~fe_node.window.ConsolidationLattice`.

The observation's energy balance is the fine level's, the heat that left it through its held
faces counted with the losses (``boundary_outflow_j``) and the energy a move brings in with the
initial energy.
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.grid_size import MAX_GRID_NODES, plan_bands
from fe_node.levels import (
    ConductionLevel,
    HeldFaces,
    Restriction,
    column_weights,
    extent,
    inside_grid,
    interpolate,
    level_axis,
    level_depth_axis,
    lumped_volumes,
    prolong,
    shift_to,
    slaved,
)
from fe_node.mesh import Grid, graded_axis
from fe_node.observe import Observation, interp_matrix, interpolate_points
from fe_node.operators import TensorOperator
from fe_node.powder import RHO_W, PowderBed
from fe_node.scan import ScanPlan
from fe_node.settings import Settings
from fe_node.solver import ThermalModel, check_command, depth_axis

FRONT_ROOM = 0.4
"""Share of ``fine_box_m`` ahead of the laser after the fine box moves (the rest holds the pool's tail)."""
MIN_FRONT = 0.15
"""The fine box moves when less than this share of its side lies ahead of the laser."""
MIN_SIDE = 0.15
"""... or less than this share of its side to either side of the laser along x or y."""
MID_MARGIN = 2
"""The intermediate box moves when the fine box comes within this many ``mid_h_m`` of its edge."""
MID_MAX_STEPS = 4
"""Most fine steps between two steps of the intermediate level (the fine box's held faces lag by at
most this; its effect on the area trace in docs/fe-scale.md)."""
PART_STEPS = 64
"""Fine steps between two steps of the part level (rounded to a multiple of the intermediate
level's), each in as many sub-steps as its stability limit needs: its restriction from the
intermediate level and its conductivity weights are updated that rarely."""


def graded_length(length: float, h: float, growth: float = 1.35, h_max: float = 0.5e-3) -> float:
    """The longest run [m] of whole elements growing from ``h`` by ``growth`` (capped at ``h_max``)
    that fits in ``length``: a box edge there needs no element smaller than ``h`` (which would
    shorten the stable time step)."""
    total, size = 0.0, h
    while True:
        size = min(size * growth, h_max)
        if total + size > length * (1 + 1e-9):
            return total
        total += size


class MultiLevelModel(ThermalModel):
    """The plant on three nested grids (module docstring); the API of :class:`ThermalModel`.

    Parameters
    ----------
    settings : Settings
        With ``mesh = "multilevel"``.
    plan : ScanPlan
    layer_plans : tuple of ScanPlan, optional

    Attributes
    ----------
    grid : Grid
        The fine level's grid (moves with the laser).
    fixed_centre : ndarray or None
        The fine box's fixed centre (x, y) [m] where it holds the whole-plan band, else None.
    mid, part : ConductionLevel
        The intermediate and part levels.
    boundary_outflow_j : float
        Heat [J] that left the fine box through its held faces.
    """

    def __init__(self, settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None):
        if settings.mesh != "multilevel":
            raise ValueError("MultiLevelModel needs settings.mesh = 'multilevel'")
        s = self.settings = settings
        bands = plan_bands(s, plan, layer_plans)
        self._domain = tuple(domain for domain, _ in bands)
        self._bands = tuple(band for _, band in bands)
        self.layer = 0
        self._zs_box, self._z_bed = self._box_heights()
        self.fixed_centre = self._plan_centre()
        self._box_centre = self._centre(*plan.locate(0.0)[1:])
        self.boundary_outflow_j = 0.0
        super().__init__(settings, plan, layer_plans)
        self._kw_powder = None if self.powder is None else self.powder.kw_powder
        (x0, x1), (y0, y1) = self._domain
        part = Grid(level_axis(x0, x1, 0.0, None, s.coarse_h_m), level_axis(y0, y1, 0.0, None, s.coarse_h_m),
                    level_depth_axis(s, s.coarse_h_m, s.depth_m, self._top))
        self.part = ConductionLevel(s, self.law, part, np.full(part.solver_shape, self._h_ref), self._level_kw(part))
        self.mid = self._mid_level(self._box_centre, None)
        self._check_nodes()
        self._faces = HeldFaces(self.grid, self.mid.grid)
        self._faces.hold(self.mid.grid, self.mid.h)
        self._set_level_steps()
        self._sent = {"mid": 0.0, "part": 0.0}
        self._synced = {"mid": 0, "part": 0}
        self._outside = {"mid": 0.0, "part": 0.0}
        self._restrictions: dict[str, Restriction] = {}
        self._weights_due = {"mid": False, "part": False}
        self._mark_outside("mid")
        self._mark_outside("part")

    def _set_level_steps(self) -> None:
        """Fine steps between two steps of the intermediate level (its stability limit, at most
        ``MID_MAX_STEPS``) and of the part level (``PART_STEPS``, rounded to a multiple)."""
        dt = self.settings.dt_s
        self.mid_every = max(1, min(MID_MAX_STEPS, math.floor(self.mid.dt_stable / dt)))
        self.part_every = self.mid_every * max(1, PART_STEPS // self.mid_every)

    @property
    def _top(self) -> float:
        """Height [m] of the powder's surface: the top of the current layer (0 on a bare plate)."""
        return (self.layer + 1) * self.settings.powder_layer_m

    @property
    def _row_m(self) -> float:
        """Thickness [m] of a powder element row (a layer holds ``powder_layer_m / h_fine_m`` of them, rounded up)."""
        s = self.settings
        return s.powder_layer_m / max(1, math.ceil(s.powder_layer_m / s.h_fine_m - 1e-9))

    def _box_heights(self) -> tuple[np.ndarray, float]:
        """Node heights [m] of the fine box, and the height from which its element rows are single powder
        rows (0 until the build is ``fine_depth_m`` high).

        The uniform grid's heights after this many layers (:func:`~fe_node.solver.depth_axis` and a row
        of elements per layer) within ``fine_depth_m`` of the top; below, down to ``fine_box_depth_m``,
        a subset of them whose spacing grows by ``growth`` (up to ``h_max_m``): buried layers coarsen.
        """
        s = self.settings
        zs = depth_axis(s)
        if self.layer > 0:
            zs = np.concatenate([zs, s.powder_layer_m + self._row_m * np.arange(1, round(
                self.layer * s.powder_layer_m / self._row_m) + 1)])
        top, tol = float(zs[-1]), 1e-9 * s.h_fine_m
        fine = zs[zs >= top - s.fine_depth_m - tol]
        below, floor = zs[zs < fine[0] - tol], top - s.fine_box_depth_m
        kept, z, size = [], float(fine[0]), float(fine[1] - fine[0])
        while len(below) and z > floor + tol:
            size = min(size * s.growth, s.h_max_m)
            deeper = below[below <= z - size + tol]
            z = float(deeper[-1] if len(deeper) else below[0])
            kept.append(z)
            below = below[below < z - tol]
        return np.concatenate([kept[::-1], fine]), max(0.0, float(fine[0]))

    def _plan_centre(self) -> np.ndarray | None:
        """The centre [m] (x, y) of the whole-plan band if the fine box's side holds the band along x and y
        (every layer's tracks plus ``fine_pad_m``), else None."""
        if all(hi - lo <= self.settings.fine_box_m for lo, hi in self._bands):
            return np.array([0.5 * (lo + hi) for lo, hi in self._bands])
        return None

    def _centre(self, xy: np.ndarray, direction: np.ndarray) -> np.ndarray:
        """The fine box's centre [m] for the laser at ``xy`` moving along ``direction``: ``FRONT_ROOM`` ahead,
        or the centre of the whole-plan band where the box holds it (:attr:`fixed_centre`)."""
        if self.fixed_centre is not None:
            return self.fixed_centre
        return np.asarray(xy, float) + (FRONT_ROOM - 0.5) * self.settings.fine_box_m * np.asarray(direction, float)

    def _initial_grid(self) -> Grid:
        return self._box_grid(self._box_centre)

    def _box_grid(self, centre: np.ndarray) -> Grid:
        """The fine box around ``centre`` [m]: inside the whole-plan band, as many elements of the band's
        lattice (spacing ``h`` about ``h_fine_m``) wherever it lies, the fewest that cover
        ``fine_box_m`` around ``centre`` (so that a move along the band is a translate,
        :meth:`TensorOperator.moved`); graded outside the band; clipped to the domain."""
        s = self.settings
        axes = []
        for c, (dlo, dhi), (blo, bhi) in zip(centre, self._domain, self._bands):
            hf = (bhi - blo) / max(1, math.ceil((bhi - blo) / s.h_fine_m - 1e-9))
            n = math.ceil(s.fine_box_m / hf - 1e-9) + 1
            first = blo + math.floor((c - 0.5 * s.fine_box_m - blo) / hf + 1e-9) * hf
            lo, hi = max(dlo, first), min(dhi, first + n * hf)
            grade = dict(h=hf, growth=s.growth, h_max=s.h_max_m)
            lo = lo if lo > blo else blo - graded_length(blo - lo, **grade)
            hi = hi if hi < bhi else bhi + graded_length(hi - bhi, **grade)
            lo, hi = max(lo, dlo), min(hi, dhi)
            axes.append(graded_axis(lo, hi, max(lo, blo), min(hi, bhi), hf * (1 + 1e-9), s.growth, s.h_max_m))
        return Grid(axes[0], axes[1], self._zs_box)

    def _level_kw(self, grid: Grid) -> tuple[np.ndarray, np.ndarray]:
        """Conductivity weights of a grid's elements (any level's), in plane and vertical, from the
        consolidation so far (:func:`~fe_node.levels.column_weights`)."""
        share = None if self.powder is None else self._lattice.fraction(grid.xs, grid.ys)
        kw_powder = 1.0 if self.powder is None else self.powder.kw_powder
        return column_weights(grid.zs, (len(grid.ys) - 1, len(grid.xs) - 1), self._row_m, kw_powder, share)

    def _mid_level(self, centre: np.ndarray, old: ConductionLevel | None) -> ConductionLevel:
        """The intermediate level around ``centre`` [m], its field carried over from ``old`` (``None``:
        from the part level alone)."""
        s = self.settings
        (x0, x1), (y0, y1) = self._domain
        grid = Grid(level_axis(x0, x1, centre[0], s.mid_box_m, s.mid_h_m),
                    level_axis(y0, y1, centre[1], s.mid_box_m, s.mid_h_m),
                    level_depth_axis(s, s.mid_h_m, s.depth_m, self._top))
        h = prolong(self.part.grid, self.part.h, None if old is None else old.grid, None if old is None else old.h,
                    grid)
        mid = ConductionLevel(s, self.law, grid, h, self._level_kw(grid), coarse=self.part.grid)
        mid.faces.hold(self.part.grid, self.part.h)
        if old is not None:
            mid.lost_j, mid.outflow_j = old.lost_j, old.outflow_j
        return mid

    def _check_nodes(self) -> None:
        """RuntimeError if the three grids hold more than :data:`~fe_node.grid_size.MAX_GRID_NODES` nodes
        (checked at every change of the mesh)."""
        if self.n_nodes > MAX_GRID_NODES:
            raise RuntimeError(f"multi-level mesh: {self.n_nodes:,} nodes, more than {MAX_GRID_NODES:,}")

    @property
    def node_updates_per_step(self) -> float:
        """Explicit node updates per step [-], the three levels' nodes times their sub-steps per step:
        the cost model of a step."""
        def per_step(level: ConductionLevel, every: int) -> float:
            return level.grid.n_nodes * math.ceil(every * self.settings.dt_s / level.dt_stable) / every
        return (self.grid.n_nodes * self.n_substeps + per_step(self.mid, self.mid_every)
                + per_step(self.part, self.part_every))

    @property
    def n_nodes(self) -> int:
        """Nodes of the three levels."""
        return self.grid.n_nodes + self.mid.grid.n_nodes + self.part.grid.n_nodes

    def _box_holds(self, centre: np.ndarray, xy: np.ndarray) -> int:
        """How many of the positions ``xy`` (shape (n, 2), [m]) the fine box around ``centre`` holds."""
        return int(np.count_nonzero(inside_grid(self._box_grid(centre), xy)))

    def _holds(self, xy: np.ndarray) -> np.ndarray:
        """True for the laser positions ``xy`` (shape (n, 2), [m]) inside the fine box; a step that
        jumps farther than the box holds deposits only the part of its power on the side of the jump
        the box holds, the side most of the step is on (the rest counted in ``laser_outside_j``)."""
        return inside_grid(self.grid, xy)

    def keyhole_depth_m(self) -> float:
        """:meth:`ThermalModel.keyhole_depth_m`; 0 while the laser is outside the fine box (the
        first sub-steps of a step that jumps farther than the box holds)."""
        _, xy, _ = self.plan.locate(np.array([self._s]))
        return super().keyhole_depth_m() if self._holds(xy)[0] else 0.0

    def _needs_move(self, grid: Grid, xy: np.ndarray, direction: np.ndarray) -> bool:
        """True if less than ``MIN_FRONT`` of the box lies ahead of ``xy`` or ``MIN_SIDE`` to a side
        (where the domain goes on)."""
        b = self.settings.fine_box_m
        probes = [xy + MIN_FRONT * b * direction] + [xy + MIN_SIDE * b * e for e in
                                                      (np.array([1.0, 0]), np.array([-1.0, 0]),
                                                       np.array([0, 1.0]), np.array([0, -1.0]))]
        box = extent(grid)[:2]
        tol = 1e-9
        for p in probes:
            for k, ((lo, hi), (dlo, dhi)) in enumerate(zip(box, self._domain)):
                if (p[k] < lo - tol and lo > dlo + tol) or (p[k] > hi + tol and hi < dhi - tol):
                    return True
        return False

    def step(self, power_w: float, speed_m_s: float) -> Observation:
        """Advance one step ``dt_s`` (:meth:`ThermalModel.step`): the coarser levels stepped first if due
        (:meth:`prepare`), then the fine box moved if it must."""
        check_command(power_w, speed_m_s)
        if self.done:
            raise RuntimeError("scan plan finished: no more steps")
        self.prepare()
        if self.layer_done:
            self.add_layer()
        total = self.plan.total_length
        _, points, directions = self.plan.locate(np.array([self._s, min(self._s + speed_m_s * self.settings.dt_s,
                                                                      total)]))
        travel = speed_m_s * self.settings.dt_s
        jumps = float(np.hypot(*(points[1] - points[0]))) > 1.5 * travel        # the step crosses to a far track
        if self.fixed_centre is None and (self._needs_move(self.grid, points[0], directions[0]) or (
                jumps and self._needs_move(self.grid, points[1], directions[1]))):
            centre = self._centre(points[0], directions[0])
            if self._needs_move(self._box_grid(centre), points[1], directions[1]):
                _, path, _ = self.plan.locate(self._s + (np.arange(8) + 0.5) / 8 * travel)
                there = self._centre(points[1], directions[1])
                if self._box_holds(there, path) >= self._box_holds(centre, path):    # most of the step is there
                    centre = there
            self.sync("mid")
            self.move(centre)
        return super().step(power_w, speed_m_s)

    def prepare(self) -> None:
        """Step the coarser levels that are due (``mid_every`` / ``part_every`` fine steps since their
        last step): the part of the next step that does not depend on its command, which a lockstep node
        does while the command is in flight (:meth:`step` does it first if it was not done)."""
        if self.step_index - self._synced["mid"] >= self.mid_every:
            self.sync("mid")
        if self.step_index - self._synced["part"] >= self.part_every:
            self.sync("part")

    def sync(self, name: str) -> None:
        """Step level ``"mid"`` or ``"part"`` (the finer levels first) over the steps since its last
        step, so that it holds the finer level's state now."""
        if name == "part":
            self.sync("mid")
        n = self.step_index - self._synced[name]
        if n <= 0:
            return
        if name == "mid":
            self._step_level(self.mid, self.grid, self._h, "mid", self.boundary_outflow_j, n)
            self._faces.hold(self.mid.grid, self.mid.h)
        else:
            self._step_level(self.part, self.mid.grid, self.mid.h, "part", self.mid.outflow_j, n)
            self.mid.faces.hold(self.part.grid, self.part.h)
            self._mark_outside("mid")
        self._synced[name] = self.step_index

    def _mark_outside(self, name: str) -> None:
        """Note the finer level's energy outside the nodes level ``name`` takes from it (after a step
        of that level or a change of either grid)."""
        h = self._h if name == "mid" else self.mid.h
        self._outside[name] = self._restriction(name).outside(h)

    def _restriction(self, name: str) -> Restriction:
        """The transfer from the finer level to level ``"mid"`` or ``"part"`` (built again when either grid changed)."""
        finer, level = (self.grid, self.mid) if name == "mid" else (self.mid.grid, self.part)
        r = self._restrictions.get(name)
        if r is None or r.fine is not finer or r.coarse is not level.grid:
            r = self._restrictions[name] = Restriction(finer, level.grid)
        return r

    def _step_level(self, level: ConductionLevel, finer: Grid, h_finer: np.ndarray, name: str, sent_j: float,
                    n_steps: int) -> None:
        """Advance a coarser level ``n_steps`` fine steps, taking the heat its finer level sent out
        through its held faces since (``sent_j`` [J], cumulative), then the finer field (:class:`Restriction`).

        Its conductivity weights are brought up to the consolidation after the finer box moved: the
        powder consolidates only inside the fine box, where the finer field overwrites this level's."""
        if self.powder is not None and self._weights_due[name]:
            level.set_weights(self._level_kw(level.grid))
            self._weights_due[name] = False
        restriction = self._restriction(name)
        outside = restriction.outside(h_finer)
        level.advance(n_steps * self.settings.dt_s, slaved(finer, level.grid),
                      sent_j - self._sent[name] + outside - self._outside[name])
        self._sent[name], self._outside[name] = sent_j, outside
        restriction.apply(h_finer, level.h)

    def _substep(self, load) -> None:
        super()._substep(load)
        out = self._faces.apply(self._h, self._m)
        self._lost += out
        self.boundary_outflow_j += out

    def move(self, centre: np.ndarray) -> None:
        """Put the fine box at ``centre`` [m] (x, y), the intermediate box with it if it must, and
        carry the state over (:func:`~fe_node.levels.prolong`)."""
        s = self.settings
        new = self._box_grid(centre)
        (x0, x1), (y0, y1), _ = extent(new)
        (mx0, mx1), (my0, my1), _ = extent(self.mid.grid)
        (dx0, dx1), (dy0, dy1) = self._domain
        margin = MID_MARGIN * s.mid_h_m
        if ((x0 - margin < mx0 and mx0 > dx0) or (x1 + margin > mx1 and mx1 < dx1)
                or (y0 - margin < my0 and my0 > dy0) or (y1 + margin > my1 and my1 < dy1)):
            self.sync("part")
            self.mid = self._mid_level(0.5 * np.array([x0 + x1, y0 + y1]), self.mid)
            self._check_nodes()
            self.mid.take(self._restriction("mid"), self._h)
            self.part.take(self._restriction("part"), self.mid.h)
            self._mark_outside("part")
            self._weights_due["part"] = True
        self._rebuild_box(new)
        self.n_remeshes += 1

    def _rebuild_box(self, new: Grid) -> None:
        """Carry the fine level over to grid ``new`` (:func:`~fe_node.levels.prolong` from the old box
        and the intermediate level): weights and powder bed from the consolidation lattice, operator
        (the old one moved, :meth:`TensorOperator.moved`, when ``new`` is a translate of the old
        box), held faces; the energy the change brings in is added to the initial energy."""
        e_before = self._energy()
        self._h = np.ascontiguousarray(prolong(self.mid.grid, self.mid.h, self.grid, self._h, new))
        ny, nz, nx = new.solver_shape
        kw = self._level_kw(new)[0]     # one weight per element, as on the uniform grid
        if self.powder is not None:
            bed = PowderBed(self.settings, new.zs - self._z_bed, (ny - 1, nx - 1))
            self._lattice_row0 = round(self._z_bed / self._row_m)
            share = self._lattice.fraction(new.xs, new.ys)
            rows = bed.consolidated.shape[1]
            bed.consolidated = share[:, self._lattice_row0:self._lattice_row0 + rows, :] >= 1.0 - 1e-9
            self.powder = bed
        self.grid = new
        self._check_nodes()
        rho_w = np.full(kw.size, RHO_W)
        moved = self.operator.moved(new, kw.ravel(), rho_w) if isinstance(self.operator, TensorOperator) else None
        self.operator = moved if moved is not None else self._build_operator(kw.ravel(), rho_w)
        self._a_top, self._a_bottom = self._face_areas()
        self._set_time_step()
        self._faces = HeldFaces(new, self.mid.grid)
        self._faces.hold(self.mid.grid, self.mid.h)
        self._e0 += self._energy() - e_before
        self.mid.take(self._restriction("mid"), self._h)
        self._mark_outside("mid")
        self._weights_due["mid"] = True

    def _face_areas(self) -> tuple[np.ndarray, np.ndarray]:
        """Top- and bottom-face areas [m²] of the fine box; its bottom face has no plate (0) unless it
        is the domain's bottom (the box's bottom face is held to the intermediate level's field)."""
        top = self.grid.top_areas()
        on_plate = self.grid.zs[0] <= -self.settings.depth_m + 1e-9 * self.settings.h_fine_m
        return top, top if on_plate else np.zeros_like(top)

    def _dwell(self, duration_s: float) -> None:
        """Cool between layers for ``duration_s`` [s] on the part level alone, then build the
        intermediate and fine levels anew from it.

        The levels are first brought up to now, each coarser one holding its finer one's field
        (energy exact), so the part level holds the whole field; it cools in its stable steps, then
        implicit ones (:meth:`~fe_node.levels.ConductionLevel.dwell`; after seconds of recoating the
        field is smooth at its resolution); the finer levels take it by :func:`prolong` (energy
        kept) on their grids.  The fine level's energy change is added to its initial energy, as at
        a move; the losses are the part level's."""
        s = self.settings
        self.sync("part")
        e_before = self._energy()
        self.part.dwell(duration_s)
        old = self.mid
        mid = ConductionLevel(s, self.law, old.grid, prolong(self.part.grid, self.part.h, None, None, old.grid),
                              self._level_kw(old.grid), coarse=self.part.grid)
        mid.faces.hold(self.part.grid, self.part.h)
        mid.lost_j, mid.outflow_j = old.lost_j, old.outflow_j
        self.mid = mid
        self._h = np.ascontiguousarray(prolong(mid.grid, mid.h, None, None, self.grid))
        self._faces.hold(mid.grid, mid.h)
        self._e0 += self._energy() - e_before
        mid.take(self._restriction("mid"), self._h)
        self.part.take(self._restriction("part"), mid.h)
        self._mark_outside("mid")
        self._mark_outside("part")
        self._sent = {"mid": self.boundary_outflow_j, "part": mid.outflow_j}

    def add_layer(self) -> None:
        """After the dwell (``dwell_s``, :meth:`_dwell`), spread a new powder layer (at the preheat
        temperature) on every level and start the next plan (:meth:`ThermalModel.add_layer`); the
        fine box's buried layers coarsen (:meth:`_box_heights`).

        Raises
        ------
        RuntimeError
            Without a powder layer (``powder_layer_m = 0``) or before the plan is done.
        """
        s = self.settings
        if self.powder is None or not self.layer_done:
            raise RuntimeError("add_layer needs powder_layer_m > 0 and a finished scan plan")
        self.sync("part")
        if s.dwell_s > 0:
            self._dwell(s.dwell_s)
        old_top = self._top
        n = round(s.powder_layer_m / self._row_m)
        self._lattice.grow(n)
        self._spread(n)
        self.layer += 1
        self.part = self._grown(self.part, level_depth_axis(s, s.coarse_h_m, s.depth_m, self._top), old_top, None)
        self.mid = self._grown(self.mid, level_depth_axis(s, s.mid_h_m, s.depth_m, self._top), old_top, self.part)
        self._set_level_steps()
        self._zs_box, self._z_bed = self._box_heights()
        self.part.take(self._restriction("part"), self.mid.h)
        self._rebuild_box(Grid(self.grid.xs, self.grid.ys, self._zs_box))
        self._mark_outside("part")
        self._s = 0.0
        if self._layer_plans is not None:
            self.plan = self._layer_plans[self.layer]

    def _spread(self, n: int) -> None:
        """Put ``n`` rows of powder elements at the preheat state on the fine box, as
        :meth:`ThermalModel.add_layer` does (the old top nodes mix their energy with the half of
        the new bottom elements their lumped volumes now hold); the energy brought in is added
        to the initial energy."""
        old = self.grid
        zs = np.concatenate([old.zs, old.zs[-1] + self._row_m * np.arange(1, n + 1)])
        grid = Grid(old.xs, old.ys, zs)
        h = np.full(grid.solver_shape, self._h_ref)
        nz = len(old.zs)
        h[:, :nz, :] = self._h
        m_old, m_new = lumped_volumes(old)[:, -1, :], lumped_volumes(grid)[:, nz - 1, :]
        h[:, nz - 1, :] = (m_old * self._h[:, -1, :] + (m_new - m_old) * self._h_ref) / m_new
        e_before = self._energy()
        self.grid, self._h = grid, h
        self._m = lumped_volumes(grid)
        self._e0 += self._energy() - e_before

    def _grown(self, level: ConductionLevel, zs: np.ndarray, old_top: float,
               coarse: ConductionLevel | None) -> ConductionLevel:
        """``level`` on heights ``zs`` [m] up to the new top: the old field below ``old_top`` [m]
        (interpolated, shifted to keep its energy), the preheat state above."""
        grid = Grid(level.grid.xs, level.grid.ys, zs)
        h = interpolate(level.grid, level.h, grid.xs, grid.ys, grid.zs)
        new = zs > old_top + 1e-9 * self.settings.h_fine_m
        h[:, new, :] = self._h_ref
        m = lumped_volumes(grid)
        added = float(np.sum(m)) - float(np.sum(level.m))
        shift_to(h, m, np.broadcast_to(~new[None, :, None], h.shape), level.energy() + self._h_ref * added)
        grown = ConductionLevel(self.settings, self.law, grid, h, self._level_kw(grid),
                                None if coarse is None else coarse.grid)
        if coarse is not None:
            grown.faces.hold(coarse.grid, coarse.h)
        grown.lost_j, grown.outflow_j = level.lost_j, level.outflow_j
        return grown

    def temperature_at(self, points: np.ndarray) -> np.ndarray:
        """Temperature [K] at ``points`` (shape (n, 3), x, y, z [m]): from the finest level whose box
        holds each point (the coarser ones as of their last step)."""
        points = np.asarray(points, dtype=float)
        h = interpolate_points(self.part.grid, self.part.h, points)
        for grid, field in ((self.mid.grid, self.mid.h), (self.grid, self._h)):
            held = inside_grid(grid, points)
            h[held] = interpolate_points(grid, field, points[held])
        return self.law.temperature(h)

    def temperature_image(self, half_length_m: float = 0.6e-3, half_width_m: float = 0.3e-3,
                          pixel_m: float = 10e-6):
        """Top-surface temperature raster centred on the laser (:meth:`ThermalModel.temperature_image`):
        the fine level's inside its box, the intermediate level's outside."""
        image, (px0, px1, py0, py1) = super().temperature_image(half_length_m, half_width_m, pixel_m)
        px = np.linspace(px0, px1, image.shape[1])
        py = np.linspace(py0, py1, image.shape[0])
        mid = self.mid
        t_mid = self.law.temperature(mid.h[:, -1, :])
        coarse = interp_matrix(mid.grid.ys, py) @ t_mid @ interp_matrix(mid.grid.xs, px).T
        (x0, x1), (y0, y1), _ = extent(self.grid)
        outside = ~(((py >= y0) & (py <= y1))[:, None] & ((px >= x0) & (px <= x1))[None, :])
        image[outside] = coarse[outside]
        return image, (px0, px1, py0, py1)


def plant_model(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None) -> ThermalModel:
    """The plant of ``settings.mesh``: :class:`ThermalModel` (``"uniform"``) or :class:`MultiLevelModel`."""
    if settings.mesh == "multilevel":
        return MultiLevelModel(settings, plan, layer_plans)
    return ThermalModel(settings, plan, layer_plans)

