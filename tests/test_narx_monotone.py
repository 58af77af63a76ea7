"""The delay-aware model's response to power keeps its sign over every commandable power
(gp_model.narx.least_squares_with_gains, static_power_gains and ``monotone_power_w`` of
NarxGPModel.fit): a fit of the squared power lags (``power_map="square"``) on staircases between 150 and 250 W would
otherwise put the vertex of its parabola inside the controller's range, where a model that says
"more power, smaller pool" drives the preview MPC to full power above its set point."""

from __future__ import annotations

import numpy as np
import scipy.optimize

from gp_model.narx import MONOTONE_POWER_W, NarxGPModel, RunSeries, least_squares_with_gains, static_power_gains
from messages.types import LASER_POWER_MAX_W

DT, SPEED = 50e-6, 0.8
B_TRUE = np.array([0.004, 0.004, 0.002, 0.0])                        # [1/W]: Σ 0.01
Q_TRUE = -np.array([2.0, 2.0, 1.0, 0.0]) / 3.0 * 0.01 / (2 * 300.0)   # [1/W²]: the static gain is 0 at 300 W


def _run(seed: int, n: int = 400) -> RunSeries:
    """A track under a power staircase between 150 and 250 W; log area quadratic in the lagged powers."""
    rng = np.random.default_rng(seed)
    p = np.repeat(rng.uniform(150.0, 250.0, n), rng.integers(3, 10, n))[:n]
    p[0] = 0.0
    t = 600.0 + 3.0 * rng.standard_normal(n).cumsum()
    lags = np.stack([np.r_[np.zeros(i), p[:n - i]] for i in range(4)], axis=1)
    z = -16.0 + lags @ B_TRUE + (lags * lags) @ Q_TRUE + 1e-3 * rng.standard_normal(n)
    return RunSeries(f"concave-{seed}", np.exp(z), t, p, np.zeros(n, dtype=int), DT, speed_m_s=SPEED)


def _fit(runs, monotone_power_w):
    return NarxGPModel.fit(runs, n_power_lags=4, n_temperature_lags=2, output="log", n_train=40, n_restarts=1,
                           profile_length=10, monotone_power_w=monotone_power_w, power_map="square")


def _static_gain(model: NarxGPModel, power_w: float) -> float:
    return float(model.power_coefficients.sum() + 2.0 * power_w * model.power_map_coefficients.sum())


def test_the_fit_keeps_the_power_gain_non_negative_up_to_the_highest_power():
    runs = [_run(s) for s in range(3)]
    free, held = _fit(runs, None), _fit(runs, MONOTONE_POWER_W)
    assert MONOTONE_POWER_W == (0.0, LASER_POWER_MAX_W)
    assert _static_gain(free, LASER_POWER_MAX_W) < -1e-3          # the data alone: past the vertex at 350 W
    assert min(_static_gain(held, p) for p in np.linspace(0.0, LASER_POWER_MAX_W, 36)) >= -1e-9
    assert _static_gain(held, 200.0) > 0.5 * _static_gain(free, 200.0)   # still the staircases' response there
    assert held.provenance["monotone_power_w"] == [0.0, LASER_POWER_MAX_W]
    assert free.provenance["monotone_power_w"] is None


def test_the_gain_rows_are_the_steady_state_derivative_of_the_lag_part():
    sizes = (2, 2, 3, 1, 2, 1, 0, 0)
    rng = np.random.default_rng(1)
    theta = rng.standard_normal(1 + sum(sizes))
    b, q, e = theta[1:3], theta[3:5], theta[9:11]
    rows = static_power_gains(sizes, (0.0, 350.0), (300.0, 900.0), "square")
    expected = [b.sum() + 2 * p * q.sum() + t * e.sum() for p in (0.0, 350.0) for t in (300.0, 900.0)]
    np.testing.assert_allclose(rows @ theta, expected, rtol=1e-12)


def test_constrained_least_squares_keeps_left_out_terms_at_zero_and_matches_a_general_solver():
    a = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])     # the third term is left out (a zero column)
    b = np.array([-1.0, 2.0])
    np.testing.assert_array_equal(least_squares_with_gains(a, b, np.array([[0.0, 1.0, 0.0]])),
                                  np.linalg.lstsq(a, b, rcond=None)[0])      # feasible: lstsq itself
    theta = least_squares_with_gains(a, b, np.array([[1.0, 0.0, 5.0]]))
    np.testing.assert_allclose(theta, [0.0, 2.0, 0.0], atol=1e-7)          # not θ₃ > 0 at no cost
    rng = np.random.default_rng(2)
    a, b = rng.standard_normal((60, 8)), rng.standard_normal(60)
    gains = rng.standard_normal((3, 8))
    assert not np.all(gains @ np.linalg.lstsq(a, b, rcond=None)[0] >= 0)    # the constraints bind
    theta = least_squares_with_gains(a, b, gains)
    reference = scipy.optimize.minimize(lambda x: np.sum((a @ x - b) ** 2), np.zeros(8), method="SLSQP",
                                        constraints={"type": "ineq", "fun": lambda x: gains @ x},
                                        options={"ftol": 1e-14, "maxiter": 500})
    assert np.all(gains @ theta >= -1e-8)
    assert np.sum((a @ theta - b) ** 2) <= reference.fun * (1 + 1e-6)
