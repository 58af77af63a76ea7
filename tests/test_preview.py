"""Delay-aware model (gp_model.narx) and the scan-plan preview MPC (controller_node.preview)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.preview_kernel import correction_into
from controller_node.preview_qp import solve_reference
from controller_node.registry import make_controller
from controller_node.settings import ControllerSettings, PreviewSettings
from controller_node.types import ConfigurationError, Measurement
from fe_node.scan import ScanPlan
from gp_model.narx import NarxGPModel, RunSeries, forecast_t_ahead

DT = 50e-6
SPEED_M_S = 0.8  # the synthetic runs' scan speed, as the measurements'
B_TRUE = 1e-12 * np.array([5.0, 10.0, 20.0, 30.0, 30.0, 20.0, 10.0, 5.0])   # m²/W, a ramp over 8 steps
C_TRUE = 1e-12 * np.array([2.0, 4.0, 6.0, 4.0, 2.0])                          # m²/K
C0 = 1.0e-8


def fir_area(p: np.ndarray, t: np.ndarray) -> np.ndarray:
    """x[j] = c0 + Σ b_i p[j−i] + Σ c_m T[j−1−m] of the synthetic FIR plant (T[0] before the start)."""
    n = p.size
    x = np.zeros(n)
    for j in range(1, n):
        x[j] = C0 + sum(B_TRUE[i] * p[j - i] for i in range(B_TRUE.size) if j - i >= 0)
        x[j] += sum(C_TRUE[m] * t[max(j - 1 - m, 0)] for m in range(C_TRUE.size))
    return x


def synthetic_run(seed: int, n: int = 400, tracks: int = 2) -> RunSeries:
    rng = np.random.default_rng(seed)
    p = np.repeat(rng.uniform(150, 300, n // 10 + 1), 10)[:n]
    p[0] = 0.0
    track = (np.arange(n) * tracks) // n
    t = 300.0 + 50.0 * rng.standard_normal(n).cumsum() * 0.1 + 400.0 * (track > 0)
    return RunSeries(f"synthetic-{seed}", fir_area(p, t), t, p, track, DT)


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    return NarxGPModel.fit([synthetic_run(s) for s in range(3)], n_power_lags=8, n_temperature_lags=5,
                           quadratic=False, output="identity", n_train=60, n_restarts=2, profile_length=50,
                           speed_m_s=SPEED_M_S)


def test_fit_recovers_the_fir_plant(model):
    assert np.allclose(model.power_coefficients, B_TRUE, rtol=1e-3, atol=1e-16)
    assert np.allclose(model.temperature_coefficients, C_TRUE, rtol=1e-3, atol=1e-16)
    run = synthetic_run(7)
    mean, var = model.predict_run(run)
    assert np.max(np.abs(mean - run.area_m2[1:])[20:]) < 1e-3 * C0
    assert np.all(var >= 0)


def test_model_file_round_trip(model, tmp_path):
    path = model.save(tmp_path / "m.json")
    again = NarxGPModel.load(path)
    run = synthetic_run(5)
    assert np.array_equal(again.predict_run(run)[0], model.predict_run(run)[0])
    assert again.sample_period_s == DT
    assert "sample_period_s" in again.input_definitions()


def test_forecast_follows_the_scan_plan():
    profile = np.array([0.0, 100.0, 300.0, 200.0, 150.0])
    held = forecast_t_ahead(400.0, 3, True, None, profile, 4)
    assert np.array_equal(held, np.full(4, 400.0))
    # on the first track, the turn is after 2 more states: T rises by the profile over the held value
    turn = forecast_t_ahead(400.0, 3, True, 2, profile, 6)
    assert np.array_equal(turn, [400.0, 400.0, 400.0, 500.0, 700.0, 600.0])
    # after a turn, the current track follows the profile's shape from its own position
    after = forecast_t_ahead(900.0, 2, False, None, profile, 3)
    assert np.array_equal(after, [800.0, 750.0, 750.0])
    # anchored on the temperature before the turn: the deviation from the profile decays with ρ
    anchored = forecast_t_ahead(600.0, 1, False, None, profile, 3, t_base_k=400.0, persistence=0.5)
    assert np.allclose(anchored, [400.0 + 300.0 + 50.0, 400.0 + 200.0 + 25.0, 400.0 + 150.0 + 12.5])


def test_log_output_with_squared_lags_fits_a_multiplicative_plant():
    rng = np.random.default_rng(3)
    runs = []
    for seed in range(3):
        run = synthetic_run(seed)
        area = np.exp(np.log(1e-8) + (run.area_m2 - C0) / 2e-8) * (run.area_m2 > 0)
        runs.append(RunSeries(run.name, area, run.t_ahead_k, run.power_w, run.track, DT))
    model = NarxGPModel.fit(runs, n_power_lags=8, n_temperature_lags=5, n_temperature_square_lags=2,
                            output="log", n_train=60, n_restarts=1, profile_length=50, seed=int(rng.integers(9)),
                            speed_m_s=SPEED_M_S)
    mean, _ = model.predict_run(runs[0])
    truth = runs[0].area_m2[1:]
    assert np.max(np.abs(mean / truth - 1.0)[20:]) < 1e-3
    linear = NarxGPModel.fit(runs, n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity",
                             n_train=60, n_restarts=1, profile_length=50, speed_m_s=SPEED_M_S)
    assert np.max(np.abs(linear.predict_run(runs[0])[0] / truth - 1.0)[20:]) > 1e-2


def test_scan_plan_preview_at_the_turn():
    plan = ScanPlan.layer(2, 1e-3, 1e-4)
    assert plan.preview(0.0) == (0.0, 1e-3, True)
    travelled, remaining, follows = plan.preview(1.5e-3)
    assert (round(travelled, 12), round(remaining, 12), follows) == (0.5e-3, 0.5e-3, False)


def _measurement(step, area, t=300.0, power=250.0, track=0, remaining=None, time_s=None):
    return Measurement(step=step, time_s=step * DT if time_s is None else time_s, area_m2=area, t_ahead_k=t,
                       power_w=power, speed_m_s=0.8, track=track, track_remaining_s=remaining,
                       next_track=None if remaining is None else True)


def test_first_state_gets_the_nominal_power(model):
    ctrl = make_controller("preview-mpc", ControllerSettings(set_point_m2=1.5e-8), model)
    command, diag = ctrl.update(_measurement(0, 0.0, power=0.0))
    assert command.power_w == ctrl.settings.nominal_power_w and not diag.fallback


def test_other_sample_period_is_refused(model):
    ctrl = PreviewMPC(ControllerSettings(set_point_m2=1.5e-8), model)
    ctrl.update(_measurement(0, 0.0, power=0.0))
    with pytest.raises(ConfigurationError, match="sample period is 100 µs .* 50 µs"):
        ctrl.update(_measurement(1, 1e-8, time_s=100e-6))


def _closed_loop(model, offset_m2, settings, steps=200, plan_turn_at=None):
    """The preview MPC against the synthetic FIR plant plus a constant area offset."""
    ctrl = PreviewMPC(settings, model)
    p = np.zeros(steps + 1)
    t = np.full(steps + 1, 300.0)
    x = np.zeros(steps + 1)
    for k in range(steps):
        remaining = None if plan_turn_at is None else max(plan_turn_at - k, 0) * DT
        track = 0 if plan_turn_at is None or k < plan_turn_at else 1
        cmd, _ = ctrl.update(_measurement(k, x[k], t[k], p[k], track, remaining))
        assert settings.power_min_w <= cmd.power_w <= settings.power_max_w
        p[k + 1] = cmd.power_w
        x[k + 1] = fir_area(p[:k + 2], t[:k + 2])[k + 1] + offset_m2
    return x, p, ctrl


def test_observer_removes_a_constant_model_error(model):
    sp = C0 + B_TRUE.sum() * 200.0 + C_TRUE.sum() * 300.0
    settings = ControllerSettings(set_point_m2=sp, preview=PreviewSettings(horizon=20, r=1.0))
    x, _, ctrl = _closed_loop(model, 0.05 * sp, settings, steps=400)   # the default L: a 50-step time constant
    assert abs(x[-20:].mean() / sp - 1.0) < 2e-3
    assert ctrl.disturbance_m2 == pytest.approx(0.05 * sp, rel=0.02)


@pytest.mark.parametrize("seed", range(30))
def test_fast_path_equals_cvxpy(model, seed):
    rng = np.random.default_rng(seed)
    sp = 1.5e-8
    settings = ControllerSettings(set_point_m2=sp, power_max_w=350.0,
                                  preview=PreviewSettings(horizon=20, r=float(rng.uniform(0.01, 1.0)),
                                                          area_max_m2=sp * float(rng.uniform(1.02, 3.0))))
    qp = PreviewMPC(settings, model).qp
    gain = np.tril(rng.uniform(0.0, 2e-11, (20, 20))) * rng.uniform(0.5, 2.0, 20)[:, None]
    gamma = gain * qp.scale / sp
    c = (rng.uniform(-0.6, 0.6) + 0.05 * rng.standard_normal(20).cumsum()
         - gamma.sum(axis=1) * rng.uniform(0, 300) / qp.scale)
    previous = float(rng.uniform(0, 350))
    fast = qp.solve(gamma, c, previous)
    reference = solve_reference(qp, gamma, c, previous)
    assert not fast.path.startswith("failed")
    assert np.max(np.abs(fast.power_w - reference)) < 1e-3


def test_trainer_builds_a_model_at_the_period_of_its_runs():
    runs = [synthetic_run(s) for s in range(2)]
    slow = [RunSeries(r.name, r.area_m2, r.t_ahead_k, r.power_w, r.track, 100e-6) for r in runs]
    model = NarxGPModel.fit(slow, n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity",
                            n_train=40, n_restarts=1, profile_length=20, speed_m_s=SPEED_M_S)
    assert model.sample_period_s == 100e-6
    with pytest.raises(Exception, match="different sample periods"):
        NarxGPModel.fit(runs + slow, n_power_lags=8, n_temperature_lags=5, n_train=40, n_restarts=1,
                        speed_m_s=SPEED_M_S)


@pytest.mark.parametrize("turn_at", [None, 33])
def test_prediction_matches_the_model_along_the_previous_plan(turn_at):
    """With the plan unchanged, the controller's prediction is the model's own (log output, squared
    lags, interactions): the condensed prediction indexes lags and temperatures as the model does."""
    runs = []
    for seed in range(3):
        run = synthetic_run(seed)
        area = np.exp(np.log(1e-8) + (run.area_m2 - C0) / 2e-8) * (run.area_m2 > 0)
        runs.append(RunSeries(run.name, area, run.t_ahead_k, run.power_w, run.track, DT))
    fitted = NarxGPModel.fit(runs, n_power_lags=8, n_temperature_lags=5, n_temperature_square_lags=2,
                             interaction=True, output="log", n_train=40, n_restarts=1, profile_length=50,
                             speed_m_s=SPEED_M_S)
    model = NarxGPModel(  # every term made visible: squares and interactions of a size that matters
        sample_period_s=DT, intercept=fitted.intercept, power_coefficients=fitted.power_coefficients,
        power_map_coefficients=np.full(8, 2e-6), temperature_coefficients=fitted.temperature_coefficients + 1e-3,
        temperature_square_coefficients=np.full(2, 1e-6), power_temperature_coefficients=np.full(5, -2e-6),
        output="log", residual=fitted.residual, turn_profile_k=fitted.turn_profile_k, forecast_persistence=1.0,
        speed_m_s=0.8)
    settings = ControllerSettings(set_point_m2=2e-8, preview=PreviewSettings(horizon=12, r=1e6, turn_learning_gain=0.0,
                                                                             learn_turn_profile=False))
    ctrl = PreviewMPC(settings, model)
    run = runs[0]
    track = np.zeros(52, dtype=int) if turn_at is None else (np.arange(52) >= turn_at).astype(int)
    ctrl._profile[:] = 0.0                                          # no T rise at a turn, ρ = 1: T held
    for k in range(40):
        plan = np.r_[ctrl._plan[1:], ctrl._plan[-1:]]             # ū: the previous plan, shifted
        _, diag = ctrl.update(_measurement(k, run.area_m2[k], run.t_ahead_k[k], run.power_w[k], int(track[k])))
    gamma, c = ctrl.last_qp[:2]
    jac = gamma * settings.set_point_m2 / ctrl.qp.scale
    at_plan = c * settings.set_point_m2 + jac @ plan + settings.set_point_m2     # the QP's x̂ at u = ū
    # the model on the same history, ū as future powers and T held (7 states after a turn, or none)
    n = 40 + 12
    p = np.r_[run.power_w[:40], plan]
    t = np.r_[run.t_ahead_k[:40], np.full(12, run.t_ahead_k[39])]
    future = RunSeries("f", np.ones(n), t, p, track, DT)
    expected = model.predict_run(future)[0][39:39 + 12] + ctrl.disturbance_m2
    assert np.allclose(at_plan, expected, rtol=1e-9, atol=0.0)
    assert np.allclose(ctrl._kernel.psi, model.residual_inputs(future)[39:39 + 12], rtol=1e-12, atol=0.0)  # the GP's ψ


def test_jacobian_is_the_models_own_including_the_gp_residual():
    """The QP's ∂x̂/∂u is the finite-difference derivative of the model's prediction (lag part and
    GP residual, whose input ψ holds the mean lagged power) around the shifted previous plan."""
    runs = []
    for seed in range(3):   # a plant with a term in the mean lagged power that only the residual GP can learn
        run = synthetic_run(seed)
        mean_p = np.convolve(run.power_w, np.full(8, 1 / 8))[:len(run)]
        runs.append(RunSeries(run.name, run.area_m2 + 2e-12 * (mean_p - 225.0) ** 2, run.t_ahead_k, run.power_w,
                              run.track, DT))
    model = NarxGPModel.fit(runs, n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity",
                            n_train=60, n_restarts=1, profile_length=50, speed_m_s=SPEED_M_S)
    settings = ControllerSettings(set_point_m2=C0, preview=PreviewSettings(horizon=12, r=1.0, turn_learning_gain=0.0))
    ctrl = PreviewMPC(settings, model)
    run = runs[0]
    for k in range(40):
        _, diag = ctrl.update(_measurement(k, run.area_m2[k], run.t_ahead_k[k], run.power_w[k]))
    plan = np.r_[diag.predicted_power_w[1:], diag.predicted_power_w[-1:]]      # ū of the next update
    _, diag = ctrl.update(_measurement(40, run.area_m2[40], run.t_ahead_k[40], run.power_w[40]))
    gamma = ctrl.last_qp[0]
    jac = gamma * settings.set_point_m2 / ctrl.qp.scale
    t = np.r_[run.t_ahead_k[:41], np.full(12, run.t_ahead_k[40])]

    def predicted(u):
        p = np.r_[run.power_w[:41], u]
        return model.predict_run(RunSeries("f", np.ones(53), t, p, np.zeros(53, dtype=int), DT))[0][40:52]

    fd = np.column_stack([(predicted(plan + 1e-3 * e) - predicted(plan - 1e-3 * e)) / 2e-3 for e in np.eye(12)])
    lag = np.arange(12)[:, None] - np.arange(12)[None, :]     # ∂x̂[k+m]/∂u[k+n] of the lag part alone: b[m−n]
    lag_part = np.where((lag >= 0) & (lag < 8), model.power_coefficients[np.clip(lag, 0, 7)], 0.0)
    assert np.abs(jac - lag_part).max() > 0.05 * np.abs(lag_part).max()   # the GP part matters
    assert np.allclose(jac, fd, rtol=0.0, atol=1e-6 * np.abs(fd).max())


def test_jacobian_of_lag_matched_interactions_uses_each_powers_own_temperature():
    """p[k+1−i] T[k−i]: the derivative by a planned power carries the temperature of its own lag in
    every predicted row (T varies strongly over the last states, so the lag matters)."""
    fitted = NarxGPModel.fit([synthetic_run(s) for s in range(3)], n_power_lags=8, n_temperature_lags=5,
                             interaction=True, output="identity", n_train=40, n_restarts=1, profile_length=50,
                             speed_m_s=SPEED_M_S)
    assert fitted.power_temperature_coefficients.size == 5
    model = NarxGPModel(
        sample_period_s=DT, intercept=fitted.intercept, power_coefficients=fitted.power_coefficients,
        power_map_coefficients=np.zeros(8), temperature_coefficients=fitted.temperature_coefficients,
        temperature_square_coefficients=np.zeros(0), power_temperature_coefficients=np.array([4, 3, 2, 1, 0.5]) * 1e-14,
        output="identity", residual=fitted.residual, turn_profile_k=fitted.turn_profile_k, forecast_persistence=1.0,
        speed_m_s=0.8)
    settings = ControllerSettings(set_point_m2=C0, preview=PreviewSettings(horizon=12, r=1.0, turn_learning_gain=0.0,
                                                                            learn_turn_profile=False))
    ctrl = PreviewMPC(settings, model)
    run = synthetic_run(0)
    t = run.t_ahead_k + 300.0 * (np.arange(len(run)) % 4)          # 0, 300, 600, 900 K on top, repeating
    for k in range(41):
        _, diag = ctrl.update(_measurement(k, run.area_m2[k], t[k], run.power_w[k]))
        plan = np.r_[diag.predicted_power_w[1:], diag.predicted_power_w[-1:]]
    forecast = t[41] + 250.0 * (np.arange(1, 13) % 3)                   # T ahead over the horizon, varying too
    ctrl._profile[:13] = np.r_[0.0, forecast - t[41]]  # state 41 starts a track: T̂ = T[41] + profile[j] − profile[0]
    _, diag = ctrl.update(_measurement(41, run.area_m2[41], t[41], run.power_w[41], track=1))
    jac = ctrl.last_qp[0] * settings.set_point_m2 / ctrl.qp.scale
    t_future = np.r_[t[:42], forecast]
    track = (np.arange(54) >= 41).astype(int)

    def predicted(u):
        p = np.r_[run.power_w[:42], u]
        return model.predict_run(RunSeries("f", np.ones(54), t_future, p, track, DT))[0][41:53]

    fd = np.column_stack([(predicted(plan + 1e-3 * e) - predicted(plan - 1e-3 * e)) / 2e-3 for e in np.eye(12)])
    assert np.allclose(jac, fd, rtol=0.0, atol=1e-4 * np.abs(fd).max())


@pytest.mark.parametrize("table, message", [
    ("[plant]\ndt_s = 1e-4", "[plant] dt_s: the plant's sample period is 100 µs but the model was identified at 50 µs"),
    ("[plant]\nspeed_m_s = 1.0", "[plant] speed_m_s: the plant scans at 1000 mm/s but the model was identified at 800"),
    ("[controller]\nnominal_speed_m_s = 0.6", "[controller] nominal_speed_m_s: 0.6 m/s, but the plant scans at 0.8"),
])
def test_launch_refuses_a_plant_of_another_process(tmp_path, table, message):
    """The FE plant at another sample period or speed than the shipped model's is refused before any
    node starts, in one line naming the setting (exit 2)."""
    from tests import forked_cli

    config = tmp_path / "process.toml"
    config.write_text(table + "\n")
    proc = forked_cli.run("launch.py", "--scenario", "single-track", "--config", str(config), "--no-progress",
                          "--out", str(tmp_path / "run.mcap"))
    output = proc.stdout + proc.stderr
    assert proc.returncode == 2 and output.strip().count("\n") == 0, output
    assert message in output and str(config) in output


def test_the_process_is_the_models(tmp_path):
    """The bare plate's shipped model records its process; :func:`process_mismatch` names each difference."""
    from dataclasses import replace

    from controller_node.process import process_mismatch
    from fe_node.material import Material
    from fe_node.scenarios import scenario
    from gp_model.shipped import PLATE_MODEL_PATH
    from launch import check_process
    from messages.cli import UsageError

    shipped = NarxGPModel.load(PLATE_MODEL_PATH)
    assert (shipped.speed_m_s, round(shipped.sample_period_s, 12), shipped.material) == (0.8, 50e-6, "IN625")
    assert shipped.provenance["process"]["plant"] == "plate"
    assert process_mismatch(shipped, speed_m_s=0.805, sample_period_s=50.4e-6, material="IN625") is None
    assert "scans at 820 mm/s" in process_mismatch(shipped, speed_m_s=0.82)
    assert "sample period is 51 µs" in process_mismatch(shipped, sample_period_s=51e-6)
    assert process_mismatch(shipped, material="IN718") == ("the plant's material is IN718 but the model was "
                                                           "identified on IN625")
    plate = scenario("layer", preset="bare-plate")
    check_process(shipped, plate, ControllerSettings(), None)
    other = replace(plate, settings=replace(plate.settings, material=Material.constant(20.0, 8000.0, 500.0)))
    with pytest.raises(UsageError, match=r"^\[plant\] material: the plant's material is constant but"):
        check_process(shipped, other, ControllerSettings(), None)
    unrecorded = json.loads(PLATE_MODEL_PATH.read_text())
    del unrecorded["provenance"]["process"]
    (tmp_path / "m.json").write_text(json.dumps(unrecorded))
    assert NarxGPModel.load(tmp_path / "m.json").material is None      # not recorded: not compared
    check_process(NarxGPModel.load(tmp_path / "m.json"), other, ControllerSettings(), None)


