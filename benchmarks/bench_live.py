"""Cost of the live Foxglove view: ``launch.py --max-steps N`` with and without ``--live``, in
alternating pairs, with a WebSocket client subscribed to every channel during the live runs.

Prints one line per pair, then, as the last line, JSON: ``pairs``, ``wall_s_median_without``,
``wall_s_median_with``, ``growth_pct_median`` (of the per-pair ratios), ``growth_pct_min``,
``growth_pct_max``, ``client_messages_min``, ``loadavg_1min_at_start``, ``loadavg_1min_at_end``.

Usage: ``python benchmarks/bench_live.py [--pairs 6] [--max-steps 400]``
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import statistics
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

from websockets.exceptions import ConnectionClosed
from websockets.sync.client import connect

REPO = Path(__file__).resolve().parent.parent


def watch_everything(port: int, counted: list[int]) -> None:
    """Connect (retrying while the run starts), subscribe to every advertised channel, count messages."""
    deadline = time.monotonic() + 60
    while True:
        try:
            ws = connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"])
            break
        except OSError:
            if time.monotonic() > deadline:
                return
            time.sleep(0.02)
    subscribed: set[int] = set()
    with ws:
        try:
            while True:
                frame = ws.recv(timeout=20)
                if isinstance(frame, bytes):
                    counted[0] += 1
                    continue
                message = json.loads(frame)
                if message.get("op") == "advertise":
                    new = [c["id"] for c in message["channels"] if c["id"] not in subscribed]
                    subscribed |= set(new)
                    ws.send(json.dumps({"op": "subscribe", "subscriptions": [{"id": c, "channelId": c} for c in new]}))
        except (ConnectionClosed, TimeoutError):
            return


def timed_run(out: Path, max_steps: int, live_port: int | None) -> float:
    """Wall time [s] of one ``launch.py`` run (raises if it fails)."""
    extra = ["--live", str(live_port)] if live_port else []
    started = time.monotonic()
    subprocess.run([sys.executable, "launch.py", "--max-steps", str(max_steps), "--no-progress", "--out", str(out),
                    *extra], cwd=REPO, check=True, capture_output=True)
    return time.monotonic() - started


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=6)
    parser.add_argument("--max-steps", type=int, default=400)
    args = parser.parse_args()
    load_start = os.getloadavg()[0]
    without, with_live, received = [], [], []
    with tempfile.TemporaryDirectory() as tmp, socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        port = probe.getsockname()[1]
        probe.close()
        for i in range(args.pairs):
            without.append(timed_run(Path(tmp) / f"off{i}.mcap", args.max_steps, None))
            counted = [0]
            client = threading.Thread(target=watch_everything, args=(port, counted))
            client.start()
            with_live.append(timed_run(Path(tmp) / f"on{i}.mcap", args.max_steps, port))
            client.join()
            received.append(counted[0])
            print(f"pair {i}: {without[-1]:.2f} s without, {with_live[-1]:.2f} s with live "
                  f"({counted[0]} messages to the client)", flush=True)
    growth = [100 * (b / a - 1) for a, b in zip(without, with_live, strict=True)]
    print(json.dumps({
        "pairs": args.pairs, "max_steps": args.max_steps,
        "wall_s_median_without": round(statistics.median(without), 2),
        "wall_s_median_with": round(statistics.median(with_live), 2),
        "growth_pct_median": round(statistics.median(growth), 1), "growth_pct_min": round(min(growth), 1),
        "growth_pct_max": round(max(growth), 1), "client_messages_min": min(received),
        "loadavg_1min_at_start": round(load_start, 2), "loadavg_1min_at_end": round(os.getloadavg()[0], 2),
    }))
    return 0


if __name__ == "__main__":
    sys.exit(main())
