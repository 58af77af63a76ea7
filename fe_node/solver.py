"""Transient 3-D heat conduction of the powder-bed plant (paper Sec. II.D, eq. 6).

The physics is the set of scikit-fem forms in :mod:`fe_node.forms`; semi-discrete with
trilinear hexahedra and row-sum lumped mass, in enthalpy form with the Kirchhoff transform
(see :mod:`fe_node.material`):

    m_i dH_i/dt = - k_ref (K_w phi(H))_i + f_i(t) - A_i q_loss(T_i),

``K_w`` the weighted unit-conductivity stiffness and ``m_i`` the lumped nodal volumes of one of
the two operators of :mod:`fe_node.operators` (``Settings.operator``: the tensor-product fast
path by default, or the CSR matrix), ``f`` the laser load (:mod:`fe_node.source`), and
``q_loss`` (:mod:`fe_node.boundary`) on the top face with ``A_i`` the lumped top-face areas;
other faces are insulated.  Time stepping is explicit (forward Euler) with as many equal
sub-steps per step as the stability limit ``dt_sub <= 0.9 * 2 / (alpha_max * lambda)``
requires, ``lambda`` the operator's element bound of ``lambda_max(M_L^-1 K_w)``, recomputed
whenever weights change (one sub-step at 25 µm).  Explicit lumped-mass stepping does not
over-diffuse along the scan like implicit Euler at 50 µs, and conserves energy to round-off:
``sum_i (K_w phi)_i = 0`` exactly.
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.boundary import evaporate_top, loss_flux
from fe_node.dwell import cool, implicit_cooling_step
from fe_node.grid_size import check_grid_size, plan_bands
from fe_node.keyhole import beam_1e2_radius_m, cavity_absorptivity, drill, keyhole_temperature_k, vapour_depth_m
from fe_node.material import Constitutive
from fe_node.mesh import Grid, graded_axis
from fe_node.observe import Observation, bilinear, interp_matrix, interpolate_points, pool_geometry, trailing_edge
from fe_node.operators import CsrOperator, TensorOperator
from fe_node.powder import KW_DENSE, RHO_W, PowderBed
from fe_node.scan import ScanPlan
from fe_node.settings import Settings
from fe_node.source import depth_weights, surface_load
from fe_node.window import ConsolidationLattice, ahead, conserve, element_map, kept, needs_move, transfer, window_axis


def depth_axis(settings: Settings) -> np.ndarray:
    """Node heights [m] of the plant's grid: graded from ``-depth_m`` to the plate's top, fine over
    ``fine_depth_m``, and a powder layer (``powder_layer_m``, elements <= ``h_fine_m``) above it."""
    s = settings
    zs = graded_axis(-s.depth_m, 0.0, -s.fine_depth_m, 0.0, h=s.h_fine_m, growth=s.growth, h_max=s.h_max_m)
    if s.powder_layer_m > 0:
        n = math.ceil(s.powder_layer_m / s.h_fine_m - 1e-9)
        zs = np.concatenate([zs, np.linspace(0.0, s.powder_layer_m, n + 1)[1:]])
    return zs


def build_grid(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None,
               window_centre: np.ndarray | None = None) -> Grid:
    """Graded grid: fine band of size ``h_fine_m`` around the tracks (or, with ``window_m > 0``, a
    window of that side around ``window_centre``, :mod:`fe_node.window`), graded outwards; the
    plate's top at z = 0, a powder layer (``powder_layer_m``, elements <= ``h_fine_m``) above it.
    ValueError if it would be too large (:func:`check_grid_size`)."""
    check_grid_size(settings, plan, layer_plans)
    s = settings
    ax = dict(h=s.h_fine_m, growth=s.growth, h_max=s.h_max_m)
    axes = []
    for k, (domain, band) in enumerate(plan_bands(settings, plan, layer_plans)):
        if s.window_m > 0 and window_centre is not None:
            axes.append(window_axis(*domain, *band, float(window_centre[k]), s.window_m, **ax))
        else:
            axes.append(graded_axis(*domain, *band, **ax))
    return Grid(axes[0], axes[1], depth_axis(settings))


def check_command(power_w: float, speed_m_s: float) -> None:
    """Raise ValueError unless 0 <= power < inf and 0 < speed < inf."""
    if not (math.isfinite(power_w) and power_w >= 0):
        raise ValueError(f"power must be finite and >= 0 W, got {power_w}")
    if not (math.isfinite(speed_m_s) and speed_m_s > 0):
        raise ValueError(f"speed must be finite and > 0 m/s, got {speed_m_s}")


class StepWork:
    """Scratch arrays of one explicit sub-step on a grid of ``shape`` (solver order).

    Re-used every sub-step: fresh multi-megabyte temporaries cost page faults that
    doubled the step time on the shipped layer (``docs/fe.md``, "Step cost").
    """

    def __init__(self, shape: tuple[int, ...]):
        self.phi = np.empty(shape)
        self.kphi = np.empty(shape)
        self.box = np.zeros(6, dtype=np.intp)
        """The node box above the mushy floor (first and past-last y, z, x index)."""

    def box_slices(self) -> tuple[slice, slice, slice]:
        """:attr:`box` as slices along y, z, x."""
        b = self.box
        return slice(int(b[0]), int(b[1])), slice(int(b[2]), int(b[3])), slice(int(b[4]), int(b[5]))


def explicit_update(h: np.ndarray, operator, law: Constitutive, c: np.ndarray, top_w: np.ndarray,
                    c_top: np.ndarray, liquid_factors: tuple[float, float] = (1.0, 1.0),
                    work: StepWork | None = None) -> None:
    """One forward-Euler sub-step of ``m dH/dt = -k_ref K_w phi(H) + top``, in place.

    With liquid conductivity factors ``(f_xy, f_z)`` the conduction term is
    ``K_w phi_xy + K_z (phi_z - phi_xy)``, ``phi_d = phi + (f_d - 1) psi``
    (:meth:`~fe_node.material.Constitutive.mushy_integral`), ``psi`` evaluated and ``K_z`` applied
    only on the box of nodes above ``Constitutive.mushy_floor``
    (:meth:`~fe_node.material.Constitutive.kirchhoff_above`).

    Parameters
    ----------
    h : ndarray, shape (ny, nz, nx)
        Nodal enthalpy [J/m³], updated in place.
    operator : TensorOperator or CsrOperator
        ``K_w`` in solver node order.
    law : Constitutive
        ``H -> phi``.
    c : ndarray, shape (ny, nz, nx)
        ``dt_sub k_ref / m`` [W s/(m⁴ K)]: ``c * (K_w phi)`` is an enthalpy change [J/m³].
    top_w : ndarray, shape (ny, nx)
        Net power into the top nodes (laser load minus losses) [W].
    c_top : ndarray, shape (ny, nx)
        ``dt_sub / m`` of the top nodes [s/m³].
    liquid_factors : (float, float)
        Horizontal and vertical liquid conductivity factors [-].
    work : StepWork, optional
        Scratch arrays of ``h``'s shape (default: allocated for this call).
    """
    from fe_node.kernels import forward_euler

    work = work if work is not None else StepWork(h.shape)
    f_xy, f_z = liquid_factors
    phi = work.phi
    liquid = law.kirchhoff_above(h, law.mushy_floor, phi, work.box) and not f_xy == f_z == 1.0   # psi = 0 outside
    if liquid:
        psi_z = law.add_mushy_integral(h, work.box, f_xy - 1.0, f_z - f_xy, phi)
    kphi = operator(phi, out=work.kphi)
    if liquid and f_z != f_xy:
        operator.add_vertical(psi_z, work.box_slices(), kphi)
    if c.shape != h.shape or c_top.shape != (h.shape[0], h.shape[2]):
        raise ValueError(f"explicit_update: c {c.shape} and c_top {c_top.shape} for h {h.shape}")
    if np.shape(top_w) != c_top.shape:
        top_w = np.broadcast_to(top_w, c_top.shape).copy()
    forward_euler(h, kphi, c, np.ascontiguousarray(top_w, dtype=float), c_top)


class ThermalModel:
    """The FE plant: assemble once, then :meth:`step` one sampling period at a time.

    Parameters
    ----------
    settings : Settings
    plan : ScanPlan
    layer_plans : tuple of ScanPlan, optional
        One plan per layer (``Settings.n_layers`` of them, the first being ``plan``); default:
        ``plan`` in every layer.

    Attributes
    ----------
    grid : Grid
    powder : PowderBed or None
        Powder and consolidated elements (``None`` without a powder layer).
    layer : int
        Current layer (0 first).
    n_substeps : int
        Explicit sub-steps per step.
    step_index : int
        Steps done so far.
    """

    def __init__(self, settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None):
        if settings.mesh != "uniform" and type(self) is ThermalModel:
            raise ValueError("settings: mesh = 'multilevel' is built by fe_node.multilevel.plant_model "
                             "(ThermalModel is the uniform mesh)")
        if layer_plans is not None and (len(layer_plans) != settings.n_layers or layer_plans[0] != plan):
            raise ValueError("thermal model: layer_plans must hold n_layers plans, the first being plan")
        from fe_node.kernels import warm

        warm()          # compiled (or loaded) now, not in the first step
        self.settings, self.plan, self._layer_plans = settings, plan, layer_plans
        self.grid = self._initial_grid()
        self.n_remeshes, self.remesh_energy_j = 0, 0.0
        self._bands = tuple(band for _, band in plan_bands(settings, plan, layer_plans))
        self.law = Constitutive(settings.material)
        ny, nz, nx = self.grid.solver_shape
        self.powder = PowderBed(settings, self.grid.zs, (ny - 1, nx - 1)) if settings.powder_layer_m > 0 else None
        self._lattice = None
        self._lattice_row0 = 0
        """The lattice row of the powder bed's first element row (its buried rows are not its own)."""
        if self.powder is not None and (settings.window_m > 0 or settings.mesh == "multilevel"):
            self._lattice = ConsolidationLattice(*self._bands, settings.h_fine_m, self.powder.consolidated.shape[1])
        self.operator = self._build_operator(*self._initial_weights())
        self._a_top, self._a_bottom = self._face_areas()
        self.layer = 0
        self._h_ref = float(self.law.enthalpy(settings.t0_k))
        self._h = np.full(self.grid.solver_shape, self._h_ref)
        self._work: StepWork | None = None
        self._evaporated: np.ndarray | None = None     # scratch of the evaporation pass: one value per top node
        self._set_time_step()
        self._e0 = self._energy()
        self.t_keyhole_k = (keyhole_temperature_k(settings.beam_radius_m, settings.material.t_boil)
                            if settings.keyhole else math.inf)
        self._h_keyhole = float(self.law.enthalpy(self.t_keyhole_k)) if settings.keyhole else None
        self._h_boil = float(self.law.enthalpy(settings.material.t_boil))
        self.keyhole_radius_m = settings.keyhole_radius_factor * beam_1e2_radius_m(settings.beam_radius_m)
        """Radius [m] of the keyhole's opening (``keyhole_radius_factor`` of the beam's 1/e² radius)."""
        self._s = 0.0
        self.step_index = 0
        self._absorbed = 0.0
        self._lost = 0.0
        self.laser_outside_j = 0.0
        """Laser energy [J] that fell outside the grid and was not deposited (a multi-level fine box
        over a step that jumps farther than the box holds, :mod:`fe_node.multilevel`)."""

    def _initial_grid(self) -> Grid:
        """The grid at the start (:func:`build_grid`, its window ahead of the plan's start)."""
        _, start, direction = self.plan.locate(0.0)
        return build_grid(self.settings, self.plan, self._layer_plans, ahead(start, direction, self.settings.window_m))

    def _initial_weights(self):
        """Per-element (kw, rho_w) [-] in solver element order: dense plate, powder above (``None``: all 1)."""
        if self.powder is None:
            return None, None
        ny, nz, nx = self.grid.solver_shape
        kw, rho_w = self.powder.layer_weights(nz - 1)
        shape = (ny - 1, nz - 1, nx - 1)
        return (np.broadcast_to(kw[None, :, None], shape).ravel(), np.broadcast_to(rho_w[None, :, None], shape).ravel())

    def _build_operator(self, kw, rho_w):
        """The ``Settings.operator`` implementation of the forms on this grid (solver node order),
        with per-element weights in solver element order (``None``: 1)."""
        if self.settings.operator == "csr":
            mesh, perm = self.grid.skfem_mesh()
            self._csr_elements = self.grid.element_order(mesh)
            sk = (None, None) if kw is None else (np.empty_like(kw), np.empty_like(rho_w))
            if kw is not None:
                sk[0][self._csr_elements], sk[1][self._csr_elements] = kw, rho_w
            return CsrOperator(mesh, *sk, order=perm, vertical=self._anisotropic)
        return TensorOperator(self.grid, kw, rho_w, vertical=self._anisotropic)

    @property
    def _anisotropic(self) -> bool:
        return self.settings.liquid_k_factor_xy != self.settings.liquid_k_factor_z

    @property
    def _liquid_factors(self) -> tuple[float, float]:
        return (self.settings.liquid_k_factor_xy, self.settings.liquid_k_factor_z)

    def _face_areas(self) -> tuple[np.ndarray, np.ndarray]:
        """Lumped top- and bottom-face areas [m²], shapes (ny, nx): the ``facet_area`` form on the
        facets (CSR operator) or its closed form on the box grid (tensor operator)."""
        if self.settings.operator != "csr":
            return self.grid.top_areas(), self.grid.top_areas()
        faces = []
        for z, k in ((self.grid.zs[-1], -1), (self.grid.zs[0], 0)):
            facets = self.operator.mesh.facets_satisfying(lambda x, z=z: np.isclose(x[2], z, rtol=0, atol=1e-12))
            faces.append(self.operator.facet_areas(facets).reshape(self.grid.solver_shape)[:, k, :])
        return faces[0], faces[1]

    def _element_weights(self) -> tuple[np.ndarray, np.ndarray]:
        """Current (kw, rho_w) [-] per element, flat in solver element order."""
        op = self.operator
        if self.settings.operator == "csr":
            return op.kw[self._csr_elements], op.rho_w[self._csr_elements]
        return op.kw.ravel().copy(), op.rho_w.ravel().copy()

    def add_layer(self) -> None:
        """Spread a new powder layer (``powder_layer_m``, at the preheat temperature) and start the next plan.

        Elements keep their weights (consolidated tracks stay consolidated); the new powder brings in
        its enthalpy at the preheat state, exactly (the old top nodes, whose lumped volumes now reach
        into it, mix their energy with it), added to the reference energy of the balance.

        Raises
        ------
        RuntimeError
            Without a powder layer (``powder_layer_m = 0``) or before the plan is done.
        """
        s, g = self.settings, self.grid
        if self.powder is None or not self.layer_done:
            raise RuntimeError("add_layer needs powder_layer_m > 0 and a finished scan plan")
        if s.dwell_s > 0:
            self._dwell(s.dwell_s)
        kw, rho_w = self._element_weights()
        e_before = self._energy()
        n = math.ceil(s.powder_layer_m / s.h_fine_m - 1e-9)
        ny, nz, nx = g.solver_shape
        self.grid = Grid(g.xs, g.ys, np.concatenate([g.zs, g.zs[-1] + np.linspace(0.0, s.powder_layer_m, n + 1)[1:]]))
        old, new = (ny - 1, nz - 1, nx - 1), (ny - 1, n, nx - 1)
        kw = np.concatenate([kw.reshape(old), np.full(new, self.powder.kw_powder)], axis=1).ravel()
        rho_w = np.concatenate([rho_w.reshape(old), np.full(new, RHO_W)], axis=1).ravel()
        self.powder.grow(n)
        if self._lattice is not None:
            self._lattice.grow(n)
        self.operator = self._build_operator(kw, rho_w)
        self._a_top, self._a_bottom = self._face_areas()
        h = np.full(self.grid.solver_shape, self._h_ref)
        h[:, :nz, :] = self._h
        self._h, m_top = h, self._m[:, -1, :].copy()
        self._set_time_step()
        grown = self._m[:, nz - 1, :]     # the old top nodes now hold half of the new powder's bottom elements too
        self._h[:, nz - 1, :] = (m_top * self._h[:, nz - 1, :] + (grown - m_top) * self._h_ref) / grown
        self._e0 += self._energy() - e_before
        self._s = 0.0
        self.layer += 1
        if self._layer_plans is not None:
            self.plan = self._layer_plans[self.layer]

    def _dwell(self, duration_s: float) -> None:
        """Cool for ``duration_s`` with the laser off, explicit sub-steps then implicit steps
        (:func:`fe_node.dwell.cool`; where they undershoot on graded elements, on the corner-rule
        stiffness of the same element weights, ``TensorOperator(nodal=True)``: an M-matrix on any
        box grid); losses counted."""
        s = self.settings
        no_load = np.zeros((1, 1))
        corner = None

        def on_corners(dt: float) -> float:
            nonlocal corner
            if corner is None:
                kw, rho_w = self._element_weights()
                corner = TensorOperator(self.grid, kw, rho_w, nodal=True)
            return self._implicit_dwell_step(dt, corner)

        for lost in cool(self._h, duration_s, self._dt_sub, lambda: self._substep(no_load),
                         lambda dt: self._implicit_dwell_step(dt, self.operator), s.dwell_step_s,
                         self.law.temperature, s.t_amb_k, fallback=on_corners):
            self._lost += lost

    def _implicit_dwell_step(self, dt: float, operator) -> float:
        """One implicit dwell step of ``dt`` [s] on ``operator`` with the top and plate losses; returns the
        energy lost [J]."""
        return implicit_cooling_step(self._h, operator, self.law, self._m, self._a_top, self._a_bottom,
                                     self.settings, dt)

    def reweight(self, elements, kw, rho_w) -> None:
        """Change the weights of solver elements (flat indices), keeping each node's energy.

        The operator and lumped mass are updated, nodal enthalpies rescaled so that ``m_i H_i``
        is unchanged, and the stability limit (sub-steps) recomputed; with the same ``rho_w``
        the masses and, unless the sub-steps change, the update factors stay.
        """
        el = np.asarray(elements, dtype=np.intp)
        el = self._csr_elements[el] if self.settings.operator == "csr" else el
        same_mass = np.array_equal(self.operator.rho_w.reshape(-1)[el], np.broadcast_to(rho_w, el.shape))
        energy = None if same_mass else self._m * self._h
        self.operator.reweight(el, kw, rho_w)
        if energy is None:
            n_substeps = self._stable_substeps()
            if n_substeps != self.n_substeps:
                self._set_factors(n_substeps)
            return
        self._set_time_step()
        np.divide(energy, self._m, out=self._h)

    def _consolidate(self) -> None:
        """Re-weight the powder elements that melted this step (:meth:`fe_node.powder.PowderBed.consolidate`)."""
        melted = self.powder.consolidate(self.law.temperature(self._h[:, self.powder.k0:, :]))
        if len(melted) and self._lattice is not None:
            j, k, i = np.unravel_index(melted, (len(self.grid.ys) - 1, len(self.grid.zs) - 1, len(self.grid.xs) - 1))
            self._lattice.mark(self.grid.xs, self.grid.ys, (j, k - self.powder.k0 + self._lattice_row0, i))
        if len(melted):
            self.reweight(melted, KW_DENSE, RHO_W)

    def _set_time_step(self) -> None:
        """Sub-steps and update factors from the current weights (stability limit, module docstring)."""
        self._m = np.reshape(self.operator.lumped_mass, self.grid.solver_shape)
        self._depth_w = depth_weights(self.grid.zs, self.settings.penetration_depth_m)
        if self._work is None or self._work.phi.shape != self._m.shape:
            self._work = StepWork(self._m.shape)
        self._set_factors(self._stable_substeps())

    def _stable_substeps(self) -> int:
        """Sub-steps per step the stability limit of the current weights needs (module docstring)."""
        lam = self.operator.stability_eigenvalue()
        alpha = self.law.max_diffusivity * max(1.0, *self._liquid_factors)
        dt_stable = 0.9 * 2.0 / (alpha * lam)
        return max(self.settings.min_substeps, math.ceil(self.settings.dt_s / dt_stable))

    def _set_factors(self, n_substeps: int) -> None:
        """``n_substeps`` and the update factors of its sub-step from the lumped masses."""
        self.n_substeps = n_substeps
        self._dt_sub = self.settings.dt_s / self.n_substeps
        self._c = (self._dt_sub * self.law.k_ref) / self._m
        self._c_top = self._dt_sub / self._m[:, -1, :]
        self._k_evap = self._dt_sub * self._a_top / self._m[:, -1, :]
        self._c_bottom = self._dt_sub / self._m[:, 0, :]

    @property
    def layer_done(self) -> bool:
        """True once the laser has reached the end of the scan plan in the current layer."""
        return self._s >= self.plan.total_length * (1 - 1e-12)

    @property
    def done(self) -> bool:
        """True once the last layer's scan plan is done (``Settings.n_layers``)."""
        return self.layer_done and self.layer + 1 >= self.settings.n_layers

    @property
    def time_s(self) -> float:
        return self.step_index * self.settings.dt_s

    def _energy(self) -> float:
        """Enthalpy content sum_i m_i H_i [J] (einsum: no multithreaded BLAS)."""
        return float(np.einsum("ijk,ijk->", self._m, self._h))

    def temperature(self) -> np.ndarray:
        """Nodal temperature [K], shape ``grid.shape`` = (nx, ny, nz)."""
        return np.ascontiguousarray(self.grid.to_xyz(self.law.temperature(self._h)))

    def temperature_at(self, points: np.ndarray) -> np.ndarray:
        """Temperature [K] at ``points`` (shape (n, 3), x, y, z [m]), trilinear in the grid (points
        outside take the nearest boundary value)."""
        return self.law.temperature(interpolate_points(self.grid, self._h, np.asarray(points, dtype=float)))

    def prepare(self) -> None:
        """Do the part of the next step that does not depend on its command, ahead of it (a lockstep
        node calls it while the command is in flight): nothing on this mesh; the multi-level mesh steps
        its coarser levels (:meth:`fe_node.multilevel.MultiLevelModel.prepare`)."""

    def step(self, power_w: float, speed_m_s: float) -> Observation:
        """Advance one step ``dt_s`` with laser power [W] and scan speed [m/s].

        The laser moves ``speed * dt`` along the plan; past the end of the plan it is
        off.  A step after the end of a layer's plan first spreads the next layer
        (:meth:`add_layer`).  Returns the observation at the end of the step.
        """
        check_command(power_w, speed_m_s)
        if self.done:
            raise RuntimeError("scan plan finished: no more steps")
        if self.layer_done:
            self.add_layer()
        s = self.settings
        if s.window_m > 0:
            self._follow(speed_m_s * s.dt_s)
        ds = speed_m_s * self._dt_sub
        n_pos = max(1, math.ceil(ds / (s.beam_radius_m / 20)))
        total = self.plan.total_length
        wall, depth_m = self.surface_absorptivity(), self.keyhole_depth_m()
        for _ in range(self.n_substeps):
            s_pos = self._s + (np.arange(n_pos) + 0.5) / n_pos * ds
            on = s_pos < total
            load = np.zeros((1, 1))
            if np.any(on) and power_w > 0:
                _, xy, _ = self.plan.locate(s_pos[on])
                held = self._holds(xy)
                self.laser_outside_j += power_w * on.mean() * (1.0 - held.mean()) * self._dt_sub
                if held.any():
                    load = surface_load(self.grid.xs, self.grid.ys, xy[held], power_w * on.mean() * held.mean(), 1.0,
                                        s.beam_radius_m)
                    load *= self._beam_absorptivity(load, wall, depth_m)
            self._substep(load)
            self._s = min(self._s + ds, total)
        if self.powder is not None:
            self._consolidate()
        self.step_index += 1
        return self._observe(power_w, speed_m_s)

    def _holds(self, xy: np.ndarray) -> np.ndarray:
        """True for the laser positions ``xy`` (shape (n, 2), [m]) on this grid (all: the grid covers
        the whole plan)."""
        return np.ones(len(xy), dtype=bool)

    def keyhole_depth_m(self) -> float:
        """Depth [m] of the keyhole now: the vapour depth of the columns within three 1/e² radii
        ``w`` of the laser, weighted by the beam's relative intensity ``exp(-2 rho² / w²)``
        (:func:`fe_node.keyhole.vapour_depth_m`); 0 without keyhole onset."""
        if self._h_keyhole is None:
            return 0.0
        g, w = self.grid, beam_1e2_radius_m(self.settings.beam_radius_m)
        _, (x, y), _ = self.plan.locate(self._s)
        i = slice(*np.searchsorted(g.xs, [x - 3 * w, x + 3 * w]))
        j = slice(*np.searchsorted(g.ys, [y - 3 * w, y + 3 * w]))
        weights = np.exp(-2.0 * ((g.xs[i][None, :] - x) ** 2 + (g.ys[j][:, None] - y) ** 2) / w**2)
        return vapour_depth_m(self._h[j, :, i], self._m[j, :, i], self._a_top[j, i], self._h_boil, self._h_keyhole,
                              weights)

    def surface_absorptivity(self) -> np.ndarray:
        """Absorptivity [-] of the surface at each top node, shape (ny, nx): ``absorptivity`` on
        dense metal, ``powder_absorptivity`` on powder, weighted by the node's dense share: the
        larger of the consolidated share of the top elements around it
        (:meth:`fe_node.powder.PowderBed.surface_fraction`) and its own liquid fraction (a molten
        surface is melt before its elements consolidate)."""
        s = self.settings
        if self.powder is None:
            return np.full(self._a_top.shape, s.absorptivity)
        m = s.material
        melt = np.clip((self.law.temperature(self._h[:, -1, :]) - m.t_solidus) / (m.t_liquidus - m.t_solidus), 0, 1)
        dense = np.maximum(self.powder.surface_fraction(), melt)
        return s.powder_absorptivity + (s.absorptivity - s.powder_absorptivity) * dense

    def _beam_absorptivity(self, load: np.ndarray, wall: np.ndarray, depth_m: float) -> float:
        """Absorptivity [-] of the whole beam: the surface's (``wall``, shape (ny, nx)) averaged
        with the beam's nodal load ``load`` (shape (nx, ny), any scale), raised by the keyhole's
        cavity absorptance at depth ``depth_m`` [m] (:func:`fe_node.keyhole.cavity_absorptivity`)."""
        a = float(np.einsum("ij,ji->", load, wall) / load.sum())
        return float(cavity_absorptivity(a, depth_m, self.keyhole_radius_m))

    def absorptivity(self) -> float:
        """Absorptivity [-] of the beam at the laser's position now (:meth:`_beam_absorptivity`)."""
        _, xy, _ = self.plan.locate(np.array([self._s]))
        load = surface_load(self.grid.xs, self.grid.ys, xy, 1.0, 1.0, self.settings.beam_radius_m)
        return self._beam_absorptivity(load, self.surface_absorptivity(), self.keyhole_depth_m())

    def _follow(self, travel_m: float) -> None:
        """Move the fine window ahead of the laser if this step would take it near the edge: ahead of
        where the step starts, or of where it ends if it jumps to a track that window would not hold."""
        _, points, directions = self.plan.locate(np.array([self._s, min(self._s + travel_m, self.plan.total_length)]))
        g, s = self.grid, self.settings
        if needs_move((g.xs, g.ys), self._bands, s.h_fine_m, points, s.window_m):
            centre = ahead(points[0], directions[0], s.window_m)
            there = build_grid(s, self.plan, self._layer_plans, centre)
            if needs_move((there.xs, there.ys), self._bands, s.h_fine_m, points[1:], s.window_m):
                centre = ahead(points[1], directions[1], s.window_m)
            self.remesh(centre)

    def remesh(self, window_centre: np.ndarray) -> None:
        """Put the fine window at ``window_centre`` [m] (x, y) and carry the state over
        (:func:`fe_node.window.transfer`); the energy the transfer changes is counted in
        ``remesh_energy_j`` (and so in the balance)."""
        old, e_before = self.grid, self._energy()
        moved = build_grid(self.settings, self.plan, self._layer_plans, window_centre)
        new = Grid(moved.xs, moved.ys, old.zs)
        jm, im = element_map(old.ys, new.ys), element_map(old.xs, new.xs)
        shape = (len(old.ys) - 1, len(old.zs) - 1, len(old.xs) - 1)
        kw, rho_w = (w.reshape(shape)[jm][:, :, im] for w in self._element_weights())
        self._h = np.ascontiguousarray(transfer(self._h, old.xs, old.ys, new.xs, new.ys))
        if self.powder is not None:     # powder: from the consolidation kept on the band's lattice
            pb, k0 = self.powder, self.powder.k0
            share = self._lattice.fraction(new.xs, new.ys)
            pb.consolidated = share >= 1.0 - 1e-9
            kw[:, k0:, :] = pb.kw_powder + share * (KW_DENSE - pb.kw_powder)
            rho_w[:, k0:, :] = RHO_W
        kw, rho_w = kw.ravel(), rho_w.ravel()
        self.grid = new
        self.operator = self._build_operator(kw, rho_w)
        self._a_top, self._a_bottom = self._face_areas()
        self._set_time_step()
        tol = 1e-6 * self.settings.h_fine_m
        interpolated = ~(kept(old.ys, new.ys, tol)[:, None, None] & kept(old.xs, new.xs, tol)[None, None, :])
        conserve(self._h, self._m, np.broadcast_to(interpolated, self._h.shape), e_before, self._h_ref)
        self.remesh_energy_j += self._energy() - e_before
        self.n_remeshes += 1

    def _substep(self, load) -> None:
        """One explicit sub-step (losses at the start temperature, capped at boiling)."""
        q = self._a_top * loss_flux(self.law.temperature(self._h[:, -1, :]), self.settings)
        s = self.settings
        if s.plate_h_w_m2k > 0:
            q_plate = self._a_bottom * s.plate_h_w_m2k * (self.law.temperature(self._h[:, 0, :]) - s.t0_k)
            self._h[:, 0, :] -= q_plate * self._c_bottom
            self._lost += float(q_plate.sum()) * self._dt_sub
        if len(self._depth_w) > 1 and load.shape != (1, 1):
            below = load.T[:, None, :] * self._depth_w[None, :0:-1, None]     # nodes under the top, deepest first
            n = len(self._depth_w) - 1
            self._h[:, -1 - n:-1, :] += below * (self._dt_sub / self._m[:, -1 - n:-1, :])
            load = load * self._depth_w[0]
            self._absorbed += float(np.sum(below)) * self._dt_sub
        explicit_update(self._h, self.operator, self.law, self._c, load.T - q, self._c_top, self._liquid_factors,
                        self._work)
        self._absorbed += float(np.sum(load)) * self._dt_sub
        self._lost += float(q.sum()) * self._dt_sub
        if self._h_keyhole is not None:
            drill(self._h, self._m, self._h_keyhole, len(self._depth_w))
        if self.settings.evaporation:
            self._evaporate()

    def _evaporate(self) -> None:
        """Evaporative cooling of liquid top nodes, implicit per node (:func:`fe_node.boundary.evaporate_top`)."""
        if self._evaporated is None or self._evaporated.size < self._k_evap.size:
            self._evaporated = np.empty(self._k_evap.size)
        self._lost += evaporate_top(self._h, self._m, self.law, self._k_evap, self._evaporated)

    def pool(self, level_k: float, t_top: np.ndarray | None = None) -> dict:
        """Geometry of the region above ``level_k`` [K] (:func:`fe_node.observe.pool_geometry`).

        ``t_top`` (nx, ny): the top-surface temperatures [K], if already at hand.
        """
        g, h = self.grid, self._h
        if t_top is None:
            t_top = self.law.temperature(h[:, -1, :]).T
        hot = np.argwhere(t_top > level_k)
        if not len(hot):
            return pool_geometry(t_top[:1, :1, None], g.xs[:1], g.ys[:1], g.zs[-1:], level_k)
        (i0, j0), (i1, j1) = hot.min(axis=0), hot.max(axis=0)
        i0, j0 = max(i0 - 1, 0), max(j0 - 1, 0)
        i1, j1 = min(i1 + 2, g.shape[0]), min(j1 + 2, g.shape[1])
        t3 = g.to_xyz(self.law.temperature(h[j0:j1, :, i0:i1]))
        return pool_geometry(t3, g.xs[i0:i1], g.ys[j0:j1], g.zs, level_k)

    def initial_observation(self) -> Observation:
        """Observation of the initial state (step 0, laser at the plan start, off)."""
        return self._observe(0.0, 0.0)

    def _observe(self, power_w: float, speed_m_s: float) -> Observation:
        s, g, h = self.settings, self.grid, self._h
        track, xy, d = self.plan.locate(self._s)
        t_top = self.law.temperature(h[:, -1, :]).T       # (nx, ny)
        geo = self.pool(s.material.t_liquidus, t_top)
        gradient = 0.0
        if geo["area_m2"] > 0:
            gradient = trailing_edge(t_top, g.xs, g.ys, xy, d, s.material.t_liquidus, s.material.t_solidus,
                                     reach_m=2 * geo["length_m"] + 4 * s.h_fine_m, step_m=0.25 * s.h_fine_m)
        rate = speed_m_s if gradient > 0 else 0.0
        ahead = xy + (speed_m_s * s.dt_s + s.beam_radius_m) * d
        stored = self._energy() - self._e0
        err = (100.0 * (self._absorbed - stored - self._lost) / self._absorbed
               if self._absorbed > 0 else 0.0)
        travelled, remaining, follows = self.plan.preview(self._s)
        return Observation(
            track_travelled_m=travelled, track_remaining_m=remaining, next_track=follows,
            layer=self.layer, z_top_m=float(g.zs[-1]),
            step=self.step_index, time_s=self.time_s, x_m=float(xy[0]), y_m=float(xy[1]),
            direction=(float(d[0]), float(d[1])), track=int(track),
            power_w=float(power_w), speed_m_s=float(speed_m_s), **geo,
            t_ahead_k=bilinear(t_top, g.xs, g.ys, ahead[0], ahead[1]),
            t_peak_k=float(self.law.temperature(h.max())),
            energy_absorbed_j=self._absorbed, energy_stored_j=stored,
            energy_lost_j=self._lost, energy_error_pct=err, thermal_gradient_k_m=gradient,
            solidification_rate_m_s=rate, cooling_rate_k_s=gradient * rate)

    def temperature_image(self, half_length_m: float = 0.6e-3, half_width_m: float = 0.3e-3,
                          pixel_m: float = 10e-6):
        """Top-surface temperature raster centred on the laser, for visualisation.

        Parameters
        ----------
        half_length_m, half_width_m : float
            Half extents of the window along x and y [m].
        pixel_m : float
            Pixel size [m].

        Returns
        -------
        image : ndarray, shape (ny_px, nx_px)
            Temperatures [K]; row index increases with y, column with x.
        extent : tuple of float
            (x_min, x_max, y_min, y_max) [m] of the pixel centres' bounding box.
        """
        if not (half_length_m > 0 and half_width_m > 0 and pixel_m > 0):
            raise ValueError("temperature_image: sizes must be > 0")
        _, xy, _ = self.plan.locate(self._s)
        px = xy[0] + np.arange(-half_length_m, half_length_m + pixel_m / 2, pixel_m)
        py = xy[1] + np.arange(-half_width_m, half_width_m + pixel_m / 2, pixel_m)
        t_top = self.law.temperature(self._h[:, -1, :]).T
        img = interp_matrix(self.grid.ys, py) @ t_top.T @ interp_matrix(self.grid.xs, px).T
        return img, (float(px[0]), float(px[-1]), float(py[0]), float(py[-1]))
