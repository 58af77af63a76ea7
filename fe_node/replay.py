"""Replay node: ``python -m fe_node.replay RECORDING [--rate-scale S]``.

Publishes the ``MeltPoolState`` messages of any meltloop recording as node ``plant``, with
``source="replay"`` and this run's id, at their recorded process-time spacing divided by
``--rate-scale`` (1: real time, 0.1: ten times slower). The controller runs unchanged against
this non-FE source; its commands are received, validated and counted but not applied (the
recording is open data). Useful to test a controller on sensor data or a past run.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import msgspec

from messages import LogLevel, MeltPoolState
from messages.bus import NodeBus, StopFlag, parse_node_arguments, run_node
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main
from messages.recording import RecordingError, read_all
from messages.topics import LASER_COMMAND, PLANT_STATE

NODE_NAME = "plant"
LAST_ANSWER_TIMEOUT_S = 2.0
"""How long the node waits after its last state for the command that answers it [s]."""


def load_states(path: Path) -> list[MeltPoolState]:
    """Every valid state of the recording, in file order (:class:`UsageError` if none or unreadable)."""
    try:
        return read_all(path, PLANT_STATE)
    except RecordingError as err:
        raise UsageError(str(err)) from None


def schedule(states: list[MeltPoolState], rate_scale: float) -> list[float]:
    """Wall-clock offset [s] of each state from the first: recorded ``time_s`` spacing / ``rate_scale``."""
    t0 = states[0].time_s
    return [max(0.0, (s.time_s - t0) / rate_scale) for s in states]


def replay(bus: NodeBus, states: list[MeltPoolState], offsets: list[float], stop: StopFlag) -> tuple[int, int]:
    """Publish the states on schedule; returns (states published, valid commands received)."""
    pub = bus.publisher(PLANT_STATE)
    commands = bus.inbox(LASER_COMMAND)
    n_commands = n_sent = 0
    started = time.monotonic()
    for state, offset in zip(states, offsets):
        while (remaining := started + offset - time.monotonic()) > 0 and not stop.is_set():
            n_commands += commands.get(timeout=remaining) is not None
        if stop.is_set():
            break
        pub.put(msgspec.structs.replace(state, run_id=bus.run_id, source="replay"))
        n_sent += 1
    last_step = states[n_sent - 1].step if n_sent else -1
    deadline = time.monotonic() + LAST_ANSWER_TIMEOUT_S
    while not stop.is_set() and (remaining := deadline - time.monotonic()) > 0:  # the answer to the last state
        cmd = commands.get(timeout=remaining)
        n_commands += cmd is not None
        if cmd is not None and cmd.step > last_step:
            break
    n_commands += sum(1 for _ in commands.drain())
    bus.log(LogLevel.INFO, f"replayed {n_sent} of {len(states)} states; {n_commands} commands received "
            f"(not applied), {commands.n_invalid} invalid", time_s=states[n_sent - 1].time_s if n_sent else 0.0)
    return n_sent, n_commands


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m fe_node.replay``."""
    parser = ArgumentParser(prog="python -m fe_node.replay", description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, help="MCAP recording with /plant/state")
    parser.add_argument("--rate-scale", type=float, default=1.0,
                        help="playback speed; 1 = real time (default: %(default)s)")
    try:
        args, bus_settings = parse_node_arguments(parser, argv)
        if not (math.isfinite(args.rate_scale) and args.rate_scale > 0):
            raise UsageError(f"--rate-scale must be finite and > 0, got {args.rate_scale}")
        states = load_states(args.recording)
    except UsageError as err:
        return exit_usage(parser.prog, err)
    offsets = schedule(states, args.rate_scale)
    stop = StopFlag()

    def body(bus: NodeBus) -> int:
        bus.ready(config={"recording": str(args.recording), "rate_scale": args.rate_scale, "states": len(states)},
                  total_steps=len(states), stop=stop)
        replay(bus, states, offsets, stop)
        return 0

    return run_node(parser.prog, NODE_NAME, bus_settings, body)


if __name__ == "__main__":
    run_main(main)
