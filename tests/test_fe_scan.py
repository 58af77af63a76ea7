"""Scan plans in any direction: rotated hatches and contours from PySLM, read by the plant and the preview."""
import dataclasses

import numpy as np
import pytest

from fe_node.node import preview_fields
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.solver import ThermalModel
from tests.plants import BARE


class XOnlyPlan:
    """The scan plan as it was before tracks could run in any direction (tracks along +-x only)."""

    def __init__(self, plan):
        self.tracks = plan.tracks
        self.lengths = np.array([abs(x1 - x0) for (x0, _), (x1, _) in self.tracks])
        self.total_length = float(self.lengths.sum())

    def bounds(self):
        pts = np.array([p for t in self.tracks for p in t])
        return pts[:, 0].min(), pts[:, 0].max(), pts[:, 1].min(), pts[:, 1].max()

    def preview(self, s):
        k = int(self.locate(s)[0])
        ends = np.cumsum(self.lengths)
        start = ends[k] - self.lengths[k]
        return float(min(s, ends[k]) - start), float(max(ends[k] - s, 0.0)), k + 1 < len(self.tracks)

    def locate(self, s):
        s = np.clip(np.asarray(s, dtype=float), 0.0, self.total_length)
        ends = np.cumsum(self.lengths)
        k = np.minimum(np.searchsorted(ends, s, side="right"), len(self.tracks) - 1)
        starts = np.array([t[0] for t in self.tracks])
        dirs = np.array([[np.sign(t[1][0] - t[0][0]), 0.0] for t in self.tracks])
        return k, starts[k] + (s - (ends - self.lengths)[k])[..., None] * dirs[k], dirs[k]


@pytest.mark.parametrize("plan", [ScanPlan.layer(4, 10e-3, 1e-4), ScanPlan.layer(3, 2e-3, 1.5e-4, False),
                                  ScanPlan.single(5e-3)], ids=["layer", "one-way", "single"])
def test_plans_along_x_locate_and_preview_bit_identically_to_the_x_only_plan(plan):
    old = XOnlyPlan(plan)
    s = np.r_[np.linspace(-1e-3, plan.total_length + 1e-3, 4001), np.cumsum(plan.lengths)]
    assert plan.total_length == old.total_length and plan.bounds() == old.bounds()
    for new_part, old_part in zip(plan.locate(s), old.locate(s)):
        assert np.array_equal(new_part, old_part)
    assert [plan.preview(v) for v in s] == [old.preview(v) for v in s]


def test_double_track_observations_are_bit_identical_to_the_x_only_plan():
    sc = scenario("double-track", preset=BARE, h_fine_m=40e-6)
    runs = []
    for plan in (sc.plan, XOnlyPlan(sc.plan)):
        model = ThermalModel(sc.settings, plan)
        runs.append([model.step(250.0, 0.8) for _ in range(135)])       # past the turn at step 125
    assert runs[0][-1].track == 1 and runs[0][-1].area_m2 > 0
    assert [dataclasses.astuple(o) for o in runs[0]] == [dataclasses.astuple(o) for o in runs[1]]


def test_a_plan_refuses_an_empty_or_non_finite_track():
    with pytest.raises(ValueError, match="track 1 is empty"):
        ScanPlan((((0.0, 0.0), (1e-3, 1e-3)), ((2e-3, 0.0), (2e-3, 0.0))))
    with pytest.raises(ValueError, match="track 0 has a non-finite point"):
        ScanPlan((((0.0, float("nan")), (1e-3, 1e-3)),))


def test_preview_follows_a_path_of_joined_tracks():
    square = (((0.0, 0.0), (1.0, 0.0)), ((1.0, 0.0), (1.0, 1.0)), ((1.0, 1.0), (0.0, 1.0)), ((0.0, 1.0), (0.0, 0.0)))
    plan = ScanPlan(square + (((0.5, 0.2), (0.5, 0.8)),))
    assert plan.angles_deg == pytest.approx([0.0, 90.0, 180.0, -90.0, 90.0])
    assert plan.preview(2.5) == pytest.approx((2.5, 1.5, True))          # on the square: one path of 4 m
    assert plan.preview(4.1) == pytest.approx((0.1, 0.5, False))         # the last line
    k, xy, d = plan.locate(np.array([1.5, 4.3]))
    assert k.tolist() == [1, 4] and np.allclose(xy, [[1.0, 0.5], [0.5, 0.5]]) and np.allclose(d, [[0, 1], [0, 1]])


