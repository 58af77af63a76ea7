"""The compiled hot path of the preview MPC (controller_node.preview_kernel) against the numpy/LAPACK
formulation: the exponential, the histories, forecast and learned correction of one update, the GP's
variance, the QP's Hessian and gradient, the Cholesky solve."""

from __future__ import annotations

import math

import numpy as np
import pytest

from controller_node import preview_kernel
from controller_node.preview_kernel import Kernel, correction_into, exp_into
from controller_node.preview_qp import PreviewQP
from controller_node.preview_stages import StateContext
from gp_model.narx import NarxGPModel, forecast_t_ahead
from gp_model.shipped import PLATE_MODEL_PATH

H = 40
SP = 0.063e-6


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    return NarxGPModel.load(PLATE_MODEL_PATH)


def _case(model: NarxGPModel, seed: int, *, r: float = 1.0, blind: int = 0, n_variance: int = H,
          area_max_m2: float = 5e-7, z_sigma: float = 0.0, power_min_w: float = -1e6, power_max_w: float = 350.0,
          stale: float | None = None):
    """One update at random histories, plan and turnaround profile (so a random T forecast), pushing
    nothing into the histories."""
    rng = np.random.default_rng(seed)
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=r, power_scale_w=350.0, power_min_w=power_min_w, power_max_w=power_max_w,
                   area_min_m2=0.0, area_max_m2=area_max_m2, slack_linear=100.0, slack_quadratic=1000.0)
    work = Kernel(model, qp, n_variance, z_sigma, len(model.turn_profile_k), 60, 0.3)
    if stale is not None:  # what a previous update left in the workspace
        work.work[...] = stale
    work.p_hist[:] = rng.uniform(150.0, 300.0, work.p_hist.size)
    work.t_hist[:] = 900.0 + rng.normal(0.0, 50.0, work.t_hist.size).cumsum()
    work.profile[:] = rng.normal(0.0, 20.0, work.profile.size).cumsum()
    work.plan[:] = _case.plan = rng.uniform(150.0, 300.0, H)
    t_now = float(work.t_hist[-1])
    context = StateContext(0, 0.0, 0, False, int(rng.integers(0, 300)), False, int(rng.integers(-1, H)), True,
                           t_now - 30.0, False, blind)
    status = work.update(context, t_now, 0.0)
    _case.kernel = work
    out = (work.gamma, work.c, work.predicted, work.z, work.std, work.hess, work.f, work.v, work.areas, status)
    return qp, work.p_hist.copy(), work.psi, out


@pytest.mark.parametrize("stale", [np.nan, 1e300])
def test_nothing_a_previous_update_left_in_the_workspace_is_read(model, stale):
    """The workspace is reused by every update: each result is written before it is read."""
    for blind, n_variance in ((0, H), (7, 1)):
        fresh = _case(model, 3, blind=blind, n_variance=n_variance)[3]
        reused = _case(model, 3, blind=blind, n_variance=n_variance, stale=stale)[3]
        for a, b in zip(fresh[:-1], reused[:-1], strict=True):
            assert np.array_equal(a, b)
        assert fresh[-1] == reused[-1]


@pytest.mark.parametrize("seed", range(3))
def test_variance_is_the_gps_own(model, seed):
    _, _, psi, (_, _, _, z, std, *_) = _case(model, seed)
    _, var = model.residual.predict(psi)
    _, slope = model.area_and_slope(z)  # the output map's slope (exp(z) for the log output, 1 for identity)
    assert np.allclose(std, slope * np.sqrt(var + model.residual.noise_variance), rtol=1e-9, atol=0.0)


def test_variance_only_for_the_rows_asked(model):
    _, _, _, (_, _, _, _, std, *_) = _case(model, 0, n_variance=1)
    assert std[0] > 0.0 and not np.any(std[1:])


