"""Controller settings: frozen dataclasses validated on construction.

One :class:`ControllerSettings` configures every controller of the registry
(:func:`controller_node.registry.make_controller`); each controller reads its own
sub-settings.  Defaults follow the paper (Table 3, section IV.B) and the project's
typical operating point (set point 0.063 mm², v = 0.8 m/s, Δt = 50 µs).
Invalid values raise ``ValueError`` with a one-line message.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Literal

from gp_model.build_up import BUILD_UP_STEPS
from messages.types import LASER_POWER_MAX_W

__all__ = ["ControllerSettings", "SoftAreaBounds", "MPCSettings", "PreviewSettings", "PIDSettings",
           "FeedForwardSettings", "FE_TEMPERATURE_GAIN_W_PER_K", "FE_MPC_TEMPERATURE_GAIN_W_PER_K",
           "FE_REFERENCE_TEMPERATURE_K"]

# Temperature feed-forward gain K_T of the FE plant (IN625, 250 W, 0.8 m/s), measured, not
# identifiable from the one-step GP (whose T-sensitivity has the wrong size and, at some
# points, sign).  Pure feed-forward on the default layer (600 steps): K_T = −0.10 W/K →
# RMSE 5.6 %, overshoot 31 %; −0.15 → 4.3 %, 10.9 %; −0.20 → 10.5 %, undershoot 34.5 %.
# Physical check: keeping the molten volume at constant enthalpy (cp + latent heat from T
# to liquidus) needs −0.11 W/K at 303 K and −0.13 W/K on average up to 1000 K.
FE_TEMPERATURE_GAIN_W_PER_K = -0.15
# The same gain as part of the MPC (with its integral action and the shipped five-input GP),
# tuned on the whole default layer (1000 steps; overshoot / undershoot / RMSE %):
# −0.14 → 15.08 / 13.18 / 3.67; −0.145 → 13.75 / 14.46 / 3.75; −0.15 → 12.23 / 15.78 / 3.85
# (integral gain 0.03; with 0.05 and −0.15: 12.55 / 15.71 / 4.01).
FE_MPC_TEMPERATURE_GAIN_W_PER_K = -0.145
# T ahead on the first (cold) track of the default layer at 250 W [K].
FE_REFERENCE_TEMPERATURE_K = 303.0


def _check(condition: bool, message: str) -> None:
    if not condition:
        raise ValueError(message)


def _finite(obj: object, *names: str) -> None:
    for name in names:
        value = getattr(obj, name)
        _check(
            isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value),
            f"{type(obj).__name__}.{name} must be a finite number, got {value!r}",
        )


@dataclass(frozen=True)
class FeedForwardSettings:
    """Temperature feed-forward (paper IV.B: "a differential plus direct feedback
    from the initial temperature is added to the MPC command").

    The added power is ``Δp = K_T · (g_direct · (T[k] − T_ref) + g_diff · (T[k] − T[k−1]))``
    with ``K_T = −(∂f/∂T)/(∂f/∂p)`` [W/K], the power change that keeps the model's
    melt-pool area (and its steady state, since both partials share the factor
    ``1/(1 − ∂f/∂x)``) unchanged for a temperature change.

    Parameters
    ----------
    enabled : bool
        Add the term (to the MPC command; the ``feedforward`` baseline always uses it).
    direct_gain : float
        ``g_direct`` (dimensionless).  0 by default for the MPC: the MPC already
        linearises at the measured ``T[k]``, a direct term would count it twice.
    differential_gain : float
        ``g_diff`` (dimensionless): compensates the temperature change the MPC's
        constant-temperature prediction misses.
    reference_temperature_k : float
        ``T_ref`` [K] of the direct term (the ``feedforward`` baseline's nominal
        power is meant for this temperature).
    gain_w_per_k : float or None
        Fixed ``K_T`` [W/K]; None derives it from the model at each step (MPC) or at
        the nominal point (``feedforward`` baseline).
    max_abs_w : float
        Clamp of the added power [W] (> 0).
    """

    enabled: bool = False
    direct_gain: float = 0.0
    differential_gain: float = 1.0
    reference_temperature_k: float = 300.0
    gain_w_per_k: float | None = None
    max_abs_w: float = 150.0

    def __post_init__(self) -> None:
        _check(isinstance(self.enabled, bool), f"FeedForwardSettings.enabled must be bool, got {self.enabled!r}")
        _finite(self, "direct_gain", "differential_gain", "reference_temperature_k", "max_abs_w")
        _check(self.reference_temperature_k > 0, "FeedForwardSettings.reference_temperature_k must be > 0 K")
        _check(self.max_abs_w > 0, "FeedForwardSettings.max_abs_w must be > 0 W")
        if self.gain_w_per_k is not None:
            _finite(self, "gain_w_per_k")


@dataclass(frozen=True)
class SoftAreaBounds:
    """The soft area bounds of an MPC's QP and their penalty, shared by :class:`MPCSettings` and
    :class:`PreviewSettings` (their first fields).

    Parameters
    ----------
    area_min_m2, area_max_m2 : float
        Soft area bounds ``x_l, x_u`` [m²] (Table 3: 0, 0.5 mm²), ``0 <= x_l < x_u``.
    slack_linear, slack_quadratic : float
        Penalty ``ρ₁·s + ρ₂·s²`` on the normalised area-bound violation ``s >= 0`` (``ρ₁ >= 0``,
        ``ρ₂ > 0``).
    """

    area_min_m2: float = 0.0
    area_max_m2: float = 0.5e-6
    slack_linear: float = 100.0
    slack_quadratic: float = 1000.0

    def __post_init__(self) -> None:
        name = type(self).__name__
        _finite(self, "area_min_m2", "area_max_m2", "slack_linear", "slack_quadratic")
        _check(0 <= self.area_min_m2 < self.area_max_m2, f"{name} needs 0 <= area_min_m2 < area_max_m2")
        _check(self.slack_linear >= 0 and self.slack_quadratic > 0,
               f"{name}.slack_linear must be >= 0 and slack_quadratic > 0")


@dataclass(frozen=True)
class MPCSettings(SoftAreaBounds):
    """Linear time-varying MPC of eq. (7)-(8) in normalised deviation variables.

    Normalisation (so that Table 3's Q, R, Q_f are meaningful):
    ``e = (x − x_sp) / x_sp`` (relative area error) and
    ``u = (p − p_ref) / (p_u − p_l)`` (power as a fraction of its range).

    Parameters
    ----------
    horizon : int
        Prediction horizon ``H`` (Table 3: 20).
    q, r, q_f : float
        Stage state, input and terminal weights on ``e`` and ``u`` (Table 3: 1, 0.1, 20).
    input_penalty : {"steady_state", "move"}
        What ``R`` weighs: ``"steady_state"`` the deviation of ``p`` from the
        model's steady-state power ``p_ss`` for the set point (offset-free target
        tracking, ``p_ref = p_ss``), ``"move"`` the moves ``Δp[i] = p[i] − p[i−1]``.
    rate_min_w, rate_max_w : float
        Bounds of ``Δp`` per step [W] (Table 3: ±350; cannot bind when
        ``p_u − p_l <= 350`` W, kept for other ranges).
    area_min_m2, area_max_m2, slack_linear, slack_quadratic : float
        Soft area bounds and their penalty (:class:`SoftAreaBounds`).
    disturbance_gain : float
        Filter gain in [0, 1] of the output-disturbance estimate (the model's
        one-step prediction error, added to the prediction); 0 disables it.
    integral_gain, integral_band : float
        Offset-free integral action on the same output-disturbance term: each step
        ``d̂ += integral_gain · (1 − a) · (x[k] − x_sp)``, which moves the model's steady
        state by ``integral_gain`` of the error. Conditional integration: frozen while
        ``|x[k] − x_sp| > integral_band · x_sp`` (hot track starts), so it does not wind up.
        Defaults 0.03 and 0.1 (tuned on the FE layer, docs/controller.md, "FE tuning").
    solver : {"daqp", "osqp", "cvxpy"}
        QP backend: condensed DAQP (exact, fastest), sparse OSQP, or the cvxpy
        reference (ms per solve).
    eps_abs, eps_rel : float
        OSQP tolerances (<= 1e-5: at 1e-3 OSQP is off by up to 9 W).
    max_iter : int
        OSQP iteration limit.
    temperature_horizon : {"constant"}
        Temperature prediction over the horizon: held at ``T[k]``.
    report_model_std : bool
        Report the model's predictive std at the linearisation point in the diagnostics (from the
        linearisation's own evaluation of the GP, :func:`controller_node.model.linearise`).
    state_gain_max : float
        Model guard (physical prior: the melt pool is open-loop stable): the
        linearised ``a = ∂f/∂x`` is clipped to ``<= state_gain_max`` (in (0, 1.5]).
        A raw ``|a| > 1.5`` is still a model error.  The one-step GP of the FE plant
        learns near-persistence (``a ≈ 1.03``) because power acts on the area with a
        distributed delay of ~10 steps; 0.9 ≈ exp(−1/10) is a pool memory of ~10 steps.
    power_gain_min_m2_per_w : float
        Model guard (physical prior: more power, larger pool): ``b = ∂f/∂p`` is
        raised to ``>= power_gain_min_m2_per_w`` [m²/W] (>= 0; 0 only rejects
        negative gains).
    power_scale_w : float or None
        Power normalisation ``u = (p − p_ref) / power_scale_w`` [W]; None: ``p_u − p_l``.
    feedforward : FeedForwardSettings
        Temperature feed-forward added to the MPC command.  With ``direct_gain``
        ``g > 0`` the MPC plans the compensated power ``p̃ = p − Δp_ff`` and
        linearises the model at ``T_ref + (1 − g)(T[k] − T_ref)`` (the temperature
        the compensated plant behaves like); the power bounds hold for ``p̃ + Δp_ff``.
    """

    horizon: int = 20
    q: float = 1.0
    r: float = 0.1
    q_f: float = 20.0
    input_penalty: Literal["steady_state", "move"] = "move"
    rate_min_w: float = -LASER_POWER_MAX_W
    rate_max_w: float = LASER_POWER_MAX_W
    disturbance_gain: float = 0.0
    integral_gain: float = 0.03
    integral_band: float = 0.1
    solver: Literal["daqp", "osqp", "cvxpy"] = "daqp"
    eps_abs: float = 1e-6
    eps_rel: float = 1e-6
    max_iter: int = 4000
    temperature_horizon: Literal["constant"] = "constant"
    report_model_std: bool = True
    state_gain_max: float = 0.9
    power_gain_min_m2_per_w: float = 2e-11
    power_scale_w: float | None = 4.0
    feedforward: FeedForwardSettings = field(default_factory=lambda: FeedForwardSettings(
        enabled=True, direct_gain=1.0, differential_gain=0.0,
        reference_temperature_k=FE_REFERENCE_TEMPERATURE_K, gain_w_per_k=FE_MPC_TEMPERATURE_GAIN_W_PER_K))

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(
            isinstance(self.horizon, int) and not isinstance(self.horizon, bool) and 1 <= self.horizon <= 500,
            f"MPCSettings.horizon must be an int in [1, 500], got {self.horizon!r}",
        )
        _finite(
            self,
            "q",
            "r",
            "q_f",
            "rate_min_w",
            "rate_max_w",
            "disturbance_gain",
            "integral_gain",
            "integral_band",
            "eps_abs",
            "eps_rel",
        )
        _check(self.q >= 0 and self.q_f >= 0, "MPCSettings.q and q_f must be >= 0")
        _check(self.r > 0, f"MPCSettings.r must be > 0 (strictly convex QP), got {self.r}")
        _check(self.input_penalty in ("steady_state", "move"),
               f"MPCSettings.input_penalty must be 'steady_state' or 'move', got {self.input_penalty!r}")
        _check(self.rate_min_w < 0 < self.rate_max_w, "MPCSettings.rate_min_w < 0 < rate_max_w required")
        _check(0 <= self.disturbance_gain <= 1, "MPCSettings.disturbance_gain must be in [0, 1]")
        _check(0 <= self.integral_gain <= 1, "MPCSettings.integral_gain must be in [0, 1]")
        _check(0 < self.integral_band <= 1, "MPCSettings.integral_band must be in (0, 1]")
        _check(self.solver in ("daqp", "osqp", "cvxpy"),
               f"MPCSettings.solver must be 'daqp', 'osqp' or 'cvxpy', got {self.solver!r}")
        _check(0 < self.eps_abs <= 1e-5 and 0 < self.eps_rel <= 1e-5,
               "MPCSettings.eps_abs and eps_rel must be in (0, 1e-5]")
        _check(isinstance(self.max_iter, int) and not isinstance(self.max_iter, bool) and self.max_iter > 0,
               "MPCSettings.max_iter must be a positive int")
        _check(self.temperature_horizon == "constant",
               f"MPCSettings.temperature_horizon must be 'constant', got {self.temperature_horizon!r}")
        _check(isinstance(self.report_model_std, bool), "MPCSettings.report_model_std must be bool")
        _finite(self, "state_gain_max", "power_gain_min_m2_per_w")
        _check(0 < self.state_gain_max <= 1.5, "MPCSettings.state_gain_max must be in (0, 1.5]")
        _check(0 <= self.power_gain_min_m2_per_w <= 1e-6,
               "MPCSettings.power_gain_min_m2_per_w must be in [0, 1e-6] m²/W")
        if self.power_scale_w is not None:
            _finite(self, "power_scale_w")
            _check(self.power_scale_w > 0, "MPCSettings.power_scale_w must be > 0 W")
        _check(isinstance(self.feedforward, FeedForwardSettings),
               "MPCSettings.feedforward must be a FeedForwardSettings")


@dataclass(frozen=True)
class PreviewSettings(SoftAreaBounds):
    """Scan-plan preview MPC on the delay-aware model (:mod:`controller_node.preview`).

    Normalisation: ``e = (x − x_sp)/x_sp`` (relative area error), ``v = p / P``.

    Parameters
    ----------
    horizon : int
        ``H`` [steps]: at least the power→area response (~15 steps) plus the turnaround
        look-ahead (default 40 = 2 ms).
    q, q_f : float
        Weights of ``e²`` on steps 1..H−1 and on step H (Table 3: 1, 20).
    r : float
        Weight of the squared normalised moves ``(Δp/P)²``.
    power_scale_w : float
        ``P`` [W].
    area_min_m2, area_max_m2, slack_linear, slack_quadratic : float
        Soft area bounds and their penalty (:class:`SoftAreaBounds`).
    uncertainty_z : float
        The area bounds are tightened by ``z σ_m`` (σ the GP's predictive std of step m);
        0 disables the tightening.
    observer_gain : float
        ``L`` in (0, 1] of the output-disturbance observer ``d̂ += L (x − x̂ − d̂)``.
    observer_start_steps : int
        States of the pool build-up after laser-on, of the run and of every layer (the model is
        not fitted on them, ``gp_model.build_up.BUILD_UP_STEPS``): the observer starts after them
        and the QP does not track them.
    learn_turn_profile : bool
        Forecast the next turnaround with the rise of T ahead seen at the last one in this run.
    turn_learning_gain : float
        κ in [0, 1] of the iterative learning over turnarounds (:meth:`PreviewMPC._learn_turn_correction`):
        the model error seen after one turn, times κ, is added to the prediction after the next ones
        of the layer and after the same turn of the next layer. 0 disables it.
    turn_learning_steps : int
        States after a turn that the learned correction covers.
    turn_learning_forgetting : float
        γ in [0, 1) of the learning's forgetting: each update is ``c ← (1 − γ)(c_j + κ ε_j)``, so the learned
        correction stays bounded where the model's answer to power differs from the plant's. 0 (the default)
        keeps all it learned; 0.2 holds the RMSE of learning over runs from rising (``docs/controller.md``).
    """

    horizon: int = 40
    q: float = 1.0
    q_f: float = 20.0
    r: float = 0.3
    power_scale_w: float = LASER_POWER_MAX_W
    uncertainty_z: float = 0.0
    observer_gain: float = 0.02
    observer_start_steps: int = BUILD_UP_STEPS
    learn_turn_profile: bool = True
    turn_learning_gain: float = 0.75
    turn_learning_steps: int = 60
    turn_learning_forgetting: float = 0.0

    def __post_init__(self) -> None:
        super().__post_init__()
        _check(isinstance(self.horizon, int) and not isinstance(self.horizon, bool) and 1 <= self.horizon <= 400,
               f"PreviewSettings.horizon must be an int in [1, 400], got {self.horizon!r}")
        _finite(self, "q", "q_f", "r", "power_scale_w", "uncertainty_z", "observer_gain")
        _check(self.q >= 0 and self.q_f >= 0, "PreviewSettings.q and q_f must be >= 0")
        _check(self.r > 0, f"PreviewSettings.r must be > 0 (strictly convex QP), got {self.r}")
        _check(self.power_scale_w > 0, "PreviewSettings.power_scale_w must be > 0 W")
        _check(self.uncertainty_z >= 0, "PreviewSettings.uncertainty_z must be >= 0")
        _check(0 < self.observer_gain <= 1, "PreviewSettings.observer_gain must be in (0, 1]")
        _check(isinstance(self.observer_start_steps, int) and not isinstance(self.observer_start_steps, bool)
               and self.observer_start_steps >= 1, "PreviewSettings.observer_start_steps must be an int >= 1")
        _check(isinstance(self.learn_turn_profile, bool), "PreviewSettings.learn_turn_profile must be bool")
        _finite(self, "turn_learning_gain")
        _check(0 <= self.turn_learning_gain <= 1, "PreviewSettings.turn_learning_gain must be in [0, 1]")
        _finite(self, "turn_learning_forgetting")
        _check(0 <= self.turn_learning_forgetting < 1, "PreviewSettings.turn_learning_forgetting must be in [0, 1)")
        _check(
            isinstance(self.turn_learning_steps, int)
            and not isinstance(self.turn_learning_steps, bool)
            and 0 <= self.turn_learning_steps <= 1000,
            "PreviewSettings.turn_learning_steps must be an int in [0, 1000]",
        )


@dataclass(frozen=True)
class PIDSettings:
    """Discrete PID on the relative area error ``e = (x_sp − x) / x_sp``.

    ``p = p_nom + kp·e + I + kd·(e[k] − e[k−1])`` with ``I += ki·e`` each step,
    limited to the headroom to the power bound the error pushes towards
    (integrator-clamping anti-windup), output clamped to the power bounds.

    Parameters
    ----------
    kp_w, ki_w, kd_w : float
        Gains [W per unit relative error] (``ki_w`` per step), >= 0.
    """

    kp_w: float = 100.0
    ki_w: float = 25.0
    kd_w: float = 0.0

    def __post_init__(self) -> None:
        _finite(self, "kp_w", "ki_w", "kd_w")
        _check(min(self.kp_w, self.ki_w, self.kd_w) >= 0, "PIDSettings gains must be >= 0")


@dataclass(frozen=True)
class ControllerSettings:
    """Settings shared by all controllers.

    Parameters
    ----------
    set_point_m2 : float
        Melt-pool area set point ``x_sp`` [m²] (> 0).
    power_min_w, power_max_w : float
        Power bounds ``p_l, p_u`` [W] (Table 3: 0, 350).  No command leaves them.
    nominal_power_w : float
        Open-loop power and the safe power before any command was issued [W].
    nominal_speed_m_s : float
        Scan speed [m/s] (power-only control, paper IV.B); used when the measured
        speed is unusable.
    max_age_steps : int
        A measurement older than this many steps (``now_step − step``) is stale.
    mpc, pid : MPCSettings, PIDSettings
        Controller-specific settings.
    feedforward : FeedForwardSettings
        Settings of the ``feedforward`` baseline.
    """

    set_point_m2: float = 0.063e-6
    power_min_w: float = 0.0
    power_max_w: float = LASER_POWER_MAX_W
    nominal_power_w: float = 250.0
    nominal_speed_m_s: float = 0.8
    max_age_steps: int = 1
    mpc: MPCSettings = field(default_factory=MPCSettings)
    preview: PreviewSettings = field(default_factory=PreviewSettings)
    pid: PIDSettings = field(default_factory=PIDSettings)
    feedforward: FeedForwardSettings = field(default_factory=lambda: FeedForwardSettings(
        enabled=True, direct_gain=1.0, differential_gain=0.0,
        reference_temperature_k=FE_REFERENCE_TEMPERATURE_K, gain_w_per_k=FE_TEMPERATURE_GAIN_W_PER_K))

    def __post_init__(self) -> None:
        _finite(self, "set_point_m2", "power_min_w", "power_max_w", "nominal_power_w", "nominal_speed_m_s")
        _check(self.set_point_m2 > 0, f"ControllerSettings.set_point_m2 must be > 0, got {self.set_point_m2}")
        _check(0 <= self.power_min_w < self.power_max_w,
               "ControllerSettings needs 0 <= power_min_w < power_max_w")
        _check(self.power_min_w <= self.nominal_power_w <= self.power_max_w,
               "ControllerSettings.nominal_power_w must lie within the power bounds")
        _check(self.nominal_speed_m_s > 0, "ControllerSettings.nominal_speed_m_s must be > 0")
        _check(isinstance(self.max_age_steps, int) and not isinstance(self.max_age_steps, bool)
               and self.max_age_steps >= 0, "ControllerSettings.max_age_steps must be an int >= 0")
        for name, cls in (("mpc", MPCSettings), ("preview", PreviewSettings), ("pid", PIDSettings),
                          ("feedforward", FeedForwardSettings)):
            _check(isinstance(getattr(self, name), cls), f"ControllerSettings.{name} must be a {cls.__name__}")
        _check(self.mpc.area_min_m2 < self.set_point_m2 < self.mpc.area_max_m2,
               "ControllerSettings.set_point_m2 must lie inside the MPC area bounds")


def merged_over(base: dict, table: dict) -> dict:
    """``table`` (a ``[controller]`` TOML table) over ``base``, nested tables merged (``table`` wins)."""
    merged = {k: dict(v) if isinstance(v, dict) else v for k, v in base.items()}
    for key, value in table.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged
