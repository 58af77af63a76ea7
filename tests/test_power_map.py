"""The delay-aware model's power map (``"log1p"``: φ(p) = log(1 + p/p_s)) and its GP without the mean-power
input, in the model file and in the preview MPC's compiled kernel (prediction, Jacobian, observer)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.settings import ControllerSettings, PreviewSettings
from gp_model.errors import ModelFormatError
from gp_model.narx import LOG_POWER_SCALE_W, RESIDUAL_INPUTS, NarxGPModel, RunSeries, static_power_gains
from gp_model.shipped import PLATE_MODEL_PATH
from tests.test_preview import DT, SPEED_M_S, _measurement, synthetic_run

H = 12


def _log_runs() -> list[RunSeries]:
    """Synthetic runs whose log area is the FIR plant's (so the log output fits them)."""
    runs = []
    for seed in range(3):
        run = synthetic_run(seed)
        area = np.exp(np.log(1e-8) + (run.area_m2 - 1e-8) / 2e-8)
        runs.append(RunSeries(run.name, area, run.t_ahead_k, run.power_w, run.track, DT))
    return runs


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    """A log1p model without the GP's power input, its map terms made large enough to matter."""
    fitted = NarxGPModel.fit(_log_runs(), n_power_lags=8, n_temperature_lags=5, interaction=True, output="log",
                             n_train=40, n_restarts=1, profile_length=50, speed_m_s=SPEED_M_S,
                             power_map="log1p", gp_power_input=False)
    assert fitted.power_map == "log1p" and fitted.gp_inputs == RESIDUAL_INPUTS[:2]
    return NarxGPModel(
        sample_period_s=DT, intercept=fitted.intercept, power_coefficients=fitted.power_coefficients,
        power_map_coefficients=np.linspace(0.3, 0.05, 8), temperature_coefficients=fitted.temperature_coefficients,
        temperature_square_coefficients=fitted.temperature_square_coefficients,
        power_temperature_coefficients=np.full(5, -1e-6), output="log", residual=fitted.residual,
        power_map="log1p", turn_profile_k=fitted.turn_profile_k, forecast_persistence=1.0, speed_m_s=SPEED_M_S)


def test_the_design_maps_the_power_lags():
    fitted = NarxGPModel.fit(_log_runs(), n_power_lags=8, n_temperature_lags=5, output="log", n_train=40,
                             n_restarts=1, profile_length=50, speed_m_s=SPEED_M_S, power_map="log1p",
                             gp_power_input=False)
    P = np.array([[0.0, 25.0, 100.0, 350.0, 0.0, 0.0, 0.0, 0.0]])
    row = fitted.design(P, np.full((1, 5), 500.0), np.zeros((1, 0)), np.zeros((1, 0)))
    assert np.allclose(row[0, 9:17], np.log1p(P[0] / LOG_POWER_SCALE_W), rtol=1e-15)
    assert fitted.residual_inputs(_log_runs()[0]).shape[1] == 2


def test_the_steady_state_gain_of_the_log_map_is_its_derivative():
    """``static_power_gains`` of the log map: Σb + Σq/(p_s + p) + T Σe, the finite difference of the
    design's steady state (every lag at p)."""
    rng = np.random.default_rng(0)
    sizes = (4, 4, 3, 1, 2, 0, 0, 0)
    theta = rng.normal(size=1 + sum(sizes))
    shell = NarxGPModel._probe(4, 3, 1, DT, 2, power_map="log1p")

    def z(p, t):
        return shell.design(np.full((1, 4), p), np.full((1, 3), t), np.zeros((1, 0)), np.zeros((1, 0)))[0] @ theta

    for p, t in ((10.0, 400.0), (300.0, 1500.0)):
        gain = static_power_gains(sizes, [p], [t], "log1p")[0] @ theta
        assert gain == pytest.approx((z(p + 1e-4, t) - z(p - 1e-4, t)) / 2e-4, rel=1e-6)


