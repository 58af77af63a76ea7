"""The fine window that follows the laser (``Settings.window_m``, :mod:`fe_node.window`)."""
from dataclasses import replace

import numpy as np
import pytest

from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.settings import Settings
from fe_node.solver import ThermalModel
from fe_node.window import ConsolidationLattice, conserve, transfer, window_axis

COARSE = dict(h_fine_m=40e-6, margin_m=0.5e-3, depth_m=0.6e-3, fine_pad_m=120e-6, fine_depth_m=120e-6,
              h_max_m=0.2e-3)


def _run(settings, plan, n=None):
    model = ThermalModel(settings, plan)
    areas = []
    while not model.done and (n is None or len(areas) < n):
        areas.append(model.step(250.0, 0.8).area_m2)
    return model, np.array(areas)


def test_window_follows_the_laser_and_keeps_the_melt_pool():
    """A 4-track layer with a 1.6 mm window: the area trace of the whole-plan mesh within 0.5 % rms,
    on 55 % of the nodes (the plan is small), the energy the remeshes change small."""
    plan = ScanPlan.layer(4, 3e-3, 1e-4)
    full_model, full = _run(Settings(**COARSE), plan)
    win_model, win = _run(Settings(**COARSE, window_m=1.6e-3), plan)
    assert win_model.n_remeshes >= 8 and win_model.grid.n_nodes < 0.6 * full_model.grid.n_nodes
    diff = (win - full)[20:] / full[20:].mean()
    assert np.sqrt(np.mean(diff**2)) < 0.01 and np.abs(diff).max() < 0.05     # 0.69 %, 4.3 % here
    absorbed = 4 * 3e-3 / 0.8 * 250.0 * 0.4
    assert abs(win_model.remesh_energy_j) < 1e-9 * absorbed                 # the transfer conserves energy


def test_node_count_stays_bounded_as_the_track_grows():
    nodes = {}
    for window in (0.0, 1.2e-3):
        for length in (2e-3, 8e-3):
            settings = Settings(**{**COARSE, "h_max_m": 0.5e-3}, window_m=window)
            nodes[window, length] = ThermalModel(settings, ScanPlan.single(length)).grid.n_nodes
    full_growth = nodes[0.0, 8e-3] - nodes[0.0, 2e-3]            # the band covers the whole track
    window_growth = nodes[1.2e-3, 8e-3] - nodes[1.2e-3, 2e-3]    # only coarse elements are added
    assert full_growth > 1.5 * nodes[0.0, 2e-3] and window_growth < 0.15 * full_growth


def test_nodes_that_stay_fine_keep_their_values():
    band = (-1.0e-3, 9.0e-3)
    a = window_axis(-2e-3, 10e-3, *band, centre=3e-3, width=2e-3, h=25e-6, growth=1.35, h_max=0.5e-3)
    b = window_axis(-2e-3, 10e-3, *band, centre=3.6e-3, width=2e-3, h=25e-6, growth=1.35, h_max=0.5e-3)
    shared = np.intersect1d(np.round(a / 1e-9), np.round(b / 1e-9)) * 1e-9
    fine_shared = shared[(shared > 2.7e-3) & (shared < 3.9e-3)]
    assert fine_shared.size >= 40                               # the overlap of the two windows
    rng = np.random.default_rng(0)
    h = rng.uniform(1e9, 5e9, (3, 2, a.size))
    ys = np.array([0.0, 1e-4, 2e-4])
    moved = transfer(h, a, ys, b, ys)
    ia, ib = (np.searchsorted(x, fine_shared - 1e-12) for x in (a, b))
    assert np.allclose(moved[:, :, ib], h[:, :, ia], rtol=1e-12, atol=0)


def test_window_on_the_default_layer_scenario_and_its_validation():
    sc = scenario("layer", h_fine_m=40e-6, mesh="uniform")
    model = ThermalModel(replace(sc.settings, window_m=2e-3), sc.plan)
    for _ in range(5):
        model.step(250.0, 0.8)
    assert model.grid.n_nodes < ThermalModel(sc.settings, sc.plan).grid.n_nodes
    with pytest.raises(ValueError, match="window_m"):
        Settings(window_m=1e-4)


def test_powder_consolidation_is_kept_across_remeshes():
    """With a powder layer the windowed layer follows the whole-plan mesh too: what consolidated
    stays consolidated on the band's lattice when the window moves on."""
    plan = ScanPlan.layer(3, 3e-3, 1e-4)
    settings = Settings(**COARSE, powder_layer_m=40e-6)
    full_model, full = _run(settings, plan)
    win_model, win = _run(replace(settings, window_m=1.6e-3), plan)
    assert win_model.n_remeshes >= 6 and win_model._lattice.melted.sum() > 100
    diff = (win - full)[20:] / full[20:].mean()
    # max 7.0 %: elements only partly consolidated on the moved window take a share of the dense
    # conductivity, and dense metal conducts 50x more than the powder (mass coordinates)
    assert np.sqrt(np.mean(diff**2)) < 0.015 and np.abs(diff).max() < 0.08


