"""The compiled condensed QP (controller_node.qp_condensed): its terms against numpy, its solutions against DAQP."""

from __future__ import annotations

import subprocess
import sys

import daqp
import numpy as np
import pytest

from controller_node.qp_condensed import condense_into

H = 20


def _reference(a, a_prev, beta, g, e0, e_prev, u_prev, weights, r, move):
    """Γ, c, Hessian and gradient by the textbook formulas, in numpy."""
    h = weights.size
    impulse = np.empty(h)
    impulse[0] = 1.0
    for n in range(1, h):
        impulse[n] = a * impulse[n - 1] + (a_prev * impulse[n - 2] if n >= 2 else 0.0)
    gamma = np.zeros((h, h))
    for j in range(h):
        for i in range(j + 1):
            gamma[j, i] = beta * impulse[j - i]
    c = np.empty(h)
    older, old = e_prev, e0
    for n in range(h):
        older, old = old, a * old + a_prev * older + g
        c[n] = old
    diff = np.eye(h) - np.eye(h, k=-1)
    r_u = 2.0 * r * (diff.T @ diff if move else np.eye(h))
    hess = 2.0 * gamma.T @ np.diag(weights) @ gamma + r_u
    grad = 2.0 * gamma.T @ (weights * c)
    if move:
        grad[0] -= 2.0 * r * u_prev
    return gamma, c, hess, grad, r_u


def _run(params, r, move, bounds):
    a, a_prev, beta, g, e0, e_prev, u_prev = params
    weights = np.full(H, 1.0)
    weights[-1] = 20.0
    gamma_ref, c_ref, hess_ref, grad_ref, r_u = _reference(*params, weights, r, move)
    out = [np.full((H, H), np.nan), np.full(H, np.nan), np.full((H, H), np.nan), np.full(H, np.nan), np.empty(H),
           np.empty(H)]
    gamma, c, hess, grad, u, e = out
    status = condense_into(a, a_prev, beta, g, e0, e_prev, u_prev, weights, r_u, r if move else 0.0,
                           np.asarray(bounds, dtype=float), gamma, c, hess, grad, u, e)
    return status, out, (gamma_ref, c_ref, hess_ref, grad_ref)


def _params(rng):
    return (rng.uniform(0.3, 0.95), rng.uniform(-0.3, 0.3), rng.uniform(0.05, 0.5), rng.normal(0.0, 0.02),
            rng.normal(0.0, 0.2), rng.normal(0.0, 0.2), rng.normal(0.0, 1.0))


LOOSE = (-1e9, 1e9, -1e9, 1e9, -1e9, 1e9)


