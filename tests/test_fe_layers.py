"""Layer-by-layer builds on the plant (powder spread on top, plan restarted) and the build-plate sink."""
import numpy as np
import pytest

from fe_node.scan import ScanPlan
from fe_node.settings import Settings
from fe_node.solver import ThermalModel

COARSE = dict(h_fine_m=40e-6, margin_m=0.5e-3, depth_m=0.6e-3, fine_pad_m=120e-6,
              fine_depth_m=120e-6, h_max_m=0.2e-3, powder_layer_m=25e-6)


def build(n_layers, **kw):
    model = ThermalModel(Settings(**{**COARSE, **kw}, n_layers=n_layers), ScanPlan.layer(2, 0.8e-3, 0.1e-3))
    layers = [[] for _ in range(n_layers)]
    while not model.done:
        obs = model.step(250.0, 0.8)
        layers[model.layer].append(obs)
    return model, layers


def test_two_layers_build_up_heat_and_keep_energy():
    model, (first, second) = build(2)
    assert model.layer == 1 and model.grid.zs[-1] == pytest.approx(50e-6)
    cons = model.powder.consolidated.sum(axis=(0, 2))
    assert cons[0] > 20 and cons[1] > 20                       # both layers' tracks consolidated
    a1, a2 = (np.mean([o.area_m2 for o in obs[-5:]]) for obs in (first, second))
    assert a2 > 1.2 * a1                                       # no dwell between layers: heat builds up
    assert max(abs(o.energy_error_pct) for o in first + second) < 1e-6
    bare = ThermalModel(Settings(**{**COARSE, "powder_layer_m": 0.0}), ScanPlan.single(0.2e-3))
    while not bare.done:
        bare.step(100.0, 0.8)
    fresh = ThermalModel(Settings(**COARSE), ScanPlan.single(0.2e-3))
    for not_ready in (bare, fresh):                          # no powder; plan not finished
        with pytest.raises(RuntimeError):
            not_ready.add_layer()
    with pytest.raises(ValueError, match="n_layers"):
        Settings(n_layers=3)


def test_build_plate_sink_removes_heat():
    kw = dict(depth_m=0.25e-3, fine_depth_m=100e-6)
    insulated, obs0 = build(1, **kw)
    cooled, obs1 = build(1, plate_h_w_m2k=1e5, **kw)
    assert cooled.temperature().mean() < insulated.temperature().mean()
    assert obs1[0][-1].energy_lost_j > obs0[0][-1].energy_lost_j
    assert max(abs(o.energy_error_pct) for o in obs1[0]) < 1e-6



def test_the_default_dwell_step_gives_the_field_of_short_steps(monkeypatch):
    """``dwell_step_s`` at its default (1 s) over a 5 s dwell: the second layer starts on the field that
    steps of 0.05 s give, within 0.01 K (a rise of tens of K above ambient), in fewer implicit steps."""
    from fe_node import solver
    from fe_node.dwell import implicit_cooling_step

    steps, fields = {}, {}
    for key, kw in (("default", {}), ("short", {"dwell_step_s": 0.05})):
        model = ThermalModel(Settings(**{**COARSE, **kw}, n_layers=2, dwell_s=5.0), ScanPlan.layer(2, 0.8e-3, 0.1e-3))
        while not model.layer_done:
            model.step(250.0, 0.8)
        calls = []
        monkeypatch.setattr(solver, "implicit_cooling_step", lambda *a, calls=calls, **k: calls.append(1) or
                            implicit_cooling_step(*a, **k))
        model.add_layer()                          # the dwell, then the next layer's powder
        monkeypatch.undo()
        steps[key], fields[key] = len(calls), model.temperature()
    assert Settings().dwell_step_s == 1.0
    assert np.max(fields["short"]) > 320.0
    assert np.max(np.abs(fields["default"] - fields["short"])) < 0.01
    assert 0 < steps["default"] < steps["short"] / 4

def test_dwell_between_layers_cools_implicitly():
    _, (_, no_dwell) = build(2)
    runs = {step: build(2, dwell_s=0.5, dwell_step_s=step, plate_h_w_m2k=1e3) for step in (0.05, 0.01)}
    model, (_, second) = runs[0.05]
    a0, a1 = (np.mean([o.area_m2 for o in obs[-5:]]) for obs in (no_dwell, second))
    assert a1 < 0.9 * a0                                       # the heat of layer 1 has spread
    assert model.temperature().min() > 300.0 - 1e-6            # no undershoot from the implicit steps
    assert max(abs(o.energy_error_pct) for o in second) < 1e-6
    lost = [r[1][1][-1].energy_lost_j for r in runs.values()]
    assert lost[0] == pytest.approx(lost[1], rel=0.02)         # converged in the dwell step


def test_a_dwell_step_that_undershoots_at_the_explicit_step_goes_on_with_the_fallback_operator():
    """``cool``: a step that cools a node below the floor even at the explicit step size is undone and the
    dwell goes on with ``fallback`` (the uniform mesh's corner-rule operator); without one it raises."""
    from fe_node.dwell import EXPLICIT_S, cool

    def undershooting(dt):                      # the trilinear operator on graded elements, say
        h[0, 0, 0] = -5.0
        return 0.0

    def on_corners(dt):                         # an M-matrix step: cools, never below the floor
        h[...] *= 0.5
        return dt

    h = np.ones((2, 2, 2))
    lost = cool(h, 0.1, 1e-3, lambda: None, undershooting, 0.05, lambda x: x, 0.0, fallback=on_corners)
    assert sum(lost) == pytest.approx(0.1 - EXPLICIT_S) and h.min() > 0.0      # every step on the fallback
    h = np.ones((2, 2, 2))
    with pytest.raises(RuntimeError, match="failed at the explicit step size"):
        cool(h, 0.1, 1e-3, lambda: None, undershooting, 0.05, lambda x: x, 0.0)
    assert h.min() == 1.0                                                      # the failed step undone
