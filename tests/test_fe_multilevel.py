"""The multi-level mesh (``mesh = "multilevel"``): energy-conserving transfers, consolidation carried
across moves, a fine box that does not grow with the part, and agreement with the uniform mesh."""
from dataclasses import replace

import numpy as np
import pytest

from fe_node.grid_size import check_grid_size
from fe_node.levels import (
    Restriction,
    column_weights,
    extent,
    interpolate,
    lumped_volumes,
    prolong,
    region_energy,
    slaved,
)
from fe_node.mesh import Grid, graded_axis
from fe_node.multilevel import MultiLevelModel, plant_model
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.settings import Settings
from fe_node.solver import ThermalModel

COARSE = dict(h_fine_m=50e-6, beam_radius_m=60e-6, fine_pad_m=150e-6, fine_depth_m=150e-6, margin_m=0.6e-3,
              depth_m=0.6e-3, min_substeps=1)
"""A coarse mesh that runs in seconds."""


def field(grid: Grid, peak: np.ndarray) -> np.ndarray:
    """A smooth, peaked enthalpy field [J/m³] on ``grid`` (solver order) around ``peak`` (x, y)."""
    y, z, x = np.meshgrid(grid.ys, grid.zs, grid.xs, indexing="ij")
    r2 = (x - peak[0]) ** 2 + (y - peak[1]) ** 2 + 4 * z**2
    return 1e9 + 5e9 * np.exp(-r2 / (2 * (120e-6) ** 2))


def test_restrict_conserves_energy():
    fine = Grid(graded_axis(-0.6e-3, 0.6e-3, -0.3e-3, 0.3e-3, 25e-6, 1.35, 0.2e-3), np.linspace(-0.5e-3, 0.5e-3, 41),
                graded_axis(-0.4e-3, 0.0, -0.1e-3, 0.0, 25e-6, 1.35, 0.2e-3))
    coarse = Grid(np.linspace(-2e-3, 2e-3, 81), np.linspace(-2e-3, 2e-3, 81), np.linspace(-1e-3, 0.0, 21))
    h_fine, h_coarse = field(fine, np.array([50e-6, 0.0])), np.full(coarse.solver_shape, 1e9)
    total_before = float(np.sum(lumped_volumes(coarse) * h_coarse))
    target = Restriction(fine, coarse).apply(h_fine, h_coarse)
    changed = h_coarse != 1e9
    assert changed.any()
    moved = float(np.sum((lumped_volumes(coarse) * h_coarse)[changed]))
    assert moved == pytest.approx(target, rel=1e-12)
    assert float(np.sum(lumped_volumes(coarse) * h_coarse)) - total_before == pytest.approx(
        target - 1e9 * float(np.sum(lumped_volumes(coarse)[changed])), rel=1e-9)
    # the restricted field is the fine one, not merely its energy
    centre = (np.argmin(abs(coarse.ys - 0.0)), -1, np.argmin(abs(coarse.xs - 50e-6)))
    assert h_coarse[centre] > 4e9


def test_restrict_keeps_a_track_edge():
    """Sideways the coarse nodes take the fine field's values, shifted alike for the energy: a field that
    steps in y (a track's edge in the powder layer) keeps its step, not smeared over a coarse element."""
    fine = Grid(np.linspace(-0.5e-3, 0.5e-3, 41), np.linspace(-0.5e-3, 0.5e-3, 41), np.linspace(-0.2e-3, 0.0, 9))
    coarse = Grid(np.linspace(-1e-3, 1e-3, 41), np.linspace(-1e-3, 1e-3, 41), np.linspace(-0.4e-3, 0.0, 9))
    h_fine = np.broadcast_to(np.where(fine.ys < 0.0, 6e9, 1e9)[:, None, None], fine.solver_shape).copy()
    h_coarse = np.full(coarse.solver_shape, 1e9)
    Restriction(fine, coarse).apply(h_fine, h_coarse)
    sy, sz, sx = slaved(fine, coarse)
    shift = h_coarse[sy, sz, sx] - interpolate(fine, h_fine, coarse.xs[sx], coarse.ys[sy], coarse.zs[sz])
    assert np.ptp(shift) < 1e-9 * 5e9


