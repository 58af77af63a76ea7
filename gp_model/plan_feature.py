"""A scan-plan thermal feature: the heat of the previous track at the laser after a turnaround.

After a turnaround of a serpentine plan the laser runs back beside the track it has just
scanned, ``hatch_m`` away, and the heat that track left (set by the powers applied along its
end) raises the pool's area for tens of states. The delay-aware model's lags (powers of the
last n_p states, T ahead measured at one point) do not carry it, and over a horizon T ahead is
forecast as a fixed profile, so a model without this feature cannot see that a power change
before a turn changes the pool after it (``benchmarks/turn_sensitivity.py``).

The feature is the temperature rise [K] that the previous track's last :attr:`TurnFeature.n_sources`
steps of power cause at the laser, by superposed moving-source solutions of the heat equation
(constant effective properties, adiabatic half-space, Gaussian beam)::

    F[t₀ + s] = Σ_{e < n_sources} K[s, e] p[t₀ − 1 − e]        s < n_targets, 0 beyond
    K[s, e]   = a Δt G(r, τ),   r² = ((e − s − ½) d)² + h²,   τ = (s + e + 3/2) Δt
    G(r, τ)   = 2 / (ρc) · exp(−r² / (2 (σ² + 2ατ))) / (2π (σ² + 2ατ) √(4π α τ))

with ``t₀`` the first state of a track after a turnaround, ``p[j]`` [W] the power applied
during the step j−1 → j (as :class:`gp_model.narx.RunSeries`), ``d = v Δt`` the step length,
``h`` the hatch, ``a`` the absorptivity and σ the beam's standard deviation. Source ``e``
(step ``t₀ − 1 − e``, the turn at the end of state ``t₀ − 1``) deposits ``a p Δt`` at its
midpoint; the target is the laser in state ``t₀ + s``, on the track run back beside it.

**Why only the previous track.** The same track's heat within n_p states is what the model's
power lags carry; beyond them it lies more than n_p steps (≈ 1 mm at 40 µm a step) behind the
laser, where ``exp(−r²/(4ατ))`` is negligible. Older tracks are further and older: their heat
reaches the laser as a slow rise that T ahead already measures. What neither carries is the
previous track's end, next to which a new track starts within a few diffusion times: that is
this feature.

The feature is linear in power and known ahead from the plan (the states since the track's
start, the turn ahead, the hatch) and the applied and planned powers, so over a horizon the
preview MPC sees ``∂F/∂p = K`` of its planned powers.

**The remnant** (:class:`RemnantFeature`, a second, learned channel). For the first tens of states
after a turn the measured pool is the new pool joined to the still-molten end of the previous track:
the area is larger while that remnant lasts, drops when it solidifies (17-21 states after the turn on
the physical plant) and the new pool is short a few states after the turn. Neither F (heat at the
laser) nor the lags carry it. The remnant's size is set by the powers along the previous track's end,
so the model takes, for the ``n_states`` states s after a turn, the terms::

    z += c_s + h_s P̄,   P̄ = (1 / n_sources) Σ_{e < n_sources} p[t₀ − 1 − e]

with ``h_s`` [1/W] and ``c_s`` (``offsets``: fitted, else 0) learned per state s after the turn. The
terms are linear in the previous track's last powers and known ahead from the plan, so over a horizon
the preview MPC sees ``∂z[t₀ + s]/∂p[t₀ − 1 − e] = h_s / n_sources`` (:meth:`RemnantFeature.kernel`).
Everything is SI.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from messages import in625

__all__ = ["RemnantFeature", "TurnFeature", "remnant_series", "turn_feature_series"]


def _rho_cp(t_k: float) -> tuple[float, float]:
    """ρc [J/(m³ K)] and α [m²/s] of the plant's IN625 (:mod:`messages.in625`) at ``t_k`` [K]."""
    t_c = t_k - 273.15
    rho, cp = in625.RHO_KG_M3, in625.CP_0C_J_KGK + in625.CP_SLOPE_J_KGK2 * t_c
    k = in625.K_0C_W_MK + in625.K_SLOPE_W_MK2 * t_c
    return rho * cp, k / (rho * cp)


_RHO_CP, _ALPHA = _rho_cp(1000.0)


