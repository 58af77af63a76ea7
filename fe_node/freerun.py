"""Free-running plant loop shared by sensor-like nodes (example sensor, GP surrogate).

A free-running plant behaves like a camera or pyrometer: it publishes ``MeltPoolState`` at a
fixed rate and never waits for the controller. Between two publishes it sleeps while whatever
``LaserCommand`` arrives is queued with its arrival time (no wake-up per command); at each tick
it takes them, applies the newest applicable command and echoes the applied power in the state
it publishes. A fast plant (period under :data:`POLL_MAX_PERIOD_S`, ``poll_commands`` on by
default) that is a zenoh peer of its controller polls zenoh's channel for the command answering
its last state instead, from :data:`POLL_AT` of the period after that publish until the command
is in or the tick comes (yielding its core between looks), then sleeps to the tick: no thread to
wake on the command's way. It polls while its controller is present, most recent commands came
on time (:data:`POLL_MIN_ON_TIME`) and the machine has a core to spare
(:class:`~messages.spare_core.SpareCore`); otherwise (a controller that cannot answer within the
period, a machine whose cores are all busy) it switches to a callback inbox read at its ticks
(:class:`CommandInboxes`). A client of a router (``launch.py``'s nodes) never polls: the router
forwards each state and each command, and the core a poller keeps is the one its threads need
(``docs/realtime.md``, "The plant's poll window"). A command's arrival time is when the polling plant took
it, or when the callback thread stamped it. A command is applicable
(:class:`~fe_node.commands.CommandGate`) if its step is newer than the last applied one, at most
one after the newest published state (no controller can answer a state not yet published) and
not more than ``RING`` − 1 steps late, and its power and speed lie within the bounds; every
other command is dropped and counted. The command answering state k (``step = k + 1``) is *on
time* if it arrives before state k+1 is published; otherwise that step is a deadline miss. Round
trips run from the moment a state is handed to zenoh to the command's arrival in this process,
as a bare zenoh ping-pong is timed. The fallback (default: the safe power) applies as soon as
the controller's liveliness token is gone, or when no command was applied for ``timeout_s``.

Functional core: :class:`CommandLatch` (which command applies, deadline and round-trip
bookkeeping; no I/O, time passed in). Thin shell: :func:`run_free` (zenoh, clock, loop).
"""

from __future__ import annotations

import argparse
import gc
import json
import os
import threading
import time
from dataclasses import dataclass, field
from typing import Any, Protocol

import numpy as np

from fe_node.commands import FALLBACKS, CommandGate, CommandPolicy, Verdict
from messages import LaserCommand, LogLevel, MeltPoolState, PlantDiagnostics
from messages.bus import BusSettings, Inbox, NodeBus, StopFlag, run_node
from messages.cli import UsageError
from messages.spare_core import SpareCore
from messages.topics import LASER_COMMAND, PLANT_DIAGNOSTICS, PLANT_STATE

RING = 1 << 14  # publish times kept for round-trip matching; older commands are stale (steps)
FREE_RUN_TIMEOUT_S = 0.5  # default fallback timeout of a free-running plant [s]
POLL_MAX_PERIOD_S = 2e-3
"""A plant faster than this polls zenoh's channel for its commands (:func:`await_command`) while it
can (:class:`CommandInboxes`); otherwise it takes them at its ticks, stamped on arrival by a
callback thread."""
POLL_MIN_ON_TIME = 0.5
ON_TIME_SMOOTHING = 0.05
"""A fast plant polls while its recent share of on-time commands (weighted by
``(1 − ON_TIME_SMOOTHING)^age``, ~20 steps) exceeds ``POLL_MIN_ON_TIME``: not for a controller
that cannot answer within the period (e.g. a 10 kHz sensor), nor on a machine too loaded for it."""
WARMUP_STEPS = 200
"""Steps left out of :attr:`FreeRunStats` ``steady_miss_pct`` (the processes warm up; the bare
ping-pong of ``benchmarks/zenoh_pingpong.py`` leaves out its first 200 round trips too)."""
POLL_AT = 0.2
"""A polling plant starts looking for the command this fraction of the period after its publish
(no controller answers sooner; ``docs/realtime.md``, the plant's poll window)."""