def test_prolong_keeps_shared_nodes_and_conserves_energy():
    coarse = Grid(np.linspace(-2e-3, 2e-3, 41), np.linspace(-2e-3, 2e-3, 41), np.linspace(-1e-3, 0.0, 11))
    h_coarse = field(coarse, np.array([0.0, 0.0]))
    old = Grid(np.linspace(-0.6e-3, 0.6e-3, 49), np.linspace(-0.6e-3, 0.6e-3, 49), np.linspace(-0.4e-3, 0.0, 17))
    h_old = field(old, np.array([0.1e-3, 0.0])) * 1.05
    new = Grid(old.xs + 0.3e-3, old.ys, old.zs)
    h_new = prolong(coarse, h_coarse, old, h_old, new)
    np.testing.assert_array_equal(h_new[:, :, :-12], h_old[:, :, 12:])       # shared nodes keep their values
    lap = ((new.xs[0], old.xs[-1]), extent(old)[1], extent(old)[2])
    expected = (region_energy(old, h_old, lap) + region_energy(coarse, h_coarse, extent(new))
                - region_energy(coarse, h_coarse, lap))
    assert float(np.sum(lumped_volumes(new) * h_new)) == pytest.approx(expected, rel=1e-12)


def model(settings: Settings, plan: ScanPlan) -> MultiLevelModel:
    return MultiLevelModel(replace(settings, mesh="multilevel"), plan)


def test_fine_box_does_not_grow_with_the_part():
    s = replace(Settings(**COARSE), mesh="multilevel", fine_box_m=1.2e-3, fine_box_depth_m=0.5e-3, mid_box_m=2.4e-3,
                mid_h_m=100e-6, coarse_h_m=400e-6)
    small, large = (MultiLevelModel(s, ScanPlan.layer(round(side / 1e-4), side, 1e-4)) for side in (4e-3, 16e-3))
    assert small.grid.n_nodes == large.grid.n_nodes
    assert small.mid.grid.n_nodes == large.mid.grid.n_nodes
    assert large.part.grid.n_nodes > 5 * small.part.grid.n_nodes       # the part level is the part
    assert large.node_updates_per_step < 1.3 * small.node_updates_per_step
    check_grid_size(s, ScanPlan.layer(400, 40e-3, 1e-4))      # 40 mm: fine under the node cap


@pytest.fixture(scope="module")
def powder_runs():
    """A 3-track powder layer, multi-level and uniform, 3 mm tracks (the fine box moves along them)."""
    s = Settings(**COARSE, powder_layer_m=50e-6, fine_box_m=1.6e-3, mid_box_m=3.2e-3, mid_h_m=100e-6,
                 coarse_h_m=300e-6)
    plan = ScanPlan.layer(3, 3e-3, 1e-4)
    ml, un = model(s, plan), ThermalModel(s, plan)
    areas, held = [], None
    while not ml.done:
        areas.append((ml.step(150.0, 0.8).area_m2, un.step(150.0, 0.8).area_m2))
        ml.prepare()                                    # the due levels step now, as in the lockstep node
        if held is None and ml.step_index >= 100 and ml._synced["mid"] == ml.step_index:   # the mid level just stepped
            again = ml.mid.h.copy()
            Restriction(ml.grid, ml.mid.grid).apply(ml._h, again)
            held = float(np.max(np.abs(ml.law.temperature(ml.mid.h) - ml.law.temperature(again))))
    return ml, un, np.array(areas), held


def test_moves_carry_consolidation(powder_runs):
    ml, un, _, _ = powder_runs
    assert ml.n_remeshes > 5
    share = ml._lattice.fraction(ml.grid.xs, ml.grid.ys)[:, 0, :]
    assert share.max() == 1.0
    ex, ey = (np.diff(e) for e in ml._lattice.edges)
    area_lattice = float(np.sum(ml._lattice.melted[:, 0, :] * ey[:, None] * ex[None, :]))
    area_uniform = float(np.sum(un.powder.consolidated[:, 0, :] * np.diff(un.grid.ys)[:, None]
                                * np.diff(un.grid.xs)[None, :]))
    assert area_lattice == pytest.approx(area_uniform, rel=0.1)
    np.testing.assert_array_equal(ml.powder.consolidated[:, 0, :], share >= 1.0 - 1e-9)


