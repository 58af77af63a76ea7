"""The FE plant as a zenoh node: ``python -m fe_node`` (lockstep with the controller).

After each step it publishes ``MeltPoolState`` (and ``PlantDiagnostics``, every few steps a
``foxglove.RawImage`` of the top surface), then waits for the ``LaserCommand`` whose step id is
the next step. Commands for other steps are stale and ignored (counted); invalid ones and
powers outside the configured bounds are dropped (counted) and never applied. If no valid
command arrives within ``--command-timeout-s``, the configured fallback (hold the last power,
or a safe power) is applied and logged; if the controller has gone away the run ends with exit
status 1 after that step. ``--open-loop`` plays the scenario's power/speed profile instead and
needs no controller.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

from fe_node.image import temperature_image
from fe_node.observe import Observation
from fe_node.scenarios import NAMES, Scenario
from fe_node.scenarios import scenario as build_scenario
from fe_node.solver import ThermalModel
from messages import LaserCommand, LogLevel, MeltPoolState, PlantDiagnostics
from messages.bus import Inbox, NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args
from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage
from messages.config import load_toml
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_STATE, PLANT_TEMPERATURE

NODE_NAME = "plant"


@dataclass(frozen=True)
class CommandPolicy:
    """How the plant accepts commands (all powers in W, speeds in m/s, times in s)."""

    power_min_w: float = 0.0
    power_max_w: float = 350.0
    speed_min_m_s: float = 0.05
    speed_max_m_s: float = 5.0
    timeout_s: float = 5.0
    fallback: str = "hold"
    safe_power_w: float = 0.0

    def __post_init__(self) -> None:
        if not 0 <= self.power_min_w < self.power_max_w:
            raise UsageError("power bounds need 0 <= --power-min-w < --power-max-w")
        if not 0 < self.speed_min_m_s < self.speed_max_m_s:
            raise UsageError("speed bounds need 0 < min < max")
        if not self.timeout_s > 0:
            raise UsageError("--command-timeout-s must be > 0")
        if self.fallback not in ("hold", "safe"):
            raise UsageError("--fallback must be 'hold' or 'safe'")
        if not self.power_min_w <= self.safe_power_w <= self.power_max_w:
            raise UsageError("--safe-power-w must lie within the power bounds")

    def accepts(self, cmd: LaserCommand) -> bool:
        """Whether a command may be applied (never apply a power outside the bounds)."""
        return (
            self.power_min_w <= cmd.power_w <= self.power_max_w
            and self.speed_min_m_s <= cmd.speed_mm_s * 1e-3 <= self.speed_max_m_s
        )


def n_steps(scenario: Scenario) -> int:
    """Steps to the end of the plan at the profile's lowest speed (exact for a constant speed)."""
    v_min = scenario.profile.speed_m_s.range()[0]
    return math.ceil(scenario.plan.total_length / (v_min * scenario.settings.dt_s) - 1e-9)


def describe(scenario: Scenario) -> dict:
    """JSON-able description of a scenario (recorded as the plant's configuration)."""
    return json.loads(json.dumps(
        {"scenario": scenario.name, "settings": dataclasses.asdict(scenario.settings),
         "plan": dataclasses.asdict(scenario.plan), "profile": dataclasses.asdict(scenario.profile)},
        default=lambda o: o.tolist() if hasattr(o, "tolist") else str(o)))


def state_message(run_id: str, obs: Observation) -> MeltPoolState:
    """SI observation → contract message (mm², µm, mm/s at this edge)."""
    return MeltPoolState(
        run_id=run_id, step=obs.step, time_s=obs.time_s, laser_x_mm=obs.x_m * 1e3, laser_y_mm=obs.y_m * 1e3,
        scan_dir_x=obs.direction[0], scan_dir_y=obs.direction[1], track=obs.track, area_mm2=obs.area_m2 * 1e6,
        t_ahead_k=obs.t_ahead_k, power_w=obs.power_w, speed_mm_s=obs.speed_m_s * 1e3, width_um=obs.width_m * 1e6,
        length_um=obs.length_m * 1e6, depth_um=obs.depth_m * 1e6, cross_section_mm2=obs.cross_section_m2 * 1e6,
        t_peak_k=obs.t_peak_k, source="fe", **preview_fields(obs),
    )


