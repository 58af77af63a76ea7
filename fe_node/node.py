"""The FE plant as a zenoh node: ``python -m fe_node`` (lockstep with the controller).

After each step it publishes ``MeltPoolState`` (and ``PlantDiagnostics``, every few steps a
``foxglove.RawImage`` of the top surface), then waits for the ``LaserCommand`` whose step id is
the next step. Every other command — another step (past, duplicated or ahead, up to 2³¹ − 1), a
power or speed outside the plant's own bounds, an invalid payload or another run's — is dropped
and counted (``PlantDiagnostics.n_dropped``) and never extends the wait. The configured fallback
(default: the safe power, 0 W) applies as soon as the controller's liveliness token is gone —
then the run ends with exit status 1 after that step — or when no applicable command arrived
within ``--command-timeout-s``. ``--open-loop`` plays the scenario's power/speed profile instead
and needs no controller.

With ``[plant] frame_period_s`` (``--frame-period-s``) P = k Δt the node is a camera-rate plant
(:mod:`fe_node.frames`): a step of the contract is a frame, k FE steps under the command held over
it; it publishes every k-th FE state as frame j at time j P, and plays an open-loop profile's value
at the frame's start.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

from fe_node.commands import FALLBACKS, CommandGate, CommandPolicy, Verdict
from fe_node.frames import camera_frame
from fe_node.freerun import state_message
from fe_node.image import temperature_image
from fe_node.multilevel import plant_model
from fe_node.observe import Observation
from fe_node.scenarios import NAMES, PART_NAMES, Scenario, check_description, describe
from fe_node.scenarios import scenario as build_scenario
from fe_node.scene import fitted_scene, laser_pose
from fe_node.solver import ThermalModel
from messages import LaserCommand, LogLevel, MeltPoolState, PlantDiagnostics
from messages.bus import (
    Inbox,
    NodeBus,
    StopFlag,
    add_bus_arguments,
    bus_settings_from_args,
    run_node,
    single_threaded_blas,
)
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main
from messages.config import load_toml
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_LASER, PLANT_SCENE, PLANT_STATE, PLANT_TEMPERATURE

NODE_NAME = "plant"
POLL_S = 0.005  # a waiting plant looks at the controller's liveliness this often [s]


@dataclass(frozen=True)
class PlantSettings:
    """How the lockstep plant node runs.

    Attributes
    ----------
    policy : CommandPolicy
        Command bounds, timeout and fallback.
    open_loop : bool
        Play the scenario's power/speed profile; no controller.
    max_steps : int or None
        Stop after this many steps (``None``: at the end of the scan plan).
    image_every : int
        Publish the temperature image every N steps.
    controller : str
        Node name of the controller whose liveliness the plant follows.

    Raises
    ------
    UsageError
        On construction, naming the option of an invalid value.
    """

    policy: CommandPolicy = field(default_factory=CommandPolicy)
    open_loop: bool = False
    max_steps: int | None = None
    image_every: int = 10
    controller: str = "controller"

    def __post_init__(self) -> None:
        if self.max_steps is not None and self.max_steps < 1:
            raise UsageError(f"--max-steps must be >= 1, got {self.max_steps}")
        if self.image_every < 1:
            raise UsageError(f"--image-every must be >= 1, got {self.image_every}")
        if not self.controller:
            raise UsageError("--controller must name a node")


DEFAULTS = PlantSettings()


def n_steps(scenario: Scenario) -> int:
    """Steps to the end of the plan (times ``n_layers``) at the profile's lowest speed (exact for a constant speed)."""
    v_min = scenario.profile.speed_m_s.range()[0]
    plans = scenario.layer_plans or (scenario.plan,) * scenario.settings.n_layers
    return sum(math.ceil(p.total_length / (v_min * scenario.settings.dt_s) - 1e-9) for p in plans)


