"""A plant node written from the contract docs alone (``docs/node-contract.md``, ``messages.md``, ``launch.md``).

``python tests/nodes/plain_sensor.py --run-id RUN --connect ENDPOINT [options]`` is what
``launch.py --nodes`` runs for ``command = ["python", "tests/nodes/plain_sensor.py"]``. Like a
camera with a laser driver, it publishes ``MeltPoolState`` at ``--rate-hz`` (steps 0..``--steps``,
``time_s`` advancing by ``--period-s`` per frame) from a first-order melt-pool model, and applies
the newest admissible ``LaserCommand`` within its own power bounds; without one for
``--command-timeout-s``, or once the controller's liveliness token is gone, the safe power.
Only ``json``, ``zenoh`` and the standard library are used, so the same steps carry over to any
language with a zenoh binding.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import queue
import signal
import sys
import threading
import time

import zenoh

PREFIX = "meltloop"
REQUIRE_TIMEOUT_S = 60.0


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    """Command line (argparse exits 2 with one line on a bad one)."""
    p = argparse.ArgumentParser(prog="plain_sensor", description=__doc__.split("\n\n")[0])
    p.add_argument("--run-id", required=True, help="run identifier (appended by launch.py)")
    p.add_argument("--connect", action="append", default=[], help="hub endpoint (appended by launch.py)")
    p.add_argument("--node", default="plant", help="node name, also its zenoh user (default: %(default)s)")
    p.add_argument("--require", action="append", default=[], help="node to wait for before the start event")
    p.add_argument("--controller", default="controller", help="controller node whose liveliness is followed")
    p.add_argument("--steps", type=int, default=500, help="last step published (default: %(default)s)")
    p.add_argument("--rate-hz", type=float, default=1000.0, help="frames per second of wall time")
    p.add_argument("--period-s", type=float, default=50e-6, help="process time per frame [s] (default: 50 µs)")
    p.add_argument("--power-w", type=float, default=250.0, help="power until the first command [W]")
    p.add_argument("--speed-mm-s", type=float, default=800.0, help="scan speed until the first command [mm/s]")
    p.add_argument("--power-min-w", type=float, default=0.0, help="lowest power ever applied [W]")
    p.add_argument("--power-max-w", type=float, default=350.0, help="highest power ever applied [W]")
    p.add_argument("--safe-power-w", type=float, default=0.0, help="power applied without a controller [W]")
    p.add_argument("--command-timeout-s", type=float, default=0.5, help="fallback after this long without a command")
    args = p.parse_args(argv)
    if not (args.steps >= 1 and args.rate_hz > 0 and args.period_s > 0 and args.command_timeout_s > 0
            and 0 <= args.power_min_w <= args.safe_power_w <= args.power_max_w
            and args.power_min_w <= args.power_w <= args.power_max_w and args.speed_mm_s > 0):
        p.error("need --steps >= 1, positive rate, period, speed and timeout, and "
                "--power-min-w <= --safe-power-w, --power-w <= --power-max-w")
    return args


def open_session(connect: list[str]) -> zenoh.Session:
    """A client of the run's hub with the credentials launch.py put in the environment (else a peer)."""
    config = zenoh.Config()
    config.insert_json5("scouting/multicast/enabled", "false")
    user, password = os.environ.get("MELTLOOP_ZENOH_USER"), os.environ.get("MELTLOOP_ZENOH_PASSWORD")
    if user and password:
        config.insert_json5("mode", '"client"')
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    else:
        config.insert_json5("mode", '"peer"')
    config.insert_json5("connect/endpoints", json.dumps(connect or ["tcp/127.0.0.1:7447"]))
    return zenoh.open(config)


class Stop:
    """Set by SIGINT/SIGTERM. The handler only flips a flag: a handler calling ``Event.set`` can
    deadlock against an ``Event.wait`` of the same (main) thread."""

    def __init__(self) -> None:
        self.requested = False

    def is_set(self) -> bool:
        return self.requested

    def wait(self, timeout: float) -> bool:
        time.sleep(timeout)
        return self.requested


