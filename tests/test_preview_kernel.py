"""The compiled hot path of the preview MPC (controller_node.preview_kernel) against the numpy/LAPACK
formulation: the GP's variance, the QP's Hessian and gradient, the Cholesky solve."""

from __future__ import annotations

import numpy as np
import pytest

from controller_node.preview_kernel import (
    Workspace,
    _linearised_qp,
    _regressors,
    correction_into,
    linearise,
    push_history,
)
from controller_node.preview_qp import PreviewQP
from gp_trainer.narx import DEFAULT_MODEL_PATH, STEPS_SINCE_START_CAP, NarxGPModel, forecast_into

H = 40
SP = 0.063e-6


@pytest.fixture(scope="module")
def model() -> NarxGPModel:
    return NarxGPModel.load(DEFAULT_MODEL_PATH)


def _case(model: NarxGPModel, seed: int, *, r: float = 1.0, blind: int = 0, n_variance: int = H,
          area_max_m2: float = 5e-7, z_sigma: float = 0.0, power_min_w: float = -1e6, power_max_w: float = 350.0,
          stale: float | None = None):
    rng = np.random.default_rng(seed)
    n_p, n_t = model.power_coefficients.size, model.temperature_coefficients.size
    qp = PreviewQP(H, SP, q=1.0, q_f=20.0, r=r, power_scale_w=350.0, power_min_w=power_min_w, power_max_w=power_max_w,
                   area_min_m2=0.0, area_max_m2=area_max_m2, slack_linear=100.0, slack_quadratic=1000.0)
    p_hist = rng.uniform(150.0, 300.0, n_p)
    t_hist = 900.0 + rng.normal(0.0, 50.0, n_t).cumsum()
    forecast = t_hist[-1] + rng.normal(0.0, 20.0, H).cumsum()
    plan = _case.plan = rng.uniform(150.0, 300.0, H)
    scalars, points, var_f = model.residual.kernel_terms()
    coef = (np.array([model.intercept]), model.power_coefficients, model.power_square_coefficients,
            model.temperature_coefficients, model.temperature_square_coefficients,
            model.power_temperature_coefficients)
    terms = np.r_[SP, qp.scale, qp.r, p_hist[0], qp.v_lo, qp.v_hi, qp.e_lo, qp.e_hi, z_sigma, qp.weights]
    work = Workspace(H, n_p, n_t, points.shape[1])
    if stale is not None:  # what a previous update left in the workspace
        for array in (work.matrices, work.vectors, work.psi, work.kern, work.powers, work.temps):
            array[...] = stale
    status = linearise(p_hist, t_hist, forecast, plan, int(rng.integers(0, 300)), int(rng.integers(-1, H)),
                       float(STEPS_SINCE_START_CAP), True, coef, scalars, points, var_f, n_variance, np.zeros(H),
                       0.0, terms, qp.moves, blind, work)
    out = (work.gamma, work.c, work.predicted, work.z, work.std, work.hess, work.f, work.v, work.areas, status)
    return qp, p_hist, work.psi, out


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
    assert np.allclose(std, np.exp(z) * np.sqrt(var + model.residual.noise_variance), rtol=1e-9, atol=0.0)


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
    *_, (_, _, _, _, _, _, _, v, _, status) = _case(model, 0, r=0.0, blind=H)  # nothing tracked, no move penalty
    assert np.all(np.isnan(v)) and status == 1


def test_a_closed_loop_compiles_the_kernel_once(model):
    """Every update calls the kernel with the argument types of its first (warm-up) call: no
    recompilation, of seconds, in the middle of a run."""
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
    assert ctrl._learned
    assert all(len(f.signatures) == 1 for f in (_regressors, _linearised_qp, push_history, forecast_into,
                                                   correction_into))


def test_building_the_controller_compiles_every_compiled_function():
    """In a fresh interpreter, constructing the controller has compiled (or loaded) every numba
    function the update calls, so none compiles at a run's first state or first learned turn."""
    import subprocess
    import sys

    script = (
        "from controller_node.registry import make_controller\n"
        "from controller_node.settings import ControllerSettings\n"
        "from controller_node import preview_kernel as k\n"
        "from gp_trainer.narx import DEFAULT_MODEL_PATH, NarxGPModel, forecast_into\n"
        "model = NarxGPModel.load(DEFAULT_MODEL_PATH)\n"
        "make_controller('preview-mpc', ControllerSettings(set_point_m2=6.3e-8), model)\n"
        "print([len(f.signatures) for f in (k._regressors, k._linearised_qp, k.push_history, k.correction_into,"
        " forecast_into)])\n"
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