def test_coarse_elements_conduct_their_rows_side_by_side_and_in_series():
    """An element over dense metal and a powder row (weight 0.02, half consolidated): in plane the
    thickness-weighted mean, vertically the harmonic one (the powder insulates the surface)."""
    row_m, kw_powder = 25e-6, 0.02
    share = np.full((1, 2, 1), 0.0)
    share[0, 0, 0] = 0.5                                   # the first powder row half consolidated
    zs = np.array([-100e-6, -25e-6, 25e-6, 50e-6])          # dense; 25 µm dense + row 0; row 1
    in_plane, vertical = column_weights(zs, (1, 1), row_m, kw_powder, share)
    row0 = kw_powder + 0.5 * (1 - kw_powder)
    np.testing.assert_allclose(in_plane[0, :, 0], [1.0, 0.5 + 0.5 * row0, kw_powder], rtol=1e-14)
    np.testing.assert_allclose(vertical[0, :, 0], [1.0, 1.0 / (0.5 + 0.5 / row0), kw_powder], rtol=1e-14)
    assert vertical[0, 0, 0] == 1.0 and vertical[0, 2, 0] == kw_powder       # one row: its weight exactly


def stale_weights(ml: MultiLevelModel, level, finer: Grid) -> tuple[int, int]:
    """Elements of a coarser level outside the nodes its finer level overwrites (those with a free
    node) whose conductivity weight differs from the consolidation's, and those consolidated."""
    expected, expected_z = ml._level_kw(level.grid)
    free = np.ones(expected.shape, dtype=bool)
    sy, sz, sx = slaved(finer, level.grid)
    free[sy.start:sy.stop - 1, sz.start:sz.stop - 1, sx.start:sx.stop - 1] = False
    stale = (level.operator.kw[free] != expected[free]) | (level.operator.kw_z[free] != expected_z[free])
    return int(np.count_nonzero(stale)), int(np.count_nonzero(expected[free] > expected.min()))


def test_coarser_levels_conduct_through_the_consolidated_tracks():
    """When the coarser levels are brought up to now, their weights outside the finer box are the
    consolidation's (they are updated only after a finer box moves: the powder consolidates inside
    the fine box alone)."""
    s = Settings(**COARSE, powder_layer_m=50e-6, fine_box_m=1.6e-3, mid_box_m=3.2e-3, mid_h_m=100e-6,
                 coarse_h_m=300e-6)
    ml = model(s, ScanPlan.layer(2, 6e-3, 1e-4))
    consolidated = {"mid": 0, "part": 0}
    while not ml.done:
        ml.step(150.0, 0.8)
        if ml.step_index % 10 == 0:
            ml.sync("part")
            for name, level, finer in (("mid", ml.mid, ml.grid), ("part", ml.part, ml.mid.grid)):
                stale, n = stale_weights(ml, level, finer)
                assert stale == 0, (name, ml.step_index)
                consolidated[name] += n > 0
    assert consolidated["mid"] > 10 and consolidated["part"] > 10


def test_multilevel_follows_the_uniform_mesh(powder_runs):
    ml, _, areas, _ = powder_runs
    a_ml, a_un = areas[10:, 0], areas[10:, 1]
    rms = np.sqrt(np.mean((a_ml - a_un) ** 2)) / a_un.mean()
    assert rms < 0.02, rms          # 1.07 % measured
    assert abs(ml.initial_observation().energy_error_pct) < 1e-6


def test_plant_model_picks_the_mesh():
    plan = ScanPlan.single(1e-3)
    assert type(plant_model(Settings(**COARSE), plan)) is ThermalModel
    assert type(plant_model(Settings(**COARSE, mesh="multilevel", mid_h_m=100e-6, coarse_h_m=400e-6), plan)) \
        is MultiLevelModel
    with pytest.raises(ValueError, match="plant_model"):
        ThermalModel(Settings(**COARSE, mesh="multilevel", mid_h_m=100e-6, coarse_h_m=400e-6), plan)
    with pytest.raises(ValueError, match="mesh must be one of"):
        Settings(mesh="adaptive")


def test_intermediate_level_holds_the_fine_field(powder_runs):
    ml, _, _, held = powder_runs
    assert held is not None
    assert held < 1e-6          # K: inside the fine box, the intermediate level is the fine field restricted