def wait_for(session: zenoh.Session, run_id: str, nodes: list[str], stop: Stop) -> None:
    """Until every node in ``nodes`` holds its liveliness token (``TimeoutError`` after the limit)."""
    missing, deadline = set(nodes), time.monotonic() + REQUIRE_TIMEOUT_S
    while missing and not stop.is_set():
        if time.monotonic() > deadline:
            raise TimeoutError(f"nodes not present after {REQUIRE_TIMEOUT_S:.0f} s: {', '.join(sorted(missing))}")
        for reply in session.liveliness().get(f"{PREFIX}/{run_id}/alive/*", timeout=0.5):
            if reply.ok is not None:
                missing.discard(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        stop.wait(0.05)


def parse_command(payload: bytes, run_id: str) -> tuple[int, float, float] | None:
    """``(step, power_w, speed_mm_s)`` of a valid command of this run, else ``None``."""
    try:
        cmd = json.loads(payload)
    except ValueError:
        return None
    if not isinstance(cmd, dict) or cmd.get("run_id") != run_id:
        return None
    step, power, speed = cmd.get("step"), cmd.get("power_w"), cmd.get("speed_mm_s")
    numbers = (power, speed)
    if type(step) is not int or step < 0 or not all(type(v) in (int, float) and math.isfinite(v) for v in numbers):
        return None
    return (step, float(power), float(speed)) if speed > 0 else None


class MeltPool:
    """First-order melt-pool area on 4 mm bidirectional tracks (SI inside)."""

    def __init__(self) -> None:
        self.distance_m = 0.0
        self.area_m2 = 0.0

    def observe(self) -> dict:
        """The observed fields of a state (contract units at this edge: mm, mm², K)."""
        track, along = divmod(self.distance_m, 4e-3)
        forward = int(track) % 2 == 0
        t_ahead_k = 300.0 + 400.0 * (1.0 - math.exp(-along / 1e-3))
        return {"laser_x_mm": (along if forward else 4e-3 - along) * 1e3, "laser_y_mm": track * 0.1,
                "scan_dir_x": 1.0 if forward else -1.0, "scan_dir_y": 0.0, "track": int(track),
                "area_mm2": self.area_m2 * 1e6, "t_ahead_k": t_ahead_k}

    def step(self, power_w: float, speed_m_s: float, dt_s: float, t_ahead_k: float) -> None:
        """Advance by ``dt_s`` [s] under ``power_w`` [W] and ``speed_m_s`` [m/s]."""
        steady = 0.063e-6 * power_w / 250.0 * math.sqrt(0.8 / speed_m_s) * (1.0 + (t_ahead_k - 300.0) / 2000.0)
        self.area_m2 += (steady - self.area_m2) * (1.0 - math.exp(-dt_s / 2e-4))
        self.distance_m += speed_m_s * dt_s


class Node:
    """The node's session, publishers and publish counts."""

    def __init__(self, session: zenoh.Session, run_id: str, name: str) -> None:
        self.session, self.run_id, self.name = session, run_id, name
        self.published: dict[str, int] = {}
        self._publishers: dict[str, zenoh.Publisher] = {}

    def put(self, suffix: str, message: dict) -> None:
        """Publish one JSON message reliably (blocking on congestion, so nothing is lost) and count it."""
        key = f"{PREFIX}/{self.run_id}/{suffix}" + (f"/{self.name}" if suffix in ("run/events", "log") else "")
        if suffix not in self._publishers:
            self._publishers[suffix] = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK, reliability=zenoh.Reliability.RELIABLE,
                express=True)
        self._publishers[suffix].put(json.dumps(message, allow_nan=False))
        self.published[suffix] = self.published.get(suffix, 0) + 1

    def event(self, kind: str, time_s: float, **fields) -> None:
        """A run event; ``end`` carries the publish counts, this event included."""
        if kind == "end":
            fields["published"] = {**self.published, "run/events": self.published.get("run/events", 0) + 1}
        self.put("run/events", {"run_id": self.run_id, "node": self.name, "event": kind, "time_s": time_s, **fields})

    def log(self, text: str, time_s: float, level: int = 2) -> None:
        """A ``foxglove.Log`` line (level 2 info, 3 warning), also printed."""
        ns = round(time_s * 1e9)
        self.put("log", {"timestamp": {"sec": ns // 10**9, "nsec": ns % 10**9}, "level": level, "message": text,
                         "name": self.name})
        print(text, flush=True)


def run(node: Node, args: argparse.Namespace, stop: Stop) -> None:
    """Subscribe, announce readiness, publish frames and apply commands until the last step or a stop."""
    inbox: queue.SimpleQueue[bytes] = queue.SimpleQueue()
    prefix = f"{PREFIX}/{args.run_id}"
    subscriber = node.session.declare_subscriber(f"{prefix}/controller/command",
                                                 lambda s: inbox.put(s.payload.to_bytes()))
    controller_gone = threading.Event()
    presence = node.session.liveliness().declare_subscriber(
        f"{prefix}/alive/{args.controller}",
        lambda s: controller_gone.set() if s.kind == zenoh.SampleKind.DELETE else None)
    wait_for(node.session, args.run_id, args.require, stop)
    config = {"power_min_w": args.power_min_w, "power_max_w": args.power_max_w, "sample_period_s": args.period_s,
              "rate_hz": args.rate_hz, "safe_power_w": args.safe_power_w, "command_timeout_s": args.command_timeout_s}
    node.event("start", 0.0, config_json=json.dumps(config), total_steps=args.steps)
    token = node.session.liveliness().declare_token(f"{prefix}/alive/{node.name}")

    model, power, speed = MeltPool(), args.power_w, args.speed_mm_s
    applied_step, applied_t, source = 0, time.monotonic(), "open-loop"
    n_applied = n_dropped = n_fallback = 0
    supervisor = os.environ.get("MELTLOOP_SUPERVISOR_PID")
    step, next_tick = 0, time.monotonic()
    while True:
        obs = model.observe()
        node.put("plant/state", {"run_id": args.run_id, "step": step, "time_s": step * args.period_s, **obs,
                                 "power_w": power, "speed_mm_s": speed, "source": "sensor"})
        if step % 100 == 0:
            node.put("plant/diagnostics", {"run_id": args.run_id, "step": step, "time_s": step * args.period_s,
                                           "step_wall_ms": 0.0, "n_fallbacks": n_fallback, "n_dropped": n_dropped,
                                           "command_source": source})
        if step >= args.steps or stop.is_set() or (supervisor and str(os.getppid()) != supervisor):
            break
        next_tick += 1.0 / args.rate_hz
        while (remaining := next_tick - time.monotonic()) > 0:
            time.sleep(min(remaining, 0.001))
        newest = None
        while True:
            try:
                cmd = parse_command(inbox.get_nowait(), args.run_id)
            except queue.Empty:
                break
            admissible = (cmd is not None and applied_step < cmd[0] <= step + 1
                          and args.power_min_w <= cmd[1] <= args.power_max_w)
            if admissible and (newest is None or cmd[0] > newest[0]):
                newest = cmd
            n_dropped += not admissible
        if newest is not None:
            applied_step, power, speed, applied_t, source = *newest, time.monotonic(), "controller"
            n_applied += 1
        if controller_gone.is_set() or time.monotonic() - applied_t > args.command_timeout_s:
            if not source.startswith("fallback"):
                node.log(f"no controller command: safe power {args.safe_power_w} W from step {step + 1}",
                         step * args.period_s, level=3)
            power, source = args.safe_power_w, "fallback-safe"
            n_fallback += 1
        model.step(power, speed * 1e-3, args.period_s, obs["t_ahead_k"])
        step += 1
    summary = f"finished at step {step}; {n_applied} commands applied, {n_dropped} dropped, {n_fallback} fallback steps"
    node.log(summary, step * args.period_s)
    node.event("end", step * args.period_s, detail=summary)
    time.sleep(0.1)  # let the end event leave before the token goes
    for entity in (token, presence, subscriber, *node._publishers.values()):
        entity.undeclare()


def main(argv: list[str] | None = None) -> int:
    """Exit status 0 done (also after SIGINT/SIGTERM), 1 no session or a required node missing, 2 usage."""
    args = parse_args(argv)
    stop = Stop()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: setattr(stop, "requested", True))
    try:
        session = open_session(args.connect)
    except zenoh.ZError as err:
        print(f"plain_sensor: error: cannot open a zenoh session to {args.connect}: {err}", file=sys.stderr)
        return 1
    try:
        run(Node(session, args.run_id, args.node), args, stop)
    except TimeoutError as err:
        print(f"plain_sensor: error: {err}", file=sys.stderr)
        return 1
    finally:
        session.close()
    return 0


if __name__ == "__main__":
    sys.exit(main())