@dataclass(frozen=True)
class PlantSample:
    """What a free-running plant observes at one tick (SI).

    Attributes
    ----------
    area_m2 : float
        Melt-pool top-surface area [m²].
    t_ahead_k : float
        Surface temperature ahead of the spot [K].
    x_m, y_m : float
        Laser spot position [m].
    direction : tuple of float
        Unit scan direction (x, y).
    track : int
        Track index in the layer.
    """

    area_m2: float
    t_ahead_k: float
    x_m: float
    y_m: float
    direction: tuple[float, float]
    track: int


class FreePlant(Protocol):
    """A plant stepped by the free-running loop (synthetic model, GP surrogate, hardware)."""

    def initial(self) -> PlantSample:
        """The observation before the first step."""

    def step(self, power_w: float, speed_m_s: float, dt_s: float) -> PlantSample:
        """Advance by ``dt_s`` [s] under ``power_w`` [W] and ``speed_m_s`` [m/s]; the new observation."""


@dataclass(frozen=True)
class FreeRunSettings:
    """Timing of a free-running plant.

    Attributes
    ----------
    rate_hz : float
        Publish rate [Hz]; also sets the process time step ``1 / rate_hz`` [s].
    max_steps : int or None
        Stop after this many steps (``None``: until stopped).
    duration_s : float or None
        Stop after this wall time [s] (``None``: no limit).
    diagnostics_every : int
        Publish ``PlantDiagnostics`` every N steps.
    dt_s : float or None
        Process time per step [s] (``None``: the wall period ``1 / rate_hz``, as a sensor;
        a model with its own time step, e.g. the GP surrogate, sets it).
    controller : str
        Node name of the controller whose liveliness the plant follows.
    poll_commands : bool
        Poll for each command (:func:`await_command`) when faster than :data:`POLL_MAX_PERIOD_S`,
        while a core is to spare, unless the bus is a client of a router (``--no-poll-commands``:
        never; ``docs/realtime.md``).
    """

    rate_hz: float = 1000.0
    max_steps: int | None = None
    duration_s: float | None = None
    diagnostics_every: int = 100
    dt_s: float | None = None
    controller: str = "controller"
    poll_commands: bool = True

    @property
    def step_s(self) -> float:
        """Process time per step [s]."""
        return self.dt_s if self.dt_s is not None else 1.0 / self.rate_hz

    def __post_init__(self) -> None:
        if not 0 < self.rate_hz <= 100_000:
            raise UsageError(f"--rate-hz must be in (0, 100000], got {self.rate_hz}")
        if self.max_steps is not None and self.max_steps < 1:
            raise UsageError("--max-steps must be >= 1")
        if self.duration_s is not None and not self.duration_s > 0:
            raise UsageError("--duration-s must be > 0")
        if self.diagnostics_every < 1:
            raise UsageError("--diagnostics-every must be >= 1")
        if self.dt_s is not None and not 0 < self.dt_s < 1:
            raise UsageError(f"process time step must be in (0, 1) s, got {self.dt_s}")
        if not self.controller:
            raise UsageError("--controller must name a node")
        if not isinstance(self.poll_commands, bool):
            raise UsageError("--poll-commands is a flag")