def fe_state(run_id: str, obs: Observation) -> MeltPoolState:
    """SI observation → contract message: :func:`~fe_node.freerun.state_message` with what an FE model
    knows besides (extents in µm, cross-section in mm², peak temperature, solidification figures,
    layer, and the scan-plan preview of :func:`preview_fields`)."""
    return state_message(run_id, obs.step, obs.time_s, obs, obs.power_w, obs.speed_m_s, "fe",
                         width_um=obs.width_m * 1e6, length_um=obs.length_m * 1e6, depth_um=obs.depth_m * 1e6,
                         cross_section_mm2=obs.cross_section_m2 * 1e6, t_peak_k=obs.t_peak_k,
                         cooling_rate_k_s=obs.cooling_rate_k_s, thermal_gradient_k_m=obs.thermal_gradient_k_m,
                         solidification_rate_mm_s=obs.solidification_rate_m_s * 1e3, layer=obs.layer,
                         **preview_fields(obs))


def preview_fields(obs: Observation) -> dict:
    """Scan-plan preview of a state: track distances → times at the applied speed (none before laser-on)."""
    if not obs.speed_m_s > 0:
        return {"next_track": obs.next_track}
    return {"track_elapsed_s": obs.track_travelled_m / obs.speed_m_s,
            "track_remaining_s": obs.track_remaining_m / obs.speed_m_s, "next_track": obs.next_track}


class CommandWaiter:
    """Waits for the command of one step; drops and counts every other one (:class:`CommandGate`)."""

    def __init__(self, inbox: Inbox, policy: CommandPolicy) -> None:
        self.inbox, self.policy = inbox, policy
        self.gate = CommandGate(policy)

    @property
    def n_dropped(self) -> int:
        """Commands dropped so far: not applicable (any reason) or invalid."""
        return self.gate.n_dropped + self.inbox.n_invalid

    def wait(self, step: int, stop: StopFlag, gone: threading.Event) -> LaserCommand | None:
        """The applicable command for ``step``; ``None`` after the timeout, once ``gone`` is set, or on stop.

        Dropped commands never extend the wait: the deadline is fixed when it starts.
        """
        deadline = time.monotonic() + self.policy.timeout_s
        while not (stop.is_set() or gone.is_set()):
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            cmd = self.inbox.get(timeout=min(remaining, POLL_S))
            if cmd is not None and self.gate.admit(cmd, step, step) is Verdict.APPLY:
                return cmd
        return None

    def summary(self) -> str:
        """Dropped commands by reason, for the end-of-run line."""
        counts = self.gate.counts
        return (f"{self.n_dropped} dropped commands ({counts[Verdict.STALE]} stale, {counts[Verdict.AHEAD]} ahead, "
                f"{counts[Verdict.OUT_OF_BOUNDS]} out of bounds, {self.inbox.n_invalid} invalid)")