def test_a_state_at_another_speed_is_refused(model):
    ctrl = PreviewMPC(ControllerSettings(set_point_m2=1.5e-8), model)
    ctrl.update(_measurement(0, 0.0, power=0.0))
    ctrl.update(dataclasses.replace(_measurement(1, 1e-8), speed_m_s=0.805))      # within 1 %
    with pytest.raises(ConfigurationError, match="the plant scans at 1000 mm/s but the model was identified at 800"):
        ctrl.update(dataclasses.replace(_measurement(2, 1e-8), speed_m_s=1.0))


def test_the_model_takes_the_speed_of_its_runs():
    from gp_model.errors import DatasetError

    runs = [dataclasses.replace(synthetic_run(s), speed_m_s=0.6) for s in range(2)]
    fit = dict(n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity", n_train=40, n_restarts=1,
               profile_length=20)
    assert NarxGPModel.fit(runs, **fit).speed_m_s == 0.6
    with pytest.raises(DatasetError, match="runs at different scan speeds: synthetic-0 0.6 m/s, synthetic-1 1 m/s"):
        NarxGPModel.fit([runs[0], dataclasses.replace(runs[1], speed_m_s=1.0)], **fit)
    with pytest.raises(DatasetError, match="speed_m_s 0.8 m/s"):
        NarxGPModel.fit(runs, **fit, speed_m_s=0.8)
    with pytest.raises(DatasetError, match="the runs record no scan speed"):
        NarxGPModel.fit([synthetic_run(0)], **fit)


