"""Bare zenoh ping-pong between two processes: the transport's own round trip, the loop's yardstick.

``pong`` echoes every payload it receives on the run's ``plant/state`` key back on the run's
``controller/command`` key; ``ping`` publishes payloads of ``--size`` bytes (default: the size
of a ``MeltPoolState``) at ``--rate-hz`` on ``plant/state`` and times each echo. Both use express,
reliable, blocking publishers, the same keys, session settings, credentials and access control
as the loop's nodes (``messages.bus.open_session``), and receive as zenoh-python's ``z_ping`` /
``z_pong`` examples do, so that ``benchmarks/bench_loop.py`` can divide the loop's round trip by
this one measured in the same run and topology. Nothing is decoded or validated: this is
zenoh-python alone. ``pong --work-us W`` keeps the CPU busy for W µs before each echo: a loop
that is the transport plus a controller update and nothing else.

Usage (``bench_loop.py`` runs both)::

    python benchmarks/zenoh_pingpong.py pong --run-id R --connect tcp/127.0.0.1:7447
    python benchmarks/zenoh_pingpong.py ping --run-id R --connect tcp/127.0.0.1:7447 --rate-hz 2000 --duration-s 2

``ping`` prints, as its last line, JSON: ``rtt_median_us``, ``rtt_p99_us``, ``pings`` (and with
``--samples`` every round trip, ``rtt_us``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

import numpy as np  # noqa: E402
import zenoh  # noqa: E402

from messages.bus import BusSettings, StopFlag, open_session, wait_for_nodes  # noqa: E402
from messages.cli import run_main  # noqa: E402
from messages.topics import LASER_COMMAND, PLANT_STATE, key_expr, liveliness_key  # noqa: E402

STATE_SIZE = 394  # bytes of a typical encoded MeltPoolState (run id of 16 characters)
WARMUP = 200  # pings before timing starts


def publisher(session: zenoh.Session, key: str) -> zenoh.Publisher:
    """An express, reliable, blocking publisher: the settings of the loop's hot path."""
    return session.declare_publisher(key, congestion_control=zenoh.CongestionControl.BLOCK,
                                      reliability=zenoh.Reliability.RELIABLE, express=True)


def spin(seconds: float) -> None:
    """Keep the CPU busy for ``seconds`` [s] (a stand-in for a controller update)."""
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        pass


def pong(settings: BusSettings, stop: StopFlag, work_s: float = 0.0) -> int:
    """Echo every ping until stopped (its liveliness token ``pong`` says it is subscribed).

    As zenoh-python's ``z_pong`` example: a plain callback that republishes the payload, after
    ``work_s`` [s] of busy CPU when it is > 0 (a controller that only computes).
    """

    def echo(sample: zenoh.Sample) -> None:
        if work_s > 0.0:
            spin(work_s)
        pub.put(sample.payload)

    with open_session(settings, "pong") as session:
        pub = publisher(session, key_expr(settings.run_id, LASER_COMMAND))
        session.declare_subscriber(key_expr(settings.run_id, PLANT_STATE), echo)
        token = session.liveliness().declare_token(liveliness_key(settings.run_id, "pong"))
        while not stop.wait(0.2):
            pass
        token.undeclare()
    return 0


def ping(settings: BusSettings, stop: StopFlag, rate_hz: float, duration_s: float, size: int,
         samples: bool = False) -> dict:
    """Ping at ``rate_hz`` for ``duration_s`` (after a warm-up); round trips [µs] of the echoes.

    As zenoh-python's ``z_ping`` example (put, then a blocking ``recv`` of the echo), paced at
    ``rate_hz`` like the loop's plant: each ping leaves at its tick, or at once if the previous
    echo came back after it.
    """
    n = WARMUP + int(rate_hz * duration_s)
    rtt = np.full(n, np.nan)
    data = bytes(max(size, 8))
    with open_session(settings, "ping") as session:
        sub = session.declare_subscriber(key_expr(settings.run_id, LASER_COMMAND), zenoh.handlers.FifoChannel(16))
        pub = publisher(session, key_expr(settings.run_id, PLANT_STATE))
        wait_for_nodes(session, settings.run_id, ["pong"], stop, timeout_s=60)
        period = 1.0 / rate_hz
        next_t = time.monotonic()
        for seq in range(n):
            if stop.is_set():
                break
            next_t = max(next_t + period, time.monotonic())
            while (remaining := next_t - time.monotonic()) > 0:
                time.sleep(remaining)
            sent = time.monotonic()
            pub.put(data)
            sub.recv()
            rtt[seq] = time.monotonic() - sent
    timed = rtt[WARMUP:] * 1e6
    ok = timed[np.isfinite(timed)]
    summary = {
        "rtt_median_us": round(float(np.median(ok)), 1) if ok.size else None,
        "rtt_p99_us": round(float(np.percentile(ok, 99)), 1) if ok.size else None,
        "pings": int(ok.size), "size_bytes": len(data), "rate_hz": rate_hz,
    }
    if samples:
        summary["rtt_us"] = [round(float(v), 1) for v in ok]
    return summary


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("role", choices=("ping", "pong"))
    parser.add_argument("--run-id", default="pingpong")
    parser.add_argument("--connect", action="append", required=True, metavar="ENDPOINT")
    parser.add_argument("--rate-hz", type=float, default=2000.0, help="ping rate [Hz]")
    parser.add_argument("--duration-s", type=float, default=2.0, help="timed pinging [s]")
    parser.add_argument("--size", type=int, default=STATE_SIZE, help="payload size [bytes] (default: a state's)")
    parser.add_argument("--samples", action="store_true", help="also print every round trip [µs] (rtt_us)")
    parser.add_argument("--low-latency", action="store_true", help="zenoh's low-latency transport (as the nodes')")
    parser.add_argument("--work-us", type=float, default=0.0,
                        help="pong: busy CPU before each echo [µs], e.g. a controller update's (default: 0)")
    args = parser.parse_args(argv)
    if not 0.0 <= args.work_us <= 1e6:
        parser.error(f"--work-us must be in [0, 1e6], got {args.work_us}")
    settings = BusSettings(run_id=args.run_id, connect=tuple(args.connect), low_latency=args.low_latency)
    stop = StopFlag()
    if args.role == "pong":
        return pong(settings, stop, args.work_us * 1e-6)
    print(json.dumps(ping(settings, stop, args.rate_hz, args.duration_s, args.size, args.samples)), flush=True)
    return 0


if __name__ == "__main__":
    run_main(main)