def preview_fields(obs: Observation) -> dict:
    """Scan-plan preview of a state: track distances → times at the applied speed (none before laser-on)."""
    if not obs.speed_m_s > 0:
        return {"next_track": obs.next_track}
    return {"track_elapsed_s": obs.track_travelled_m / obs.speed_m_s,
            "track_remaining_s": obs.track_remaining_m / obs.speed_m_s, "next_track": obs.next_track}


class CommandWaiter:
    """Waits for the command of a given step; counts stale and rejected commands."""

    def __init__(self, inbox: Inbox, policy: CommandPolicy) -> None:
        self.inbox, self.policy = inbox, policy
        self.n_stale = 0
        self.n_rejected = 0

    def wait(self, step: int, stop: StopFlag) -> LaserCommand | None:
        """The valid command for ``step``, or ``None`` after the timeout (or on stop)."""
        deadline = time.monotonic() + self.policy.timeout_s
        while not stop.is_set():
            remaining = deadline - time.monotonic()
            if remaining <= 0:
                return None
            cmd = self.inbox.get(timeout=min(remaining, 0.1))
            if cmd is None:
                continue
            if cmd.step != step:
                self.n_stale += 1
            elif not self.policy.accepts(cmd):
                self.n_rejected += 1
            else:
                return cmd
        return None


