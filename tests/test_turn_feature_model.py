"""The turnaround feature as a model input (gp_model.narx) and in the preview MPC's prediction
(controller_node.preview_kernel): fitted, saved, predicted over the horizon as the model does, and
its derivative in the planned powers before a turn."""

from __future__ import annotations

import json

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.settings import ControllerSettings, PreviewSettings
from controller_node.types import Measurement
from gp_model.errors import ModelVersionError
from gp_model.narx import NarxGPModel, RunSeries
from gp_model.plan_feature import RemnantFeature, TurnFeature

DT, SPEED = 50e-6, 0.8
FEATURE = TurnFeature(n_targets=20, n_sources=40)
B = 1e-12 * np.array([5.0, 10.0, 20.0, 30.0, 30.0, 20.0, 10.0, 5.0])
C = 1e-12 * np.array([2.0, 4.0, 6.0, 4.0, 2.0])
G_TRUE = 3e-12           # m²/K of F[j] in the synthetic plant
REMNANT = RemnantFeature(n_states=10, n_sources=6, offsets=True)
H_TRUE = 1e-11 * np.sin(np.arange(10) / 3.0)   # m²/W of P̄ s states after a turn in the synthetic plant


def _run(seed: int, n: int = 450, tracks: int = 3, area_of_feature: float = G_TRUE,
         area_of_remnant: np.ndarray | None = None) -> RunSeries:
    """A serpentine run whose area is an FIR in power and T plus ``area_of_feature`` F (plus, with
    ``area_of_remnant`` h_s, the remnant's ``h_s P̄`` s states after a turn)."""
    rng = np.random.default_rng(seed)
    p = np.repeat(rng.uniform(150, 300, n // 10 + 1), 10)[:n]
    p[0] = 0.0
    track = (np.arange(n) * tracks) // n
    t = 300.0 + 5.0 * rng.standard_normal(n).cumsum() + 300.0 * (track > 0)
    shell = RunSeries("s", np.ones(n), t, p, track, DT, speed_m_s=SPEED)
    probe = NarxGPModel._probe(8, 5, 0, DT, 0, 1, FEATURE, SPEED, REMNANT)
    feature = probe.features(shell)
    remnant = probe.remnant_inputs(shell)[:, :REMNANT.n_states] @ (
        np.zeros(REMNANT.n_states) if area_of_remnant is None else area_of_remnant)
    x = np.full(n, 1e-8)
    for j in range(1, n):
        x[j] += sum(B[i] * p[j - i] for i in range(8) if j - i >= 0)
        x[j] += sum(C[m] * t[max(j - 1 - m, 0)] for m in range(5)) + area_of_feature * feature[j] + remnant[j]
    return RunSeries(f"turn-{seed}", x, t, p, track, DT, speed_m_s=SPEED)


def _fit(runs, feature_lags, feature=FEATURE, remnant=None):
    return NarxGPModel.fit(runs, n_power_lags=8, n_temperature_lags=5, quadratic=False, output="identity",
                           feature_lags=feature_lags, turn_feature=feature, remnant=remnant, n_train=40, n_restarts=1,
                           profile_length=50)


def test_the_fit_takes_the_feature_and_the_file_records_it(tmp_path):
    runs = [_run(s) for s in range(3)]
    with_feature, without = _fit(runs, 4), _fit(runs, 0, None)
    held_out = _run(9)
    error = [np.max(np.abs(m.predict_run(held_out)[0] - held_out.area_m2[1:])[20:]) for m in (with_feature, without)]
    assert error[0] < 1e-3 * 1e-8 < 1e-2 * 1e-8 < error[1]      # the plant's F term needs the feature
    path = with_feature.save(tmp_path / "m.json")
    again = NarxGPModel.load(path)
    assert again.turn_feature == FEATURE
    assert np.array_equal(again.predict_run(held_out)[0], with_feature.predict_run(held_out)[0])
    doc = json.loads(path.read_text())
    assert doc["format_version"] == 6 and doc["turn_feature"]["hatch_m"] == FEATURE.hatch_m
    old = dict(without.to_dict(), format_version=3)               # a format-3 file: no feature, squares
    old["power_square_coefficients"] = old.pop("power_map_coefficients")
    for key in ("turn_feature", "feature_coefficients", "feature_temperature_gain", "feature_profile_k",
                "remnant_feature", "remnant_coefficients", "remnant_offsets", "power_map"):
        del old[key]
    (tmp_path / "old.json").write_text(json.dumps(old))
    assert NarxGPModel.load(tmp_path / "old.json").turn_feature is None
    (tmp_path / "older.json").write_text(json.dumps(dict(old, format_version=2)))
    with pytest.raises(ModelVersionError, match="format version 2, this code reads 3, 4, 5, 6; retrain it"):
        NarxGPModel.load(tmp_path / "older.json")


def test_the_remnant_terms_are_the_least_squares_of_the_lag_parts_residual_per_state(tmp_path):
    """A plant with the remnant's ``h_s P̄`` after each turn: the lag part is the one fitted without the
    remnant, and (h_s, c_s) are, state by state after a turn, the least squares of its residual on
    (P̄, 1), written out here; they lower the held-out error; the file round-trips them; without
    ``offsets`` the c_s are 0."""
    runs = [_run(s, area_of_remnant=H_TRUE) for s in range(3)]
    with_remnant, without = _fit(runs, 4, remnant=REMNANT), _fit(runs, 4)
    np.testing.assert_allclose(with_remnant.coefficients()[:-2 * REMNANT.n_states], without.coefficients(),
                               rtol=1e-9, atol=0.0)
    rows = []                                       # (s, P̄, residual of the lag part) of every fitted sample
    for run in runs:
        lag_part = without.design(*without._lagged(run)) @ without.coefficients()
        since = run.steps_since_track_start()
        for start in run.turn_starts():
            mean = run.power_w[start - REMNANT.n_sources:start].mean()
            for s in range(REMNANT.n_states):
                rows.append((s, mean, run.area_m2[start + s] - lag_part[start + s - 1]))
                assert since[start + s] == s
    rows = np.array(rows)
    for s in range(REMNANT.n_states):
        at = rows[rows[:, 0] == s]
        direct = np.linalg.lstsq(np.column_stack([at[:, 1], np.ones(len(at))]), at[:, 2], rcond=None)[0]
        np.testing.assert_allclose([with_remnant.remnant_coefficients[s], with_remnant.remnant_offsets[s]], direct,
                                   rtol=1e-6, atol=1e-9 * np.abs(direct).max())
    held_out = _run(9, area_of_remnant=H_TRUE)
    error = [np.max(np.abs(m.predict_run(held_out)[0] - held_out.area_m2[1:])[20:]) for m in (with_remnant, without)]
    assert error[0] < 0.8 * error[1]
    again = NarxGPModel.load(with_remnant.save(tmp_path / "m.json"))
    assert again.remnant_feature == REMNANT
    assert np.array_equal(again.predict_run(held_out)[0], with_remnant.predict_run(held_out)[0])
    off = _fit(runs, 4, remnant=RemnantFeature(n_states=10, n_sources=6, offsets=False))
    assert np.all(off.remnant_offsets == 0.0) and np.any(with_remnant.remnant_offsets != 0.0)


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    """Every term visible: the fitted FIR and residual, squared T lags, p × T terms, the feature's
    coefficients and its part of the T forecast of a size that matters (no turnaround profile, ρ = 1)."""
    fitted = _fit([_run(s) for s in range(3)], 6)
    return NarxGPModel(**{**_constructor_args(fitted), "forecast_persistence": 1.0, "turn_profile_k": np.zeros(50),
                          "temperature_square_coefficients": np.full(2, 3e-15),
                          "power_temperature_coefficients": np.full(5, -5e-15), "feature_temperature_gain": 0.7,
                          "feature_coefficients": G_TRUE * np.array([1.0, 0.8, 0.6, 0.4, 0.3, 0.2])})


@pytest.fixture(scope="module")
def remnant_model(model) -> NarxGPModel:
    """``model`` with remnant terms of a size that matters: slopes and offsets that vary by state."""
    return NarxGPModel(**{**_constructor_args(model), "remnant_feature": REMNANT,
                          "remnant_coefficients": H_TRUE, "remnant_offsets": 2e-9 * np.cos(np.arange(10.0))})


def _controller_at_turn(model, k=54, track_length=30, horizon=12):
    """The preview MPC after the states 0..k of three tracks of ``track_length`` states (the turn
    ahead ``to_end`` states after k), T held over the horizon; its Γ as ∂x̂/∂u, ū and the run."""
    run = _run(4, n=3 * track_length, tracks=3)
    settings = ControllerSettings(set_point_m2=2e-8, preview=PreviewSettings(horizon=horizon, r=1e6,
                                                                             turn_learning_gain=0.0,
                                                                             learn_turn_profile=False))
    ctrl = PreviewMPC(settings, model)
    for j in range(k + 1):
        plan = np.r_[ctrl._plan[1:], ctrl._plan[-1:]]               # ū of this update
        remaining = ((j // track_length + 1) * track_length - 1 - j + 1) * DT
        ctrl.update(Measurement(step=j, time_s=j * DT, area_m2=run.area_m2[j], t_ahead_k=run.t_ahead_k[j],
                                power_w=run.power_w[j], speed_m_s=SPEED, track=int(run.track[j]),
                                track_remaining_s=remaining, next_track=True))
    gamma, c = ctrl.last_qp[:2]
    jac = gamma * settings.set_point_m2 / ctrl.qp.scale
    return ctrl, jac, c, plan, run


def _model_prediction(model, run, k, u):
    """The model's own x̂[k+1..k+H] with the applied powers up to k, then ``u``, T forecast as the
    model forecasts it from them (:meth:`NarxGPModel.forecast`)."""
    h = u.size
    p = np.r_[run.power_w[:k + 1], u]
    t = np.r_[run.t_ahead_k[:k + 1], np.zeros(h)]
    track = run.track[:k + 1 + h]
    t[k + 1:] = model.forecast(RunSeries("f", np.ones(k + 1 + h), t, p, track, DT), k, h)
    return model.predict_run(RunSeries("f", np.ones(k + 1 + h), t, p, track, DT))[0][k:k + h]


@pytest.mark.parametrize("with_remnant", [False, True])
@pytest.mark.parametrize("k", [35, 54])
def test_the_controllers_prediction_and_jacobian_are_the_models_own_across_a_turn(model, remnant_model, k,
                                                                                 with_remnant):
    """k = 35: 5 states after a turn (the feature of the track's own previous track, and its lags);
    k = 54: the next turn after state 59, 5 rows before it; with and without the remnant terms."""
    model = remnant_model if with_remnant else model
    ctrl, jac, c, plan, run = _controller_at_turn(model, k)
    sp = ctrl.settings.set_point_m2
    at_plan = c * sp + jac @ plan + sp
    assert np.allclose(at_plan, _model_prediction(model, run, k, plan) + ctrl.disturbance_m2, rtol=1e-9, atol=0.0)
    fd = np.column_stack([(_model_prediction(model, run, k, plan + 1e-2 * e)
                           - _model_prediction(model, run, k, plan - 1e-2 * e)) / 2e-2 for e in np.eye(plan.size)])
    assert np.allclose(jac, fd, rtol=0.0, atol=1e-6 * np.abs(fd).max())
    work, gamma = ctrl._kernel, ctrl.last_qp[0]                     # the QP over the dense rows: LAPACK's
    assert np.allclose(work.hess, ctrl.qp.hessian(gamma), rtol=1e-12, atol=1e-12 * np.abs(work.hess).max())
    assert np.allclose(work.v, np.linalg.solve(work.hess, -work.f), rtol=1e-9, atol=1e-12)
    if k == 54:
        assert np.abs(jac[11, :3]).max() > 0.01 * np.abs(jac).max()  # beyond the lag band: the feature's
    else:
        assert ctrl._kernel.feats.min() > 50.0                      # F [K] of every row and lag


def test_a_power_cut_before_the_turn_lowers_the_predicted_area_after_it(model):
    """−20 W on the planned powers before the turn: the rows after it (beyond the power lags'
    reach) predict a smaller area, with the feature (in the T forecast and as lags); without it they
    do not move."""
    delta = np.zeros(12)
    delta[:3] = -20.0                                               # p[k+1..k+3], the turn after k+5
    with_feature = _controller_at_turn(model)[1] @ delta
    blind = NarxGPModel(**{**_constructor_args(model), "feature_coefficients": None, "turn_feature": None,
                           "feature_temperature_gain": 0.0, "feature_profile_k": None})
    without = _controller_at_turn(blind)[1] @ delta
    assert np.all(with_feature[11:] < -1e-3 * 2e-8)                 # row 11: 8 lags after the last change
    assert np.all(without[11:] == 0.0)


def _constructor_args(model: NarxGPModel) -> dict:
    return dict(sample_period_s=model.sample_period_s, intercept=model.intercept,
                power_coefficients=model.power_coefficients, power_map_coefficients=model.power_map_coefficients,
                temperature_coefficients=model.temperature_coefficients,
                temperature_square_coefficients=model.temperature_square_coefficients, output=model.output,
                residual=model.residual, power_temperature_coefficients=model.power_temperature_coefficients,
                turn_feature=model.turn_feature, feature_coefficients=model.feature_coefficients,
                feature_temperature_gain=model.feature_temperature_gain, feature_profile_k=model.feature_profile_k,
                remnant_feature=model.remnant_feature, remnant_coefficients=model.remnant_coefficients,
                remnant_offsets=model.remnant_offsets,
                turn_profile_k=model.turn_profile_k, forecast_persistence=model.forecast_persistence,
                speed_m_s=model.speed_m_s, provenance=model.provenance)


def test_the_forecast_adds_the_features_deviation_and_decays_the_rest():
    """``adjust_forecast``: on the current track β (ΔF[k+j] − ρʲ ΔF[k]), after the turn ahead β ΔF[k+j]
    plus what the track's last state got; nothing on a layer's first track."""
    from gp_model.narx import adjust_forecast

    f_mean = np.array([100.0, 90.0, 80.0, 70.0, 60.0, 50.0, 40.0, 30.0])
    future = np.array([95.0, 85.0, 300.0, 250.0, 200.0])           # F[k+1..k+5]; the turn after k+2
    decay = 0.5 ** np.arange(1.0, 6.0)
    out = np.zeros(5)
    adjust_forecast(out, future, 110.0, f_mean, 2.0, 1, False, 2, decay)   # k: 1 state after a turn
    d_now = 110.0 - 90.0
    on_track = 2.0 * (future[:2] - f_mean[2:4] - decay[:2] * d_now)
    np.testing.assert_allclose(out, np.r_[on_track, on_track[1] + 2.0 * (future[2:] - f_mean[:3])])
    first = np.zeros(5)
    adjust_forecast(first, future, 110.0, f_mean, 2.0, 1, True, 2, decay)
    np.testing.assert_allclose(first, np.r_[0.0, 0.0, 2.0 * (future[2:] - f_mean[:3])])


def test_the_turnaround_profile_spans_the_feature():
    """The forecast's feature part is fitted against the turnaround profile at every state the feature
    reaches: a feature longer than ``profile_length`` lengthens the profile (it held its last value)."""
    long_feature = TurnFeature(n_targets=80, n_sources=100)
    model = _fit([_run(s) for s in range(3)], 2, long_feature)
    assert model.turn_profile_k.size == model.feature_profile_k.size == 80


def test_the_compiled_kernel_keeps_every_source_that_reaches_the_horizon():
    """The preview kernel reads the turnaround feature's kernel only in the H rows after a turn and keeps
    the sources that reach them: the dropped ones give less than 1e-9 K at 350 W on every source, the
    kept ones are fewer than the feature's (the default feature holds a whole track)."""
    from controller_node.preview_kernel import Kernel

    kernel = TurnFeature().kernel(SPEED * DT, DT)
    for h in (8, 40, 60):
        kept = Kernel._horizon_kernel(kernel, h)
        assert kept.shape[0] == kernel.shape[0] and h <= kept.shape[1] < kernel.shape[1]
        assert np.array_equal(kept, kernel[:, :kept.shape[1]])
        assert np.max(kernel[:h, kept.shape[1]:].sum(axis=1)) * 350.0 < 1e-9
        last = kernel[:h, kept.shape[1] - 1]
        assert kept.shape[1] == h or np.max(last) > 1e-17 * np.max(kernel[:h])   # no column more than needed