@pytest.fixture(scope="module")
def layered_runs():
    """Four 50 µm layers of a 3-track plan (1.5 mm tracks), multi-level and uniform, 150 W."""
    s = Settings(**COARSE, powder_layer_m=50e-6, n_layers=4, fine_box_m=1.0e-3, mid_box_m=2.4e-3,
                 mid_h_m=100e-6, coarse_h_m=300e-6)
    plan = ScanPlan.layer(3, 1.5e-3, 1e-4)
    ml, un = model(s, plan), ThermalModel(s, plan)
    rows, starts = [], []
    while not ml.done:
        layer = ml.layer
        o_ml, o_un = ml.step(150.0, 0.8), un.step(150.0, 0.8)
        if ml.layer != layer or ml.step_index == 1:
            rows.append(len(ml.grid.zs))
            starts.append((o_ml.t_ahead_k, o_un.t_ahead_k))
    return ml, un, rows, np.array(starts)


def test_box_heights_do_not_grow_with_the_build():
    """The fine box's rows at layer 0, 5 and 20: the layers within fine_depth_m keep a row each,
    deeper ones merge (the uniform grid gains a row of elements per layer)."""
    s = Settings(**COARSE, powder_layer_m=50e-6, n_layers=21, fine_box_m=1.0e-3, mid_box_m=2.4e-3,
                 mid_h_m=100e-6, coarse_h_m=300e-6)
    ml = model(s, ScanPlan.layer(3, 1.5e-3, 1e-4))
    rows = []
    for layer in (0, 5, 20):
        ml.layer = layer
        zs, z_bed = ml._box_heights()
        rows.append(len(zs))
        assert zs[-1] == pytest.approx((layer + 1) * s.powder_layer_m)
        assert zs[-1] - zs[0] == pytest.approx(s.fine_box_depth_m, abs=s.h_max_m)
        single = np.diff(zs[zs >= zs[-1] - s.fine_depth_m - 1e-12])
        np.testing.assert_allclose(single, s.powder_layer_m)             # one row per layer near the top
        if layer == 20:
            assert np.diff(zs)[0] > 1.5 * s.powder_layer_m                  # buried layers merged
    assert max(rows) - min(rows) <= 1


@pytest.mark.slow
def test_buried_layers_coarsen(layered_runs):
    ml, un, rows, _ = layered_runs
    assert ml.layer == un.layer == 3
    assert len(un.grid.zs) - rows[0] >= 3                  # the uniform grid gains a row per layer
    assert max(rows) - min(rows) <= 1                      # the fine box does not
    assert ml.grid.zs[-1] == pytest.approx(un.grid.zs[-1])
    assert ml.part.grid.zs[-1] == pytest.approx(un.grid.zs[-1])


@pytest.mark.slow
def test_layer_starts_follow_the_uniform_mesh(layered_runs):
    _, _, _, starts = layered_runs
    rise_ml, rise_un = starts[:, 0] - 300.0, starts[:, 1] - 300.0
    np.testing.assert_allclose(rise_ml, rise_un, rtol=0.05)


@pytest.mark.parametrize("layers", [dict(), dict(powder_layer_m=50e-6, n_layers=2),
                                    dict(powder_layer_m=50e-6, n_layers=2, dwell_s=0.05)],
                         ids=["plate", "2 layers", "2 layers, dwell"])
def test_levels_keep_the_absorbed_energy(layers):
    """No losses: the part level's energy grows by what the fine level absorbed plus the powder spread
    at the preheat state, to round-off (the levels hand on the heat the finer one sends out of the
    nodes they overwrite; a changed finer grid moves no energy)."""
    s = Settings(**COARSE, h_conv_w_m2k=0.0, emissivity=0.0, mesh="multilevel", fine_box_m=1.0e-3,
                 mid_box_m=2.4e-3, mid_h_m=100e-6, coarse_h_m=300e-6, **layers)
    ml = MultiLevelModel(s, ScanPlan.layer(3, 1.5e-3, 1e-4))
    e0, g = ml.part.energy(), ml.part.grid
    powder_j = ml._h_ref * (g.xs[-1] - g.xs[0]) * (g.ys[-1] - g.ys[0]) * s.powder_layer_m
    while not ml.done:
        ml.step(150.0, 0.8)
    ml.sync("part")                        # every level takes its finer one's state now
    assert ml.n_remeshes > 5
    assert ml.part.energy() - e0 - ml.layer * powder_j == pytest.approx(ml._absorbed, rel=1e-9)


