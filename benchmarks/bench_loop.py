"""Benchmark of the closed loop over zenoh: free-running GP surrogate plant ↔ controller node,
against the bare transport measured in the same run and topology.

Four phases on one hub (the bench process), each pair of nodes a separate process:

1. a bare zenoh ping-pong (``benchmarks/zenoh_pingpong.py``: a state-sized payload out on the
   run's ``plant/state`` key, echoed back on ``controller/command``; express publishers; no
   decoding) at ``--rate-hz`` for ``--pingpong-s``;
2. the loop: ``python -m controller_node`` (default: GP-MPC) and ``python -m fe_node.surrogate
   --rate-hz R`` for ``--duration-s``; the bench subscribes to the controller's diagnostics and
   takes the controller update time from their ``solve_time_us``;
3. the ping-pong again (both ping-pongs' round trips are pooled);
4. the ping-pong once more, its pong keeping the CPU busy for the controller's median update
   before each echo (``zenoh_pingpong.py pong --work-us``): a loop that is only transport and
   computation, the yardstick of the misses.

``--transport low-latency`` (default): every zenoh session of the run (hub, ping, pong, plant,
controller) on zenoh's low-latency unicast transport, the nodes started with ``--low-latency``
(``messages.bus``: the publishing thread writes to the socket, no QoS, messages up to 32 KiB), as
a sensor loop is best deployed (``docs/realtime.md``); ``--transport default``: zenoh's default
transport (a transmit thread per zenoh session), what nodes use without ``--low-latency``.

``--topology peer`` (default): unauthenticated peers on loopback, as nodes started by hand (the
plant and the controller connect to each other directly). ``--topology router``: what
``launch.py`` runs, an authenticating zenoh router with per-node access control in the bench
process (:class:`messages.auth.RunCredentials`) and every node its client (each message crosses
the router). ``--load`` starts a busy loop on one core (a ``stress``-like process) for the whole
measurement; ``--fifo-priority N`` runs every node process under ``SCHED_FIFO`` (``chrt``);
``--busy-wait`` starts the controller node with ``--busy-wait`` (it polls for states);
``--no-poll-commands`` starts the plant with ``--no-poll-commands`` (it never polls for its
commands; by default it polls while a core is to spare, ``fe_node.freerun.CommandInboxes``, but
never as a client of the router of ``--topology router``);
``--pin`` pins the plant side (surrogate, ping) to CPU 0 and the controller side (controller,
pong) to CPU 1, as a real-time deployment would (the bench process and its hub are not pinned).
``docs/realtime.md`` has the measured figures.

Prints the node output, then, as the last line, JSON: the loop's round trip state → command
(``rtt_median_us``, ``rtt_p99_us``), the achieved rate, the share of steps whose command arrived
after the next state was published (``deadline_miss_pct``; ``steady_miss_pct`` the same after the
first 200 steps, as the ping-pongs leave out their first 200 round trips), the bare round trip
(``zenoh_rtt_median_us``, ``zenoh_rtt_p99_us``), ``controller_update_median_us``,
``overhead_ratio`` = loop round-trip median ÷ (bare median + update median),
``controller_update_p99_us``, ``transport_miss_pct`` (the misses a loop with no overhead of its
own would have: random pairs of a bare round trip and an update whose sum exceeds the period),
``worked_rtt_median_us``, ``worked_rtt_p99_us`` and ``worked_miss_pct`` (phase 4: the share of
echoes later than a period, what this machine leaves a loop with this update and no code of its
own), the plant's steps for which it polled (``plant_polled_pct``), the runs of consecutive
misses (``miss_bursts``, ``longest_miss_burst_steps``: a stall of the machine is one long run),
the topology and the transport, the load (1-minute load average at the start and end, the
machine's CPU use during the loop, the busy loop if any) and context. The numbers depend on
what else runs on the machine; the ratio, measured in the same run, much less.

Usage: ``python benchmarks/bench_loop.py --rate-hz 2000 [--duration-s 5] [--topology router]
[--transport default] [--load]
[--fifo-priority 10] [--busy-wait] [--controller preview-mpc]``
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import platform
import subprocess
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from fe_node.freerun import FreeRunSettings  # noqa: E402
from launch import free_loopback_endpoint  # noqa: E402
from messages.auth import RunCredentials  # noqa: E402
from messages.bus import SUPERVISOR_ENV, BusSettings, StopFlag, wait_for_nodes, zenoh_config  # noqa: E402
from messages.cli import run_main  # noqa: E402
from messages.codec import MessageError, decode  # noqa: E402
from messages.hub import router_config  # noqa: E402
from messages.spare_core import cpu_times, proc_stat_line  # noqa: E402
from messages.topics import CONTROLLER_DIAGNOSTICS, key_expr  # noqa: E402

PINGPONG = str(REPO / "benchmarks" / "zenoh_pingpong.py")
NODES = {"plant": ("plant",), "controller": ("controller",), "ping": ("plant",), "pong": ("controller",)}
BUSY_LOOP = "import os, sys\nos.sched_setaffinity(0, {int(sys.argv[1])})\nwhile True:\n    pass\n"


FIFO_PRIORITY: int | None = None  # --fifo-priority: every node process under SCHED_FIFO at this priority
PIN = False  # --pin: the plant side on CPU 0, the controller side on CPU 1
SIDE_CPU = {"plant": 0, "controller": 1}


def spawn(argv: list[str], env: dict[str, str], side: str) -> subprocess.Popen[str]:
    """``python argv`` in its own process group, output captured, ``env`` added; on its side's CPU
    (:data:`SIDE_CPU`) with ``--pin``."""
    prefix = [] if FIFO_PRIORITY is None else ["chrt", "--fifo", str(FIFO_PRIORITY)]
    cpu = SIDE_CPU[side] if PIN else None
    return subprocess.Popen([*prefix, sys.executable, "-u", *argv], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True,
                            env={**os.environ, **env},
                            preexec_fn=None if cpu is None else lambda: os.sched_setaffinity(0, {cpu}))


def transport_miss_pct(bare_us: np.ndarray, updates_us: list[float], period_us: float,
                       n: int = 200_000) -> float | None:
    """Share [%] of steps a loop with no overhead of its own would miss: random pairs of a bare
    round trip and a controller update (both measured in this run) whose sum exceeds the period."""
    if bare_us.size == 0 or not updates_us:
        return None
    rng = np.random.default_rng(0)
    total = rng.choice(bare_us, n) + rng.choice(np.asarray(updates_us, dtype=float), n)
    return round(float(100.0 * np.mean(total > period_us)), 3)


def worked_summary(rtt_us: list[float], period_us: float) -> dict[str, float | None]:
    """The ping-pong whose pong computes for the update's median: its round trip's median and p99
    [µs] and the share [%] of echoes later than a period (``worked_miss_pct``)."""
    rtt = np.asarray(rtt_us, dtype=float)
    if rtt.size == 0:
        return {"worked_rtt_median_us": None, "worked_rtt_p99_us": None, "worked_miss_pct": None}
    return {"worked_rtt_median_us": round(float(np.median(rtt)), 1),
            "worked_rtt_p99_us": round(float(np.percentile(rtt, 99)), 1),
            "worked_miss_pct": round(float(100.0 * np.mean(rtt > period_us)), 3)}


def ratio(loop_us: float | None, bare_us: float | None, update_us: float | None) -> float | None:
    """Loop round trip ÷ (bare round trip + controller update), or ``None`` if one is missing."""
    if loop_us is None or bare_us is None or update_us is None or bare_us + update_us <= 0:
        return None
    return round(loop_us / (bare_us + update_us), 3)


class Hub:
    """The run's hub in the bench process: an open peer, or launch.py's authenticating router."""

    def __init__(self, topology: str, run_id: str, low_latency: bool) -> None:
        self.endpoint = free_loopback_endpoint()
        self.run_id = run_id
        self.topology = topology
        self.low_latency = low_latency
        self._stack = contextlib.ExitStack()
        self.credentials = None
        if topology == "router":
            self.credentials = self._stack.enter_context(RunCredentials(run_id, NODES))
        if self.credentials is not None:  # the hub launch.py opens
            config = router_config(self.credentials, self.endpoint, low_latency=low_latency)
        else:
            config = zenoh_config(BusSettings(run_id=run_id, connect=(), listen=(self.endpoint,),
                                              low_latency=low_latency))
        self.session = self._stack.enter_context(zenoh.open(config))

    def close(self) -> None:
        self._stack.close()

    def env(self, node: str) -> dict[str, str]:
        """A node's environment: its credentials (router), none (peer)."""
        env = {SUPERVISOR_ENV: str(os.getpid())}
        return {**env, **self.credentials.env(node)} if self.credentials is not None else env

    def common(self) -> list[str]:
        return ["--run-id", self.run_id, "--connect", self.endpoint, *(["--low-latency"] if self.low_latency else [])]