@dataclass
class CommandLatch:
    """Which command applies at each tick, and the deadline/round-trip bookkeeping.

    Parameters
    ----------
    policy : CommandPolicy
        Bounds (never apply a power outside them), timeout and fallback.
    power_w, speed_m_s : float
        Initial (nominal) command, step 0, applied until the first command arrives [W], [m/s].
    """

    policy: CommandPolicy
    power_w: float
    speed_m_s: float
    gate: CommandGate = field(init=False)
    newest_step: int = 0
    last_command_t: float | None = None
    on_time_step: int = -1
    n_late: int = 0
    n_fallbacks: int = 0
    rtt_s: list[float] = field(default_factory=list)
    _published_t: np.ndarray = field(default_factory=lambda: np.full(RING, np.nan))
    _published_step: int = -1
    _applied: LaserCommand | None = None

    def __post_init__(self) -> None:
        self.gate = CommandGate(self.policy)

    def published(self, step: int, t: float) -> None:
        """State ``step`` was published at monotonic time ``t`` [s]."""
        self._published_t[step % RING] = t
        self._published_step = step

    def offer(self, cmd: LaserCommand, t: float) -> None:
        """A decoded command received at monotonic time ``t`` [s]: applied if the gate admits it.

        The command applied last, offered again, is ignored: the same message received by both of
        the plant's subscribers while it switches between them (:class:`CommandInboxes`).
        """
        if cmd == self._applied:
            return
        first = max(self.newest_step + 1, self._published_step + 2 - RING)
        if self.gate.admit(cmd, first, self._published_step + 1) is not Verdict.APPLY:
            return
        self.rtt_s.append(t - float(self._published_t[(cmd.step - 1) % RING]))
        if cmd.step <= self._published_step:
            self.n_late += 1  # its state's successor is already out: too late for its step
        else:
            self.on_time_step = cmd.step
        self.newest_step, self._applied = cmd.step, cmd
        self.power_w, self.speed_m_s = cmd.power_w, cmd.speed_mm_s * 1e-3
        self.last_command_t = t

    def command_for(self, t: float, started_t: float, controller_gone: bool) -> tuple[float, float, str]:
        """(power [W], speed [m/s], ``command_source``) to apply at monotonic time ``t`` [s].

        The fallback applies once the controller is gone or ``timeout_s`` passed without an
        applied command (since ``started_t`` before the first); the initial command before the
        first one arrives is ``open-loop``.
        """
        last = self.last_command_t if self.last_command_t is not None else started_t
        if controller_gone or t - last > self.policy.timeout_s:
            self.n_fallbacks += 1
            return self.policy.fallback_power(self.power_w), self.speed_m_s, self.policy.fallback_source
        return self.power_w, self.speed_m_s, "open-loop" if self.last_command_t is None else "controller"

    def missed(self, step: int) -> bool:
        """Whether the command for ``step`` had not arrived when state ``step`` was published."""
        return self.on_time_step < step


@dataclass
class MissBursts:
    """Runs of consecutive deadline misses: how many, and the longest [steps]. A stall of the
    machine shows as one long run; a controller slower than the period as one run of every step."""

    count: int = 0
    longest: int = 0
    _current: int = 0

    def add(self, missed: bool) -> None:
        """Count one step, missed or not."""
        if not missed:
            self._current = 0
            return
        if self._current == 0:
            self.count += 1
        self._current += 1
        self.longest = max(self.longest, self._current)


@dataclass(frozen=True)
class FreeRunStats:
    """Outcome of a free-running run (times in s; command counts by what became of them)."""

    steps: int
    wall_s: float
    misses: int
    late: int
    dropped: int
    rejected: int
    invalid: int
    fallbacks: int
    rtt_s: tuple[float, ...]
    warmup_misses: int = 0
    """Misses among the first :data:`WARMUP_STEPS` steps (included in ``misses``)."""
    polled: int = 0
    """Steps for which the plant polled for its command (:class:`CommandInboxes`)."""
    miss_bursts: int = 0
    """Runs of consecutive misses (:class:`MissBursts`)."""
    longest_miss_burst: int = 0
    """The longest of them [steps]."""

    def summary(self) -> dict[str, float | int | None]:
        """JSON-able figures: achieved rate [Hz], deadline misses [%] (all steps, and
        ``steady_miss_pct`` after the first :data:`WARMUP_STEPS`), round trip [µs], command counts."""
        rtt = np.asarray(self.rtt_s) * 1e6
        steady = self.steps - WARMUP_STEPS
        return {
            "steps": self.steps,
            "rate_hz": round(self.steps / self.wall_s, 1) if self.wall_s > 0 else 0.0,
            "deadline_miss_pct": round(100.0 * self.misses / self.steps, 3) if self.steps else 0.0,
            "steady_miss_pct": round(100.0 * (self.misses - self.warmup_misses) / steady, 3) if steady > 0 else None,
            "rtt_median_us": round(float(np.median(rtt)), 1) if rtt.size else None,
            "rtt_p99_us": round(float(np.percentile(rtt, 99)), 1) if rtt.size else None,
            "polled_pct": round(100.0 * self.polled / self.steps, 1) if self.steps else 0.0,
            "commands": int(rtt.size),
            "late_commands": self.late,
            "miss_bursts": self.miss_bursts,
            "longest_miss_burst_steps": self.longest_miss_burst,
            "dropped_commands": self.dropped,
            "rejected_commands": self.rejected,
            "invalid_commands": self.invalid,
            "fallback_steps": self.fallbacks,
        }


