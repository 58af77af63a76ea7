"""The ``part`` scenario: an STL sliced and hatched by PySLM drives a layer-by-layer build."""
import importlib.util
import subprocess
import sys

import numpy as np
import pytest

from fe_node.part import EXAMPLE_STL, part_plans
from fe_node.scenarios import PART_DWELL_S, scenario
from fe_node.scene import laser_pose, part_model, scene_update
from fe_node.solver import ThermalModel
from messages import decode, encode
from messages.topics import PLANT_LASER, PLANT_SCENE
from tests.conftest import REPO
from tests.plants import BARE, BARE_ARGS

pytestmark = pytest.mark.skipif(importlib.util.find_spec("pyslm") is None, reason="needs PySLM (the [part] extra)")
"""Skipped without PySLM, found without importing it (its import costs each collecting worker 0.7 s)."""

BLOCK_STL = EXAMPLE_STL.parent / "block_5mm.stl"
"""The shipped 5 x 5 x 1.5 mm block (the 50-layer build)."""


def test_example_part_slices_into_ten_hatched_layers():
    plans = part_plans(EXAMPLE_STL, 50e-6, 100e-6, hatch_rotation_deg=0.0, contours=False)   # hatch along x only
    assert len(plans) == 10
    for plan in plans:
        ends = np.array([p for track in plan.tracks for p in track])
        assert np.all(np.hypot(*ends.T) <= 0.75e-3 + 2e-6)               # inside the 1.5 mm cylinder (48-gon)
        ys = np.array([t[0][1] for t in plan.tracks])
        assert np.allclose(np.diff(ys), 100e-6, atol=1e-8)               # hatch distance
        assert len(plan.tracks) == 15 and plan.total_length == pytest.approx(17.6e-3, rel=0.01)


def test_shipped_block_builds_50_layers_of_5_by_5_mm_contoured_and_turning_67_degrees():
    """The default plant on ``--part fe_node/parts/block_5mm.stl --layers 50``: 25 µm layers, each a contour
    around the 5 mm square, then a hatch turned by 67° from the layer below's (the part defaults)."""
    sc = scenario("part", part_stl=str(BLOCK_STL), n_layers=50)
    assert sc.settings.powder_layer_m == 25e-6 and len(sc.layer_plans) == 50
    angles_deg = []
    for plan in sc.layer_plans[:3]:
        tracks = np.array(plan.tracks)
        closes = next(k for k, t in enumerate(tracks) if np.array_equal(t[1], tracks[0, 0]))   # the contour's end
        contour, hatch = tracks[:closes + 1], tracks[closes + 1:]
        assert np.hypot(*(contour[:, 1] - contour[:, 0]).T).sum() == pytest.approx(20e-3, rel=1e-3)
        assert contour.min(axis=(0, 1)) == pytest.approx([-2.5e-3] * 2, abs=2e-6)
        assert contour.max(axis=(0, 1)) == pytest.approx([2.5e-3] * 2, abs=2e-6)
        assert np.all(np.abs(hatch) <= 2.5e-3 - 40e-6)                          # inset half a hatch
        d = hatch[:, 1] - hatch[:, 0]
        along = np.degrees(np.arctan2(d[:, 1], d[:, 0])) % 180.0
        assert np.ptp(along) < 0.05 or np.ptp((along + 90.0) % 180.0) < 0.05     # one direction (0° ~ 180°)
        angles_deg.append(along[0])
    assert np.diff(angles_deg) % 180.0 == pytest.approx([67.0, 67.0], abs=0.05)


def test_shipped_l_bracket_is_hatched_inside_its_l():
    """``fe_node/parts/l_bracket_3mm.stl``: 20 layers of 25 µm; each layer's contour is the L (3 × 3 mm, 1.2 mm
    arms: 12 mm around) and no hatch point lies in the square the L leaves out."""
    sc = scenario("part", part_stl=str(BLOCK_STL.parent / "l_bracket_3mm.stl"))
    assert len(sc.layer_plans) == 20
    for plan in sc.layer_plans[:2]:
        tracks = np.array(plan.tracks)
        closes = next(k for k, t in enumerate(tracks) if np.array_equal(t[1], tracks[0, 0]))
        contour, hatch = tracks[:closes + 1], tracks[closes + 1:]
        assert np.hypot(*(contour[:, 1] - contour[:, 0]).T).sum() == pytest.approx(12e-3, rel=1e-3)
        points = hatch.reshape(-1, 2) + 1.5e-3                     # back to the STL's frame (centred on its box)
        assert np.all(points >= -1e-6) and np.all(points <= 3e-3 + 1e-6)
        assert not np.any((points[:, 0] > 1.2e-3 + 1e-6) & (points[:, 1] > 1.2e-3 + 1e-6))   # the cut-out square


