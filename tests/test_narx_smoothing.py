"""The smoothness prior on the delay-aware model's lag kernels (gp_model.narx.smoothing_rows and the
``smoothing`` of NarxGPModel.fit): rows within each group of lags only, and a smooth kernel recovered
from staircase data whose long holds make the plain least squares alternate in sign."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gp_model.errors import DatasetError
from gp_model.narx import NarxGPModel, RunSeries, smoothing_rows

DT, SPEED = 50e-6, 0.8
B_TRUE = 1e-12 * np.sin(np.linspace(0.0, math.pi, 16)) ** 2 * 40.0   # a smooth power kernel [m²/W]


def _staircase(seed: int, n: int = 400) -> RunSeries:
    """One track: power held 10-30 steps at random levels, area the FIR of B_TRUE plus noise."""
    rng = np.random.default_rng(seed)
    holds = rng.integers(10, 31, n)
    p = np.repeat(rng.uniform(150.0, 250.0, n), holds)[:n]
    p[0] = 0.0
    area = 1e-8 + np.convolve(p, B_TRUE)[:n] + 2e-9 * rng.standard_normal(n)
    return RunSeries(f"stairs-{seed}", area, np.full(n, 500.0), p, np.zeros(n, dtype=int), DT, speed_m_s=SPEED)


def _fit(runs, smoothing):
    return NarxGPModel.fit(runs, n_power_lags=16, n_temperature_lags=1, quadratic=False, output="identity",
                           smoothing=smoothing, n_train=40, n_restarts=1, profile_length=10)


def test_rows_difference_consecutive_lags_within_each_group_only():
    rows = smoothing_rows((3, 0, 2), 4.0)
    expected = 2.0 * np.array([[0, -1, 1, 0, 0, 0], [0, 0, -1, 1, 0, 0], [0, 0, 0, 0, -1, 1]], dtype=float)
    np.testing.assert_array_equal(rows, expected)                 # no row across a group's boundary
    assert smoothing_rows((3, 2), 0.0).shape == (0, 6)
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(DatasetError, match="smoothing must be a finite number >= 0"):
            smoothing_rows((3,), bad)


def test_the_prior_recovers_a_smooth_kernel_that_plain_least_squares_does_not():
    runs = [_staircase(s) for s in range(2)]
    plain, smooth = _fit(runs, 0.0), _fit(runs, 0.01)
    error = [np.linalg.norm(m.power_coefficients - B_TRUE) / np.linalg.norm(B_TRUE) for m in (plain, smooth)]
    assert error[1] < 0.5 * error[0]
    assert np.sum(np.diff(np.sign(np.diff(smooth.power_coefficients))) != 0) < np.sum(
        np.diff(np.sign(np.diff(plain.power_coefficients))) != 0)
    assert smooth.provenance["smoothing"] == 0.01 and plain.provenance["smoothing"] == 0.0