def state_message(run_id: str, step: int, time_s: float, s: PlantSample, power_w: float, speed_m_s: float,
                  source: str, **details: Any) -> MeltPoolState:
    """SI sample → contract message (mm², mm, mm/s at this edge): the one construction of a plant's
    ``MeltPoolState``; ``details`` are its optional fields, already in the message's units."""
    return MeltPoolState(
        run_id=run_id, step=step, time_s=time_s, laser_x_mm=s.x_m * 1e3, laser_y_mm=s.y_m * 1e3,
        scan_dir_x=s.direction[0], scan_dir_y=s.direction[1], track=s.track, area_mm2=s.area_m2 * 1e6,
        t_ahead_k=s.t_ahead_k, power_w=power_w, speed_mm_s=speed_m_s * 1e3, source=source,  # type: ignore[arg-type]
        **details,
    )


def sleep_until(t: float) -> None:
    """Sleep until monotonic time ``t`` [s] (at once if it has passed)."""
    while (remaining := t - time.monotonic()) > 0:
        time.sleep(remaining)


def await_command(inbox: Inbox, latch: CommandLatch, step: int, start: float, tick: float) -> None:
    """Poll ``inbox`` from monotonic time ``start`` until the command answering state ``step`` is
    in (offered to ``latch``) or ``tick`` [s] comes, yielding the core between looks."""
    sleep_until(start)
    while latch.on_time_step <= step and time.monotonic() < tick:
        offer_all(inbox, latch)
        if latch.on_time_step <= step:
            os.sched_yield()


class CommandInboxes:
    """Where a free-running plant takes its commands from: one subscriber at a time.

    A slow plant (or one without ``poll_commands``) has a callback inbox: zenoh-python's callback
    thread stamps each command on arrival. A fast one reads zenoh's channel
    (:class:`~messages.bus.PolledInbox`) while it polls (no thread to wake on the command's way),
    and switches to a callback inbox while it does not (its controller too slow or gone, or no
    core to spare: a callback plant then, the one measured better under load, ``docs/realtime.md``).
    A switch declares the new subscriber, then takes what the old one holds and closes it (a
    channel cannot be read once closed), so that no command is lost; a copy of the command
    applied last, received by both, is ignored by :meth:`CommandLatch.offer`.
    """

    def __init__(self, bus: NodeBus, fast: bool) -> None:
        self.bus, self.fast, self.polling = bus, fast, fast
        self.inbox: Inbox = bus.polled_inbox(LASER_COMMAND) if fast else bus.inbox(LASER_COMMAND)
        self._n_invalid_closed = 0

    def read(self, polling: bool, latch: CommandLatch) -> Inbox:
        """The inbox to read this step: zenoh's channel if ``polling`` (a fast plant only), else a
        callback inbox; at a switch, what the old one holds is offered to ``latch`` first."""
        if not self.fast or polling == self.polling:
            return self.inbox
        old = self.inbox
        self.inbox = self.bus.polled_inbox(LASER_COMMAND) if polling else self.bus.inbox(LASER_COMMAND)
        self.polling = polling
        offer_all(old, latch)  # what comes from now on is in the new inbox too
        self.bus.close_inbox(old)
        self._n_invalid_closed += old.n_invalid
        return self.inbox

    @property
    def n_invalid(self) -> int:
        """Invalid commands dropped, by every inbox the plant read."""
        return self._n_invalid_closed + self.inbox.n_invalid


def offer_all(inbox: Inbox, latch: CommandLatch) -> None:
    """Offer ``latch`` every valid command in ``inbox``, oldest first, each with its arrival time."""
    for cmd in inbox.drain():
        latch.offer(cmd, inbox.received_t)


