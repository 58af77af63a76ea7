"""Synthetic melt-pool recordings shaped like the paper's Table 2 campaign (tests, demos).

A stand-in for the FE plant so that the dataset → train → evaluate pipeline can be exercised
without it. The dynamics is a first-order lag of the top-surface area towards a quasi-steady
area with Rosenthal-like scalings,

    x_ss(T, p, v) = x_ref (p / 250 W)^1.3 (0.8 m/s / v)^0.6 ((T_l − 300 K) / (T_l − T))^0.5,
    x[k+1] = x_k + (1 − exp(−Δt v / L)) (x_ss − x_k),  L = 0.5 mm (pool length, lag in space),

and a surface temperature ahead of the laser that is ambient on a first track and starts hot
next to the previous track, decaying exponentially along it (paper Fig. 3c). Each track starts
with no pool (area 0), so start-up steps are present as in the FE data.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from messages.in625 import T_LIQUIDUS_K

T_AMBIENT_K = 300.0
DT_S = 50e-6
TRACK_LENGTH_M = 5e-3


@dataclass(frozen=True)
class SyntheticState:
    """One plant state with the fields of ``messages.MeltPoolState`` the dataset uses."""

    step: int
    time_s: float
    track: int
    area_mm2: float
    t_ahead_k: float
    power_w: float
    speed_mm_s: float


def steady_area_m2(t_k: np.ndarray | float, power_w: np.ndarray | float, speed_m_s: np.ndarray | float,
                   area_ref_m2: float = 0.07e-6) -> np.ndarray | float:
    """Quasi-steady top-surface area [m²] at temperature [K], power [W] and speed [m/s]."""
    preheat = ((T_LIQUIDUS_K - T_AMBIENT_K) / (T_LIQUIDUS_K - np.minimum(t_k, T_LIQUIDUS_K - 50.0))) ** 0.5
    return area_ref_m2 * (np.asarray(power_w) / 250.0) ** 1.3 * (0.8 / np.asarray(speed_m_s)) ** 0.6 * preheat


def next_area_m2(area_m2: float, t_k: float, power_w: float, speed_m_s: float) -> float:
    """One step of the synthetic dynamics ``x[k+1] = f(x_k, T_k, p_k, v_k)`` [m²]."""
    gain = 1.0 - math.exp(-DT_S * speed_m_s / 0.5e-3)
    return float(area_m2 + gain * (steady_area_m2(t_k, power_w, speed_m_s) - area_m2))


def _profile(kind: str, t: float, mean: float, amplitude: float, period_s: float) -> float:
    if kind == "constant":
        return mean
    if kind == "sinusoidal":
        return mean + amplitude * math.sin(2.0 * math.pi * t / period_s)
    # "profile": a staircase of levels, as in the paper's case 9 (Fig. 3a)
    levels = (0.0, 1.0, -0.6, 0.4, -1.0, 0.7)
    return mean + amplitude * levels[int(t / period_s * 2.0) % len(levels)]


def table2_case(case: int, *, noise_rel: float = 0.0, seed: int = 0) -> list[SyntheticState]:
    """States of a synthetic version of Table 2 case ``case`` (1-9), 5 mm tracks.

    Parameters
    ----------
    case : int
        1-4 single track (power/speed constant or sinusoidal), 5-7 double track at hatch
        0.1/0.15/0.05 mm, 8-9 double track with sinusoid/staircase profiles.
    noise_rel : float
        Relative Gaussian measurement noise on the area (e.g. 0.002 for raster noise).
    seed : int
        Seed of the noise.

    Returns
    -------
    list[SyntheticState]
        One state per 50 µs step, starting with step 0 (no pool yet).
    """
    power_kind, speed_kind, hatch_mm, n_tracks = {
        1: ("constant", "constant", 0.1, 1), 2: ("sinusoidal", "constant", 0.1, 1),
        3: ("constant", "sinusoidal", 0.1, 1), 4: ("sinusoidal", "sinusoidal", 0.1, 1),
        5: ("constant", "constant", 0.1, 2), 6: ("constant", "constant", 0.15, 2),
        7: ("constant", "constant", 0.05, 2), 8: ("sinusoidal", "profile", 0.1, 2),
        9: ("profile", "profile", 0.1, 2),
    }[case]
    rng = np.random.default_rng(seed)
    states = [SyntheticState(0, 0.0, 0, 0.0, T_AMBIENT_K, 0.0, 800.0)]
    area, step = 0.0, 0
    peak_rise = 900.0 * (0.1 / hatch_mm) ** 0.7
    for track in range(n_tracks):
        position, area = 0.0, 0.0
        while position < TRACK_LENGTH_M:
            t = step * DT_S
            t_ahead = T_AMBIENT_K + (peak_rise * math.exp(-position / 1.0e-3) + 60.0 if track else 0.0)
            power = _profile(power_kind, t, 250.0, 70.0, 2.5e-3)
            speed = _profile(speed_kind, t, 0.8, 0.2, 2.0e-3)
            area = next_area_m2(area, t_ahead, power, speed)
            position += speed * DT_S
            step += 1
            noisy = area * (1.0 + noise_rel * rng.standard_normal())
            next_t_ahead = T_AMBIENT_K + (peak_rise * math.exp(-position / 1.0e-3) + 60.0 if track else 0.0)
            states.append(SyntheticState(step, step * DT_S, track, noisy * 1e6, next_t_ahead, power, speed * 1e3))
    return states
