"""The ``part`` scenario: an STL sliced and hatched by PySLM drives a layer-by-layer build."""
import numpy as np
import pytest

from fe_node.part import EXAMPLE_STL, part_plans
from fe_node.scenarios import scenario
from fe_node.solver import ThermalModel

pytest.importorskip("pyslm")


def test_example_part_slices_into_ten_hatched_layers():
    plans = part_plans(EXAMPLE_STL, 50e-6, 100e-6)
    assert len(plans) == 10
    for plan in plans:
        ends = np.array([p for track in plan.tracks for p in track])
        assert np.all(np.hypot(*ends.T) <= 0.75e-3 + 2e-6)               # inside the 1.5 mm cylinder (48-gon)
        ys = np.array([t[0][1] for t in plan.tracks])
        assert np.allclose(np.diff(ys), 100e-6, atol=1e-8)               # hatch distance
        assert len(plan.tracks) == 15 and plan.total_length == pytest.approx(17.6e-3, rel=0.01)


def test_part_scenario_builds_layer_by_layer():
    sc = scenario("part", n_layers=2, hatch_m=0.3e-3, h_fine_m=40e-6, powder_layer_m=50e-6)
    assert sc.settings.n_layers == 2 and len(sc.layer_plans) == 2 and sc.plan == sc.layer_plans[0]
    model = ThermalModel(sc.settings, sc.plan, sc.layer_plans)
    layers = set()
    while not model.done:
        obs = model.step(*sc.profile.command(model.step_index))
        layers.add(model.layer)
    assert layers == {0, 1} and model.grid.zs[-1] == pytest.approx(100e-6)
    assert abs(obs.energy_error_pct) < 1e-6 and model.powder.consolidated.sum() > 0


def test_part_scenario_errors():
    with pytest.raises(ValueError, match="n_layers"):
        scenario("part", n_layers=11)
    with pytest.raises(ValueError, match="no STL"):
        scenario("part", part_stl="/nonexistent.stl")
    with pytest.raises(ValueError, match="unknown scenario override"):
        scenario("part", bogus=1)
