"""meltloop's own message types (JSON on the wire and in MCAP).

Units are SI except where a field name says otherwise (``area_mm2``, ``speed_mm_s``,
``width_um``): those are the units process engineers read on a plot, converted at the node's
edge. Every message carries ``time_s``, the *process* time (simulated time for the FE plant,
machine time since the start of the layer for a sensor), which the recorder uses as MCAP
``log_time``.

Step semantics (lockstep and free-running alike): ``MeltPoolState.step = k`` is the state
after k steps of duration Δt. ``LaserCommand.step = k + 1`` is the command to apply during
the step k → k+1; the plant echoes what it actually applied in ``MeltPoolState(step=k+1)
.power_w``. A training sample of the paper's eq. (8) is therefore
``(state[k].area_mm2, state[k].t_ahead_k, state[k+1].power_w, state[k+1].speed_mm_s) ->
state[k+1].area_mm2``.
"""

from __future__ import annotations

from typing import Annotated, Literal

import msgspec

from messages.base import Message

RunId = Annotated[
    str,
    msgspec.Meta(
        pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$",
        description="Run identifier; also the second segment of every key expression.",
    ),
]
NodeName = Annotated[str, msgspec.Meta(pattern=r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,31}$")]
MAX_STEP = 2**31 - 1
"""The largest step index of the contract."""
MAX_STEPS_AHEAD = 1000
"""Admission limit: a state or command more than this many steps ahead of the last one admitted on
its topic is not believed (a forged or corrupted step; 50 ms at 50 µs, far beyond any real gap of a
plant in lockstep or free-running at its frame period). The controller node and the recorder both
drop such a message and count it."""
Step = Annotated[int, msgspec.Meta(ge=0, le=MAX_STEP, description="Step index k.")]
TimeS = Annotated[float, msgspec.Meta(ge=0.0, le=1.0e6, description="Process time [s].")]
TempK = Annotated[float, msgspec.Meta(gt=0.0, le=1.0e5, description="Temperature [K].")]
PositionMm = Annotated[float, msgspec.Meta(ge=-1.0e4, le=1.0e4)]
UnitComponent = Annotated[float, msgspec.Meta(ge=-1.0, le=1.0)]
PowerW = Annotated[float, msgspec.Meta(ge=0.0, le=1.0e5, description="Laser power [W].")]
SpeedMmS = Annotated[float, msgspec.Meta(ge=0.0, le=1.0e5, description="Scan speed [mm/s].")]
LengthUm = Annotated[float, msgspec.Meta(ge=0.0, le=1.0e6)]
AreaMm2 = Annotated[float, msgspec.Meta(ge=0.0, le=1.0e4)]
ShortText = Annotated[str, msgspec.Meta(max_length=64)]
Horizon = Annotated[list[float], msgspec.Meta(max_length=1000)]


class MeltPoolState(Message, frozen=True, kw_only=True):
    """Melt-pool observation published by the plant after each step (FE node or sensor node).

    Required fields are what the controller and the GP need; the optional ones are what an FE
    model knows and a camera/pyrometer may not.
    """

    run_id: RunId
    step: Step
    time_s: TimeS
    laser_x_mm: Annotated[PositionMm, msgspec.Meta(description="Laser spot x [mm].")]
    laser_y_mm: Annotated[PositionMm, msgspec.Meta(description="Laser spot y [mm].")]
    scan_dir_x: Annotated[UnitComponent, msgspec.Meta(description="Scan direction, x component.")]
    scan_dir_y: Annotated[UnitComponent, msgspec.Meta(description="Scan direction, y component.")]
    track: Annotated[int, msgspec.Meta(ge=0, le=1_000_000, description="Track index in the layer.")]
    area_mm2: Annotated[
        AreaMm2,
        msgspec.Meta(description="Melt-pool top-surface (plan-view) area above liquidus [mm²]: the paper's x."),
    ]
    t_ahead_k: Annotated[
        TempK,
        msgspec.Meta(description="Surface temperature at the next spot plus one beam radius ahead [K]: the paper's T."),
    ]
    power_w: Annotated[PowerW, msgspec.Meta(description="Power applied during the step that produced this state [W].")]
    speed_mm_s: Annotated[SpeedMmS, msgspec.Meta(description="Speed applied during that step [mm/s].")]
    width_um: LengthUm | None = None
    length_um: LengthUm | None = None
    depth_um: LengthUm | None = None
    cross_section_mm2: AreaMm2 | None = None
    t_peak_k: TempK | None = None
    cooling_rate_k_s: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e12, description=(
        "Cooling rate G R at the pool's trailing edge on the scan line, top surface [K/s]."))] | None = None
    thermal_gradient_k_m: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e12, description=(
        "Temperature gradient G at the pool's trailing edge on the scan line, top surface [K/m]."))] | None = None
    solidification_rate_mm_s: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e5, description=(
        "Solidification rate R (boundary speed along its normal) at that point [mm/s]."))] | None = None
    track_elapsed_s: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e6, description=(
        "Scan-plan preview: time since the current track started [s]."))] | None = None
    track_remaining_s: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e6, description=(
        "Scan-plan preview: time until the laser reaches the end of the current track [s]."))] | None = None
    next_track: Annotated[bool, msgspec.Meta(description=(
        "Scan-plan preview: another track starts where this one ends (false on the last track)."))] | None = None
    layer: Annotated[int, msgspec.Meta(ge=0, le=1_000_000, description=(
        "Layer of a multi-layer build, 0 first (track indices restart in each layer). A new layer is a new "
        "laser-on on fresh powder: the report and the preview MPC treat its first 1 ms as pool build-up."
    ))] | None = None
    source: Literal["fe", "sensor", "replay", "surrogate"] = "fe"