def _constants(cls: type, doc: Any, what: str) -> Mapping[str, Any]:
    """``doc`` checked to hold exactly the fields of the dataclass ``cls`` (``ValueError`` naming
    ``what`` and the missing or unknown keys)."""
    if not isinstance(doc, Mapping):
        raise ValueError(f"{what}: not an object")
    fields = set(cls.__dataclass_fields__)
    unknown, missing = set(doc) - fields, fields - set(doc)
    if unknown or missing:
        raise ValueError(f"{what}: unknown keys {sorted(unknown)}, missing keys {sorted(missing)}")
    return doc


@dataclass(frozen=True)
class TurnFeature:
    """Constants of the turnaround feature (module docstring); frozen, validated on construction.

    Parameters
    ----------
    hatch_m : float
        Distance between a track and the one run back beside it, h [m].
    absorptivity : float
        a [-].
    volumetric_heat_j_m3_k : float
        ρc [J/(m³ K)] (default: IN625 at 1000 K).
    diffusivity_m2_s : float
        α [m²/s] (default: IN625 at 1000 K).
    beam_sigma_m : float
        σ of the Gaussian beam [m] (the plant's ``r_s / √6``, r_s = 50 µm).
    n_targets : int
        States after a turn that get the feature (0 beyond): by default a whole 10 mm track at
        0.8 m/s and 50 µs (250 states), so that the feature decays along the track instead of
        stepping to 0 in its middle (the model would see a step in the heat that the plant does not).
    n_sources : int
        States of the previous track, back from its end, whose powers contribute: by default
        ``n_targets`` plus the diffusion length of the last target (about 12 states), with a margin.
    """

    hatch_m: float = 1e-4
    absorptivity: float = 0.4
    volumetric_heat_j_m3_k: float = _RHO_CP
    diffusivity_m2_s: float = _ALPHA
    beam_sigma_m: float = 50e-6 / math.sqrt(6.0)
    n_targets: int = 256
    n_sources: int = 320

    def __post_init__(self) -> None:
        for name in ("hatch_m", "absorptivity", "volumetric_heat_j_m3_k", "diffusivity_m2_s", "beam_sigma_m"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (math.isfinite(value)
                                                                                      and value > 0):
                raise ValueError(f"TurnFeature.{name} must be a finite number > 0, got {value!r}")
        for name in ("n_targets", "n_sources"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 10_000:
                raise ValueError(f"TurnFeature.{name} must be an int in [1, 10000], got {value!r}")

    def green_k_per_j(self, r_m: np.ndarray, tau_s: np.ndarray) -> np.ndarray:
        """Temperature rise [K] at surface distance ``r_m`` [m] and time ``tau_s`` > 0 [s] after 1 J
        absorbed from the Gaussian beam at the surface of the adiabatic half-space."""
        spread = self.beam_sigma_m ** 2 + 2.0 * self.diffusivity_m2_s * np.asarray(tau_s)
        depth = np.sqrt(4.0 * math.pi * self.diffusivity_m2_s * np.asarray(tau_s))
        return 2.0 / self.volumetric_heat_j_m3_k * np.exp(-np.square(r_m) / (2.0 * spread)) / (
            2.0 * math.pi * spread * depth)

    def kernel(self, step_m: float, dt_s: float) -> np.ndarray:
        """``K[s, e]`` [K/W], shape (n_targets, n_sources), for the step length ``step_m`` = v Δt [m]
        and the sample period ``dt_s`` [s]."""
        if not (step_m > 0 and dt_s > 0):
            raise ValueError(f"step length and sample period must be > 0, got {step_m}, {dt_s}")
        s = np.arange(self.n_targets)[:, None]
        e = np.arange(self.n_sources)[None, :]
        r = np.hypot((e - s - 0.5) * step_m, self.hatch_m)
        return self.absorptivity * dt_s * self.green_k_per_j(r, (s + e + 1.5) * dt_s)

    def to_dict(self) -> dict[str, Any]:
        """The constants, JSON-able (recorded in the model file)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> TurnFeature:
        """The inverse of :meth:`to_dict` (``ValueError`` naming a missing, unknown or bad key)."""
        return cls(**_constants(cls, doc, "turn feature"))


def turn_feature_series(kernel: np.ndarray, power_w: np.ndarray, turn_starts: np.ndarray,
                        track_ends: np.ndarray) -> np.ndarray:
    """``F[j]`` [K] of every state of a run (module docstring), shape (n,).

    Parameters
    ----------
    kernel : numpy.ndarray, shape (S, E)
        :meth:`TurnFeature.kernel`.
    power_w : numpy.ndarray, shape (n,)
        ``p[j]`` [W] (``p[0]``: 0 before laser-on).
    turn_starts : numpy.ndarray of int, shape (m,)
        First states of the tracks that follow a turnaround (not a layer's first track).
    track_ends : numpy.ndarray of int, shape (n,)
        Index of the last state of each state's track.
    """
    n_targets, n_sources = kernel.shape
    power = np.asarray(power_w, dtype=float)
    out = np.zeros(power.size)
    for start in np.asarray(turn_starts, dtype=int):
        sources = power[max(start - n_sources, 0):start][::-1]       # p[t₀−1], p[t₀−2], ...
        stop = min(start + n_targets, int(track_ends[start]) + 1)
        out[start:stop] = kernel[:stop - start, :sources.size] @ sources
    return out


@dataclass(frozen=True)
class RemnantFeature:
    """Constants of the remnant terms (module docstring, "The remnant"); frozen, validated on construction.

    Parameters
    ----------
    n_states : int
        States after a turn that get a remnant term each (the remnant solidifies within them).
    n_sources : int
        States of the previous track, back from its end, whose mean power P̄ [W] scales the terms
        (about the pool's length at 0.8 m/s and 50 µs).
    offsets : bool
        Fit an offset ``c_s`` per state besides the slope ``h_s`` (False: ``c_s`` = 0).
    """

    n_states: int = 24
    n_sources: int = 16
    offsets: bool = False

    def __post_init__(self) -> None:
        for name in ("n_states", "n_sources"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or not 1 <= value <= 10_000:
                raise ValueError(f"RemnantFeature.{name} must be an int in [1, 10000], got {value!r}")
        if not isinstance(self.offsets, bool):
            raise ValueError(f"RemnantFeature.offsets must be a bool, got {self.offsets!r}")

    def kernel(self, coefficients: np.ndarray) -> np.ndarray:
        """``W[s, e] = h_s / n_sources`` [z/W], shape (n_states, n_sources): ∂z of the state s after a turn
        by the power e states before it, for the slopes ``coefficients`` h_s [1/W], shape (n_states,)."""
        h = np.asarray(coefficients, dtype=float)
        if h.shape != (self.n_states,):
            raise ValueError(f"remnant coefficients must have shape ({self.n_states},), got {h.shape}")
        return np.repeat(h[:, None] / self.n_sources, self.n_sources, axis=1)

    def to_dict(self) -> dict[str, Any]:
        """The constants, JSON-able (recorded in the model file)."""
        return asdict(self)

    @classmethod
    def from_dict(cls, doc: Mapping[str, Any]) -> RemnantFeature:
        """The inverse of :meth:`to_dict` (``ValueError`` naming a missing, unknown or bad key)."""
        return cls(**_constants(cls, doc, "remnant feature"))


def remnant_series(remnant: RemnantFeature, power_w: np.ndarray, turn_starts: np.ndarray,
                   track_ends: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The remnant's regressors of every state of a run: ``P̄`` [W] in column s of the state s after a
    turn, and 1 there (the offsets' column), shapes (n, n_states); zero rows elsewhere (module docstring).

    Parameters as :func:`turn_feature_series` (``p[0]``: 0 before laser-on; powers before the run count 0).
    """
    power = np.asarray(power_w, dtype=float)
    slopes, ones = np.zeros((power.size, remnant.n_states)), np.zeros((power.size, remnant.n_states))
    for start in np.asarray(turn_starts, dtype=int):
        mean = power[max(start - remnant.n_sources, 0):start].sum() / remnant.n_sources
        s = np.arange(min(remnant.n_states, int(track_ends[start]) + 1 - start))
        slopes[start + s, s], ones[start + s, s] = mean, 1.0
    return slopes, ones