def test_part_scenario_builds_layer_by_layer():
    sc = scenario("part", preset=BARE, n_layers=2, hatch_m=0.6e-3, h_fine_m=50e-6, powder_layer_m=50e-6,
                  mesh="uniform", dwell_s=5e-3)  # a short dwell: the dwell has tests of its own
    assert sc.settings.n_layers == 2 and len(sc.layer_plans) == 2 and sc.plan == sc.layer_plans[0]
    model = ThermalModel(sc.settings, sc.plan, sc.layer_plans)
    layers, scenes = set(), {}
    while not model.done:
        obs = model.step(*sc.profile.command(model.step_index))
        layers.add(model.layer)
        if obs.layer not in scenes:      # what the plant node publishes on /plant/scene
            scenes[obs.layer] = decode(PLANT_SCENE, encode(scene_update(model.plan, obs, sc.part_stl)))
        pose = laser_pose(obs).pose
        assert (pose.position.x, pose.position.y, pose.position.z) == (obs.x_m, obs.y_m, obs.z_top_m)
    assert layers == {0, 1} and model.grid.zs[-1] == pytest.approx(100e-6)
    for layer, scene in scenes.items():       # the tracks lie on that layer's top, the part is there
        assert [e.id for e in scene.entities] == ["scan_plan", "part"]
        points = scene.entities[0].lines[0].points
        assert len(points) == 2 * len(sc.layer_plans[layer].tracks)
        assert [p.z for p in points] == pytest.approx([50e-6 * (layer + 1)] * len(points))
    assert abs(obs.energy_error_pct) < 1e-6 and model.powder.consolidated.sum() > 0


def test_a_part_cools_for_a_recoating_time_between_layers_unless_the_plant_sets_another():
    assert PART_DWELL_S == 10.0 and scenario("part", n_layers=1).settings.dwell_s == PART_DWELL_S
    assert scenario("ident-part", n_layers=1).settings.dwell_s == PART_DWELL_S
    assert scenario("part", n_layers=1, dwell_s=0.0).settings.dwell_s == 0.0
    assert scenario("layer").settings.dwell_s == 0.0          # the plate's layer: one layer, nothing to wait for


def test_part_scenario_errors():
    with pytest.raises(ValueError, match=r"n_layers must be in \[1, 20\]"):   # 25 µm layers of the default plant
        scenario("part", n_layers=21)
    with pytest.raises(ValueError, match=r"n_layers must be in \[1, 10\]"):   # 50 µm layers of the bare plate
        scenario("part", preset=BARE, n_layers=11)
    with pytest.raises(ValueError, match="no STL"):
        scenario("part", part_stl="/nonexistent.stl")
    with pytest.raises(ValueError, match="unknown scenario override"):
        scenario("part", bogus=1)
    with pytest.raises(ValueError, match=r"window_m = 0.002 needs mesh = 'uniform' \(a part's default mesh is 'multi"):
        scenario("part", window_m=2e-3)
    assert scenario("part", n_layers=1, window_m=2e-3, mesh="uniform").settings.window_m == 2e-3


def test_part_model_sits_where_its_scan_paths_are():
    import trimesh

    model = part_model(EXAMPLE_STL)
    assert model.media_type == "model/stl" and model.data == EXAMPLE_STL.read_bytes()
    lo, hi = trimesh.load(EXAMPLE_STL, file_type="stl").bounds * model.scale.x + np.array(
        [model.pose.position.x, model.pose.position.y, model.pose.position.z])
    assert lo[2] == pytest.approx(0.0, abs=1e-12) and hi[2] == pytest.approx(0.5e-3)
    ends = np.array([p for plan in part_plans(EXAMPLE_STL, 50e-6, 100e-6) for t in plan.tracks for p in t])
    assert np.all(ends >= lo[:2] - 2e-6) and np.all(ends <= hi[:2] + 2e-6)   # contours: PySLM's section, ~1 µm out
    assert (lo[:2] + hi[:2]) == pytest.approx([0.0, 0.0], abs=1e-12)