def test_dwell_cools_as_on_the_uniform_mesh():
    """A 0.5 s recoating dwell with the plate's losses between two layers: the second layer starts
    from the same surface temperatures as on the uniform mesh, and the heat lost (the levels' and
    the plate's) is the uniform mesh's."""
    s = Settings(**COARSE, powder_layer_m=50e-6, n_layers=2, dwell_s=0.5, plate_h_w_m2k=1e3, fine_box_m=1.0e-3,
                 mid_box_m=2.4e-3, mid_h_m=100e-6, coarse_h_m=300e-6)
    plan = ScanPlan.layer(3, 1.5e-3, 1e-4)
    ml, un = model(s, plan), ThermalModel(s, plan)
    while ml.layer == 0:
        ml.step(150.0, 0.8), un.step(150.0, 0.8)
    g = ml.part.grid
    x, y = np.meshgrid(np.linspace(0.0, 1.5e-3, 7), np.linspace(-0.2e-3, 0.2e-3, 5))
    points = np.column_stack([x.ravel(), y.ravel(), np.full(x.size, g.zs[-1])])
    rise_ml, rise_un = (m.temperature_at(points) - s.t0_k for m in (ml, un))
    assert rise_un.mean() > 20.0                                   # still warm after the dwell
    np.testing.assert_allclose(rise_ml.mean(), rise_un.mean(), rtol=0.03)
    lost_ml = ml._lost + ml.mid.lost_j + ml.part.lost_j
    assert lost_ml == pytest.approx(un._lost, rel=0.035)
    assert not ml._a_bottom.any()          # the fine box's bottom face is held: the plate is the levels'


def test_part_level_resolves_the_surface(powder_runs):
    ml = powder_runs[0]          # the part level's top elements as thin as the intermediate level's
    assert np.diff(ml.part.grid.zs)[-2:] == pytest.approx([ml.settings.mid_h_m] * 2)


def test_a_jump_farther_than_the_box_keeps_the_laser_on_the_grid():
    """Two tracks 3 mm apart (a contour's end to a hatch's start): the box follows the jump, the
    laser never leaves the grid for a whole step, and what fell outside is counted."""
    s = Settings(**COARSE, mesh="multilevel", fine_box_m=1.0e-3, mid_box_m=2.4e-3, mid_h_m=100e-6,
                 coarse_h_m=300e-6)
    plan = ScanPlan(tracks=(((0.0, 0.0), (1.01e-3, 0.0)), ((1e-3, 3e-3), (0.0, 3e-3))))   # the jump 1/4 into a step
    ml = MultiLevelModel(s, plan)
    areas = []
    while not ml.done:
        obs = ml.step(150.0, 0.8)
        assert np.isfinite(obs.area_m2) and np.isfinite(obs.energy_absorbed_j)
        areas.append(obs.area_m2)
    assert 0 < ml.laser_outside_j < 0.5 * 150.0 * s.dt_s    # the smaller side of the jump's step
    assert min(areas[-5:]) > 0.5 * max(areas)           # the second track melts as the first


def test_thin_wall_with_a_dwell_stays_above_ambient():
    """Three layers of a 2 mm wall on the default plant with a 1 s dwell: the part level's flat top
    elements under the tracks' heat stay monotone (nodal stiffness), so no node of it falls 10 K
    below the preheat and the dwell's implicit steps, which refuse a step that undershoots, go
    through (with the exact trilinear stiffness: 100 K undershoot, the dwell fails)."""
    sc = scenario("layer", n_tracks=1, track_length_m=2e-3, n_layers=3, mesh="multilevel", dwell_s=1.0)
    ml = MultiLevelModel(sc.settings, sc.plan, sc.layer_plans)
    coldest = np.inf
    while not ml.done:
        ml.step(*sc.profile.command(ml.step_index))
        coldest = min(coldest, float(ml.law.temperature(ml.part.h.min())))
    assert ml.layer == 2
    assert coldest > sc.settings.t0_k - 10.0