def run_free(bus: NodeBus, plant: FreePlant, latch: CommandLatch, settings: FreeRunSettings, stop: StopFlag,
             source: str, controller_gone: threading.Event) -> FreeRunStats:
    """Publish states at ``settings.rate_hz`` until the step/time limit or a stop; apply the newest command.

    The node must have announced readiness (``bus.ready``) before; the loop never blocks on
    the controller. Ticks follow a fixed schedule; an overrun by more than one period restarts
    it from now (no burst to catch up). The achieved rate is reported. Each switch to the
    fallback is logged once (``controller_gone``: the controller's liveliness token is gone).
    With ``settings.poll_commands``, a plant faster than :data:`POLL_MAX_PERIOD_S` whose commands
    come straight from its controller (``bus.routed`` false: no router on their way) polls zenoh's
    channel for each command while the controller is present, most recent commands came on time
    and a core is to spare (:func:`await_command`, :class:`CommandInboxes`).
    """
    states = bus.publisher(PLANT_STATE)
    diagnostics = bus.publisher(PLANT_DIAGNOSTICS)
    period, dt = 1.0 / settings.rate_hz, settings.step_s
    fast = settings.poll_commands and period < POLL_MAX_PERIOD_S
    if fast and bus.routed:
        bus.log(LogLevel.INFO, "commands taken at the ticks, not polled for: this session is a client of a router "
                "(docs/realtime.md)")
        fast = False
    on_time_share = 1.0  # recent share of on-time commands (exponentially weighted)
    inboxes, spare = CommandInboxes(bus, fast), SpareCore()
    polled_steps = 0
    sample = plant.initial()
    power, speed = latch.power_w, latch.speed_m_s
    step = misses = warmup_misses = 0
    bursts = MissBursts()
    command_source = "open-loop"
    started = next_tick = time.monotonic()
    published_t = states.put(state_message(bus.run_id, 0, 0.0, sample, power, speed, source))
    latch.published(0, published_t)
    end_t = None if settings.duration_s is None else started + settings.duration_s
    gc.collect()
    gc.freeze()  # what exists now lives to the end: keep it out of the collections on the hot path
    while not stop.is_set() and (settings.max_steps is None or step < settings.max_steps):
        next_tick += period
        if next_tick < time.monotonic() - period:  # overrun by more than a period: restart the schedule
            next_tick = time.monotonic()
        if end_t is not None and next_tick > end_t:
            break
        polling = (fast and on_time_share > POLL_MIN_ON_TIME and not controller_gone.is_set()
                   and spare.spare(time.monotonic()))
        inbox = inboxes.read(polling, latch)
        if polling:
            polled_steps += 1
            await_command(inbox, latch, step, min(published_t + POLL_AT * period, next_tick), next_tick)
        sleep_until(next_tick)
        offer_all(inbox, latch)  # each stamped with its arrival (callback inbox) or when taken (channel)
        step += 1
        now = time.monotonic()
        gone = controller_gone.is_set()
        power, speed, new_source = latch.command_for(now, started, gone)
        if new_source.startswith("fallback") and not command_source.startswith("fallback"):
            reason = (f"controller {settings.controller!r} gone (liveliness lost)" if gone
                      else f"no command for {latch.policy.timeout_s} s")
            bus.log(LogLevel.WARNING, f"{reason}: applying {new_source} {power:.1f} W from step {step} "
                    f"at wall {time.time():.6f} s", time_s=step * dt)
        command_source = new_source
        missed = latch.missed(step)
        misses += missed
        bursts.add(missed)
        if step <= WARMUP_STEPS:
            warmup_misses += missed
        on_time_share += ON_TIME_SMOOTHING * (float(not missed) - on_time_share)
        sample = plant.step(power, speed, dt)
        published_t = states.put(state_message(bus.run_id, step, step * dt, sample, power, speed, source))
        latch.published(step, published_t)
        if step % settings.diagnostics_every == 0:
            diagnostics.put(PlantDiagnostics(
                run_id=bus.run_id, step=step, time_s=step * dt, step_wall_ms=(time.monotonic() - now) * 1e3,
                n_fallbacks=latch.n_fallbacks, n_stale_commands=latch.gate.n_stale,
                n_dropped=latch.gate.n_dropped + inboxes.n_invalid, command_source=command_source,
            ))
    wall = time.monotonic() - started
    offer_all(inboxes.inbox, latch)  # count what is still queued
    stats = FreeRunStats(step, wall, misses, latch.n_late, latch.gate.n_dropped + inboxes.n_invalid,
                         latch.gate.counts[Verdict.OUT_OF_BOUNDS], inboxes.n_invalid, latch.n_fallbacks,
                         tuple(latch.rtt_s), warmup_misses, polled_steps, bursts.count, bursts.longest)
    bus.log(LogLevel.INFO, f"{'stopped' if stop.is_set() else 'finished'} after {step} steps in {wall:.2f} s; "
            f"{misses} deadline misses, {stats.dropped} dropped commands ({latch.gate.n_stale} stale, "
            f"{latch.gate.counts[Verdict.AHEAD]} ahead, {stats.rejected} out of bounds, {stats.invalid} invalid), "
            f"{latch.n_fallbacks} fallback steps", time_s=step * dt)
    return stats