@pytest.mark.parametrize(("seed", "blind"), [(0, 0), (1, 7)])
def test_qp_terms_and_solution_are_lapacks(model, seed, blind):
    qp, p_hist, _, (gamma, c, predicted, _, _, hess, f, v, areas, status) = _case(model, seed, blind=blind)
    tracked_gamma, tracked_c = gamma.copy(), c.copy()
    tracked_gamma[:blind], tracked_c[:blind] = 0.0, 0.0
    assert np.allclose(hess, qp.hessian(tracked_gamma), rtol=1e-12, atol=1e-12 * np.abs(hess).max())
    assert np.allclose(f, qp.gradient(tracked_gamma, tracked_c, p_hist[0]), rtol=1e-12, atol=1e-12 * np.abs(f).max())
    assert np.allclose(v, np.linalg.solve(hess, -f), rtol=1e-9, atol=1e-12)
    result = qp.solve(tracked_gamma, tracked_c, p_hist[0])
    assert (status == 0) == (result.path == "fast")
    assert np.allclose(qp.finish(tracked_gamma, tracked_c, hess, f, v).power_w, result.power_w, rtol=0.0, atol=1e-6)
    plan = _case.plan
    assert np.allclose(areas, predicted + gamma * SP / qp.scale @ (v * qp.scale - np.r_[plan[1:], plan[-1]]),
                       rtol=1e-9, atol=0.0)


@pytest.mark.parametrize(("area_max_m2", "z_sigma", "power_max_w", "fast"),
                         [(5e-7, 0.0, 1e6, True), (SP * 1.0001, 0.0, 1e6, False), (5e-7, 1e9, 1e6, False),
                          (5e-7, 0.0, 100.0, False)])
def test_the_fast_path_is_taken_exactly_when_no_bound_is_active(model, area_max_m2, z_sigma, power_max_w, fast):
    """The kernel's verdict is PreviewQP.finish's: a power bound, an area bound or its tightening
    by zσ active sends the problem to DAQP."""
    qp, p_hist, _, (gamma, c, _, _, std, hess, f, v, _, status) = _case(model, 0, area_max_m2=area_max_m2,
                                                                           z_sigma=z_sigma, power_max_w=power_max_w)
    margin = z_sigma * std / SP if z_sigma else None
    assert (status == 0) is fast
    assert (qp.finish(gamma, c, hess, f, v, margin).path == "fast") is fast


def test_a_hessian_that_is_not_positive_definite_gives_no_step(model):
    *_, (*_, status) = _case(model, 0, r=0.0, blind=H)  # nothing tracked, no move penalty
    assert not _case.kernel.has_step and status == 1
    _case(model, 0, blind=H)
    assert _case.kernel.has_step


def test_a_closed_loop_compiles_the_kernel_once_and_predicts_with_what_it_learned(model):
    """Every update calls the kernel with the argument types of its first (warm-up) call: no
    recompilation, of seconds, in the middle of a run; after a turn it predicts with the correction
    learned at the turns before."""
    from controller_node.registry import make_controller
    from controller_node.settings import ControllerSettings
    from controller_node.types import Measurement

    ctrl = make_controller("preview-mpc", ControllerSettings(set_point_m2=SP), model)
    for k in range(90):  # three tracks of 30 states: learning at the second turn
        track = k // 30
        ctrl.update(Measurement(step=k, time_s=k * 50e-6, area_m2=SP * min(1.0, k / 20), t_ahead_k=900.0 + 5 * k,
                                power_w=0.0 if k == 0 else 250.0, speed_m_s=0.8, track=track,
                                track_elapsed_s=(k % 30) * 50e-6, track_remaining_s=(29 - k % 30) * 50e-6,
                                next_track=track < 2))
        if k == 65:  # 5 states into the layer's last track: the prediction carries what the turns taught
            expected = np.zeros(H)
            correction_into(5, False, -1, ctrl._correction_for(ctrl._turn), ctrl._correction_for(ctrl._turn + 1),
                            expected)
            assert np.any(expected) and np.array_equal(ctrl._kernel.correction, expected)
    assert ctrl._learned
    assert all(len(f.signatures) == 1 for f in (preview_kernel.update_into, preview_kernel.prepare_into,
                                                  preview_kernel.feedback_into))


