"""Test node: forges schema-valid messages of other nodes during a run, from its own process.

``python -m tests.nodes.rogue --count N [--after-step K]``. Run by ``launch.py`` in a node
list, it is an authenticated node of the run **without a role** (name ``rogue``). Once the
plant has published state ``--after-step`` it

1. tries to open a zenoh session to the hub **without credentials** and reports whether that
   was refused (``unauthenticated session refused`` / ``... accepted``);
2. sends N schema-valid forgeries, spread over: states with the next step and a wrong area,
   commands for the next step at 123 W, ``end`` events and logs in the plant's and the
   controller's name (under their keys and under its own), all blocking-reliable;
3. declares liveliness tokens in the plant's and controller's names;

then prints ``rogue done: sent {...}`` and stays until the plant is gone (``--count 0``: a clean
run with the same nodes). Every forgery must be stopped by the hub's access control or dropped
by its receivers; none may be applied or recorded.
"""

from __future__ import annotations

import json
import os
import sys
from collections import Counter

import zenoh

from messages import LaserCommand, Log, LogLevel, MeltPoolState, RunEvent, Timestamp, encode
from messages.auth import PASSWORD_ENV, USER_ENV
from messages.bus import NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args, zenoh_config
from messages.cli import ArgumentParser
from messages.topics import LASER_COMMAND, LOG, PLANT_STATE, RUN_EVENTS, key_expr, liveliness_key

FORGED_POWER_W = 123.0


def forgeries(run_id: str, state: MeltPoolState, n: int) -> list[tuple[str, bytes]]:
    """``n`` (key, payload) pairs, every one a valid message of another node."""
    out = []
    for i in range(n):
        kind = i % 6
        step = state.step + 1 + i % 3
        if kind == 0:
            msg = MeltPoolState(**{**{f: getattr(state, f) for f in state.__struct_fields__},
                                   "step": step, "area_mm2": 0.5 * state.area_mm2})
            out.append((key_expr(run_id, PLANT_STATE), encode(msg)))
        elif kind == 1:
            msg = LaserCommand(run_id=run_id, step=step, time_s=state.time_s, power_w=FORGED_POWER_W,
                               speed_mm_s=800.0, controller="preview-mpc")
            out.append((key_expr(run_id, LASER_COMMAND), encode(msg)))
        elif kind in (2, 3):
            node = ("plant", "controller")[kind - 2]
            msg = RunEvent(run_id=run_id, node=node, event="end", time_s=state.time_s,
                           published={"plant/state": 1})
            out.append((key_expr(run_id, RUN_EVENTS, node if i % 2 else "rogue"), encode(msg)))
        else:
            node = ("plant", "controller")[kind - 4]
            msg = Log(timestamp=Timestamp.from_seconds(state.time_s), level=LogLevel.ERROR, message="forged",
                      name=node)
            out.append((key_expr(run_id, LOG, node), encode(msg)))
    return out


def unauthenticated_refused(settings) -> bool:
    """Whether the hub refuses a session that has no credentials."""
    config = zenoh_config(settings, credentials=None)
    config.insert_json5("mode", '"client"')
    try:
        session = zenoh.open(config)
    except zenoh.ZError:
        return True
    linked = bool(list(session.info.routers_zid()) or list(session.info.peers_zid()))
    session.close()
    return not linked


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="rogue")
    parser.add_argument("--count", type=int, default=10_000)
    parser.add_argument("--after-step", type=int, default=20)
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    settings = bus_settings_from_args(args)
    stop = StopFlag()
    with NodeBus("rogue", settings) as bus:
        assert bus.session is not None
        states = bus.inbox(PLANT_STATE)
        plant_gone = bus.watch_presence("plant")
        bus.ready()
        if args.count:
            state = None
            while not stop.is_set() and not plant_gone.is_set() and (state is None or state.step < args.after_step):
                state = states.get(timeout=0.1) or state
            if state is None or plant_gone.is_set():
                print("error: the plant ended before the forging started", flush=True)
                return 1
            env = {k: os.environ.pop(k) for k in (USER_ENV, PASSWORD_ENV) if k in os.environ}
            refused = unauthenticated_refused(settings)
            os.environ.update(env)
            print(f"unauthenticated session {'refused' if refused else 'accepted'}", flush=True)
            publishers: dict[str, zenoh.Publisher] = {}
            sent: Counter[str] = Counter()
            for key, payload in forgeries(bus.run_id, state, args.count):
                if key not in publishers:
                    publishers[key] = bus.session.declare_publisher(
                        key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE)
                publishers[key].put(payload)
                sent[key.split("/", 2)[2]] += 1
            tokens = [bus.session.liveliness().declare_token(liveliness_key(bus.run_id, n))
                      for n in ("plant", "controller")]
            print(f"rogue done: sent {json.dumps(dict(sent), sort_keys=True)}", flush=True)
        while not stop.is_set() and not plant_gone.is_set():
            stop.wait(0.05)
        if args.count:
            for token in tokens:
                token.undeclare()
            for pub in publishers.values():
                pub.undeclare()
    return 0


if __name__ == "__main__":
    sys.exit(main())
