"""The plant's configuration is refused in one line naming the key, before anything is allocated:
types of scenario overrides and settings, and grids too large to build."""

from __future__ import annotations

import time

import numpy as np
import pytest

from fe_node.grid_size import MAX_GRID_NODES, grid_shape
from fe_node.mesh import graded_axis, graded_axis_size
from fe_node.scan import ScanPlan
from fe_node.scenarios import scenario
from fe_node.solver import build_grid
from tests import forked_cli

BAD_OVERRIDES = [
    ({"n_tracks": "three"}, "'n_tracks' must be an integer, got 'three'"),
    ({"n_tracks": True}, "'n_tracks' must be an integer, got True"),
    ({"n_tracks": 2.5}, "'n_tracks' must be an integer, got 2.5"),
    ({"track_length_m": "x"}, "'track_length_m' must be a finite number"),
    ({"track_length_m": float("inf")}, "'track_length_m' must be a finite number, got inf"),
    ({"hatch_m": [1]}, "'hatch_m' must be a finite number"),
    ({"bidirectional": 3}, "'bidirectional' must be true or false, got 3"),
    ({"power_w": float("nan")}, "'power_w' must be a finite number, got nan"),
    ({"power_w": -1.0}, "'power_w' must be >= 0, got -1.0"),
    ({"speed_m_s": 0.0}, "'speed_m_s' must be > 0, got 0.0"),
    ({"t0_k": "hot"}, "settings: t0_k must be a finite number, got 'hot'"),
    ({"evaporation": 1}, "settings: evaporation must be true or false, got 1"),
    ({"operator": 3}, "settings: operator must be a string, got 3"),
    ({"n_tracks": 100_000, "mesh": "uniform"}, "the FE grid would have"),
    ({"track_length_m": 1e9, "mesh": "uniform"}, "the FE grid would have"),
    ({"track_length_m": 1e9}, "the multi-level mesh would have"),   # the layer's default mesh
    ({"h_fine_m": 5e-5}, "the multi-level mesh needs h_fine_m < mid_h_m < coarse_h_m, got 5e-05, 5e-05, 0.0002: "
                         "raise mid_h_m"),   # (then it names mesh = "uniform", the other way out)
]


@pytest.mark.parametrize("overrides, message", BAD_OVERRIDES, ids=[str(o) for o, _ in BAD_OVERRIDES])
def test_a_bad_override_is_refused_naming_it(overrides, message):
    t0 = time.perf_counter()
    with pytest.raises(ValueError, match="^.*" + message.replace("[", r"\[").replace("(", r"\(")):
        scenario("layer", **overrides)
    assert time.perf_counter() - t0 < 5.0  # counted, not built


def test_numbers_of_the_right_kind_are_accepted():
    sc = scenario("layer", n_tracks=np.int64(3), track_length_m=6e-3, t0_k=400, power_w=np.float64(150.0))
    assert len(sc.plan.tracks) == 3 and sc.settings.t0_k == 400


@pytest.mark.parametrize("name, overrides", [
    ("layer", {}), ("double-track", {}), ("single-track", {}),
    ("layer", {"n_tracks": 3, "track_length_m": 0.006, "hatch_m": 0.00012}),
    ("layer", {"powder_layer_m": 50e-6}), ("layer", {"h_fine_m": 20e-6, "growth": 1.2}),
])
def test_the_counted_grid_is_the_built_one(name, overrides):
    sc = scenario(name, **overrides)
    grid = build_grid(sc.settings, sc.plan, sc.layer_plans)
    assert grid_shape(sc.settings, sc.plan, sc.layer_plans) == (grid.xs.size, grid.ys.size, grid.zs.size)


AXES = [(-1e-3, 2e-3, 0.0, 1e-3, 25e-6, 1.35, 0.3e-3), (0.0, 1e-3, 0.0, 1e-3, 25e-6, 1.35, 0.3e-3),
        (-5e-3, 5e-3, -1e-4, 1e-4, 10e-6, 1.1, 1e-3), (-0.4e-3, 0.0, -0.1e-3, 0.0, 30e-6, 1.4, 2e-4)]


@pytest.mark.parametrize("args", AXES)
def test_graded_axis_size_counts_graded_axis(args):
    assert graded_axis_size(*args) == graded_axis(*args).size


def test_the_largest_plan_under_the_limit_is_accepted_and_the_next_refused():
    base = scenario("layer", mesh="uniform")
    length, hatch = float(base.plan.lengths[0]), abs(base.plan.tracks[1][0][1] - base.plan.tracks[0][0][1])

    def nodes(n_tracks):
        return int(np.prod(grid_shape(base.settings, ScanPlan.layer(n_tracks, length, hatch))))

    under, over = 1, 100_000
    while over - under > 1:                      # nodes() grows with the number of tracks
        mid = (under + over) // 2
        under, over = (mid, over) if nodes(mid) <= MAX_GRID_NODES else (under, mid)
    assert scenario("layer", n_tracks=under, mesh="uniform").plan.tracks
    with pytest.raises(ValueError, match=f"the FE grid would have {nodes(over):,} nodes"):
        scenario("layer", n_tracks=over, mesh="uniform")


@pytest.mark.parametrize("mesh, message", [
    ('mesh = "uniform"\n', "[plant]: the FE grid would have"),
    ("", "[plant]: the scenario's description (100000 tracks) would take"),   # the layer's multi-level mesh
])
def test_launch_refuses_an_oversized_plan_before_starting_a_node(tmp_path, mesh, message):
    """On the uniform mesh the grid is too large; the multi-level mesh holds it, but the plan's
    description would not fit in the plant's start event (the plant would exit at its start)."""
    config = tmp_path / "big.toml"
    config.write_text("[plant]\nn_tracks = 100000\n" + mesh)
    run = forked_cli.run("launch.py", "--config", str(config))
    assert run.returncode == 2 and run.stdout == "", run.stdout
    assert run.stderr.count("\n") == 1 and message in run.stderr, run.stderr


def test_an_array_of_tables_is_refused(tmp_path):
    config = tmp_path / "list.toml"
    config.write_text("[[plant]]\nn_tracks = 2\n")
    run = forked_cli.run("launch.py", "--config", str(config))
    assert run.returncode == 2 and "[plant] must be a table, got list" in run.stderr, run.stderr


def test_the_default_layer_is_on_the_multilevel_mesh_and_the_uniform_one_a_key_away():
    """``layer`` (launch.py's default) is built on the multi-level mesh with its own box
    (:data:`fe_node.scenarios.LAYER_MESH`); ``mesh = "uniform"`` is the reference; the other plate
    scenarios (the identification runs among them) stay on the models' training mesh; a uniform-only
    option without the mesh is refused in one line naming it."""
    from fe_node.scenarios import LAYER_MESH, TRAINING_MESH

    default = scenario("layer").settings
    assert (default.mesh, default.fine_box_m) == ("multilevel", LAYER_MESH["fine_box_m"]) != ("multilevel", 2.4e-3)
    assert scenario("layer", fine_box_m=4e-3).settings.fine_box_m == 4e-3
    assert scenario("layer", mesh="uniform").settings.mesh == "uniform"
    assert {scenario(name).settings.mesh for name in ("double-track", "ident-layer", "single-track")} == {TRAINING_MESH}
    with pytest.raises(ValueError, match=r"^scenario layer: window_m = 0.002 needs mesh = 'uniform' \(the layer "
                                         r"scenario's default mesh is 'multilevel'\)$"):
        scenario("layer", window_m=2e-3)
    assert scenario("layer", window_m=2e-3, mesh="uniform").settings.window_m == 2e-3