def add_free_run_arguments(parser: argparse.ArgumentParser, rate_hz: float) -> None:
    """Options of every free-running plant: rate, limits, command bounds and fallback."""
    defaults, policy = FreeRunSettings(), CommandPolicy()
    parser.add_argument("--rate-hz", type=float, default=rate_hz, help="publish rate [Hz] (default: %(default)s)")
    parser.add_argument("--max-steps", type=int, help="stop after this many steps")
    parser.add_argument("--duration-s", type=float, help="stop after this wall time [s]")
    parser.add_argument("--diagnostics-every", type=int, default=defaults.diagnostics_every,
                        help="PlantDiagnostics every N steps (default: %(default)s)")
    parser.add_argument("--power-w", type=float, default=250.0, help="power until the first command [W]")
    parser.add_argument("--speed-mm-s", type=float, default=800.0, help="speed until the first command [mm/s]")
    parser.add_argument("--power-min-w", type=float, default=policy.power_min_w, help="lowest power ever applied [W]")
    parser.add_argument("--power-max-w", type=float, default=policy.power_max_w, help="highest power ever applied [W]")
    parser.add_argument("--command-timeout-s", type=float, default=FREE_RUN_TIMEOUT_S,
                        help="fallback after this long without an applied command [s] (default: %(default)s)")
    parser.add_argument("--fallback", choices=FALLBACKS, default=policy.fallback,
                        help="apply --safe-power-w or hold the last power (default: %(default)s)")
    parser.add_argument("--safe-power-w", type=float, default=policy.safe_power_w,
                        help="power of the 'safe' fallback [W] (default: %(default)s)")
    parser.add_argument("--controller", default=defaults.controller,
                        help="controller node whose liveliness the plant follows (default: %(default)s)")
    parser.add_argument("--poll-commands", action=argparse.BooleanOptionalAction, default=defaults.poll_commands,
                        help="faster than 2 ms: poll for each command while a core is to spare, instead of sleeping "
                             "to the tick; never as a client of a router, e.g. under launch.py (default: %(default)s; "
                             "docs/realtime.md)")
    parser.add_argument("--json", action="store_true", help="print the timing summary as JSON (last line)")


def settings_from_args(args: argparse.Namespace, dt_s: float | None = None) -> tuple[FreeRunSettings, CommandPolicy]:
    """Validated settings (process step ``dt_s`` [s], ``None``: the wall period) and command policy.

    Raises :class:`UsageError`.
    """
    settings = FreeRunSettings(args.rate_hz, args.max_steps, args.duration_s, args.diagnostics_every, dt_s,
                               args.controller, args.poll_commands)
    policy = CommandPolicy(args.power_min_w, args.power_max_w, timeout_s=args.command_timeout_s,
                           fallback=args.fallback, safe_power_w=args.safe_power_w)
    if not policy.within_bounds(args.power_w, args.speed_mm_s * 1e-3):
        raise UsageError("--power-w/--speed-mm-s must lie within the command bounds")
    return settings, policy


def serve(node: str, plant: FreePlant, bus_settings: BusSettings, args: argparse.Namespace,
          settings: FreeRunSettings, policy: CommandPolicy, config: dict, source: str) -> int:
    """Open the bus as ``node``, announce readiness (after any ``--require`` nodes), run; exit status."""
    stop = StopFlag()
    latch = CommandLatch(policy, args.power_w, args.speed_mm_s * 1e-3)
    summary: dict[str, float | int] = {}

    def body(bus: NodeBus) -> int:
        controller_gone = bus.watch_presence(settings.controller)
        bus.ready(config={**config, "rate_hz": settings.rate_hz, "policy": vars(policy)},
                  total_steps=settings.max_steps, stop=stop)
        summary.update(run_free(bus, plant, latch, settings, stop, source, controller_gone).summary())
        bus.end_detail(json.dumps(summary))
        return 0

    status = run_node(node, node, bus_settings, body)
    if status == 0 and args.json:
        print(json.dumps(summary), flush=True)
    return status
