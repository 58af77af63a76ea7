"""Construction-time validation of the controller's data types and settings."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller_node import (
    Command,
    ControllerSettings,
    FeedForwardSettings,
    Measurement,
    MPCSettings,
    PIDSettings,
    make_controller,
)
from controller_node.settings import PreviewSettings


def test_measurement_accepts_numpy_and_flags_implausible_values() -> None:
    m = Measurement(np.int64(3), np.float64(1.5e-4), 0.07e-6, 500.0, 250, 0.8)
    assert m.step == 3 and isinstance(m.power_w, float) and m.is_plausible()
    assert not Measurement(0, 0.0, math.nan, 500.0, 250.0, 0.8).is_plausible()
    assert not Measurement(0, 0.0, 0.07e-6, math.inf, 250.0, 0.8).is_plausible()
    assert not Measurement(0, 0.0, -1e-9, 500.0, 250.0, 0.8).is_plausible()
    assert not Measurement(0, 0.0, 0.07e-6, 500.0, 250.0, 0.0).is_plausible()
    for bad in (math.nan, math.inf, -1e-6):  # scan-plan preview fields: finite and >= 0 when given
        assert not Measurement(0, 0.0, 0.07e-6, 500.0, 250.0, 0.8, track_elapsed_s=bad).is_plausible()
        assert not Measurement(0, 0.0, 0.07e-6, 500.0, 250.0, 0.8, track_remaining_s=bad).is_plausible()
    assert Measurement(0, 0.0, 0.07e-6, 500.0, 250.0, 0.8, track_elapsed_s=0.0, track_remaining_s=0.0).is_plausible()
    assert not Measurement(0, math.inf, 0.07e-6, 500.0, 250.0, 0.8).is_plausible()


@pytest.mark.parametrize(
    "kwargs",
    [
        dict(step=-1),
        dict(step=1.0),
        dict(step=True),
        dict(area_m2="0.07"),
        dict(power_w=None),
        dict(t_ahead_k=True),
    ],
)
def test_measurement_rejects_bad_types(kwargs: dict) -> None:
    base = dict(step=0, time_s=0.0, area_m2=0.07e-6, t_ahead_k=500.0, power_w=250.0, speed_m_s=0.8)
    base.update(kwargs)
    with pytest.raises(ValueError):
        Measurement(**base)


@pytest.mark.parametrize(
    "power,speed", [(-1.0, 0.8), (math.nan, 0.8), (math.inf, 0.8), (100.0, 0.0), (100.0, math.nan)]
)
def test_command_rejects_unsafe_values(power: float, speed: float) -> None:
    with pytest.raises(ValueError):
        Command(1, power, speed)


@pytest.mark.parametrize(
    "factory",
    [
        lambda: ControllerSettings(set_point_m2=0.0),
        lambda: ControllerSettings(power_min_w=300.0, power_max_w=200.0),
        lambda: ControllerSettings(nominal_power_w=400.0),
        lambda: ControllerSettings(nominal_speed_m_s=math.nan),
        lambda: ControllerSettings(max_age_steps=-1),
        lambda: ControllerSettings(set_point_m2=0.6e-6),  # outside the MPC area bounds
        lambda: ControllerSettings(mpc="fast"),
        lambda: MPCSettings(horizon=0),
        lambda: MPCSettings(horizon=2.5),
        lambda: MPCSettings(r=0.0),
        lambda: MPCSettings(q=-1.0),
        lambda: MPCSettings(input_penalty="absolute"),
        lambda: MPCSettings(rate_min_w=10.0),
        lambda: MPCSettings(area_min_m2=1e-6, area_max_m2=0.5e-6),
        lambda: PreviewSettings(area_min_m2=1e-6, area_max_m2=0.5e-6),  # the bounds both MPCs share
        lambda: PreviewSettings(slack_quadratic=0.0),
        lambda: MPCSettings(eps_abs=1e-3),
        lambda: MPCSettings(disturbance_gain=1.5),
        lambda: MPCSettings(solver="gurobi"),
        lambda: MPCSettings(temperature_horizon="ramp"),
        lambda: PIDSettings(kp_w=-1.0),
        lambda: PIDSettings(ki_w=math.inf),
        lambda: FeedForwardSettings(max_abs_w=0.0),
        lambda: FeedForwardSettings(enabled=1),
        lambda: FeedForwardSettings(gain_w_per_k=math.nan),
    ],
)
def test_settings_validation_raises_one_line_value_error(factory) -> None:
    with pytest.raises(ValueError) as info:
        factory()
    assert "\n" not in str(info.value)


def test_settings_are_frozen() -> None:
    s = ControllerSettings()
    with pytest.raises(AttributeError):
        s.set_point_m2 = 1.0  # type: ignore[misc]


def test_registry_rejects_unknown_name_and_missing_model() -> None:
    with pytest.raises(ValueError, match="unknown controller"):
        make_controller("lqr")
    with pytest.raises(ValueError, match="needs a model"):
        make_controller("mpc", ControllerSettings())
    with pytest.raises(ValueError):  # no fixed gain and no model to derive it from
        make_controller("feedforward", ControllerSettings(
            feedforward=FeedForwardSettings(enabled=True, direct_gain=1.0, differential_gain=0.0)))
    assert make_controller("feedforward", ControllerSettings()).name == "feedforward"  # fixed FE gain by default
    assert make_controller("feedforward", ControllerSettings(
        feedforward=FeedForwardSettings(enabled=True, direct_gain=1.0, gain_w_per_k=-0.1))).name == "feedforward"


def test_command_fields_are_plain_python_numbers():
    """numpy and int inputs become int and float (what the codec and the bounds checks expect)."""
    cmd = Command(step=np.int64(3), power_w=200, speed_m_s=np.float32(0.8))
    assert (type(cmd.step), type(cmd.power_w), type(cmd.speed_m_s)) == (int, float, float)
    assert (cmd.step, cmd.power_w) == (3, 200.0) and cmd.speed_m_s == pytest.approx(0.8)