def run(bus: NodeBus, scenario: Scenario, model: ThermalModel, settings: PlantSettings, stop: StopFlag,
        setup_s: float) -> int:
    """Step the plant until the scan plan ends (or ``settings.max_steps``); returns the exit status."""
    policy = settings.policy
    states = bus.publisher(PLANT_STATE)
    diagnostics = bus.publisher(PLANT_DIAGNOSTICS)
    images = bus.publisher(PLANT_TEMPERATURE)
    lasers = bus.publisher(PLANT_LASER)
    scenes = bus.publisher(PLANT_SCENE)
    scene_layer, scene_notes = None, set()
    waiter = None if settings.open_loop else CommandWaiter(bus.inbox(LASER_COMMAND), policy)
    gone = threading.Event() if waiter is None else bus.watch_presence(settings.controller)
    k, period_s = scenario.settings.steps_per_frame, scenario.settings.sample_period_s
    frames = n_steps(scenario) // k                     # whole frames only (a camera sees no partial one)
    total = frames if settings.max_steps is None else min(frames, settings.max_steps)
    bus.ready(config={**describe(scenario), "sample_period_s": period_s, "policy": vars(policy),
                      "open_loop": settings.open_loop,
                      "setup_s": round(setup_s, 3), "nodes": model.grid.n_nodes}, total_steps=total, stop=stop)
    bus.log(LogLevel.INFO, f"{scenario.name}: {total} steps, {model.grid.n_nodes} nodes, setup {setup_s:.1f} s")
    power_w, speed_m_s = scenario.profile.command(0)
    obs = dataclasses.replace(model.initial_observation(), speed_m_s=speed_m_s)  # laser off, about to scan at v
    n_fallbacks = 0
    status = 0
    t_min, t_max = scenario.settings.t0_k, scenario.settings.material.t_liquidus + 600.0
    while not stop.is_set():
        states.put(fe_state(bus.run_id, obs))
        lasers.put(laser_pose(obs))
        if obs.layer != scene_layer:
            scene, notes = fitted_scene(model.plan, obs, scenario.part_stl)
            for note in notes:
                if note not in scene_notes:  # (a decimated part: once, not at every layer)
                    bus.log(LogLevel.WARNING, note, time_s=obs.time_s)
            scene_notes.update(notes)
            scenes.put(scene)
            scene_layer = obs.layer
        if obs.step % settings.image_every == 0:
            image, _ = model.temperature_image()
            images.put(temperature_image(image, obs.time_s, t_min, t_max))
        if obs.step >= total or model.done:
            break
        t0 = time.perf_counter()
        model.prepare()                                 # while the command is in flight
        prepared_s = time.perf_counter() - t0
        source = "open-loop"
        if waiter is None:
            power_w, speed_m_s = scenario.profile.command(obs.step * k)
        elif (cmd := waiter.wait(obs.step + 1, stop, gone)) is not None:
            power_w, speed_m_s, source = cmd.power_w, cmd.speed_mm_s * 1e-3, "controller"
        elif stop.is_set():
            break
        else:
            n_fallbacks += 1
            power_w, source = policy.fallback_power(power_w), policy.fallback_source
            if gone.is_set():
                status = 1
                bus.log(LogLevel.WARNING, f"controller {settings.controller!r} gone (liveliness lost): applying "
                        f"{source} {power_w:.1f} W to step {obs.step + 1} at wall {time.time():.6f} s; "
                        "ending the run after that step", time_s=obs.time_s)
            else:
                bus.log(LogLevel.WARNING, f"no command for step {obs.step + 1} within {policy.timeout_s} s; "
                        f"applying {source} {power_w:.1f} W", time_s=obs.time_s)
        t0 = time.perf_counter()
        if k == 1:
            obs = model.step(power_w, speed_m_s)
        else:
            obs = camera_frame([model.step(power_w, speed_m_s) for _ in range(k)], obs.step + 1, period_s)
        diagnostics.put(PlantDiagnostics(
            run_id=bus.run_id, step=obs.step, time_s=obs.time_s,
            step_wall_ms=(prepared_s + time.perf_counter() - t0) * 1e3,
            absorbed_j=obs.energy_absorbed_j, stored_j=obs.energy_stored_j, lost_j=obs.energy_lost_j,
            energy_error_pct=obs.energy_error_pct, n_fallbacks=n_fallbacks,
            n_stale_commands=waiter.gate.n_stale if waiter else 0,
            n_dropped=waiter.n_dropped if waiter else 0, command_source=source,
        ))
        if status:
            states.put(fe_state(bus.run_id, obs))
            break
    ended = "aborted" if status else "stopped" if stop.is_set() else "finished"  # "finished": end of the plan
    summary = (f"{ended} at step {obs.step}{': controller lost' if status else ''}; {n_fallbacks} fallbacks"
               + (f", {waiter.summary()}" if waiter else ""))
    bus.log(LogLevel.ERROR if status else LogLevel.INFO, summary, time_s=obs.time_s)
    bus.end_detail(summary)
    return status


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``python -m fe_node`` (node mode); defaults from :data:`DEFAULTS`."""
    policy = DEFAULTS.policy
    parser = ArgumentParser(prog="python -m fe_node", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="layer", help=f"one of {', '.join(NAMES)} (default: %(default)s)")
    parser.add_argument("--power-w", type=float, help="nominal / open-loop power [W] (scenario default)")
    parser.add_argument("--speed-mm-s", type=float, help="scan speed [mm/s] (scenario default)")
    parser.add_argument("--h-um", type=float, help="fine element size [µm] (default: converged 25 µm)")
    parser.add_argument("--part", type=Path, metavar="STL", help="scenario part: the part to build (default: the "
                        "shipped example)")
    parser.add_argument("--layers", type=int, help="layers to build (scenario part: default all of the part's)")
    parser.add_argument("--config", type=Path,
                        help="TOML run configuration; its [plant] table overrides plant settings")
    parser.add_argument("--frame-period-s", type=float, metavar="P",
                        help="publish one state per camera frame of P [s], a whole number of FE steps, holding each "
                             "command over the frame ([plant] frame_period_s; default: every FE step)")
    parser.add_argument("--open-loop", action="store_true",
                        help="play the scenario's power/speed profile; no controller")
    parser.add_argument("--max-steps", type=int, help="stop after this many steps (short runs)")
    parser.add_argument("--command-timeout-s", type=float, default=policy.timeout_s,
                        help="fallback when no applicable command came within this time [s] (default: %(default)s)")
    parser.add_argument("--fallback", choices=FALLBACKS, default=policy.fallback,
                        help="without a command apply --safe-power-w or hold the last power (default: %(default)s)")
    parser.add_argument("--safe-power-w", type=float, default=policy.safe_power_w,
                        help="power of the 'safe' fallback [W] (default: %(default)s)")
    parser.add_argument("--power-min-w", type=float, default=policy.power_min_w, help="lowest power ever applied [W]")
    parser.add_argument("--power-max-w", type=float, default=policy.power_max_w, help="highest power ever applied [W]")
    parser.add_argument("--image-every", type=int, default=DEFAULTS.image_every,
                        help="publish the temperature image every N steps (default: %(default)s)")
    parser.add_argument("--controller", default=DEFAULTS.controller,
                        help="controller node whose liveliness the plant follows (default: %(default)s)")
    add_bus_arguments(parser)
    return parser


def settings_from_args(args: argparse.Namespace) -> PlantSettings:
    """Validated :class:`PlantSettings` from parsed arguments (raises :class:`UsageError`)."""
    policy = CommandPolicy(args.power_min_w, args.power_max_w, timeout_s=args.command_timeout_s,
                           fallback=args.fallback, safe_power_w=args.safe_power_w)
    return PlantSettings(policy, args.open_loop, args.max_steps, args.image_every, args.controller)


def main(argv: list[str] | None = None) -> int:
    """Entry point of the node mode of ``python -m fe_node``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    single_threaded_blas()
    try:
        bus_settings = bus_settings_from_args(args)
        settings = settings_from_args(args)
        plant_table = load_toml(args.config).get("plant", {})
        try:
            overrides = {k: v for k, v in {
                "power_w": args.power_w,
                "speed_m_s": None if args.speed_mm_s is None else args.speed_mm_s * 1e-3,
                "h_fine_m": None if args.h_um is None else args.h_um * 1e-6,
                "part_stl": None if args.part is None else str(args.part),
                "n_layers": args.layers,
                "frame_period_s": args.frame_period_s,
            }.items() if v is not None}
            if args.part is not None and args.scenario not in PART_NAMES:
                raise ValueError("--part needs --scenario part or ident-part")
            scenario = build_scenario(args.scenario, **{**plant_table, **overrides})
            check_description(scenario)
        except ValueError as err:
            raise UsageError(str(err)) from None
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = StopFlag()
    t0 = time.perf_counter()
    model = plant_model(scenario.settings, scenario.plan, scenario.layer_plans)
    setup_s = time.perf_counter() - t0
    return run_node(parser.prog, NODE_NAME, bus_settings,
                    lambda bus: run(bus, scenario, model, settings, stop, setup_s))


if __name__ == "__main__":
    run_main(main)