def test_a_recorded_run_carries_its_speed():
    from types import SimpleNamespace

    from gp_model.errors import DatasetError
    from gp_model.narx import series_from_states

    def state(k, speed_mm_s=800.0):
        return SimpleNamespace(step=k, time_s=k * DT, track=0, area_mm2=0.05, t_ahead_k=500.0, power_w=250.0,
                               speed_mm_s=speed_mm_s, layer=None)

    assert series_from_states([state(k) for k in range(5)], "run").speed_m_s == pytest.approx(0.8)
    with pytest.raises(DatasetError, match="run: the scan speed varies"):
        series_from_states([state(k, 1000.0 if k == 3 else 800.0) for k in range(5)], "run")


def test_evaluate_of_the_delay_aware_model_names_the_command_when_data_are_missing(tmp_path, capsys):
    from gp_model.files import is_model_file
    from gp_model.narx import FORMAT_NAME
    from gp_model.shipped import DEFAULT_MODEL_PATH
    from gp_trainer.cli import main

    assert is_model_file(DEFAULT_MODEL_PATH, FORMAT_NAME) and not is_model_file(tmp_path / "none.json", FORMAT_NAME)
    assert main(["evaluate", "--plant", "plate", "--recordings-dir", str(tmp_path), "--json", "--no-identify"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    command = ("python -m gp_trainer identify --plant plate --runs ident-layer-p250-s2 ident-double-track-p250-s5 "
               f"ident-mpc-double-track-a0.063 --out-dir {tmp_path}")
    assert len(err) == 1 and f"run `{command}`" in err[0]
    # the shipped model was learned (`learn`): its held-out runs are its design's
    from gp_trainer.learn import design_from_record

    design, _ = design_from_record(NarxGPModel.load(DEFAULT_MODEL_PATH).provenance["design"])
    assert main(["evaluate", "--recordings-dir", str(tmp_path), "--json", "--no-identify"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"({', '.join(design.held_out())}): run `python -m gp_trainer learn" in err[0]


def test_the_learning_state_records_the_paths_the_states_show(model):
    """The plan a learning state was learned on: each path's length, from the first state of each path
    (``track_elapsed_s + track_remaining_s`` times the speed), the last layer's only."""
    ctrl = PreviewMPC(ControllerSettings(set_point_m2=6.3e-8), model)
    dt, k = 50e-6, 0
    for layer, steps in ((0, (30, 30)), (1, (20, 40, 20))):
        for track, n in enumerate(steps):
            for j in range(n):
                ctrl.update(Measurement(step=k, time_s=k * dt, area_m2=6.3e-8, t_ahead_k=900.0, power_w=250.0,
                                        speed_m_s=0.8, track=track, layer=layer, track_elapsed_s=j * dt,
                                        track_remaining_s=(n - j) * dt, next_track=track < len(steps) - 1))
                k += 1
    assert ctrl.learning_state()["path_lengths_m"] == pytest.approx([20 * dt * 0.8, 40 * dt * 0.8, 20 * dt * 0.8])


def test_learning_state_round_trip_and_refusal(model):
    settings = ControllerSettings(set_point_m2=1.5e-8, preview=PreviewSettings(horizon=10, turn_learning_steps=5))
    first = PreviewMPC(settings, model)
    first.turn_correction_m2[:] = [1e-9, 2e-9, 0.0, -1e-9, 0.0]
    first._profile[:3] = [10.0, 20.0, 30.0]
    doc = json.loads(json.dumps(first.learning_state()))
    second = PreviewMPC(settings, model)
    second.load_learning_state(doc)
    assert np.array_equal(second.turn_correction_m2, first.turn_correction_m2)
    assert np.array_equal(second._profile, first._profile)
    other = PreviewMPC(ControllerSettings(set_point_m2=1.5e-8, preview=PreviewSettings(horizon=10)), model)
    with pytest.raises(ValueError, match="turn_learning_steps"):
        other.load_learning_state(doc)
    with pytest.raises(ValueError, match="sample period"):
        second.load_learning_state({**doc, "sample_period_s": 1e-4})
    with pytest.raises(ValueError, match="older meltloop"):
        second.load_learning_state({**doc, "format": "meltloop-preview-learning-1"})


def test_turnaround_learning_is_indexed_by_the_turn_across_layers(model):
    """Within a layer each turn starts from the latest learned correction; in the next layer turn j
    starts from what turn j learned (a later turn is on a hotter plate), through the learning state."""
    def _same(a, b):  # corrections are ~1e-9 m²: compare relative to them, not to numpy's 1e-8 default
        return np.allclose(a, b, rtol=1e-12, atol=1e-21)

    def _seen(ctrl, turn, errors):  # the estimator saw these errors after turn ``turn`` (NaN: not seen)
        errors = np.asarray(errors, dtype=float)
        ctrl._turn = turn
        ctrl._kernel.turn_errors[:], ctrl._kernel.turn_error_seen[:] = np.nan_to_num(errors), ~np.isnan(errors)

    settings = ControllerSettings(set_point_m2=1.5e-8, preview=PreviewSettings(
        horizon=10, turn_learning_steps=3, turn_learning_gain=0.5))
    first = PreviewMPC(settings, model)
    errors = [np.array([2e-9, 0.0, -2e-9]), np.array([4e-9, 2e-9, 0.0]), np.array([np.nan, 6e-9, 2e-9])]
    for turn, e in enumerate(errors):
        _seen(first, turn, e)
        first._learn_turn_correction()
    learned = first.turn_corrections_by_turn_m2
    assert _same(learned[0], 0.5 * errors[0])
    assert _same(learned[1], learned[0] + 0.5 * errors[1])            # the chain within the layer
    assert _same(learned[2], learned[1] + 0.5 * np.nan_to_num(errors[2]))
    second = PreviewMPC(settings, model)
    second.load_learning_state(json.loads(json.dumps(first.learning_state())))
    for turn in range(3):
        assert _same(second._correction_for(turn), learned[turn])
    assert _same(second._correction_for(3), first.turn_correction_m2)  # a turn the last layer lacked
    _seen(second, 1, [1e-9, 1e-9, 1e-9])
    second._learn_turn_correction()
    assert _same(second.turn_corrections_by_turn_m2[0], learned[1] + 0.5e-9)   # from turn 1's own
    second._turn = 0  # state k is the 1st of track 1 (after turn 0); turn 1 comes after k+2
    second._sync_corrections()

    def over_horizon(on_first):  # what the update lays out over the horizon from the kernel's copies
        out = np.zeros(10)
        correction_into(0, on_first, 2, second._kernel.current, second._kernel.following, out)
        return out

    assert _same(over_horizon(False),
                 [learned[0][1], learned[0][2], learned[1][0], learned[1][1], learned[1][2]] + [0.0] * 5)
    assert _same(over_horizon(True),   # the layer's first track: none before the turn
                 [0.0, 0.0, learned[1][0], learned[1][1], learned[1][2]] + [0.0] * 5)
    with pytest.raises(ValueError, match="by_turn"):
        second.load_learning_state({**first.learning_state(), "turn_corrections_by_turn_m2": [[1.0]]})


def test_turnaround_learning_forgets_a_share_of_what_it_learned_at_each_update(model):
    """With forgetting γ each update is ``c ← (1 − γ)(c_j + κ ε_j)``: an error seen once decays by (1 − γ) per
    turn it is not seen again, and a constant error leads to a bounded correction, κ ε (1 − γ)/γ at most."""
    settings = ControllerSettings(set_point_m2=1.5e-8, preview=PreviewSettings(
        horizon=10, turn_learning_steps=3, turn_learning_gain=0.5, turn_learning_forgetting=0.2))
    ctrl = PreviewMPC(settings, model)
    error = np.array([2e-9, 0.0, -2e-9])
    for turn in range(40):
        ctrl._turn = turn
        ctrl._kernel.turn_errors[:], ctrl._kernel.turn_error_seen[:] = error, True
        ctrl._learn_turn_correction()
    learned = ctrl.turn_corrections_by_turn_m2
    assert np.allclose(learned[0], 0.8 * 0.5 * error, rtol=1e-12, atol=1e-21)
    assert np.allclose(learned[1], 0.8 * (learned[0] + 0.5 * error), rtol=1e-12, atol=1e-21)
    last = learned[-1].copy()
    assert np.allclose(last, 0.5 * error * 0.8 / 0.2, rtol=1e-3, atol=1e-21)   # the bound, reached
    ctrl._turn = 40
    ctrl._kernel.turn_error_seen[:] = False
    ctrl._learn_turn_correction()                 # not seen again: it decays
    assert np.allclose(ctrl.turn_correction_m2, 0.8 * last, rtol=1e-12, atol=1e-21)
    with pytest.raises(ValueError, match="turn_learning_forgetting"):
        PreviewSettings(turn_learning_forgetting=1.0)


def test_node_learning_state_option_errors(tmp_path):
    from controller_node.node import main

    path = tmp_path / "learn.json"
    path.write_text("{not json")
    assert main(["--controller", "pid", "--learning-state", str(path)]) == 2
    assert main(["--controller", "preview-mpc", "--learning-state", str(path)]) == 2


def _two_layer_run() -> RunSeries:
    """Layer 0: tracks 0 (states 0-39), 1 (40-79); layer 1: tracks 0 (80-119), 1 (120-159)."""
    run = synthetic_run(3, n=160, tracks=4)
    layer = np.r_[np.zeros(80, int), np.ones(80, int)]
    return RunSeries(run.name, run.area_m2, run.t_ahead_k, run.power_w, run.track % 2, DT, layer)


def test_a_layer_start_is_neither_a_turnaround_nor_fitted_build_up():
    from gp_model.build_up import BUILD_UP_STEPS
    from gp_model.narx import turn_bases

    run = _two_layer_run()
    assert run.turn_starts().tolist() == [40, 120]                  # not 80: layer 1 starts a new pool
    assert run.steps_since_track_start()[[39, 40, 80, 81, 125]].tolist() == [39, 0, 0, 1, 5]
    assert run.steps_to_track_end()[[0, 79, 80, 119]].tolist() == [39, 0, 39, 0]
    assert run.steps_since_layer_start()[[79, 80, 99]].tolist() == [79, 0, 19]
    assert run.first_track_of_layer()[[0, 40, 80, 120]].tolist() == [True, False, True, False]
    assert run.last_track_of_layer()[[39, 40, 119, 120]].tolist() == [False, True, False, True]
    base = turn_bases(run)
    assert np.isnan(base[:40]).all() and np.isnan(base[80:120]).all()
    assert (base[40:80] == run.t_ahead_k[39]).all() and (base[120:] == run.t_ahead_k[119]).all()
    one = RunSeries(run.name, run.area_m2, run.t_ahead_k, run.power_w, run.track, DT)
    fit = dict(n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity", n_train=40, n_restarts=1,
               profile_length=20, speed_m_s=SPEED_M_S)
    assert NarxGPModel.fit([run], **fit).provenance["n_samples"] == 159 - 2 * BUILD_UP_STEPS + 1
    assert NarxGPModel.fit([one], **fit).provenance["n_samples"] == 159 - BUILD_UP_STEPS + 1


def test_every_layers_pool_build_up_is_planned_for_but_not_tracked(model):
    """Inside a pool build-up (the first ``observer_start_steps`` states of the run and of every
    layer) the QP does not track the states the model is not fitted on and the observer stands
    still; the plan aims at the states after it. Step 0 gets the nominal power."""
    settings = ControllerSettings(set_point_m2=1.5e-8, preview=PreviewSettings(horizon=20))
    ctrl = PreviewMPC(settings, model)
    powers, blind, disturbance = [], {}, {}
    for k in range(70):
        layer = 0 if k < 40 else 1
        m = Measurement(step=k, time_s=k * DT, area_m2=1.4e-8 if k % 40 > 3 else 0.0, t_ahead_k=300.0,
                        power_w=0.0 if k == 0 else powers[-1], speed_m_s=0.8, track=0, layer=layer)
        powers.append(ctrl.update(m)[0].power_w)
        gamma, c = ctrl.last_qp[:2]
        blind[k] = int(np.sum(~gamma.any(axis=1) & (c == 0)))
        disturbance[k] = ctrl.disturbance_m2
    assert powers[0] == settings.nominal_power_w and len(set(powers[1:20])) > 1
    assert [blind[k] for k in (1, 5, 19, 20, 41, 45, 59, 60)] == [18, 14, 0, 0, 18, 14, 0, 0]
    assert disturbance[40] == disturbance[59] and disturbance[20] != disturbance[39]   # observer off in build-up
    assert ctrl._first_track == 0 and ctrl._turn_base_k is None and ctrl._layer_start_step == 40


def test_evaluate_splits_error_and_coverage_between_turnarounds_and_tracks():
    """A plant that departs from the model only in the 50 states after a turn: the turnaround
    window's coverage and error say so, the along-track ones do not."""
    from gp_trainer.narx_fit import evaluate_model

    rng = np.random.default_rng(0)

    def noisy(run: RunSeries, bump: float = 0.0) -> RunSeries:
        after_turn = (run.track > 0) & (run.steps_since_track_start() < 50)
        area = run.area_m2 + 0.01 * C0 * rng.standard_normal(len(run)) + np.where(after_turn, bump, 0.0)
        return RunSeries(run.name, area, run.t_ahead_k, run.power_w, run.track, DT)

    model = NarxGPModel.fit([noisy(synthetic_run(s)) for s in range(3)], n_power_lags=8, n_temperature_lags=5,
                            quadratic=False, output="identity", n_train=60, n_restarts=1, profile_length=50,
                            speed_m_s=SPEED_M_S)
    result = evaluate_model(model, [noisy(synthetic_run(11), bump=0.2 * C0)])
    assert result["n_turnaround"] == 50
    assert result["coverage_95_along_pct"] > 85.0 and result["coverage_95_turnaround_pct"] < 10.0
    assert result["mape_turnaround_pct"] > 5 * result["mape_along_pct"]
    assert -5.0 < result["bias_turnaround_pct"] < -2.5 and abs(result["bias_along_pct"]) < 0.5   # model minus plant


def test_evaluate_places_the_model_error_after_a_turn_in_bins_of_states_since_the_turn():
    """A plant that departs from the model only 5-9 states after each turn: the after-turn bias profile puts
    the error in that bin alone, model minus plant."""
    from gp_trainer.narx_fit import evaluate_model

    rng = np.random.default_rng(1)

    def noisy(run: RunSeries, bump: float = 0.0) -> RunSeries:
        since = run.steps_since_track_start()
        dip = (run.track > 0) & (since >= 5) & (since < 10)
        area = run.area_m2 + 0.01 * C0 * rng.standard_normal(len(run)) - np.where(dip, bump, 0.0)
        return RunSeries(run.name, area, run.t_ahead_k, run.power_w, run.track, DT)

    model = NarxGPModel.fit([noisy(synthetic_run(s)) for s in range(3)], n_power_lags=8, n_temperature_lags=5,
                            quadratic=False, output="identity", n_train=60, n_restarts=1, profile_length=50,
                            speed_m_s=SPEED_M_S)
    result = evaluate_model(model, [noisy(synthetic_run(11), bump=0.2 * C0)])
    profile = result["bias_after_turn_pct"]
    assert result["after_turn_bin_states"] == 5 and len(profile) == 10
    assert profile[1] > 2.5 and max(abs(b) for i, b in enumerate(profile) if i != 1) < 0.5


def _record_run(path, run: RunSeries, speed_mm_s: float = 1e3 * SPEED_M_S):
    """``run`` as the ``/plant/state`` messages of an MCAP recording at ``path``."""
    import time

    from messages import MeltPoolState, encode
    from messages.recorder import McapRecorder
    from messages.topics import PLANT_STATE

    recorder = McapRecorder(path, "evaluate-test", path.open("wb"))
    for k in range(len(run)):
        msg = MeltPoolState(run_id="evaluate-test", step=k, time_s=k * DT, laser_x_mm=0.0, laser_y_mm=0.0,
                            scan_dir_x=1.0, scan_dir_y=0.0, track=int(run.track[k]),
                            area_mm2=float(1e6 * run.area_m2[k]), t_ahead_k=float(run.t_ahead_k[k]),
                            power_w=float(run.power_w[k]), speed_mm_s=speed_mm_s)
        recorder.write(PLANT_STATE, encode(msg), msg, time.time_ns())
    recorder.finish({"complete": "true"})
    return path


def test_evaluate_on_recordings_reports_the_bias_and_refuses_another_process(tmp_path, model, capsys):
    """``evaluate --runs REC``: the model judged on any recording of its process (bias after the turns where
    the plant's area is 0.2 C0, 3-4 %, above the model's), and a recording at another speed refused in one line."""
    from gp_trainer.cli import main

    path = model.save(tmp_path / "model.json")
    run = synthetic_run(11)
    after_turn = (run.track > 0) & (run.steps_since_track_start() < 50)
    bumped = RunSeries(run.name, run.area_m2 + np.where(after_turn, 0.2 * C0, 0.0), run.t_ahead_k, run.power_w,
                       run.track, DT)
    assert main(["evaluate", "--model", str(path), "--runs", str(_record_run(tmp_path / "run.mcap", bumped)),
                 "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["runs"] == ["run"] and result["training_runs"] == [] and result["n_turnaround"] == 50
    assert -5.0 < result["bias_turnaround_pct"] < -2.5 and abs(result["bias_along_pct"]) < 0.5
    from gp_model.shipped import ONE_STEP_MODEL_PATH

    assert main(["evaluate", "--model", str(ONE_STEP_MODEL_PATH), "--runs", str(tmp_path / "run.mcap")]) == 2
    assert "--runs evaluates a delay-aware one" in capsys.readouterr().err
    fast = _record_run(tmp_path / "fast.mcap", run, speed_mm_s=1000.0)
    assert main(["evaluate", "--model", str(path), "--runs", str(fast)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--runs fast.mcap: the plant scans at 1000 mm/s" in err[0]


def test_a_new_controller_answers_as_one_reset_after_a_run():
    """Nothing of the compile warm-up or of a previous run reaches the next run's commands."""
    from gp_model.shipped import PLATE_MODEL_PATH

    model = NarxGPModel.load(PLATE_MODEL_PATH)
    settings = ControllerSettings(set_point_m2=0.063e-6)

    def run(ctrl: PreviewMPC, n: int = 80) -> list[float]:
        powers, power = [], 0.0
        for k in range(n):
            area = 0.063e-6 * min(1.0, k / 25) * (1.0 + 0.02 * np.sin(k))
            cmd, _ = ctrl.update(Measurement(step=k, time_s=k * 50e-6, area_m2=area, t_ahead_k=900.0 + 3.0 * k,
                                             power_w=power, speed_m_s=0.8))
            powers.append(power := cmd.power_w)
        return powers

    used = PreviewMPC(settings, model)
    run(used)
    used.reset()
    assert run(PreviewMPC(settings, model)) == run(used)


@pytest.mark.parametrize("content, message", [
    ("{not json", "not JSON (Expecting property name"),
    ('{"format": "meltloop-preview-learning-1"}', "written by an older meltloop"),
    ("[]", "not a meltloop-preview-learning-3 document"),
    (None, "learned at a sample period of 0.0001 s"),
    ("short", "another turn_learning_steps"),
    ("plan", "learned on a plan of 4 paths of 10 mm; this run's plan has 2 paths of 5 mm"),
])
def test_launch_checks_the_learning_state_before_any_node_starts(tmp_path, content, message):
    """``launch.py --learning-state FILE``: a file the controller could not start from is a usage
    error of launch.py (the same checks as :meth:`PreviewMPC.load_learning_state`), a written one passes."""
    import launch
    from fe_node.scenarios import scenario
    from gp_model.shipped import PLATE_MODEL_PATH
    from messages.cli import UsageError

    model, settings = NarxGPModel.load(PLATE_MODEL_PATH), ControllerSettings()
    written = {**make_controller("preview-mpc", settings, model).learning_state(), "path_lengths_m": [0.01] * 4}
    path, plan = tmp_path / "learn.json", scenario("layer").plan
    path.write_text(json.dumps(written))
    launch.check_learning_state(path, model, settings, plan)            # what a run wrote is accepted
    if content == "plan":
        content, plan = json.dumps(written), scenario("double-track").plan
    elif content is None:
        content = json.dumps({**written, "sample_period_s": 1e-4})
    elif content == "short":
        content = json.dumps({**written, "turn_correction_m2": written["turn_correction_m2"][:-1],
                              "turn_corrections_by_turn_m2": []})
    path.write_text(content)
    with pytest.raises(UsageError, match=f"^--learning-state {path}: .*" + message.replace("(", r"\(")):
        launch.check_learning_state(path, model, settings, plan)
