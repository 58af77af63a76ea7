"""The turnaround feature (gp_model.plan_feature): linear in power, a superposition of the moving
source's heat-equation solution that matches its quadrature."""

import math

import numpy as np
import pytest
from scipy import integrate

from gp_model.plan_feature import RemnantFeature, TurnFeature, remnant_series, turn_feature_series

DT, STEP = 50e-6, 40e-6


def _runs():
    """Two tracks after a first one: 3 tracks of 90 states, a turn at 90 and 180."""
    track = np.repeat([0, 1, 2], 90)
    starts = np.array([90, 180])
    ends = np.repeat([89, 179, 269], 90)
    return track, starts, ends


def test_feature_is_the_plan_matrix_times_the_powers_and_linear():
    feature = TurnFeature(n_targets=40, n_sources=70)
    kernel = feature.kernel(STEP, DT)
    _, starts, ends = _runs()
    n = ends.size
    matrix = np.zeros((n, n))                      # K[k, j] of the plan, written out
    for start in starts:
        for s in range(min(feature.n_targets, ends[start] + 1 - start)):
            for e in range(min(feature.n_sources, start)):
                matrix[start + s, start - 1 - e] = kernel[s, e]
    rng = np.random.default_rng(0)
    p1, p2 = rng.uniform(100, 350, n), rng.uniform(100, 350, n)
    f1 = turn_feature_series(kernel, p1, starts, ends)
    np.testing.assert_allclose(f1, matrix @ p1, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(turn_feature_series(kernel, p1 + 3.0 * p2, starts, ends),
                               f1 + 3.0 * turn_feature_series(kernel, p2, starts, ends), rtol=1e-12, atol=1e-9)
    assert np.all(f1[:90] == 0.0) and np.all(f1[90 + 40:180] == 0.0) and np.all(f1[90:130] > 0)


def test_green_function_is_the_point_source_over_the_gaussian_beam():
    f = TurnFeature()
    alpha, rho_cp, sigma = f.diffusivity_m2_s, f.volumetric_heat_j_m3_k, f.beam_sigma_m
    for r, tau in ((0.0, 2e-4), (1e-4, 1e-3), (6e-5, 4e-4)):
        def point(y, x, r=r, tau=tau):
            beam = np.exp(-(x * x + y * y) / (2 * sigma**2)) / (2 * math.pi * sigma**2)
            d2 = (r - x) ** 2 + y * y
            return beam * 2.0 / (rho_cp * (4 * math.pi * alpha * tau) ** 1.5) * math.exp(-d2 / (4 * alpha * tau))
        span = 8 * sigma
        direct, _ = integrate.dblquad(point, -span, span, -span, span, epsabs=0, epsrel=1e-9)
        assert float(f.green_k_per_j(r, tau)) == pytest.approx(direct, rel=1e-6)


def test_kernel_is_the_moving_source_integral_of_the_previous_track():
    """Constant power P along the previous track (it ends at the turn, t = 0, x = 0): Σ_e K[s, e] P
    against the time integral of the moving Gaussian source, at the laser run back beside it."""
    f = TurnFeature(n_sources=400)
    kernel, power = f.kernel(STEP, DT), 250.0
    v = STEP / DT
    for s in (2, 10, 30):
        t_s, x_s = (s + 1) * DT, -(s + 1) * STEP     # the laser in state t0 + s

        def heat(t, x_s=x_s, t_s=t_s):                                  # the source at time t < 0 is at x = v t
            return f.absorptivity * power * float(f.green_k_per_j(math.hypot(x_s - v * t, f.hatch_m), t_s - t))
        direct, _ = integrate.quad(heat, -400 * DT, 0.0, limit=400, epsrel=1e-10)
        assert kernel[s] @ np.full(f.n_sources, power) == pytest.approx(direct, rel=0.02)


def test_constants_round_trip_and_bad_ones_are_refused():
    f = TurnFeature(hatch_m=9e-5)
    assert TurnFeature.from_dict(f.to_dict()) == f
    with pytest.raises(ValueError, match="hatch_m"):
        TurnFeature(hatch_m=0.0)
    with pytest.raises(ValueError, match="n_sources"):
        TurnFeature(n_sources=0)
    with pytest.raises(ValueError, match="unknown keys"):
        TurnFeature.from_dict({**f.to_dict(), "extra": 1})


def test_the_default_feature_decays_along_a_whole_track_without_a_step():
    """A 10 mm track at 0.8 m/s (250 states) after a turn: the feature falls smoothly from its peak to the
    track's end; it does not drop to 0 in the middle of the track (a step in the heat the model would see
    and the plant does not, which moved the preview MPC's power along every track)."""
    f = TurnFeature()
    n = 250
    power = np.r_[0.0, np.full(n - 1, 180.0), np.full(n, 180.0)]
    ends = np.r_[np.full(n, n - 1), np.full(n, 2 * n - 1)]
    after = turn_feature_series(f.kernel(STEP, DT), power, np.array([n]), ends)[n:]
    peak = int(np.argmax(after))
    assert np.all(after > 0) and np.all(np.diff(after[peak:]) < 0)
    assert np.max(-np.diff(after[50:])) < 0.05 * after[50]     # no step along the rest of the track


def test_remnant_series_is_the_mean_of_the_previous_tracks_last_powers_by_state_after_the_turn():
    """Written out: the state s < n_states after a turn gets P̄ (the previous track's last n_sources powers'
    mean) in column s and 1 beside it; every other entry is 0; the terms ``Σ_e W[s, e] p`` of the kernel are
    ``h_s P̄``, and the series is linear in power."""
    remnant = RemnantFeature(n_states=12, n_sources=7)
    _, starts, ends = _runs()
    n = ends.size
    rng = np.random.default_rng(1)
    p1, p2 = rng.uniform(100, 350, n), rng.uniform(100, 350, n)
    slopes, ones = remnant_series(remnant, p1, starts, ends)
    direct_slopes, direct_ones = np.zeros((n, 12)), np.zeros((n, 12))
    for j in range(n):
        start = 90 if 90 <= j < 180 else 180 if j >= 180 else None
        if start is not None and j - start < 12:
            direct_slopes[j, j - start] = sum(p1[start - 1 - e] for e in range(7)) / 7
            direct_ones[j, j - start] = 1.0
    np.testing.assert_allclose(slopes, direct_slopes, rtol=1e-12)
    np.testing.assert_array_equal(ones, direct_ones)
    np.testing.assert_allclose(remnant_series(remnant, p1 + 3.0 * p2, starts, ends)[0],
                               slopes + 3.0 * remnant_series(remnant, p2, starts, ends)[0], rtol=1e-12)
    h = rng.normal(size=12)
    kernel = remnant.kernel(h)
    for start in starts:
        for s in range(12):
            assert kernel[s] @ p1[start - 1 - np.arange(7)] == pytest.approx(h[s] * slopes[start + s, s], rel=1e-12)


def test_remnant_constants_round_trip_and_bad_ones_are_refused():
    r = RemnantFeature(n_states=30, n_sources=8, offsets=True)
    assert RemnantFeature.from_dict(r.to_dict()) == r
    with pytest.raises(ValueError, match="n_states"):
        RemnantFeature(n_states=0)
    with pytest.raises(ValueError, match="offsets"):
        RemnantFeature(offsets=1)
    with pytest.raises(ValueError, match="missing keys"):
        RemnantFeature.from_dict({"n_states": 3})
    with pytest.raises(ValueError, match="shape"):
        r.kernel(np.zeros(29))