def test_the_fine_operator_moves_with_the_box(monkeypatch):
    """Along a track the fine box moves by whole cells: its operator is moved (factors reused,
    changed weights re-weighted), not assembled again at each move; it is assembled at the start
    and where the box's spacings change (graded near the track's ends)."""
    builds = []
    build = MultiLevelModel._build_operator
    monkeypatch.setattr(MultiLevelModel, "_build_operator", lambda self, *a: builds.append(1) or build(self, *a))
    s = Settings(**COARSE, powder_layer_m=50e-6, fine_box_m=1.6e-3, mid_box_m=3.2e-3, mid_h_m=100e-6,
                 coarse_h_m=300e-6)
    ml = model(s, ScanPlan.layer(1, 4e-3, 1e-4))
    while not ml.done:
        ml.step(150.0, 0.8)
    assert len(builds) <= 4 < ml.n_remeshes - 3


def test_prepare_steps_the_due_levels_ahead_and_changes_nothing(monkeypatch):
    """``prepare`` between two steps (the lockstep node calls it while the command is in flight) steps
    the coarser levels that are due, so none is due when the next step starts; the plant's states and
    fields are bit for bit those of steps alone (which step the due levels first)."""
    s = Settings(**COARSE, powder_layer_m=50e-6, fine_box_m=1.6e-3, mid_box_m=3.2e-3, mid_h_m=100e-6,
                 coarse_h_m=300e-6)
    plan = ScanPlan.layer(2, 3e-3, 1e-4)
    alone, ahead = model(s, plan), model(s, plan)
    synced = []
    sync = MultiLevelModel.sync
    monkeypatch.setattr(MultiLevelModel, "sync", lambda self, name: synced.append(name) or sync(self, name))
    n_prepared = 0
    while not alone.done:
        obs_alone = alone.step(150.0, 0.8)
        synced.clear()
        ahead.prepare()
        n_prepared += len(synced)
        assert all(ahead.step_index - ahead._synced[name] < every
                   for name, every in (("mid", ahead.mid_every), ("part", ahead.part_every)))
        assert ahead.step(150.0, 0.8) == obs_alone
    assert n_prepared >= ahead.step_index // ahead.mid_every - ahead.n_remeshes   # (a move steps "mid" itself)
    for a, b in ((alone._h, ahead._h), (alone.mid.h, ahead.mid.h), (alone.part.h, ahead.part.h)):
        assert np.array_equal(a, b)


def test_a_box_that_holds_the_plan_stays_on_it_and_a_wall_matches_the_uniform_mesh():
    """A two-track wall whose whole-plan band fits in the fine box: the box is centred on the band and
    never moves (nor at the jumps between tracks), so the heat of the earlier layers stays on the fine
    level, and the mean melt-pool area of each of six layers (no dwell) is the uniform mesh's within
    0.5 % (2.0 % off with a box that follows the laser). A plan wider than the box keeps a moving box."""
    s = Settings(**COARSE, powder_layer_m=50e-6, n_layers=6, fine_box_m=1.6e-3, mid_box_m=3.2e-3,
                 mid_h_m=100e-6, coarse_h_m=300e-6)
    plan = ScanPlan.layer(2, 1.2e-3, 1e-4)
    areas = {}
    for mesh in ("uniform", "multilevel"):
        m = plant_model(replace(s, mesh=mesh), plan, (plan,) * s.n_layers)
        per_layer = [[] for _ in range(s.n_layers)]
        while not m.done:
            layer = m.layer + (m.layer_done and m.step_index > 0)
            per_layer[layer].append(m.step(200.0, 0.8).area_m2)
        areas[mesh] = np.array([np.mean(a[2:]) for a in per_layer])
    assert areas["uniform"][-1] > 1.2 * areas["uniform"][0]                # the wall heats up
    np.testing.assert_allclose(areas["multilevel"], areas["uniform"], rtol=0.005)
    assert m.n_remeshes == 0 and m.fixed_centre == pytest.approx([0.6e-3, 0.0])
    wider = ScanPlan.layer(1, 2e-3, 1e-4)
    assert MultiLevelModel(replace(s, mesh="multilevel", n_layers=1), wider).fixed_centre is None