def run(bus: NodeBus, scenario: Scenario, model: ThermalModel, policy: CommandPolicy, args: argparse.Namespace,
        stop: StopFlag, setup_s: float) -> int:
    """Step the plant until the scan plan ends (or ``--max-steps``); returns the exit status."""
    states = bus.publisher(PLANT_STATE)
    diagnostics = bus.publisher(PLANT_DIAGNOSTICS)
    images = bus.publisher(PLANT_TEMPERATURE, express=False)
    waiter = CommandWaiter(bus.inbox(LASER_COMMAND), policy) if not args.open_loop else None
    controller_gone = bus.watch_presence(args.controller) if waiter else None
    total = n_steps(scenario) if args.max_steps is None else min(n_steps(scenario), args.max_steps)
    bus.ready(config={**describe(scenario), "policy": vars(policy), "open_loop": args.open_loop,
                      "setup_s": round(setup_s, 3), "nodes": model.grid.n_nodes}, total_steps=total, stop=stop)
    bus.log(LogLevel.INFO, f"{scenario.name}: {total} steps, {model.grid.n_nodes} nodes, setup {setup_s:.1f} s")
    power_w, speed_m_s = scenario.profile.command(0)
    obs = dataclasses.replace(model.initial_observation(), speed_m_s=speed_m_s)  # laser off, about to scan at v
    n_fallbacks = 0
    status = 0
    t_min, t_max = scenario.settings.t0_k, scenario.settings.material.t_liquidus + 600.0
    while not stop.is_set():
        states.put(state_message(bus.run_id, obs))
        if obs.step % args.image_every == 0:
            image, _ = model.temperature_image()
            images.put(temperature_image(image, obs.time_s, t_min, t_max))
        if obs.step >= total or model.done:
            break
        source = "open-loop"
        if waiter is None:
            power_w, speed_m_s = scenario.profile.command(obs.step)
        else:
            cmd = waiter.wait(obs.step + 1, stop)
            if cmd is not None:
                power_w, speed_m_s, source = cmd.power_w, cmd.speed_mm_s * 1e-3, "controller"
            elif stop.is_set():
                break
            else:
                n_fallbacks += 1
                if policy.fallback == "safe":
                    power_w = policy.safe_power_w
                source = f"fallback-{policy.fallback}"
                gone = controller_gone is not None and controller_gone.is_set()
                bus.log(LogLevel.ERROR if gone else LogLevel.WARNING,
                        f"no command for step {obs.step + 1} within {policy.timeout_s} s"
                        f"{' (controller gone)' if gone else ''}; applying {source} {power_w:.1f} W", time_s=obs.time_s)
                if gone:
                    status = 1
        t0 = time.perf_counter()
        obs = model.step(power_w, speed_m_s)
        diagnostics.put(PlantDiagnostics(
            run_id=bus.run_id, step=obs.step, time_s=obs.time_s, step_wall_ms=(time.perf_counter() - t0) * 1e3,
            absorbed_j=obs.energy_absorbed_j, stored_j=obs.energy_stored_j, lost_j=obs.energy_lost_j,
            energy_error_pct=obs.energy_error_pct, n_fallbacks=n_fallbacks,
            n_stale_commands=waiter.n_stale if waiter else 0,
            n_dropped=(waiter.n_rejected + waiter.inbox.n_invalid) if waiter else 0, command_source=source,
        ))
        if status:
            states.put(state_message(bus.run_id, obs))
            break
    summary = (f"{'stopped' if stop.is_set() else 'finished'} at step {obs.step}; {n_fallbacks} fallbacks"
               + (f", {waiter.n_stale} stale, {waiter.n_rejected} rejected, {waiter.inbox.n_invalid} invalid commands"
                  if waiter else ""))
    bus.log(LogLevel.ERROR if status else LogLevel.INFO,
            summary + ("; ending the run: controller lost" if status else ""), time_s=obs.time_s)
    bus.end_detail(summary)
    return status


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``python -m fe_node`` (node mode)."""
    parser = ArgumentParser(prog="python -m fe_node", description=__doc__.split("\n\n")[0])
    parser.add_argument("--scenario", default="layer", help=f"one of {', '.join(NAMES)} (default: %(default)s)")
    parser.add_argument("--power-w", type=float, help="nominal / open-loop power [W] (scenario default)")
    parser.add_argument("--speed-mm-s", type=float, help="scan speed [mm/s] (scenario default)")
    parser.add_argument("--h-um", type=float, help="fine element size [µm] (default: converged 25 µm)")
    parser.add_argument("--config", type=Path, help="TOML run configuration; its [plant] table overrides plant settings")
    parser.add_argument("--open-loop", action="store_true", help="play the scenario's power/speed profile; no controller")
    parser.add_argument("--max-steps", type=int, help="stop after this many steps (short runs)")
    parser.add_argument("--command-timeout-s", type=float, default=5.0, help="wait this long for each command (default: %(default)s)")
    parser.add_argument("--fallback", choices=("hold", "safe"), default="hold", help="on timeout hold the last power or apply --safe-power-w")
    parser.add_argument("--safe-power-w", type=float, default=0.0, help="power of the 'safe' fallback [W] (default: %(default)s)")
    parser.add_argument("--power-min-w", type=float, default=0.0, help="lowest power ever applied [W]")
    parser.add_argument("--power-max-w", type=float, default=350.0, help="highest power ever applied [W]")
    parser.add_argument("--image-every", type=int, default=10, help="publish the temperature image every N steps")
    parser.add_argument("--controller", default="controller", help="controller node to follow (default: %(default)s)")
    add_bus_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of the node mode of ``python -m fe_node``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        bus_settings = bus_settings_from_args(args)
        if args.max_steps is not None and args.max_steps < 1:
            raise UsageError("--max-steps must be >= 1")
        if args.image_every < 1:
            raise UsageError("--image-every must be >= 1")
        policy = CommandPolicy(args.power_min_w, args.power_max_w, timeout_s=args.command_timeout_s,
                               fallback=args.fallback, safe_power_w=args.safe_power_w)
        plant_table = load_toml(args.config).get("plant", {})
        try:
            overrides = {k: v for k, v in {
                "power_w": args.power_w,
                "speed_m_s": None if args.speed_mm_s is None else args.speed_mm_s * 1e-3,
                "h_fine_m": None if args.h_um is None else args.h_um * 1e-6,
            }.items() if v is not None}
            scenario = build_scenario(args.scenario, **{**plant_table, **overrides})
        except ValueError as err:
            raise UsageError(str(err)) from None
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = StopFlag()
    t0 = time.perf_counter()
    model = ThermalModel(scenario.settings, scenario.plan)
    setup_s = time.perf_counter() - t0
    try:
        with NodeBus(NODE_NAME, bus_settings) as bus:
            return run(bus, scenario, model, policy, args, stop, setup_s)
    except TimeoutError as err:  # a --require node never appeared
        return exit_error(parser.prog, err)


if __name__ == "__main__":
    sys.exit(main())