def test_laser_pose_heads_along_the_scan_direction():
    sc = scenario("double-track", preset=BARE, h_fine_m=40e-6)
    model = ThermalModel(sc.settings, sc.plan)
    obs = model.step(250.0, 0.8)
    assert decode(PLANT_LASER, encode(laser_pose(obs))).pose.orientation.w == pytest.approx(1.0)   # +x
    while obs.track == 0:
        obs = model.step(250.0, 0.8)
    q = laser_pose(obs).pose.orientation                                                            # -x: pi about z
    assert obs.direction[0] == -1.0 and (q.z, q.w) == (pytest.approx(1.0), pytest.approx(0.0, abs=1e-12))


def test_launch_builds_a_part_and_shows_it(tmp_path):
    """``launch.py --scenario part --part STL --layers N``: the plant builds it, the recording holds the scene."""
    from messages.recording import read_messages
    from tests import forked_cli
    from tests.test_end_to_end import run_launch

    out = tmp_path / "part.mcap"
    status, output = run_launch("--scenario", "part", "--part", str(EXAMPLE_STL), "--layers", "3", "--max-steps",
                                "20", "--h-um", "40", *BARE_ARGS, "--controller", "none", "--out", str(out))
    assert status == 0, output
    config = next(e for e in read_messages(out, "/run/events") if e.node == "plant" and e.event == "start")
    assert '"n_layers": 3' in config.config_json
    scene = next(iter(read_messages(out, "/plant/scene")))
    assert [e.id for e in scene.entities] == ["scan_plan", "part"] and scene.entities[1].models[0].data[:5] == b"\0" * 5
    refused = forked_cli.run("launch.py", "--scenario", "part", "--layers", "21")   # the default plant: 25 µm layers
    assert refused.returncode == 2 and refused.stdout == "" and refused.stderr.strip() == (
        "python launch.py: error: scenario part: n_layers must be in [1, 20] for this part, got 21")


@pytest.mark.parametrize("content", [b"", b"solid x\nendsolid x\n", bytes(range(256)) * 12],
                         ids=["empty", "no facets", "binary noise"])
def test_a_file_that_is_no_stl_mesh_is_refused_in_one_line(tmp_path, content):
    stl = tmp_path / "bad.stl"
    stl.write_bytes(content)
    with pytest.raises(ValueError, match=r"^scenario part: cannot read .*bad\.stl' as an STL mesh \(") as err:
        scenario("part", part_stl=str(stl))
    assert "\n" not in str(err.value)


def test_a_flat_mesh_is_refused_as_no_solid(tmp_path):
    stl = tmp_path / "flat.stl"
    stl.write_text("solid x\nfacet normal 0 0 1\nouter loop\nvertex 0 0 0\nvertex 1 0 0\nvertex 0 1 0\nendloop\n"
                   "endfacet\nendsolid x\n")
    with pytest.raises(ValueError, match=r"flat\.stl' holds no solid \(bounding box 0\.\.1 x 0\.\.1 x 0\.\.0 mm\)"):
        scenario("part", part_stl=str(stl))


def test_launch_refuses_a_part_file_that_is_not_an_stl():
    from tests import forked_cli

    run = forked_cli.run("launch.py", "--scenario", "part", "--part", "README.md")
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert "cannot read 'README.md' as an STL mesh" in run.stderr


def test_slicing_a_part_leaves_the_root_logger_as_it_was():
    """PySLM's module-level ``logging.info`` calls ``logging.basicConfig``: without the guard every later INFO
    record of any library (Dask's scheduler in ``learn --scenario part``) would print."""
    code = ("import logging; from fe_node.scenarios import scenario; scenario('part', n_layers=1); "
            "print(len(logging.getLogger().handlers))")   # in a fresh process: pytest gives the root logger handlers
    out = subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0 and out.stdout.strip() == "0", out.stdout + out.stderr