def test_building_the_controller_compiles_every_compiled_function():
    """In a fresh interpreter, constructing the controller has compiled (or loaded) every numba
    function the update calls, so none compiles at a run's first state or first learned turn."""
    import subprocess
    import sys

    script = (
        "from controller_node.registry import make_controller\n"
        "from controller_node.settings import ControllerSettings\n"
        "from controller_node import preview_kernel as k, preview_stages as s\n"
        "from gp_model.narx import NarxGPModel\n"
        "from gp_model.shipped import PLATE_MODEL_PATH\n"
        "model = NarxGPModel.load(PLATE_MODEL_PATH)\n"
        "make_controller('preview-mpc', ControllerSettings(set_point_m2=6.3e-8), model)\n"
        "print([len(f.signatures) for f in (k.update_into, k.prepare_into, k.feedback_into, s._has_step,\n"
        "                                    s.forget_prediction)])\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, check=True, timeout=600)
    assert out.stdout.strip().splitlines()[-1] == "[1, 1, 1, 1, 1]"


@pytest.mark.parametrize("seed", range(6))
def test_the_plan_equals_cvxpy_at_random_states_of_the_shipped_model(model, seed):
    """Issue 12: the fast path (or DAQP where a bound is active) equals the cvxpy reference within
    1e-3 W, at random histories, plans and forecasts of the shipped model, with the power bounds of
    Table 3 and, for odd seeds, an upper area bound 3 % above the set point."""
    from controller_node.preview_qp import solve_reference

    area_max = SP * 1.03 if seed % 2 else 5e-7
    qp, p_hist, _, (gamma, c, _, _, _, hess, f, v, _, status) = _case(model, seed, area_max_m2=area_max,
                                                                         power_min_w=0.0)
    plan = v * qp.scale if status == 0 else qp.finish(gamma, c, hess, f, v).power_w
    assert np.max(np.abs(plan - solve_reference(qp, gamma, c, p_hist[0]))) < 1e-3


def test_an_absurd_state_gives_the_fallback_never_a_plan_from_it(model):
    """A plausible-looking but absurd temperature ahead (1e7 K) drives the log-area model past
    exp's range: the kernel flags the prediction, the update falls back, the power stays in bounds."""
    from controller_node.registry import make_controller
    from controller_node.settings import ControllerSettings
    from controller_node.types import Measurement

    settings = ControllerSettings(set_point_m2=SP)
    ctrl = make_controller("preview-mpc", settings, model)
    for k in range(30):
        ctrl.update(Measurement(step=k, time_s=k * 50e-6, area_m2=SP, t_ahead_k=900.0, power_w=250.0 if k else 0.0,
                                speed_m_s=0.8, track=0))
    cmd, diag = ctrl.update(Measurement(step=30, time_s=30 * 50e-6, area_m2=SP, t_ahead_k=1e7, power_w=250.0,
                                        speed_m_s=0.8, track=0))
    assert diag.status == "model_error" and diag.fallback
    assert ctrl.last_qp is None  # no QP from it (the workspace holds the absurd linearisation)
    assert settings.power_min_w <= cmd.power_w <= settings.power_max_w


def test_the_exponential_is_numpys_within_one_ulp():
    """exp_into, the kernel's vectorisable exponential, against numpy.exp over the kernel's range and
    at its edges: +inf above 709.78, 0 below -708, NaN kept."""
    rng = np.random.default_rng(0)
    x = np.r_[rng.uniform(-708.0, 709.0, 20000), rng.uniform(-1.0, 1.0, 20000), rng.uniform(-40.0, 0.0, 20000),
              -708.0, 0.0, 709.0, np.log(2.0) / 2, -np.log(2.0) / 2]
    got = x.copy()
    exp_into(got, np.zeros(x.size, dtype=np.int64))
    assert np.all(np.abs(got - np.exp(x)) <= np.spacing(np.exp(x)))
    edges = np.array([710.0, np.inf, -709.0, -np.inf, np.nan])
    exp_into(edges, np.zeros(edges.size, dtype=np.int64))
    assert edges[0] == edges[1] == np.inf and edges[2] == edges[3] == 0.0 and np.isnan(edges[4])


def test_one_update_pushes_forecasts_and_lays_out_the_correction_as_the_reference_functions(model):
    """The fused update's first steps: the histories shifted by p_fill/t_fill copies, T ahead forecast
    as gp_model.narx.forecast_t_ahead, the learned correction as correction_into (0 when nothing
    is learned)."""
    rng = np.random.default_rng(7)
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=1.0, power_scale_w=350.0, power_min_w=0.0, power_max_w=350.0,
                   area_min_m2=0.0, area_max_m2=5e-7, slack_linear=100.0, slack_quadratic=1000.0)
    work = Kernel(model, qp, 1, 0.0, len(model.turn_profile_k), 60, 0.3)
    work.p_hist[:] = p_before = rng.uniform(150.0, 300.0, work.p_hist.size)
    work.t_hist[:] = t_before = 900.0 + rng.normal(0.0, 50.0, work.t_hist.size).cumsum()
    work.profile[:] = rng.normal(0.0, 20.0, work.profile.size).cumsum()
    work.current[:], work.following[:] = rng.normal(0.0, 1e-9, 60), rng.normal(0.0, 1e-9, 60)
    work.plan[:] = rng.uniform(150.0, 300.0, H)
    for since, to_end, learned in ((12, 25, True), (3, -1, True), (40, 5, False)):
        work.p_hist[:], work.t_hist[:] = p_before, t_before
        context = StateContext(2, 210.0, 3, False, since, False, to_end, True, 950.0, learned, 0)
        assert work.update(context, 1010.0, 0.0) in (0, 1)
        assert np.array_equal(work.p_hist, np.r_[210.0, 210.0, p_before[:-2]])
        assert np.array_equal(work.t_hist, np.r_[t_before[3:], 1010.0, 1010.0, 1010.0])
        expected = forecast_t_ahead(1010.0, since, False, None if to_end < 0 else to_end, work.profile, H, 950.0,
                                    model.forecast_persistence)
        assert np.allclose(work.forecast, expected, rtol=1e-15, atol=0.0)
        correction = np.zeros(H)
        if learned:
            correction_into(since, False, to_end, work.current, work.following, correction)
            assert np.any(correction)
        assert np.array_equal(work.correction, correction)


