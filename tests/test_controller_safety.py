"""Safety layer: no power outside the bounds, ever; fallback paths are taken and counted."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller_node import CONTROLLERS, ControllerSettings, Measurement, MPCSettings, make_controller
from controller_node.mpc import MPCController
from controller_node.qp import QPSolution
from controller_node.registry import PREVIEW_CONTROLLERS
from controller_node.synthetic import AnalyticMeltPoolModel
from controller_node.types import ConfigurationError

MODEL = AnalyticMeltPoolModel()


def _delay_model():
    from gp_model.narx import NarxGPModel
    from tests.test_preview import synthetic_run

    return NarxGPModel.fit([synthetic_run(s) for s in range(2)], n_power_lags=8, n_temperature_lags=5,
                           n_train=40, n_restarts=1, profile_length=20, speed_m_s=0.8)


DELAY_MODEL = _delay_model()
SETTINGS = ControllerSettings(power_min_w=20.0, power_max_w=330.0, nominal_power_w=250.0)


class ScriptedModel:
    """A model returning whatever the test scripts (NaN, inf, huge, or raising)."""

    def __init__(self, mean: float, jac: tuple[float, float, float, float], var: float, fail: bool) -> None:
        self.mean, self.jac, self.var, self.fail = mean, np.array(jac), var, fail

    def mean_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        if self.fail:
            raise RuntimeError("model blew up")
        return self.mean, self.jac

    def predict(self, z: np.ndarray) -> tuple[float, float]:
        return self.mean, self.var


anything = st.floats(allow_nan=True, allow_infinity=True)
plausible_area = st.floats(0.0, 1e-6)
measurement_value = st.one_of(anything, plausible_area, st.floats(0.0, 2000.0))


@st.composite
def measurements(draw) -> Measurement:
    return Measurement(
        step=draw(st.integers(0, 10**6)),
        time_s=draw(st.one_of(anything, st.floats(0.0, 1.0))),
        area_m2=draw(st.one_of(anything, plausible_area)),
        t_ahead_k=draw(st.one_of(anything, st.floats(1.0, 3000.0))),
        power_w=draw(st.one_of(anything, st.floats(0.0, 1000.0))),
        speed_m_s=draw(st.one_of(anything, st.floats(0.01, 5.0))),
    )


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(
    name=st.sampled_from(CONTROLLERS),
    sequence=st.lists(st.tuples(measurements(), st.one_of(st.none(), st.integers(0, 10**6 + 50))), min_size=1,
                      max_size=6),
    scripted=st.one_of(
        st.none(),
        st.builds(ScriptedModel, anything, st.tuples(anything, anything, anything, anything), anything, st.booleans()),
    ),
)
def test_power_never_leaves_bounds(name, sequence, scripted) -> None:
    model = MODEL if scripted is None else scripted
    if name in PREVIEW_CONTROLLERS:
        model = DELAY_MODEL
    try:
        controller = make_controller(name, SETTINGS, model)
    except ValueError:
        # the feedforward baseline refuses a model without a usable power gain at construction
        assert name == "feedforward" and scripted is not None
        return
    n_fallbacks = 0
    for measurement, now_step in sequence:
        try:
            command, diag = controller.update(measurement, now_step)
        except ConfigurationError:  # another sample period than the model's: the run is refused
            assert name in PREVIEW_CONTROLLERS
            return
        assert math.isfinite(command.power_w)
        assert SETTINGS.power_min_w <= command.power_w <= SETTINGS.power_max_w
        assert command.step == max(measurement.step, now_step or 0) + 1
        n_fallbacks += diag.fallback
        assert diag.n_fallbacks == n_fallbacks
        assert diag.fallback == (diag.status != "ok")


def _m(step: int, area: float = 0.07e-6, t: float = 600.0, power: float = 250.0) -> Measurement:
    return Measurement(step, step * 50e-6, area, t, power, 0.8)


def test_nan_measurement_falls_back_to_shifted_plan() -> None:
    mpc = make_controller("mpc", ControllerSettings(), MODEL)
    _, first = mpc.update(_m(0, area=0.05e-6, power=200.0))
    plan = first.predicted_power_w
    cmd, diag = mpc.update(_m(1, area=math.nan))
    assert diag.fallback and diag.status == "invalid_measurement" and diag.n_fallbacks == 1
    assert cmd.step == 2 and cmd.power_w == pytest.approx(plan[1])
    cmd, diag = mpc.update(_m(2, t=math.inf))
    assert diag.n_fallbacks == 2 and cmd.power_w == pytest.approx(plan[2])
    cmd, diag = mpc.update(_m(3))
    assert not diag.fallback and diag.n_fallbacks == 2


def test_stale_and_out_of_order_measurements_fall_back() -> None:
    mpc = make_controller("mpc", ControllerSettings(max_age_steps=1), MODEL)
    _, first = mpc.update(_m(10, area=0.05e-6, power=200.0))
    plan = first.predicted_power_w
    cmd, diag = mpc.update(_m(11), now_step=14)  # 3 steps old
    assert diag.status == "stale" and cmd.step == 15 and cmd.power_w == pytest.approx(plan[15 - 11])
    cmd, diag = mpc.update(_m(11))  # duplicate step
    assert diag.status == "stale"
    cmd, diag = mpc.update(_m(9))  # out of order
    assert diag.status == "stale" and diag.n_fallbacks == 3
    cmd, diag = mpc.update(_m(12), now_step=13)  # 1 step old: accepted
    assert diag.status == "ok"


def test_fallback_holds_last_power_beyond_the_plan_and_nominal_at_start() -> None:
    settings = ControllerSettings(nominal_power_w=180.0)
    mpc = make_controller("mpc", settings, MODEL)
    cmd, diag = mpc.update(_m(0, area=math.nan))
    assert diag.fallback and cmd.power_w == 180.0  # nothing known yet: nominal power
    cmd, _ = mpc.update(_m(1, area=0.09e-6))
    cmd_far, diag = mpc.update(_m(2), now_step=500)  # plan does not reach step 501
    assert diag.status == "stale" and cmd_far.power_w == pytest.approx(cmd.power_w)


class FailingBackend:
    def __init__(self, status: str = "primal infeasible", raise_: bool = False) -> None:
        self.status, self.raise_ = status, raise_

    def solve(self, data):
        if self.raise_:
            raise RuntimeError("solver crashed")
        return QPSolution(self.status, np.full(20, np.nan), np.full(20, np.nan), 7)


@pytest.mark.parametrize("backend,status", [(FailingBackend(), "solver_failed:primal infeasible"),
                                            (FailingBackend(raise_=True), "controller_error:RuntimeError")])
def test_solver_failure_is_contained(backend, status) -> None:
    mpc = MPCController(ControllerSettings(), MODEL, backend=backend)
    cmd, diag = mpc.update(_m(0, power=300.0))
    assert diag.fallback and diag.status == status and cmd.power_w == 250.0  # nominal: no plan, no command yet
    cmd, diag = mpc.update(_m(1))
    assert cmd.power_w == 250.0 and diag.n_fallbacks == 2


def test_model_returning_nan_or_explosive_dynamics_falls_back() -> None:
    nan_model = ScriptedModel(math.nan, (0.9, 1e-11, 1e-10, 0.0), 0.0, False)
    cmd, diag = make_controller("mpc", ControllerSettings(), nan_model).update(_m(0))
    assert diag.status == "model_error" and diag.fallback
    explosive = ScriptedModel(0.07e-6, (3.0, 1e-11, 1e-10, 0.0), 0.0, False)
    cmd, diag = make_controller("mpc", ControllerSettings(), explosive).update(_m(0))
    assert diag.status == "model_error"


def test_huge_measured_power_is_clamped_for_linearisation_and_output() -> None:
    mpc = make_controller("mpc", ControllerSettings(mpc=MPCSettings()), MODEL)
    cmd, diag = mpc.update(_m(0, power=1e12))
    assert not diag.fallback and 0.0 <= cmd.power_w <= 350.0
