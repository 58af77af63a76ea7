"""Closed-loop regression guard: the shipped preview-MPC models on the FE plant, with thresholds.

The loop runs in process (no zenoh) as the nodes run it: every plant observation becomes the
contract's ``MeltPoolState`` (:func:`fe_node.node.fe_state`) and the controller's
``Measurement`` (:func:`controller_node.node.measurement_from_state`); the controller answers it,
then prepares its next update (the real-time iteration, as the controller node does after every
command), and the plant takes the commanded power and speed for its next step. The controller's
settings are those ``launch.py`` gives it: the defaults under the model's recorded process
(:func:`controller_node.process.process_table`). The metrics are the run report's
(:func:`controller_node.report.metrics`, over the fixed window from 1 ms after laser-on).

In sample, or next to it: each shipped model's identification runs include the double track at and
around the default set point on its plant (the bare plate's and the physical plant's). They guard
against a regression of the model or the law; they say nothing about cases the model never saw.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from controller_node import ControllerSettings, make_controller
from controller_node.node import measurement_from_state
from controller_node.process import process_table
from controller_node.report import Metrics, Trace, metrics
from fe_node.multilevel import plant_model
from fe_node.node import fe_state, n_steps
from fe_node.scenarios import PART_POWER_W, Scenario, scenario
from gp_model.narx import NarxGPModel
from gp_model.shipped import PART_MODEL_PATH, default_model_path
from messages.config import build
from tests.plants import BARE

SETPOINT_MM2 = 0.063


def closed_loop(name: str, preset: str, setpoint_mm2: float = SETPOINT_MM2) -> Metrics:
    """Run ``preview-mpc`` with the shipped model of the plant's layer on scenario ``name`` of plant
    ``preset`` to its end, with the settings of that model's process; its metrics."""
    sc = scenario(name, preset=preset)
    path = default_model_path(sc.settings.powder_layer_m)
    settings = build(ControllerSettings, process_table(path), "[controller]", set_point_m2=setpoint_mm2 * 1e-6)
    return run_preview(sc, path, settings, setpoint_mm2)


def part_closed_loop(n_layers: int) -> Metrics:
    """Run ``preview-mpc`` on the first ``n_layers`` layers of the example part (the ``part`` scenario on its
    multi-level mesh, 10 s between layers) with the part model and the settings ``launch.py --scenario part``
    gives it: the defaults, started from the part's open-loop power; its metrics."""
    sc = scenario("part", n_layers=n_layers)
    settings = ControllerSettings(set_point_m2=SETPOINT_MM2 * 1e-6, nominal_power_w=PART_POWER_W)
    return run_preview(sc, PART_MODEL_PATH, settings, SETPOINT_MM2)


def run_preview(sc: Scenario, path: Path, settings: ControllerSettings, setpoint_mm2: float) -> Metrics:
    """``preview-mpc`` with the model at ``path`` and ``settings`` on the plant of ``sc`` (as ``python -m
    fe_node`` builds it) to the scenario's end; its metrics."""
    plant = plant_model(sc.settings, sc.plan, sc.layer_plans)
    ctrl = make_controller("preview-mpc", settings, NarxGPModel.load(path))
    total = n_steps(sc)
    obs = dataclasses.replace(plant.initial_observation(), speed_m_s=sc.profile.command(0)[1])  # as fe_node
    seen = []
    while True:
        state = fe_state("guard", obs)
        seen.append(state)
        if obs.step >= total or plant.done:
            break
        command, diagnostics = ctrl.update(measurement_from_state(state))
        assert not diagnostics.fallback, (state.step, diagnostics.status)
        ctrl.prepare()
        obs = plant.step(command.power_w, command.speed_m_s)
    trace = Trace(time_s=np.array([s.time_s for s in seen]), area_mm2=np.array([s.area_mm2 for s in seen]),
                  power_w=np.array([s.power_w for s in seen]), t_ahead_k=np.array([s.t_ahead_k for s in seen]),
                  track=np.array([s.track for s in seen]), layer=np.array([s.layer or 0 for s in seen]))
    return metrics(trace, setpoint_mm2)


def test_double_track_holds_the_area():
    """The double track at 0.063 mm² (in sample, 250 steps). Measured: 5.71 / 9.64 / 1.44 % (over / under /
    RMSE); the thresholds are a little above."""
    m = closed_loop("double-track", BARE)
    assert m.overshoot_pct <= 6.0 and m.undershoot_pct <= 10.0 and m.steady_rmse_pct <= 1.5, m


@pytest.mark.slow
def test_default_layer_meets_the_acceptance_figures():
    """The layer at 0.063 mm² (in sample), against the acceptance target ≤ 7 / 10 / 1.5 %
    (over / under / RMSE). Measured: 5.76 / 9.60 / 1.20 %."""
    m = closed_loop("layer", BARE)
    assert m.overshoot_pct <= 7.0 and m.undershoot_pct <= 10.0 and m.steady_rmse_pct <= 1.5, m


def test_double_track_holds_the_area_on_the_physical_plant():
    """The double track at 0.063 mm² on the physical plant with its shipped model (next to in sample: its
    training runs include preview-MPC double tracks at 0.058 and 0.068 mm² and the feed-forward one at
    0.063 mm²). Measured: 6.39 / 12.37 / 3.24 % (over / under / RMSE, turnarounds 5.4 %, along the
    tracks 2.3 %); the thresholds are a little above."""
    m = closed_loop("double-track", "physical")
    assert m.overshoot_pct <= 7.5 and m.undershoot_pct <= 14.0 and m.steady_rmse_pct <= 3.6, m


@pytest.mark.slow
def test_default_layer_on_the_physical_plant():
    """The default layer at 0.063 mm² on the physical plant (in sample: the model's training runs include
    its geometry). Measured: 10.34 / 13.67 / 2.25 % (over / under / RMSE); the model whose turnaround
    feature stopped 64 states after a turn gave 9.85 / 19.38 / 2.66 %. Issue 33's target is 7 / 10 / 2 %;
    the thresholds are a little above what is reached."""
    m = closed_loop("layer", "physical")
    assert m.overshoot_pct <= 11.0 and m.undershoot_pct <= 14.5 and m.steady_rmse_pct <= 2.4, m


def test_first_layer_of_the_example_part():
    """Layer 1 of the example part under the settings ``launch.py --scenario part`` gives (in sample: the part
    model's training runs built the part's first four layers). Measured: 41.55 / 37.29 / 13.65 % (over /
    under / RMSE); with no learning over turnarounds (κ = 0): 47.49 / 46.29 / 15.20 %; with the settings of
    the part preset that was removed (observer gain 1, κ = 0, r = 1): 42.90 / 61.40 / 21.65 %."""
    m = part_closed_loop(1)
    assert m.overshoot_pct <= 45.0 and m.undershoot_pct <= 45.0 and m.steady_rmse_pct <= 15.0, m