def test_consolidation_lattice_and_energy_correction():
    lattice = ConsolidationLattice((0.0, 1e-3), (0.0, 0.5e-3), 0.1e-3, n_layers=1)
    fine_x, fine_y = np.linspace(0.0, 1e-3, 11), np.linspace(0.0, 0.5e-3, 6)
    lattice.mark(fine_x, fine_y, (np.array([2]), np.array([0]), np.array([3])))   # one fine element
    assert lattice.melted.sum() == 1
    coarse_x, coarse_y = np.array([-1e-3, 0.0, 0.4e-3, 1e-3, 2e-3]), np.array([0.0, 0.5e-3])
    share = lattice.fraction(coarse_x, coarse_y)
    assert share[0, 0].tolist() == [0.0, 0.05, 0.0, 0.0]    # 1 of the 4 x 5 cells of element 1; none outside
    h, mass = np.array([1.0, 3.0, 2.0]), np.array([1.0, 2.0, 1.0])
    factor = conserve(h, mass, np.array([False, True, True]), energy_j=7.0, h_ref=1.0)
    assert np.sum(mass * h) == pytest.approx(7.0) and h[0] == 1.0 and factor == pytest.approx(0.6)


def test_lattice_fraction_counts_only_the_cells_under_the_grid():
    """The share of each element from the summed-area table of the cells under the grid equals the
    count over the whole lattice, for grids inside the band, straddling its edge and outside it."""
    rng = np.random.default_rng(5)
    lattice = ConsolidationLattice((0.0, 2e-3), (0.0, 1e-3), 25e-6, n_layers=2)
    lattice.melted[...] = rng.uniform(size=lattice.melted.shape) < 0.3
    centres = [0.5 * (e[1:] + e[:-1]) for e in lattice.edges]
    for x, y in ((np.linspace(0.3e-3, 0.9e-3, 9), np.linspace(0.2e-3, 0.5e-3, 4)),
                 (np.array([-0.5e-3, 0.0, 0.1e-3, 0.35e-3, 2.5e-3]), np.array([0.8e-3, 1.0e-3, 1.2e-3])),
                 (np.array([2.1e-3, 2.4e-3]), np.array([0.1e-3, 0.2e-3]))):
        cx = [(centres[0] >= a) & (centres[0] < b) for a, b in zip(x[:-1], x[1:])]
        cy = [(centres[1] >= a) & (centres[1] < b) for a, b in zip(y[:-1], y[1:])]
        expected = np.array([[[lattice.melted[my, k][:, mx].mean() if mx.any() and my.any() else 0.0 for mx in cx]
                              for k in range(2)] for my in cy])
        np.testing.assert_allclose(lattice.fraction(x, y), expected, rtol=1e-15, atol=0)


def test_kept_lattice_fractions_follow_marks_and_new_layers():
    """``fraction`` keeps its result per grid and recomputes only the layers marked or grown since:
    after every change it equals the fraction computed afresh, bit for bit, on three grids in turn."""
    rng = np.random.default_rng(11)
    lattice = ConsolidationLattice((0.0, 2e-3), (0.0, 1e-3), 25e-6, n_layers=2)
    grids = [(np.linspace(0.0, 2e-3, 21), np.linspace(0.0, 1e-3, 11)),
             (np.linspace(0.3e-3, 0.9e-3, 25), np.linspace(0.2e-3, 0.5e-3, 13)),
             (np.array([-0.5e-3, 0.0, 0.35e-3, 2.5e-3]), np.array([0.0, 0.6e-3, 1.2e-3]))]
    for change in range(12):
        xs, ys = grids[change % 3]
        if change % 4 == 3:
            lattice.grow(1)
        n = lattice.melted.shape[1]
        elements = (rng.integers(0, len(ys) - 1, 5), rng.integers(max(n - 2, 0), n, 5), rng.integers(0, len(xs) - 1, 5))
        lattice.mark(xs, ys, elements)
        for x, y in grids:
            kept = lattice.fraction(x, y)
            assert not kept.flags.writeable
            np.testing.assert_array_equal(kept, lattice._layer_shares(x, y, np.arange(n)))


def test_both_operators_follow_the_window_alike():
    plan = ScanPlan.layer(2, 3e-3, 1e-4)
    traces = {}
    for operator in ("tensor", "csr"):
        model = ThermalModel(Settings(**COARSE, window_m=1.6e-3, operator=operator), plan)
        traces[operator] = np.array([model.step(250.0, 0.8).area_m2 for _ in range(50)])
        assert model.n_remeshes >= 2  # the window moves every 20 steps
    assert np.allclose(traces["csr"], traces["tensor"], rtol=1e-10, atol=0)
