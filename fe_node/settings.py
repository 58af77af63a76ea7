"""Plant settings (process, boundary conditions, discretisation), validated on construction."""
from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, fields

from fe_node.frames import frame_ratio
from fe_node.material import Material


def check_type(what: str, value: object, kind: str) -> None:
    """Raise ValueError (naming ``what``) unless ``value`` is of ``kind``: ``"float"`` a finite real
    number (an integer too, not a boolean), ``"int"`` an integer (not a boolean), ``"bool"`` true or
    false, ``"str"`` a string; other kinds are not checked here."""
    ok = {"float": lambda v: isinstance(v, numbers.Real) and not isinstance(v, bool) and math.isfinite(v),
          "int": lambda v: isinstance(v, numbers.Integral) and not isinstance(v, bool),
          "bool": lambda v: isinstance(v, bool),
          "str": lambda v: isinstance(v, str)}.get(kind)
    if ok is not None and not ok(value):
        name = {"float": "a finite number", "int": "an integer", "bool": "true or false", "str": "a string"}[kind]
        raise ValueError(f"{what} must be {name}, got {value!r}")


OPERATORS = ("tensor", "csr")
MESHES = ("uniform", "multilevel")


@dataclass(frozen=True)
class Settings:
    """Thermal-model settings (SI units).  Defaults follow paper Table 1: the bare physics (a dense
    plate, conduction only), the ``bare-plate`` preset.  The default *plant* of the entry points is
    the ``physical`` preset over these (:func:`fe_node.scenarios.scenario`, :mod:`fe_node.presets`).

    Parameters
    ----------
    material : Material
        Default: temperature-dependent IN625 (see :mod:`fe_node.material`).
    absorptivity : float
        a of eq. 6 [-] (Table 1: 0.4).
    beam_radius_m : float
        r_s of eq. 6 [m] (Table 1: 50 µm).
    penetration_depth_m : float
        c of eq. 6 [m]: the depth scale of the absorbed power, ``exp(-3 z² / c²)``.  0 (default)
        is its c -> 0 limit, a surface flux: the paper's c = 3 µm is far below any affordable
        element size (:mod:`fe_node.source`).
    dt_s : float
        Sampling/step time [s] (50 µs: the laser moves 40 µm per step at 800 mm/s).
    frame_period_s : float
        A camera's frame period [s], a whole number of ``dt_s``: the node publishes one state per
        frame and holds the commanded power over it (:mod:`fe_node.frames`); 0 (default): every step.
    h_fine_m : float
        Element size in the refined band around the scan paths [m]; 25 µm is converged
        to ~1 % (``python -m fe_node validate``), and matches the paper's 25 µm mesh.
    growth, h_max_m : float
        Geometric growth factor of element sizes outside the band, and size cap [m].
    fine_pad_m : float
        Refined band extends this far around the tracks in x and y [m].
    fine_depth_m : float
        Depth of the refined band below the top surface [m].
    margin_m : float
        Domain extends this far around the tracks in x and y [m].
    depth_m : float
        Domain depth [m].  The side and bottom faces are insulated; with margin 1 mm and
        depth 1.5 mm they sit >= 2 thermal diffusion lengths sqrt(alpha t) (~0.49 mm
        for the 50 ms layer) from the heated band, so they hardly affect the melt pool.
    t0_k : float
        Initial (preheat) temperature [K].
    t_amb_k : float
        Ambient temperature for convection and radiation [K].
    h_conv_w_m2k : float
        Top-surface convection coefficient [W/(m² K)] (gas flow; 10 by default).
    emissivity : float
        Top-surface emissivity [-] (IN625 about 0.4-0.5).
    powder_layer_m : float
        Thickness of a powder layer on top of the dense plate [m]; 0 (default) = bare plate
        (the ``physical`` preset: 25 µm).  Powder elements conduct
        ``powder_k_w_mk`` at 500 °C (scaling with T like the dense metal) and hold
        ``powder_packing`` of the dense heat capacity; an element whose mean nodal temperature
        passes the liquidus consolidates (docs/fe.md).
    powder_packing : float
        Packing density of the powder bed, relative to the dense metal [-].
    powder_k_w_mk : float
        Powder-bed conductivity at 500 °C [W/(m K)] (IN625: 1.01, ASME J. Manuf. Sci. Eng.
        140(11):111008).
    powder_absorptivity : float
        Absorptivity of the powder bed [-], on top nodes over unconsolidated powder
        (``absorptivity`` applies on dense metal; a node is dense by the larger of its top
        elements' consolidated share and its liquid fraction, and the beam absorbs the average
        under its load, :meth:`fe_node.solver.ThermalModel.absorptivity`).  Powder layers absorb
        about twice as much as a flat surface
        of the same metal at conduction-mode powers (Trapp et al., Appl. Mater. Today 9 (2017)
        341, for 316L): 0.65 against the calibrated dense value.
    evaporation : bool
        Evaporative cooling of the top surface (:func:`fe_node.boundary.evaporation_flux`).
    keyhole : bool
        Keyhole onset (:mod:`fe_node.keyhole`): the surface never exceeds the temperature at
        which the vapour's recoil pressure opens a keyhole; the excess energy is deposited at
        the keyhole's bottom, down the node's column, and the beam absorbs the keyhole's cavity
        absorptance (multiple reflections, rising with its depth).
    keyhole_radius_factor : float
        Radius of the keyhole's opening over the beam's 1/e² radius [-] (``keyhole`` on): sets
        the keyhole's depth from its vapour volume and its cavity absorptance
        (:mod:`fe_node.keyhole`).
    n_layers : int
        Layers built one on top of the other (default 1): after each pass over the scan plan
        a new ``powder_layer_m`` of powder is spread and the plan restarts
        (:meth:`fe_node.solver.ThermalModel.add_layer`); more than 1 needs a powder layer.
    dwell_s : float
        Time between layers (recoating, laser off) [s]; 0 (default) = none.  Simulated by
        implicit steps of at most ``dwell_step_s`` (:mod:`fe_node.dwell`).
    dwell_step_s : float
        Largest implicit dwell step [s] (default 1 s: within 0.01 K of 0.05 s steps,
        ``tests/test_fe_layers.py``; ``docs/fe.md``).
    plate_h_w_m2k : float
        Build-plate heat sink: heat transfer coefficient [W/(m² K)] from the bottom face to the
        plate at ``t0_k``; 0 (default) = insulated.  ``k_plate / L`` of the plate below the
        domain, e.g. 10 W/(m K) / 10 mm = 1000.
    liquid_k_factor_xy, liquid_k_factor_z : float
        Effective liquid conductivity of Marangoni flow: the conductivity in the horizontal
        (x, y) and vertical (z) directions is multiplied by ``1 + (f - 1) f_liq``, ``f_liq`` the
        liquid fraction (default 1, 1: off; docs/fe.md).
    window_m : float
        Side of the fine window that follows the laser [m] (:mod:`fe_node.window`): the
        ``h_fine_m`` band covers only this square around the laser, so the node count stays
        bounded as the part grows.  0 (default): the band covers the whole scan plan.
    min_substeps : int
        Least explicit sub-steps per step (default 3; more if stability needs them).  Three
        keep the area within 1 % of the time-converged one at 25 µm (``dt_convergence_pct`` of
        ``python -m fe_node validate``; one sub-step, which stability allows, is 2.7 % low).
    mesh : str
        ``"uniform"`` (default): one graded grid, fine over the whole plan (or the ``window_m``
        around the laser); ``"multilevel"``: three nested grids that move with the laser
        (:mod:`fe_node.multilevel`, docs/fe-scale.md): the fine box below, an intermediate box of
        ``mid_h_m`` elements and the part at ``coarse_h_m``, each stepped at its own time step.
    fine_box_m, fine_box_depth_m : float
        Side of the fine level's square box around the laser, and its depth below the plate's
        top [m] (``mesh = "multilevel"``).
    mid_h_m, mid_box_m : float
        Element size and box side [m] of the intermediate level.
    coarse_h_m : float
        Element size [m] of the part level (the whole domain).
    operator : str
        Implementation of the forms (:mod:`fe_node.operators`): ``"tensor"`` (the fast
        tensor-product path, default) or ``"csr"`` (scikit-fem-assembled CSR matrix, same result).
    """

    material: Material = field(default_factory=Material.in625)
    absorptivity: float = 0.4
    beam_radius_m: float = 50e-6
    penetration_depth_m: float = 0.0
    dt_s: float = 50e-6
    frame_period_s: float = 0.0
    h_fine_m: float = 25e-6
    growth: float = 1.35
    h_max_m: float = 0.5e-3
    fine_pad_m: float = 150e-6
    fine_depth_m: float = 150e-6
    margin_m: float = 1.0e-3
    depth_m: float = 1.5e-3
    t0_k: float = 300.0
    t_amb_k: float = 300.0
    h_conv_w_m2k: float = 10.0
    emissivity: float = 0.4
    powder_layer_m: float = 0.0
    powder_packing: float = 0.55
    powder_k_w_mk: float = 1.01
    powder_absorptivity: float = 0.65
    evaporation: bool = False
    keyhole: bool = False
    keyhole_radius_factor: float = 1.0
    n_layers: int = 1
    dwell_s: float = 0.0
    dwell_step_s: float = 1.0
    plate_h_w_m2k: float = 0.0
    liquid_k_factor_xy: float = 1.0
    liquid_k_factor_z: float = 1.0
    window_m: float = 0.0
    min_substeps: int = 3
    mesh: str = "uniform"
    fine_box_m: float = 2.4e-3
    fine_box_depth_m: float = 0.4e-3
    mid_h_m: float = 50e-6
    mid_box_m: float = 5e-3
    coarse_h_m: float = 200e-6
    operator: str = "tensor"

    @property
    def steps_per_frame(self) -> int:
        """FE steps per published state: ``frame_period_s / dt_s`` (1 without a frame period)."""
        return 1 if self.frame_period_s == 0 else frame_ratio(self.frame_period_s, self.dt_s)

    @property
    def sample_period_s(self) -> float:
        """The period of the published states [s]: ``frame_period_s``, else ``dt_s``."""
        return self.frame_period_s or self.dt_s

    def __post_init__(self):
        if not isinstance(self.material, Material):
            raise ValueError("settings: material must be a fe_node.material.Material")
        for f in fields(self):
            check_type(f"settings: {f.name}", getattr(self, f.name), f.type)
        positive = ("beam_radius_m", "dt_s", "h_fine_m", "h_max_m", "fine_pad_m",
                    "fine_depth_m", "margin_m", "depth_m", "t0_k", "t_amb_k")
        for name in positive:
            if not getattr(self, name) > 0:
                raise ValueError(f"settings: {name} must be > 0, got {getattr(self, name)}")
        for name in ("absorptivity", "powder_absorptivity"):
            if not 0 < getattr(self, name) <= 1:
                raise ValueError(f"settings: {name} must be in (0, 1], got {getattr(self, name)}")
        if not 0.1 <= self.keyhole_radius_factor <= 2:
            raise ValueError(f"settings: keyhole_radius_factor must be in [0.1, 2], got {self.keyhole_radius_factor}")
        if not 0 <= self.penetration_depth_m <= self.fine_depth_m:
            raise ValueError(f"settings: penetration_depth_m must be in [0, fine_depth_m], "
                             f"got {self.penetration_depth_m}")
        if not 0 <= self.emissivity <= 1:
            raise ValueError(f"settings: emissivity must be in [0, 1], got {self.emissivity}")
        if isinstance(self.min_substeps, bool) or not isinstance(self.min_substeps, int) or self.min_substeps < 1:
            raise ValueError(f"settings: min_substeps must be an integer >= 1, got {self.min_substeps!r}")
        if not (0 <= self.powder_layer_m <= self.fine_depth_m):
            raise ValueError(f"settings: powder_layer_m must be in [0, fine_depth_m], got {self.powder_layer_m}")
        if not 0 < self.powder_packing <= 1:
            raise ValueError(f"settings: powder_packing must be in (0, 1], got {self.powder_packing}")
        if not self.powder_k_w_mk > 0:
            raise ValueError(f"settings: powder_k_w_mk must be > 0, got {self.powder_k_w_mk}")
        if isinstance(self.n_layers, bool) or not isinstance(self.n_layers, int) or self.n_layers < 1:
            raise ValueError(f"settings: n_layers must be an integer >= 1, got {self.n_layers!r}")
        if self.n_layers > 1 and self.powder_layer_m == 0:
            raise ValueError("settings: n_layers > 1 needs powder_layer_m > 0 (the layer thickness)")
        if not (0 <= self.dwell_s < float("inf") and 0 < self.dwell_step_s < float("inf")):
            raise ValueError(f"settings: dwell_s must be >= 0 and dwell_step_s > 0, got {self.dwell_s}, "
                             f"{self.dwell_step_s}")
        if self.frame_period_s != 0:
            frame_ratio(self.frame_period_s, self.dt_s, "settings: frame_period_s")
        if not 0 <= self.plate_h_w_m2k < float("inf"):
            raise ValueError(f"settings: plate_h_w_m2k must be finite and >= 0, got {self.plate_h_w_m2k}")
        for name in ("liquid_k_factor_xy", "liquid_k_factor_z"):
            if not 1 <= getattr(self, name) <= 20:
                raise ValueError(f"settings: {name} must be in [1, 20], got {getattr(self, name)}")
        if self.operator not in OPERATORS:
            raise ValueError(f"settings: operator must be one of {', '.join(OPERATORS)}, got {self.operator!r}")
        if self.mesh not in MESHES:
            raise ValueError(f"settings: mesh must be one of {', '.join(MESHES)}, got {self.mesh!r}")
        if self.h_conv_w_m2k < 0:
            raise ValueError(f"settings: h_conv_w_m2k must be >= 0, got {self.h_conv_w_m2k}")
        if not 1 <= self.growth <= 2:
            raise ValueError(f"settings: growth must be in [1, 2], got {self.growth}")
        if self.h_fine_m > self.beam_radius_m:
            raise ValueError(f"settings: mesh too coarse for the beam: h_fine_m "
                             f"{self.h_fine_m:g} m > beam radius {self.beam_radius_m:g} m")
        if self.h_max_m < self.h_fine_m:
            raise ValueError("settings: h_max_m must be >= h_fine_m")
        if not (self.window_m == 0 or 8 * self.h_fine_m <= self.window_m < float("inf")):
            raise ValueError(f"settings: window_m must be 0 (off) or >= 8 h_fine_m, got {self.window_m}")
        if self.fine_pad_m > self.margin_m or self.fine_depth_m > self.depth_m:
            raise ValueError("settings: refined band must lie inside the domain")
        if self.mesh == "multilevel":
            self._check_levels()

    def _check_levels(self) -> None:
        """The multi-level mesh's sizes nest: fine box < intermediate box, fine < mid < coarse elements."""
        if self.operator != "tensor" or self.window_m != 0:
            raise ValueError("settings: mesh = 'multilevel' needs operator = 'tensor' and window_m = 0")
        if not 16 * self.h_fine_m <= self.fine_box_m:
            raise ValueError(f"settings: fine_box_m must be >= 16 h_fine_m, got {self.fine_box_m}")
        if not self.fine_depth_m <= self.fine_box_depth_m <= self.depth_m:
            raise ValueError(f"settings: fine_box_depth_m must be in [fine_depth_m, depth_m], "
                             f"got {self.fine_box_depth_m}")
        if not self.h_fine_m < self.mid_h_m < self.coarse_h_m:
            raise ValueError(f"settings: the multi-level mesh needs h_fine_m < mid_h_m < coarse_h_m, got "
                             f"{self.h_fine_m}, {self.mid_h_m}, {self.coarse_h_m}: raise mid_h_m (and coarse_h_m), "
                             "or set mesh = 'uniform'")
        if not self.mid_box_m >= self.fine_box_m + 4 * self.mid_h_m:
            raise ValueError(f"settings: mid_box_m must be >= fine_box_m + 4 mid_h_m, got {self.mid_box_m}")

    @classmethod
    def field_names(cls) -> set[str]:
        return {f.name for f in fields(cls)}