def _hatch_lines(plan):
    """Indices of the tracks that are a path on their own (hatch lines, not a contour's edges)."""
    starts = np.array([t[0] for t in plan.tracks])
    ends = np.array([t[1] for t in plan.tracks])
    joined = np.r_[False, np.all(starts[1:] == ends[:-1], axis=1)]
    return np.flatnonzero(~joined & ~np.r_[joined[1:], False])


def test_rotated_hatches_turn_by_67_degrees_a_layer_and_cover_the_slice():
    pytest.importorskip("pyslm")
    from fe_node.part import EXAMPLE_STL, part_plans

    plans = part_plans(EXAMPLE_STL, 50e-6, 100e-6)            # the part defaults: 67°, contours
    assert len(plans) == 10
    grid = np.stack(np.meshgrid(np.linspace(-0.8e-3, 0.8e-3, 81), np.linspace(-0.8e-3, 0.8e-3, 81)), -1).reshape(-1, 2)
    inside = grid[np.hypot(*grid.T) < 0.748e-3]                       # the slice: a 48-gon, 1.5 mm across
    for i, plan in enumerate(plans):
        hatch = _hatch_lines(plan)
        assert len(hatch) >= 12
        assert np.mod(plan.angles_deg[hatch], 180.0) == pytest.approx(np.full(len(hatch), (67.0 * i) % 180), abs=0.02)
        a, b = (np.array([plan.tracks[k][j] for k in hatch]) for j in (0, 1))
        normal = np.array([-np.sin(np.radians(67.0 * i)), np.cos(np.radians(67.0 * i))])
        assert np.abs(np.diff(np.sort(a @ normal))) == pytest.approx(np.full(len(hatch) - 1, 100e-6), abs=1e-7)
        assert np.all(np.hypot(*np.r_[a, b].T) <= 0.70e-3 + 1e-6)                # inside the contour's inset
        core = inside[np.hypot(*inside.T) < 0.65e-3]
        assert _distance(core, a, b).max() <= 50e-6 + 1e-6                         # half a hatch from a line
        ends = np.array(plan.tracks)
        assert _distance(inside, ends[:, 0], ends[:, 1]).max() <= 100e-6 / np.sqrt(2) + 1e-6   # or from the contour


def _distance(points, a, b):
    """Distance [m] of each point to the nearest segment ``a[k] -> b[k]``."""
    t = np.clip(np.einsum("pkd,kd->pk", points[:, None] - a, b - a) / np.sum((b - a) ** 2, axis=1), 0, 1)
    return np.min(np.linalg.norm(points[:, None] - a - t[..., None] * (b - a), axis=2), axis=1)


def test_contours_come_first_in_a_layer():
    pytest.importorskip("pyslm")
    from fe_node.part import EXAMPLE_STL, part_plans

    with_contour, without = (part_plans(EXAMPLE_STL, 50e-6, 100e-6, 67.0, flag)[3] for flag in (True, False))
    hatch = _hatch_lines(with_contour)
    n_contour = hatch[0]
    assert n_contour >= 48 and np.array_equal(hatch, np.arange(n_contour, len(with_contour.tracks)))
    loop = np.array([p for t in with_contour.tracks[:n_contour] for p in t])
    assert np.array_equal(loop[0], loop[-1])                                      # a closed path
    assert np.hypot(*loop.T) == pytest.approx(np.full(len(loop), 0.75e-3), abs=0.01e-3)     # on the outline
    assert with_contour.preview(1e-6)[1] == pytest.approx(with_contour.lengths[:n_contour].sum() - 1e-6)
    assert np.array_equal(_hatch_lines(without), np.arange(len(without.tracks)))  # no contour: hatch only


def test_islands_are_a_checkerboard_turned_with_the_layer_and_cover_the_slice():
    pytest.importorskip("pyslm")
    from fe_node.part import EXAMPLE_STL, part_plans

    plans = part_plans(EXAMPLE_STL, 50e-6, 100e-6, island_width_m=0.5e-3)
    grid = np.stack(np.meshgrid(np.linspace(-0.8e-3, 0.8e-3, 81), np.linspace(-0.8e-3, 0.8e-3, 81)), -1).reshape(-1, 2)
    inside = grid[np.hypot(*grid.T) < 0.748e-3]
    for i, plan in enumerate(plans[:4]):
        hatch = _hatch_lines(plan)
        assert hatch[0] >= 48                                                       # the contour first
        turn = np.mod(plan.angles_deg[hatch] - 67.0 * i, 90.0)                      # along the island grid's axes
        assert np.minimum(turn, 90.0 - turn) == pytest.approx(np.zeros(len(hatch)), abs=0.1)   # 10 nm on µm lines
        across = np.mod(plan.angles_deg[hatch] - 67.0 * i, 180.0)
        assert np.any(np.abs(across - 90.0) < 1) and np.any(np.minimum(across, 180 - across) < 1)   # both ways
        assert plan.lengths[hatch].max() <= 0.5e-3 + 1e-7                           # no line leaves its island
        ends = np.array(plan.tracks)
        assert _distance(inside, ends[:, 0], ends[:, 1]).max() <= 75e-6             # the slice covered
    with pytest.raises(ValueError, match="island_width_m must be 0 .no islands. or at least hatch_m"):
        part_plans(EXAMPLE_STL, 50e-6, 100e-6, island_width_m=50e-6)


