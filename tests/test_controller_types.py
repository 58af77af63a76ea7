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


def test_trusted_construction_equals_the_constructor_and_stays_frozen():
    """``trusted`` (the controllers' hot path) builds what the dataclass constructor builds from the same
    checked values, field by field and type by type, and the result is still frozen; a wrong field count
    is refused. The proposal's plan fields are the diagnostics' plan report, in its order."""
    from controller_node.base import Proposal
    from controller_node.types import PLAN_REPORT_FIELDS, Diagnostics, trusted

    assert Proposal._fields[2:] == PLAN_REPORT_FIELDS
    cmd = trusted(Command, 4, 201.5, 0.8)
    assert cmd == Command(step=4, power_w=201.5, speed_m_s=0.8) and type(cmd) is Command
    plan = Proposal(150.0, predicted_area_m2=(6e-8, 6.1e-8), predicted_power_w=(150.0, 151.0), model_std_m2=1e-9,
                    solver_iterations=1)
    diag = trusted(Diagnostics, *plan[2:], 1e-4, "ok", False, 2)
    built = Diagnostics(1e-4, "ok", False, 2, **{name: getattr(plan, name) for name in PLAN_REPORT_FIELDS})
    assert diag == built
    assert [type(getattr(diag, f)) for f in Diagnostics.__dataclass_fields__] == \
        [type(getattr(built, f)) for f in Diagnostics.__dataclass_fields__]
    with pytest.raises(AttributeError):
        cmd.power_w = 0.0  # type: ignore[misc]
    with pytest.raises(TypeError, match="3 fields, got 2"):
        trusted(Command, 4, 201.5)


def test_every_controller_answers_with_plain_numbers_from_any_number_type():
    """The update's command and diagnostics carry int and float, whatever number types the settings hold
    (TOML integers) and the control law returns: the hot path builds them without the constructor's
    conversions, so the update converts."""
    settings = ControllerSettings(power_min_w=0, power_max_w=350, nominal_power_w=250, nominal_speed_m_s=1)
    for name in ("open-loop", "pid", "feedforward"):
        controller = make_controller(name, settings)
        for step in range(3):
            cmd, diag = controller.update(Measurement(step, step * 5e-5, 0.06e-6, 500.0, 250.0, 1.0))
            assert (type(cmd.step), type(cmd.power_w), type(cmd.speed_m_s)) == (int, float, float)
            assert cmd.step == step + 1 and 0.0 <= cmd.power_w <= 350.0 and cmd.speed_m_s == 1.0
            assert type(diag.solve_time_s) is float and diag.status == "ok" and diag.fallback is False