def test_each_turn_of_a_layer_predicts_with_the_previous_layers_correction_of_that_turn(model):
    """Learning over layers: after turn j the kernel holds what the previous layer learned at turn j
    (and at turn j + 1 for the states after the next turn)."""
    from controller_node.learning_state import LEARNING_FORMAT
    from controller_node.registry import make_controller
    from controller_node.settings import ControllerSettings
    from controller_node.types import Measurement

    ctrl = make_controller("preview-mpc", ControllerSettings(set_point_m2=SP), model)
    by_turn = [np.full(60, (j + 1) * 1e-9) for j in range(3)]
    ctrl.load_learning_state({"format": LEARNING_FORMAT, "sample_period_s": model.sample_period_s,
                              "turn_correction_m2": [0.0] * 60,
                              "turn_corrections_by_turn_m2": [c.tolist() for c in by_turn],
                              "turn_profile_k": list(model.turn_profile_k)})
    for k in range(100):  # four tracks of 25 states: turns 0, 1, 2
        track = k // 25
        ctrl.update(Measurement(step=k, time_s=k * 50e-6, area_m2=SP * min(1.0, k / 20), t_ahead_k=900.0 + 5 * k,
                                power_w=0.0 if k == 0 else 250.0, speed_m_s=0.8, track=track,
                                track_elapsed_s=(k % 25) * 50e-6, track_remaining_s=(24 - k % 25) * 50e-6,
                                next_track=track < 3))
        if track and k % 25 == 3:
            assert np.array_equal(ctrl._kernel.current, by_turn[track - 1])
            assert np.array_equal(ctrl._kernel.following, by_turn[track] if track < 3 else ctrl.turn_correction_m2)


