"""Baselines behind the same interface: open-loop, PID (anti-windup), temperature feed-forward."""

from __future__ import annotations

import numpy as np
import pytest

from controller_node import (
    CONTROLLERS,
    ControllerSettings,
    FeedForwardSettings,
    Measurement,
    PIDSettings,
    make_controller,
)
from controller_node.model import linearise
from controller_node.registry import PREVIEW_CONTROLLERS
from controller_node.synthetic import AnalyticMeltPoolModel, multitrack_temperature, run_closed_loop

MODEL = AnalyticMeltPoolModel()
SET_POINT = ControllerSettings().set_point_m2  # the controllers below use the default


def _m(step: int, area: float = SET_POINT, t: float = 300.0, power: float = 250.0) -> Measurement:
    return Measurement(step, step * 50e-6, area, t, power, 0.8)


def test_registry_builds_every_controller_with_its_name() -> None:
    from tests.test_controller_safety import DELAY_MODEL

    for name in CONTROLLERS:
        controller = make_controller(name, ControllerSettings(), DELAY_MODEL if name in PREVIEW_CONTROLLERS else MODEL)
        assert controller.name == name
        cmd, diag = controller.update(_m(0))
        assert cmd.step == 1 and not diag.fallback and cmd.speed_m_s == 0.8


def test_open_loop_is_constant() -> None:
    c = make_controller("open-loop", ControllerSettings(nominal_power_w=210.0))
    powers = {c.update(_m(k, area=a))[0].power_w for k, a in enumerate((0.01e-6, 0.2e-6, 0.07e-6))}
    assert powers == {210.0}


def test_pid_direction_and_clamping() -> None:
    c = make_controller("pid", ControllerSettings(pid=PIDSettings(kp_w=100.0, ki_w=0.0, kd_w=0.0)))
    assert c.update(_m(0, area=0.0))[0].power_w == 250.0  # laser-on: every controller starts at nominal
    assert c.update(_m(1, area=0.5 * SET_POINT))[0].power_w == pytest.approx(300.0)  # too small -> more power
    assert c.update(_m(2, area=1.5 * SET_POINT))[0].power_w == pytest.approx(200.0)
    assert c.update(_m(3, area=0.0))[0].power_w == pytest.approx(350.0)  # 250 + 100
    assert c.update(_m(4, area=10 * SET_POINT))[0].power_w == 0.0  # clamped at p_l


def test_pid_anti_windup_recovers_immediately_after_saturation() -> None:
    gains = PIDSettings(kp_w=50.0, ki_w=20.0, kd_w=0.0)
    c = make_controller("pid", ControllerSettings(pid=gains))
    powers = [c.update(_m(k, area=0.2 * SET_POINT))[0].power_w for k in range(200)]  # area stuck low
    assert all(p == 350.0 for p in powers[10:])  # saturated at p_u
    assert c.integral_w == pytest.approx(350.0 - 250.0 - 50.0 * 0.8)  # integral stops at the headroom
    cmd, _ = c.update(_m(200, area=1.2 * SET_POINT))  # error reverses sign
    assert cmd.power_w < 350.0  # leaves saturation at once (a wound-up integral would hold 350 W)
    naive_integral = 200 * 20.0 * 0.8
    assert c.integral_w < 0.1 * naive_integral


def test_pid_closed_loop_is_stable_and_tracks() -> None:
    temps = np.full(400, 600.0)
    run = run_closed_loop(make_controller("pid", ControllerSettings()), MODEL, temps, area0_m2=0.03e-6)
    assert abs(run.area_m2[-1] / SET_POINT - 1.0) < 0.01


def test_feedforward_sign_and_magnitude_from_model_sensitivity() -> None:
    ff = FeedForwardSettings(enabled=True, direct_gain=1.0, differential_gain=0.5, reference_temperature_k=300.0)
    settings = ControllerSettings(feedforward=ff)
    c = make_controller("feedforward", settings, MODEL)
    lin = linearise(MODEL, np.array([SET_POINT, 300.0, 250.0, 0.8]))
    k_t = -lin.e / lin.b
    assert k_t < 0.0 and c.gain_w_per_k == pytest.approx(k_t)
    cmd0, d0 = c.update(_m(0, t=300.0))
    assert cmd0.power_w == pytest.approx(250.0) and d0.feedforward_w == 0.0
    cmd1, d1 = c.update(_m(1, t=400.0))  # +100 K: direct 100 K + differential 0.5 * 100 K
    assert d1.feedforward_w == pytest.approx(k_t * 150.0)
    assert cmd1.power_w == pytest.approx(250.0 + k_t * 150.0) and cmd1.power_w < 250.0
    cmd2, d2 = c.update(_m(2, t=10_000.0))  # absurd preheat: clamped contribution
    assert d2.feedforward_w == -ff.max_abs_w


def test_feedforward_keeps_steady_area_for_small_preheat_changes() -> None:
    ff = FeedForwardSettings(enabled=True, direct_gain=1.0, differential_gain=0.0, reference_temperature_k=300.0)
    c = make_controller("feedforward", ControllerSettings(feedforward=ff), MODEL)
    for t in (320.0, 350.0):
        cmd, _ = c.update(_m(int(t), t=t))
        exact = MODEL.steady_power_w(MODEL.area_ref_m2, t, 0.8)
        assert cmd.power_w == pytest.approx(exact, abs=0.5)


def test_feedforward_beats_open_loop_on_multitrack_preheat() -> None:
    temps = multitrack_temperature(3, 100)
    rmse = {}
    for name in ("open-loop", "feedforward"):
        # the synthetic plant's own K_T (the default fixed gain is the FE plant's)
        feedforward = FeedForwardSettings(enabled=True, direct_gain=1.0, differential_gain=0.0)
        settings = ControllerSettings(feedforward=feedforward)
        run = run_closed_loop(make_controller(name, settings, MODEL), MODEL, temps)
        rmse[name] = float(np.sqrt(np.mean((run.area_m2 / SET_POINT - 1.0) ** 2)))
    assert rmse["feedforward"] < 0.5 * rmse["open-loop"]
