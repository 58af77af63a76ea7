"""The smoothness prior on the delay-aware model's lag kernels (gp_model.narx.smoothing_rows and the
``smoothing`` of NarxGPModel.fit): rows within each smoothed group of lags only, and a smooth
T-ahead kernel recovered from a slowly varying T ahead, where the plain least squares alternates in
sign, while the power kernel is left to the data."""

from __future__ import annotations

import math

import numpy as np
import pytest

from gp_model.errors import DatasetError
from gp_model.narx import SMOOTHED_GROUPS, NarxGPModel, RunSeries, smoothing_rows

DT, SPEED = 50e-6, 0.8
C_TRUE = 1e-12 * np.sin(np.linspace(0.0, math.pi, 16)) ** 2 * 4.0    # a smooth T-ahead kernel [m²/K]
B_TRUE = 1e-12 * np.array([30.0, 30.0, 0.0, 0.0])                    # a sharp power kernel [m²/W]


def _run(seed: int, n: int = 400) -> RunSeries:
    """One track: T ahead a slow random walk (nearly collinear lags), power a staircase; the area the
    FIR of both plus noise."""
    rng = np.random.default_rng(seed)
    t = 600.0 + 3.0 * rng.standard_normal(n).cumsum()
    p = np.repeat(rng.uniform(150.0, 250.0, n), rng.integers(3, 10, n))[:n]
    p[0] = 0.0
    t_lagged = np.r_[t[:1], t[:-1]]                                  # x[j] sees T[j−1−m]
    area = (1e-8 + np.convolve(p, B_TRUE)[:n] + np.convolve(t_lagged, C_TRUE)[:n]
            + 2e-10 * rng.standard_normal(n))
    return RunSeries(f"walk-{seed}", area, t, p, np.zeros(n, dtype=int), DT, speed_m_s=SPEED)


def _fit(runs, smoothing):
    return NarxGPModel.fit(runs, n_power_lags=4, n_temperature_lags=16, quadratic=False, output="identity",
                           smoothing=smoothing, n_train=40, n_restarts=1, profile_length=10)


def test_rows_difference_consecutive_lags_within_each_smoothed_group_only():
    rows = smoothing_rows((3, 0, 2), 4.0)
    expected = 2.0 * np.array([[0, -1, 1, 0, 0, 0], [0, 0, -1, 1, 0, 0], [0, 0, 0, 0, -1, 1]], dtype=float)
    np.testing.assert_array_equal(rows, expected)                 # no row across a group's boundary
    np.testing.assert_array_equal(smoothing_rows((3, 0, 2), 4.0, (False, True, True)), expected[2:])
    assert smoothing_rows((3, 2), 0.0).shape == (0, 6)
    assert SMOOTHED_GROUPS == (False, False, True, True, True, True, False, False)   # power, power², remnant: data
    for bad in (-1.0, math.nan, math.inf):
        with pytest.raises(DatasetError, match="smoothing must be a finite number >= 0"):
            smoothing_rows((3,), bad)


def test_the_prior_recovers_a_smooth_temperature_kernel_and_leaves_the_power_kernel():
    runs = [_run(s) for s in range(2)]
    plain, smooth = _fit(runs, 0.0), _fit(runs, 0.01)
    error = [np.linalg.norm(m.temperature_coefficients - C_TRUE) / np.linalg.norm(C_TRUE) for m in (plain, smooth)]
    assert error[1] < 0.5 * error[0]
    assert np.sum(np.diff(np.sign(np.diff(smooth.temperature_coefficients))) != 0) < np.sum(
        np.diff(np.sign(np.diff(plain.temperature_coefficients))) != 0)
    np.testing.assert_allclose(smooth.power_coefficients, B_TRUE, rtol=0.05, atol=1e-12)  # still sharp
    assert smooth.provenance["smoothing"] == 0.01 and plain.provenance["smoothing"] == 0.0