def test_part_options_are_checked_and_other_scenarios_refuse_them():
    pytest.importorskip("pyslm")
    with pytest.raises(ValueError, match="^scenario override 'hatch_rotation_deg' must be a finite number, got 'x'$"):
        scenario("part", hatch_rotation_deg="x")
    with pytest.raises(ValueError, match="^scenario override 'contours' must be true or false, got 1$"):
        scenario("part", contours=1)
    with pytest.raises(ValueError, match="^scenario override 'island_width_m' must be a finite number, got nan$"):
        scenario("part", island_width_m=float("nan"))
    for key, value in (("hatch_rotation_deg", 67.0), ("contours", True), ("island_width_m", 1e-3)):
        with pytest.raises(ValueError, match=f"unknown scenario override '{key}'"):
            scenario("layer", **{key: value})
    flat = scenario("part", n_layers=2, hatch_rotation_deg=0, contours=False).layer_plans[1]
    assert np.all(np.mod(flat.angles_deg, 180.0) == pytest.approx(0.0, abs=0.02))


def _path_firsts(plan):
    """For each track, the first track of its path (the run of tracks each starting where the last ended)."""
    first = [0]
    for k in range(1, len(plan.tracks)):
        first.append(first[-1] if plan.tracks[k][0] == plan.tracks[k - 1][1] else k)
    return np.array(first)


def test_the_plant_builds_a_rotated_layer_with_energy_conserved_and_a_consistent_preview():
    pytest.importorskip("pyslm")
    sc = scenario("part", preset=BARE, n_layers=2, hatch_m=0.3e-3, h_fine_m=40e-6, window_m=0.6e-3,
                  mesh="uniform", dwell_s=5e-3)  # a short dwell: the rotated layer is what is checked here
    model = ThermalModel(sc.settings, sc.plan, sc.layer_plans)
    v = sc.profile.command(0)[1]
    hatch_seen, contour_steps = set(), 0
    while not model.done:
        obs = model.step(*sc.profile.command(model.step_index))
        if obs.layer == 0:
            continue
        plan, k = model.plan, obs.track
        first = _path_firsts(plan)
        path = np.flatnonzero(first == first[k])
        heading = np.degrees(np.arctan2(obs.direction[1], obs.direction[0]))
        assert heading == pytest.approx(plan.angles_deg[k], abs=1e-9)
        if len(path) == 1:
            hatch_seen.add(k)
            assert np.mod(heading, 180.0) == pytest.approx(67.0, abs=0.02)
        else:
            contour_steps += 1
        on_track = obs.track_travelled_m - plan.lengths[path[0]:k].sum()           # the laser where the preview says
        (x0, y0), (x1, y1) = plan.tracks[k]
        assert np.hypot(obs.x_m - x0, obs.y_m - y0) == pytest.approx(on_track, abs=1e-9)
        assert obs.track_travelled_m + obs.track_remaining_m == pytest.approx(plan.lengths[path].sum(), abs=1e-12)
        preview = preview_fields(obs)
        assert preview["track_remaining_s"] == pytest.approx(obs.track_remaining_m / v)
        assert preview["next_track"] == (path[-1] < len(plan.tracks) - 1)
        for coords, xy in ((model.grid.xs, obs.x_m), (model.grid.ys, obs.y_m)):    # the window follows the laser
            fine = np.flatnonzero(np.diff(coords) <= sc.settings.h_fine_m * (1 + 1e-6))
            assert coords[fine[0]] <= xy <= coords[fine[-1] + 1]
    assert contour_steps > 100 and len(hatch_seen) >= 4 and model.n_remeshes > 2
    assert abs(obs.energy_error_pct) < 1e-6 and obs.next_track is False and obs.area_m2 >= 0