@pytest.mark.parametrize("after_turn", [False, True])
def test_the_observer_compares_the_state_with_the_last_prediction(model, after_turn):
    """d̂ ← d̂ + L (x[k] − x̂[k|k−1] − d̂), x̂[k|k−1] the previous update's row 0 completed with the
    power applied; the error is kept by state since the turn only after a turn."""
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=1.0, power_scale_w=350.0, power_min_w=-1e6, power_max_w=350.0,
                   area_min_m2=0.0, area_max_m2=5e-7, slack_linear=100.0, slack_quadratic=1000.0)
    work = Kernel(model, qp, 1, 0.0, len(model.turn_profile_k), 60, 0.3)
    work.p_hist[:], work.t_hist[:], work.plan[:] = 230.0, 1000.0, 240.0
    work.current[:] = work.following[:] = 2e-9
    estimator = work.estimator
    assert work.update(StateContext(0, 0.0, 0, False, 5, False, -1, after_turn, 950.0, True, 0), 1000.0, 0.0) in (0, 1)
    u1 = work.powers[work.p_hist.size]                  # ū[0] = p[k+1] of row 0
    b0, q0 = model.power_coefficients[0], model.power_map_coefficients[0]
    e0 = model.power_temperature_coefficients[0]
    base = work.z[0] - (b0 + q0 * u1 + e0 * 1000.0) * u1
    z_base, t_ahead_k, correction_m2 = estimator.prediction
    assert estimator.has_prediction and z_base == pytest.approx(base, rel=1e-14) and t_ahead_k == 1000.0
    assert correction_m2 == work.correction[0] == 2e-9
    applied, area, d_before = 215.0, 0.07e-6, estimator.disturbance_m2
    predicted = math.exp(base + (b0 + q0 * applied + e0 * 1000.0) * applied) + 2e-9
    work.update(StateContext(1, applied, 1, True, 6, False, -1, after_turn, 950.0, True, 0), 1005.0, area)
    error = area - predicted - d_before
    assert estimator.disturbance_m2 == pytest.approx(d_before + 0.3 * error, rel=1e-12)
    assert np.array_equal(np.flatnonzero(work.turn_error_seen), [6] if after_turn else [])
    if after_turn:
        assert work.turn_errors[6] == pytest.approx(error, rel=1e-12)


def test_the_estimator_steps_as_do_mpcs_make_step(model):
    """The estimator on its own: no prediction held, nothing moves; with one, d̂ moves by L times
    the one-step error, which is kept by state since the turn only after a turn."""
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=1.0, power_scale_w=350.0, power_min_w=-1e6, power_max_w=350.0,
                   area_min_m2=0.0, area_max_m2=5e-7, slack_linear=100.0, slack_quadratic=1000.0)
    kernel = Kernel(model, qp, 1, 0.0, len(model.turn_profile_k), 60, 0.3)
    estimator = kernel.estimator
    assert estimator.make_step(SP, 240.0, 3) == 0.0 and not estimator.has_prediction
    b0, q0 = model.power_coefficients[0], model.power_map_coefficients[0]
    e0 = model.power_temperature_coefficients[0]
    z_base = math.log(SP) - (b0 + q0 * 240.0 + e0 * 900.0) * 240.0 + 0.01
    for since_turn in (None, 3):
        estimator.reset()
        estimator.hold_prediction(z_base, 900.0, 1e-10)
        error = 1.05 * SP - (SP * math.exp(0.01) + 1e-10)
        assert estimator.make_step(1.05 * SP, 240.0, since_turn) == pytest.approx(0.3 * error, rel=1e-9)
        assert estimator.disturbance_m2 == pytest.approx(0.3 * error, rel=1e-9)
        assert np.array_equal(np.flatnonzero(kernel.turn_error_seen), [] if since_turn is None else [3])
        assert kernel.turn_errors[3] == (0.0 if since_turn is None else pytest.approx(error, rel=1e-9))
