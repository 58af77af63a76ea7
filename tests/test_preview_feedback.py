"""The preview MPC's real-time iteration (controller_node.preview_kernel.prepare_into / feedback_into,
PreviewMPC.prepare): the feedback phase predicts as the full update does at the measured T ahead,
keeps the prepared linearisation, solves its own QP exactly, and any state other than the prepared
one gets the full update."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.preview_kernel import Kernel
from controller_node.preview_qp import PreviewQP, solve_reference
from controller_node.preview_stages import StateContext
from controller_node.settings import ControllerSettings
from controller_node.types import Measurement
from gp_model.narx import NarxGPModel
from gp_model.shipped import PLATE_MODEL_PATH

H = 40
SP = 0.063e-6
DT = 50e-6


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    return NarxGPModel.load(PLATE_MODEL_PATH)


def _kernels(model, seed: int, blind: int, z_sigma: float = 0.0) -> tuple[PreviewQP, list[Kernel]]:
    """Three kernels with the same random histories, plan, turnaround profile and disturbance (the
    variance of every row with bound tightening zσ > 0, else of the first)."""
    rng = np.random.default_rng(seed)
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=0.5, power_scale_w=350.0, power_min_w=0.0, power_max_w=350.0,
                   area_min_m2=0.0, area_max_m2=5e-7, slack_linear=100.0, slack_quadratic=1000.0)
    p_hist = rng.uniform(200.0, 260.0, model.power_coefficients.size)
    t_hist = 600.0 + rng.normal(0.0, 5.0, model.temperature_coefficients.size).cumsum()
    profile = rng.normal(0.0, 10.0, len(model.turn_profile_k)).cumsum()
    plan = rng.uniform(200.0, 260.0, H)
    kernels = []
    for _ in range(3):
        k = Kernel(model, qp, H if z_sigma else 1, z_sigma, len(model.turn_profile_k), 60, 0.3)
        k.p_hist[:], k.t_hist[:], k.profile[:], k.plan[:] = p_hist, t_hist, profile, plan
        k.estimator.disturbance_m2 = 2e-10
        k.estimator.hold_prediction(math.log(SP) - 0.5, 600.0, 0.0)   # x̂[k+1|k]: z without p[k+1] terms, T, correction
        kernels.append(k)
    return qp, kernels


@pytest.mark.parametrize("seed", range(3))
@pytest.mark.parametrize("shift_k", [0.0, 3.0, -20.0, 60.0])
@pytest.mark.parametrize(("blind", "z_sigma"), [(0, 0.0), (5, 0.0), (0, 2.0)])
def test_the_feedback_predicts_as_the_update_and_solves_the_prepared_qp(model, seed, shift_k, blind, z_sigma):
    """Prepared at the forecast T ahead, fed the measured one: the observer, histories, forecast and
    the prediction x̂ at ū are those of the full update (within the series' truncation); Γ and the
    Hessian are those of the update at the forecast T ahead; c, the gradient and the step are the
    QP of that Γ and this prediction, solved as cvxpy solves it (the variance from the prepared series
    without bound tightening, from the kernel values with it)."""
    qp, (fed, updated, at_forecast) = _kernels(model, seed, blind, z_sigma)
    t_forecast, power, area = 610.0, 240.0, 1.02 * SP
    context = StateContext(1, power, 1, True, 40, False, 25, True, 590.0, False, blind)
    assert fed.prepare(context, t_forecast)
    t_measured = t_forecast + shift_k
    status = fed.feedback(context, t_measured, area)
    full = updated.update(context, t_measured, area)
    at_forecast.update(context, t_forecast, area)
    assert status >= 0 and (status == 2) == (full == 2)
    for name in ("p_hist", "t_hist", "forecast", "powers", "temps", "psi"):
        assert np.array_equal(getattr(fed, name), getattr(updated, name)), name
    assert fed.estimator.disturbance_m2 == updated.estimator.disturbance_m2
    assert fed.estimator.prediction[1] == updated.estimator.prediction[1]
    assert np.allclose(fed.predicted, updated.predicted, rtol=1e-9, atol=0.0)
    assert np.allclose(fed.z, updated.z, rtol=0.0, atol=1e-9)
    assert np.allclose(fed.std, updated.std, rtol=1e-9, atol=0.0)
    assert np.allclose(fed.gamma, at_forecast.gamma, rtol=1e-12, atol=0.0)
    assert np.allclose(fed.hess, at_forecast.hess, rtol=1e-12, atol=0.0)
    tracked_gamma, tracked_c = fed.gamma.copy(), fed.c.copy()
    tracked_gamma[:blind], tracked_c[:blind] = 0.0, 0.0
    assert np.allclose(fed.f, qp.gradient(tracked_gamma, tracked_c, power), rtol=1e-12, atol=1e-12)
    margin = z_sigma * fed.std / SP if z_sigma else None
    plan = fed.v * qp.scale if status == 0 else qp.finish(tracked_gamma, tracked_c, fed.hess, fed.f, fed.v,
                                                            margin).power_w
    assert np.allclose(plan, solve_reference(qp, tracked_gamma, tracked_c, power, margin), rtol=0.0, atol=1e-3)
    if shift_k == 0.0:  # at the forecast itself the feedback is the update
        assert np.allclose(fed.v, updated.v, rtol=1e-9, atol=1e-12)
        assert np.allclose(fed.c, updated.c, rtol=1e-9, atol=1e-12)


def _run_state(k: Kernel) -> np.ndarray:
    """What a run carries from one update to the next (its arrays and its estimator's state)."""
    estimator = k.estimator
    return np.r_[k.p_hist, k.t_hist, k.plan, k.profile, k.current, k.following, k.turn_errors, k.turn_error_seen,
                 estimator.disturbance_m2, estimator.has_prediction, estimator.prediction]


def test_a_measured_t_ahead_beyond_the_series_changes_nothing(model):
    (_, (fed, untouched, _)) = _kernels(model, 0, 0)
    context = StateContext(1, 240.0, 1, True, 40, False, 25, True, 590.0, False, 0)
    assert fed.prepare(context, 610.0)
    state = _run_state(fed)
    assert fed.feedback(context, 610.0 + 2000.0, SP) == -1
    assert np.array_equal(_run_state(fed), state) and np.array_equal(state, _run_state(untouched))


def _state(k: int, power: float, t: float, area: float, track_length: int = 120) -> Measurement:
    """State k of a two-track layer of ``track_length`` states per track."""
    track, s = divmod(k, track_length)
    return Measurement(step=k, time_s=k * DT, area_m2=area, t_ahead_k=t, power_w=power, speed_m_s=0.8, track=track,
                       track_elapsed_s=s * DT, track_remaining_s=(track_length - 1 - s) * DT, next_track=track == 0)


def _synthetic_layer(n: int = 240, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """T ahead and area of a two-track layer: near ambient on the first track, the previous track's
    heat decaying after the turn, with noise of a few kelvin and of 1 % of the area."""
    rng = np.random.default_rng(seed)
    s = np.arange(n) % 120
    t = np.where(np.arange(n) < 120, 310.0, 300.0 + 750.0 * np.exp(-s / 25.0)) + rng.normal(0.0, 4.0, n)
    area = SP * np.minimum(1.0, np.arange(n) / 15.0) * (1.0 + 0.01 * rng.standard_normal(n))
    return t, area


def test_the_closed_loop_with_preparation_follows_the_full_update(model):
    """The same measurements to a controller that prepares after each command and to one that does
    not: every state takes the feedback path but the first two (nothing is prepared after the
    first), the turn and a few after it (T ahead beyond the series), and the commands differ by the
    real-time iteration's linearisation lag only (< 1 W on ~240 W)."""
    settings = ControllerSettings(set_point_m2=SP)
    rti, full = PreviewMPC(settings, model), PreviewMPC(settings, model)
    t, area = _synthetic_layer()
    power, diffs = 0.0, []
    for k in range(t.size):
        m = _state(k, power, float(t[k]), float(area[k]))
        a, _ = rti.update(m)
        b, _ = full.update(m)
        rti.prepare()
        diffs.append(abs(a.power_w - b.power_w))
        power = a.power_w
    assert rti.n_feedback >= t.size - 8 and full.n_feedback == 0
    assert max(diffs) < 1.0 and np.median(diffs) < 0.05


@pytest.mark.parametrize("case", ["another power", "a gap", "a new track", "T far from the forecast"])
def test_a_state_other_than_the_prepared_one_gets_the_full_update(model, case):
    settings = ControllerSettings(set_point_m2=SP)
    rti, full = PreviewMPC(settings, model), PreviewMPC(settings, model)
    t, area = _synthetic_layer()
    power = 0.0
    for k in range(60):
        m = _state(k, power, float(t[k]), float(area[k]))
        a, _ = rti.update(m)
        full.update(m)
        power = a.power_w
    rti.prepare()
    k, t_next = 60, float(t[60])
    if case == "another power":
        power += 7.0
    elif case == "a gap":
        k += 1
    elif case == "a new track":
        k = 120
    else:
        t_next += 2000.0
    m = _state(k, power, t_next, float(area[k]))
    a, da = rti.update(m)
    b, db = full.update(m)
    assert rti.n_feedback == 0
    assert a == b and da.predicted_power_w == db.predicted_power_w and da.predicted_area_m2 == db.predicted_area_m2
