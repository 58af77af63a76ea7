"""The plant grid's size, counted from the settings and the scan plan without building the grid:
the whole-plan band and the domain (:func:`plan_bands`), the node count of the uniform grid
(:func:`grid_shape`) and of the multi-level mesh (:func:`level_nodes`), and the cap
:data:`MAX_GRID_NODES` (:func:`check_grid_size`).

It imports no sparse algebra, so that a process that only checks a configuration (``launch.py``,
:func:`fe_node.scenarios.scenario`) starts without it.
"""
from __future__ import annotations

import math

import numpy as np

from fe_node.mesh import graded_axis_size
from fe_node.scan import ScanPlan
from fe_node.settings import Settings


def plan_bands(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None):
    """Per axis x, y: the domain (every layer's tracks plus ``margin_m``) and the whole-plan fine
    band (plus ``fine_pad_m``) [m], as ``((domain_lo, domain_hi), (band_lo, band_hi))``."""
    b = np.array([p.bounds() for p in (layer_plans or (plan,))])
    s = settings
    return tuple(((lo - s.margin_m, hi + s.margin_m), (lo - s.fine_pad_m, hi + s.fine_pad_m))
                 for lo, hi in ((b[:, 0].min(), b[:, 1].max()), (b[:, 2].min(), b[:, 3].max())))


MAX_GRID_NODES = 50_000_000
"""Most nodes a plant grid may have: about 9 GB of nodal fields at the 184 B per node measured on
the default layer (``docs/fe.md``). A larger plan is refused (:func:`check_grid_size`) before
anything is allocated."""


def grid_shape(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None
               ) -> tuple[int, int, int]:
    """Nodes along x, y, z of :func:`~fe_node.solver.build_grid`'s grid, counted without building it (exact for the
    whole-plan band; with ``window_m > 0`` an estimate, as if the whole window lay inside the band)."""
    s = settings
    ax = dict(h=s.h_fine_m, growth=s.growth, h_max=s.h_max_m)
    counts = []
    for domain, (band_lo, band_hi) in plan_bands(settings, plan, layer_plans):
        if s.window_m > 0:
            band_hi = min(band_hi, band_lo + s.window_m + 2 * s.h_fine_m)
        counts.append(graded_axis_size(*domain, band_lo, band_hi, **ax))
    nz = graded_axis_size(-s.depth_m, 0.0, -s.fine_depth_m, 0.0, **ax)
    if s.powder_layer_m > 0:
        nz += math.ceil(s.powder_layer_m / s.h_fine_m - 1e-9)
    return counts[0], counts[1], nz


def level_nodes(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None) -> int:
    """Upper bound of the nodes of the multi-level mesh's three grids (``mesh = "multilevel"``,
    :mod:`fe_node.multilevel`): the fine box at most ``fine_box_m`` square at ``h_fine_m`` (as deep
    as the uniform grid's top ``fine_box_depth_m``), the intermediate box and the part level."""
    s = settings
    (x, _), (y, _) = plan_bands(settings, plan, layer_plans)
    nz_fine = grid_shape(settings, plan, layer_plans)[2]
    fine = (math.ceil(s.fine_box_m / s.h_fine_m) + 2) ** 2 * nz_fine
    top = s.n_layers * s.powder_layer_m      # the last layer's (the levels grow with the build)
    nz = [graded_axis_size(-s.depth_m, top, max(-s.depth_m, top - 2 * min(h, s.mid_h_m)), top, h=min(h, s.mid_h_m),
                           growth=s.growth, h_max=max(s.h_max_m, h)) for h in (s.mid_h_m, s.coarse_h_m)]
    mid = (math.ceil(s.mid_box_m / s.mid_h_m) + 2) ** 2 * nz[0]
    part = (math.ceil((x[1] - x[0]) / s.coarse_h_m) + 1) * (math.ceil((y[1] - y[0]) / s.coarse_h_m) + 1) * nz[1]
    return fine + mid + part


def check_grid_size(settings: Settings, plan: ScanPlan, layer_plans: tuple[ScanPlan, ...] | None = None) -> None:
    """Raise ValueError (one line, naming what to change) if the plant's grid (or, with the
    multi-level mesh, its three grids, :func:`level_nodes`) would have more than
    :data:`MAX_GRID_NODES` nodes."""
    if settings.mesh == "multilevel":
        n = level_nodes(settings, plan, layer_plans)
        if n > MAX_GRID_NODES:
            raise ValueError(f"the multi-level mesh would have {n:,} nodes, more than {MAX_GRID_NODES:,}: "
                             "coarsen coarse_h_m or mid_h_m, or shrink fine_box_m or mid_box_m")
        return
    nx, ny, nz = grid_shape(settings, plan, layer_plans)
    if nx * ny * nz > MAX_GRID_NODES:
        raise ValueError(f"the FE grid would have {nx * ny * nz:,} nodes ({nx} x {ny} x {nz}), more than "
                         f"{MAX_GRID_NODES:,}: shorten the scan plan (n_tracks, track_length_m, hatch_m), coarsen "
                         "h_fine_m, or let a fine window follow the laser (window_m)")