@pytest.mark.parametrize("move", [True, False])
def test_terms_match_numpy_and_the_optimum_solves_the_unconstrained_qp(move):
    rng = np.random.default_rng(3)
    for _ in range(50):
        params = _params(rng)
        status, (gamma, c, hess, grad, u, e), (gamma_ref, c_ref, hess_ref, grad_ref) = _run(params, 0.1, move, LOOSE)
        assert status == 0
        np.testing.assert_allclose(gamma, gamma_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(c, c_ref, rtol=1e-12, atol=1e-15)
        np.testing.assert_allclose(hess, hess_ref, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(grad, grad_ref, rtol=1e-12, atol=1e-14)
        np.testing.assert_allclose(u, np.linalg.solve(hess_ref, -grad_ref), rtol=1e-9, atol=1e-12)
        np.testing.assert_allclose(e, c_ref + gamma_ref @ u, rtol=1e-12, atol=1e-14)


@pytest.mark.parametrize("bound", range(2, 6))
def test_a_rate_or_area_bound_just_past_the_optimum_sends_the_qp_to_daqp(bound):
    """Tighten one rate or area bound just inside the unconstrained optimum's extreme value: the
    compiled call does not claim the solution."""
    rng = np.random.default_rng(11)
    params = _params(rng)
    _, (_, _, _, _, u, e), _ = _run(params, 0.1, True, LOOSE)
    moves = np.diff(np.r_[params[6], u])
    extreme = [u.min(), u.max(), moves.min(), moves.max(), e.min(), e.max()][bound]
    bounds = list(LOOSE)
    bounds[bound] = extreme + (0.01 if bound % 2 == 0 else -0.01) * max(abs(extreme), 1e-3)
    status, _, _ = _run(params, 0.1, True, bounds)
    assert status == -1


def _daqp_box(hess, grad, lo, hi):
    """DAQP's solution of the QP with the box bounds only (the library result, to its primal
    tolerance of 1e-6)."""
    x, _, flag, _ = daqp.solve(hess.copy(), grad.copy(), np.zeros((0, H)), np.full(H, hi), np.full(H, lo),
                               np.zeros(H, dtype=np.int32))
    assert flag == 1
    return x


@pytest.mark.parametrize("move", [True, False])
def test_the_active_set_solves_the_power_bounded_qp_as_daqp_does(move):
    """Power bounds cut through the unconstrained optimum (or hold all of it at a bound): the compiled
    active set keeps the bounds exactly, meets the optimality conditions (gradient zero on the free
    inputs, of the right sign at each bound) and agrees with DAQP to DAQP's tolerance."""
    rng = np.random.default_rng(17 if move else 19)
    iterations = []
    for trial in range(200):
        params = _params(rng)
        _, (_, _, _, _, u_free, _), _ = _run(params, 0.1, move, LOOSE)
        if trial % 4 == 0:      # the whole plan beyond one bound: a saturated laser
            lo, hi = (u_free.max() + 0.1, u_free.max() + 1.0) if trial % 8 == 0 else (u_free.min() - 1.0,
                                                                                     u_free.min() - 0.1)
        else:
            lo, hi = np.sort(rng.uniform(u_free.min(), u_free.max(), 2))
        status, (gamma, c, hess, grad, u, e), _ = _run(params, 0.1, move, (lo, hi, *LOOSE[2:]))
        assert status > 0, trial
        iterations.append(status)
        np.testing.assert_allclose(u, _daqp_box(hess, grad, lo, hi), rtol=0, atol=2e-6)
        assert np.all((u >= lo) & (u <= hi))
        r = hess @ u + grad
        tol = 1e-9 * (1.0 + np.abs(grad).max())
        at_lo, at_hi = u == lo, u == hi
        assert np.all(np.abs(r[~at_lo & ~at_hi]) <= tol)
        assert np.all(r[at_lo] >= -tol) and np.all(r[at_hi] <= tol)
        np.testing.assert_allclose(e, c + gamma @ u, rtol=1e-12, atol=1e-14)
    assert max(iterations) >= 3   # problems where the active set had to free or add several bounds


def test_feasible_optimum_equals_daqp():
    """Where no bound binds, the compiled optimum is DAQP's solution of the bounded QP."""
    rng = np.random.default_rng(5)
    for _ in range(30):
        params = _params(rng)
        bounds = (-50.0, 50.0, -50.0, 50.0, -50.0, 50.0)
        status, (gamma, c, hess, grad, u, e), _ = _run(params, 0.1, True, bounds)
        assert status == 0
        diff = np.eye(H) - np.eye(H, k=-1)
        bu = np.r_[np.full(H, 50.0), params[6] + 50.0, np.full(H - 1, 50.0)]
        bl = -np.r_[np.full(H, 50.0), -params[6] + 50.0, np.full(H - 1, 50.0)]
        x, _, flag, _ = daqp.solve(hess.copy(), grad.copy(), diff, bu, bl, np.zeros(2 * H, dtype=np.int32))
        assert flag == 1
        np.testing.assert_allclose(u, x, rtol=1e-9, atol=1e-12)


def test_the_backend_is_compiled_when_built():
    """Building the DAQP backend compiles (or loads) the condensing: no compilation at a run's first
    state. In a fresh process, where no earlier call compiled it."""
    code = (
        "from controller_node import ControllerSettings\n"
        "from controller_node.qp import QPData\n"
        "from controller_node.qp_condensed import condense_into\n"
        "from controller_node.qp_daqp import DaqpBackend\n"
        "backend = DaqpBackend(ControllerSettings())\n"
        "known = len(condense_into.signatures)\n"
        "sol = backend.solve(QPData(a=0.8, beta=0.2, g=0.01, e0=0.1, u_lo=-5.0, u_hi=5.0, u_prev=0.3,\n"
        "                           p_ref_w=200.0, a_prev=0.05, e_prev=0.12))\n"
        "print(sol.status, sol.iterations, known, len(condense_into.signatures))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[:2] == ["solved", "0"] and out[2] == out[3]


def test_indefinite_hessian_is_not_solved():
    """A Hessian without a Cholesky factor (a negative input weight) never passes as solved."""
    rng = np.random.default_rng(2)
    status, _, _ = _run(_params(rng), -10.0, False, LOOSE)
    assert status == -1