@pytest.mark.parametrize("turn_at", [None, 33])
def test_the_kernels_prediction_and_observer_are_the_models(model, turn_at):
    """Along the previous plan the controller predicts the model's own areas, its GP reads two inputs
    (ψ's mean power is not one), and the observer completes the held prediction with b0 p + q0 φ(p)."""
    settings = ControllerSettings(set_point_m2=1e-8, preview=PreviewSettings(horizon=H, r=1e6, turn_learning_gain=0.0,
                                                                             learn_turn_profile=False))
    ctrl = PreviewMPC(settings, model)
    run = _log_runs()[0]
    track = np.zeros(52, dtype=int) if turn_at is None else (np.arange(52) >= turn_at).astype(int)
    ctrl._profile[:] = 0.0
    for k in range(40):
        plan = np.r_[ctrl._plan[1:], ctrl._plan[-1:]]
        ctrl.update(_measurement(k, run.area_m2[k], run.t_ahead_k[k], run.power_w[k], int(track[k])))
    gamma, c = ctrl.last_qp[:2]
    at_plan = c * settings.set_point_m2 + gamma * settings.set_point_m2 / ctrl.qp.scale @ plan + settings.set_point_m2
    p = np.r_[run.power_w[:40], plan]
    t = np.r_[run.t_ahead_k[:40], np.full(H, run.t_ahead_k[39])]
    future = RunSeries("f", np.ones(40 + H), t, p, track, DT)
    expected = model.predict_run(future)[0][39:39 + H] + ctrl.disturbance_m2
    assert np.allclose(at_plan, expected, rtol=1e-9, atol=0.0)
    assert np.allclose(ctrl._kernel.psi[:, :2], model.residual_inputs(future)[39:39 + H], rtol=1e-12, atol=0.0)
    u1, t_now = plan[0], run.t_ahead_k[39]
    b0, q0, e0 = model.power_coefficients[0], model.power_map_coefficients[0], model.power_temperature_coefficients[0]
    z_base = ctrl._kernel.estimator.prediction[0]
    assert z_base == pytest.approx(ctrl._kernel.z[0] - (b0 + e0 * t_now) * u1 - q0 * math.log1p(u1 / 25.0), rel=1e-13)


def test_the_kernels_jacobian_is_the_models_own(model):
    """∂x̂/∂u of the QP is the finite-difference derivative of the model's prediction: φ'(u) = 1/(p_s + u)
    on the map terms, no slope through a GP power input."""
    settings = ControllerSettings(set_point_m2=1e-8, preview=PreviewSettings(horizon=H, r=1.0, turn_learning_gain=0.0,
                                                                             learn_turn_profile=False))
    ctrl = PreviewMPC(settings, model)
    run = _log_runs()[1]
    ctrl._profile[:] = 0.0
    for k in range(40):
        _, diag = ctrl.update(_measurement(k, run.area_m2[k], run.t_ahead_k[k], run.power_w[k]))
    plan = np.r_[diag.predicted_power_w[1:], diag.predicted_power_w[-1:]]
    ctrl.update(_measurement(40, run.area_m2[40], run.t_ahead_k[40], run.power_w[40]))
    jac = ctrl.last_qp[0] * settings.set_point_m2 / ctrl.qp.scale
    t = np.r_[run.t_ahead_k[:41], np.full(H, run.t_ahead_k[40])]

    def predicted(u):
        p = np.r_[run.power_w[:41], u]
        return model.predict_run(RunSeries("f", np.ones(41 + H), t, p, np.zeros(41 + H, dtype=int), DT))[0][40:40 + H]

    fd = np.column_stack([(predicted(plan + 1e-3 * e) - predicted(plan - 1e-3 * e)) / 2e-3 for e in np.eye(H)])
    assert np.allclose(jac, fd, rtol=0.0, atol=1e-6 * np.abs(fd).max())


def test_the_model_file_records_the_map_and_the_gps_inputs(model, tmp_path):
    path = model.save(tmp_path / "m.json")
    doc = json.loads(path.read_text())
    assert doc["format_version"] == 6 and doc["power_map"] == "log1p"
    assert doc["residual_gp"]["inputs_names"] == list(RESIDUAL_INPUTS[:2])
    again = NarxGPModel.load(path)
    held = _log_runs()[2]
    assert again.power_map == "log1p" and np.array_equal(again.predict_run(held)[0], model.predict_run(held)[0])
    doc["residual_gp"]["inputs_names"] = list(RESIDUAL_INPUTS)      # three names for a two-input GP
    (tmp_path / "bad.json").write_text(json.dumps(doc))
    with pytest.raises(ModelFormatError, match="inputs_names"):
        NarxGPModel.load(tmp_path / "bad.json")
    shipped = NarxGPModel.load(PLATE_MODEL_PATH)                    # format 5: squares, three GP inputs
    assert shipped.power_map == "square" and shipped.gp_inputs == RESIDUAL_INPUTS
