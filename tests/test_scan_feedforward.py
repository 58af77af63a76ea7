"""The scan-plan feed-forward baseline: the preview MPC's schedule, blind to every measurement after
laser-on (area and T ahead), and the preview MPC it is built from is not."""

from __future__ import annotations

import numpy as np
import pytest

from controller_node.registry import make_controller
from controller_node.settings import ControllerSettings
from controller_node.types import Measurement
from gp_model.narx import NarxGPModel
from gp_model.shipped import PLATE_MODEL_PATH

SP = 0.063e-6


@pytest.fixture(scope="module")
def model():
    return NarxGPModel.load(PLATE_MODEL_PATH)


def run(name: str, model, area_scale: float, t_offset_k: float) -> list[float]:
    """Commands [W] of ``name`` over a layer of three 30-state tracks whose measured areas are scaled by
    ``area_scale`` and whose measured T ahead, after the first state, is offset by ``t_offset_k``."""
    ctrl = make_controller(name, ControllerSettings(set_point_m2=SP), model)
    powers, power = [], 0.0
    for k in range(90):
        track = k // 30
        area = area_scale * SP * min(1.0, k / 20) * (1.0 + 0.1 * np.sin(k / 3))
        ctrl_state = Measurement(step=k, time_s=k * 50e-6, area_m2=area,
                                 t_ahead_k=900.0 + 5 * k + (t_offset_k if k else 0.0), power_w=power,
                                 speed_m_s=0.8, track=track, track_elapsed_s=(k % 30) * 50e-6,
                                 track_remaining_s=(29 - k % 30) * 50e-6, next_track=track < 2)
        command, diagnostics = ctrl.update(ctrl_state)
        assert diagnostics.status == "ok", diagnostics.status
        ctrl.prepare()
        power = command.power_w
        powers.append(power)
    return powers


def test_the_schedule_ignores_every_measurement_after_laser_on(model):
    nominal = run("scan-feedforward", model, 1.0, 0.0)
    assert run("scan-feedforward", model, 1.3, 80.0) == nominal
    assert len(set(nominal[25:])) > 10   # it schedules: the power moves along the plan


def test_the_preview_mpc_it_is_built_from_uses_them(model):
    nominal = run("preview-mpc", model, 1.0, 0.0)
    assert run("preview-mpc", model, 1.3, 0.0) != nominal
    assert run("preview-mpc", model, 1.0, 80.0) != nominal


def test_it_needs_the_delay_aware_model():
    with pytest.raises(ValueError, match="'scan-feedforward' controller needs a delay-aware model"):
        make_controller("scan-feedforward", ControllerSettings(), None)