LASER_POWER_MAX_W = 350.0
"""Highest power of the process (paper Table 3, p_u) [W]: the one default of the controller's and
the plant's power bounds (each node still enforces its own configured bounds)."""


class LaserCommand(Message, frozen=True, kw_only=True):
    """Laser set-points published by the controller for one step.

    ``step`` is the index of the state this command produces: answer ``MeltPoolState(step=k)``
    with ``LaserCommand(step=k+1)``.
    """

    run_id: RunId
    step: Step
    time_s: TimeS
    power_w: PowerW
    speed_mm_s: Annotated[float, msgspec.Meta(gt=0.0, le=1.0e5, description="Scan speed [mm/s].")]
    controller: ShortText


class ControllerDiagnostics(Message, frozen=True, kw_only=True):
    """What the controller did for one step: timing, solver status, predicted horizon."""

    run_id: RunId
    step: Step
    time_s: TimeS
    controller: ShortText
    status: ShortText
    solve_time_us: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e9, description="Update wall time [µs].")]
    fallback: bool = False
    n_fallbacks: Annotated[int, msgspec.Meta(ge=0)] = 0
    n_dropped: Annotated[int, msgspec.Meta(ge=0, description="Invalid or stale inputs dropped so far.")] = 0
    setpoint_mm2: AreaMm2 | None = None
    predicted_area_mm2: Horizon = []
    predicted_power_w: Horizon = []
    model_std_mm2: AreaMm2 | None = None
    feedforward_w: Annotated[float, msgspec.Meta(ge=-1.0e5, le=1.0e5)] | None = None


class PlantDiagnostics(Message, frozen=True, kw_only=True):
    """Plant-side bookkeeping for one step: energy balance (FE), command handling."""

    run_id: RunId
    step: Step
    time_s: TimeS
    step_wall_ms: Annotated[float, msgspec.Meta(ge=0.0, le=1.0e9)]
    absorbed_j: Annotated[float, msgspec.Meta(ge=0.0)] | None = None
    stored_j: float | None = None
    lost_j: float | None = None
    energy_error_pct: float | None = None
    n_fallbacks: Annotated[int, msgspec.Meta(ge=0)] = 0
    n_stale_commands: Annotated[int, msgspec.Meta(ge=0)] = 0
    n_dropped: Annotated[int, msgspec.Meta(ge=0)] = 0
    command_source: Literal["controller", "open-loop", "fallback-hold", "fallback-safe"] = "controller"


CONFIG_JSON_MAX_CHARS = 200_000
"""Longest configuration a start event carries (:attr:`RunEvent.config_json`) [characters]."""


class RunEvent(Message, frozen=True, kw_only=True):
    """Life-cycle event of one node: ``start`` (with its resolved configuration), ``end`` (with
    how many messages it published per topic, so the recorder can prove nothing was lost) or
    ``fault``."""

    run_id: RunId
    node: NodeName
    event: Literal["start", "end", "fault"]
    time_s: TimeS
    config_json: Annotated[str, msgspec.Meta(max_length=CONFIG_JSON_MAX_CHARS)] = ""
    total_steps: Annotated[int, msgspec.Meta(ge=0)] | None = None
    published: dict[Annotated[str, msgspec.Meta(max_length=64)], Annotated[int, msgspec.Meta(ge=0)]] = {}
    detail: Annotated[str, msgspec.Meta(max_length=2000)] = ""