def finish(proc: subprocess.Popen[str], timeout: float, name: str) -> str:
    """Wait for ``proc``; its output. Raises RuntimeError (after killing it) if it hangs or fails."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise RuntimeError(f"{name} did not finish within {timeout:.0f} s:\n{out}") from None
    if proc.returncode != 0:
        raise RuntimeError(f"{name} exited {proc.returncode}:\n{out}")
    return out


def pingpong(hub: Hub, rate_hz: float, duration_s: float, work_us: float = 0.0) -> list[float]:
    """Round trips [µs] of a bare ping-pong between two node processes through ``hub``; the pong
    keeps its CPU busy ``work_us`` [µs] before each echo."""
    pong = spawn([PINGPONG, "pong", *hub.common(), "--work-us", repr(work_us)], hub.env("pong"), "controller")
    try:
        ping = spawn([PINGPONG, "ping", *hub.common(), "--rate-hz", repr(rate_hz), "--duration-s",
                      repr(duration_s), "--samples"], hub.env("ping"), "plant")
        out = finish(ping, duration_s + 90, "ping")
    finally:
        pong.terminate()
        finish(pong, 20, "pong")
    return json.loads(out.strip().splitlines()[-1])["rtt_us"]


def loop(hub: Hub, args: argparse.Namespace) -> tuple[dict, list[float], str]:
    """Run the surrogate against the controller; (plant stats, update times [µs], node output)."""
    # queued by zenoh (no Python callback) and decoded after the loop: the bench stays light while it runs
    capacity = int(args.rate_hz * (args.duration_s + 30)) + 1024
    sub = hub.session.declare_subscriber(key_expr(hub.run_id, CONTROLLER_DIAGNOSTICS),
                                         zenoh.handlers.FifoChannel(capacity))
    busy = ["--busy-wait"] if args.busy_wait else []
    controller = spawn(["-m", "controller_node", "--controller", args.controller, *busy, *hub.common()],
                       hub.env("controller"), "controller")
    try:
        wait_for_nodes(hub.session, hub.run_id, ["controller"], StopFlag(), timeout_s=60)
        poll = [] if args.poll_commands else ["--no-poll-commands"]
        plant = spawn(["-m", "fe_node.surrogate", "--rate-hz", repr(args.rate_hz), "--duration-s",
                       repr(args.duration_s), "--require", "controller", "--json", *poll, *hub.common()],
                      hub.env("plant"), "plant")
        plant_out = finish(plant, args.duration_s + 90, "plant")
        controller_out = finish(controller, 30, "controller")
    finally:
        if controller.poll() is None:
            controller.kill()
            controller.communicate()
        updates = []
        while (sample := sub.try_recv()) is not None:
            with contextlib.suppress(MessageError):
                updates.append(decode(CONTROLLER_DIAGNOSTICS, sample.payload.to_bytes()).solve_time_us)
        sub.undeclare()
    output = "\n".join([*(f"[plant] {line}" for line in plant_out.splitlines()[:-1]),
                        *(f"[controller] {line}" for line in controller_out.splitlines())])
    return json.loads(plant_out.strip().splitlines()[-1]), updates, output


def start_load(cpu: int) -> subprocess.Popen:
    """A busy loop pinned to ``cpu``, at the nodes' priority."""
    return subprocess.Popen([sys.executable, "-c", BUSY_LOOP, str(cpu)], start_new_session=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate-hz", type=float, default=2000.0, help="surrogate publish rate [Hz]")
    parser.add_argument("--duration-s", type=float, default=5.0, help="measured wall time of the loop [s]")
    parser.add_argument("--controller", default="mpc", help="controller node's control law (default: %(default)s)")
    parser.add_argument("--busy-wait", action="store_true",
                        help="the controller node polls for states (its --busy-wait) instead of sleeping in zenoh")
    parser.add_argument("--topology", choices=("peer", "router"), default="peer",
                        help="peer: open peers on loopback (nodes started by hand); router: launch.py's "
                             "authenticating router, nodes its clients (default: %(default)s)")
    parser.add_argument("--transport", choices=("low-latency", "default"), default="low-latency",
                        help="zenoh transport of every session: low-latency (the nodes' --low-latency) or zenoh's "
                             "default (default: %(default)s)")
    parser.add_argument("--pingpong-s", type=float, default=2.0,
                        help="bare ping-pong before and after the loop, each [s] (default: %(default)s)")
    parser.add_argument("--load", action="store_true", help="run a busy loop on one core during the measurement")
    parser.add_argument("--load-cpu", type=int, default=0, help="the core of --load (default: %(default)s)")
    parser.add_argument("--fifo-priority", type=int, metavar="N",
                        help="run every node process (ping, pong, plant, controller) under SCHED_FIFO priority N "
                             "(chrt; needs CAP_SYS_NICE): how a real-time deployment would run them")
    parser.add_argument("--poll-commands", action=argparse.BooleanOptionalAction,
                        default=FreeRunSettings().poll_commands,
                        help="the surrogate plant polls for each command while a core is to spare "
                             "(default: %(default)s; --no-poll-commands: it takes them at its ticks)")
    parser.add_argument("--pin", action="store_true",
                        help="pin the plant side (surrogate, ping) to CPU 0 and the controller side (controller, pong) "
                             "to CPU 1")
    args = parser.parse_args()
    global FIFO_PRIORITY, PIN
    FIFO_PRIORITY, PIN = args.fifo_priority, args.pin
    if PIN and len(os.sched_getaffinity(0)) < 2:
        parser.error("--pin needs two CPUs")
    run_id = f"bench-loop-{os.getpid()}"
    load_at_start = os.getloadavg()[0]
    busy = start_load(args.load_cpu) if args.load else None
    hub = Hub(args.topology, run_id, args.transport == "low-latency")
    try:
        if busy is not None:
            time.sleep(1.0)  # let the busy loop settle on its core
        bare = pingpong(hub, args.rate_hz, args.pingpong_s)
        cpu0 = cpu_times(proc_stat_line())
        stats, updates, output = loop(hub, args)
        cpu1 = cpu_times(proc_stat_line())
        bare += pingpong(hub, args.rate_hz, args.pingpong_s)
        worked = pingpong(hub, args.rate_hz, args.pingpong_s, float(np.median(updates))) if updates else []
    except RuntimeError as err:
        print(json.dumps({"error": str(err).splitlines()[0], "target_rate_hz": args.rate_hz}))
        print(err, file=sys.stderr)
        return 1
    finally:
        hub.close()
        if busy is not None:
            busy.kill()
            busy.wait()
    print(output)
    bare_us = np.asarray(bare)
    zenoh_median = round(float(np.median(bare_us)), 1) if bare_us.size else None
    update_median = round(float(np.median(updates)), 1) if updates else None
    result = {
        "rtt_median_us": stats["rtt_median_us"], "rtt_p99_us": stats["rtt_p99_us"], "rate_hz": stats["rate_hz"],
        "deadline_miss_pct": stats["deadline_miss_pct"], "steady_miss_pct": stats["steady_miss_pct"],
        "target_rate_hz": args.rate_hz,
        "zenoh_rtt_median_us": zenoh_median,
        "zenoh_rtt_p99_us": round(float(np.percentile(bare_us, 99)), 1) if bare_us.size else None,
        "controller_update_median_us": update_median,
        "overhead_ratio": ratio(stats["rtt_median_us"], zenoh_median, update_median),
        "controller_update_p99_us": round(float(np.percentile(updates, 99)), 1) if updates else None,
        "transport_miss_pct": transport_miss_pct(bare_us, updates, 1e6 / args.rate_hz),
        **worked_summary(worked, 1e6 / args.rate_hz),
        "topology": args.topology, "transport": args.transport,
        "steps": stats["steps"], "plant_polled_pct": stats["polled_pct"], "commands": stats["commands"],
        "late_commands": stats["late_commands"], "miss_bursts": stats["miss_bursts"],
        "longest_miss_burst_steps": stats["longest_miss_burst_steps"],
        "zenoh_pings": int(bare_us.size), "controller_updates": len(updates),
        "controller": args.controller, "duration_s": args.duration_s, "cpus": os.cpu_count(),
        "loadavg_1min_at_start": round(load_at_start, 2), "loadavg_1min_at_end": round(os.getloadavg()[0], 2),
        "cpu_busy_pct_during_loop": round(100.0 * (cpu1[0] - cpu0[0]) / max(1, cpu1[1] - cpu0[1]), 1),
        "load": f"busy loop on cpu {args.load_cpu}" if args.load else "none added",
        "scheduling": f"SCHED_FIFO {args.fifo_priority}" if args.fifo_priority is not None else "default",
        "controller_busy_wait": args.busy_wait,
        "plant_poll_commands": args.poll_commands,
        "pinning": "plant side cpu 0, controller side cpu 1" if args.pin else "none",
        "python": platform.python_version(),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    run_main(main)
