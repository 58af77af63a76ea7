"""Benchmark of the closed loop over zenoh: free-running GP surrogate plant ↔ controller node.

Starts ``python -m controller_node`` (default: GP-MPC) and ``python -m fe_node.surrogate
--rate-hz R`` as separate processes on a loopback hub, runs for ``--duration-s`` and reports
what the surrogate measured: round trip state → command (median and p99) [µs], the achieved
publish rate [Hz] and the share of steps whose command arrived after the next state was
published (deadline misses) [%]. The controller answers the newest state and skips older ones,
so a slow controller shows up as misses, not as a growing queue.

Prints the node output, then, as the last line, JSON: ``rtt_median_us``, ``rtt_p99_us``,
``rate_hz``, ``deadline_miss_pct``, the target rate and context (controller, CPU count, load
average at the start: the numbers depend on what else runs on the machine).

Usage: ``python benchmarks/bench_loop.py --rate-hz 2000 [--duration-s 5] [--controller mpc]``
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
sys.path.insert(0, str(REPO))

from launch import free_loopback_endpoint  # noqa: E402
from messages.bus import BusSettings, NodeBus, StopFlag  # noqa: E402


def spawn(module: str, *args: str) -> subprocess.Popen[str]:
    """``python -m module args`` in its own process group, output captured."""
    return subprocess.Popen([sys.executable, "-u", "-m", module, *args], cwd=REPO, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, start_new_session=True)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--rate-hz", type=float, default=2000.0, help="surrogate publish rate [Hz]")
    parser.add_argument("--duration-s", type=float, default=5.0, help="measured wall time [s]")
    parser.add_argument("--controller", default="mpc", help="controller node's control law (default: %(default)s)")
    args = parser.parse_args()
    hub = free_loopback_endpoint()
    run_id = f"bench-loop-{os.getpid()}"
    common = ("--run-id", run_id, "--connect", hub)
    load = os.getloadavg()[0]
    with NodeBus("bench", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        controller = spawn("controller_node", "--controller", args.controller, *common)
        bus.wait_for_nodes(["controller"], StopFlag(), timeout_s=60)
        plant = spawn("fe_node.surrogate", "--rate-hz", repr(args.rate_hz), "--duration-s", repr(args.duration_s),
                      "--require", "controller", "--json", *common)
        try:
            plant_out, _ = plant.communicate(timeout=args.duration_s + 60)
            controller_out, _ = controller.communicate(timeout=30)
        except subprocess.TimeoutExpired as err:
            for proc in (plant, controller):
                proc.kill()
                proc.communicate()
            print(json.dumps({"error": f"{err.cmd[3]} did not finish within {err.timeout:.0f} s",
                              "target_rate_hz": args.rate_hz}))
            return 1
    print("\n".join(f"[plant] {line}" for line in plant_out.splitlines()[:-1]))
    print("\n".join(f"[controller] {line}" for line in controller_out.splitlines()))
    if plant.returncode != 0 or controller.returncode != 0:
        print(f"error: plant exited {plant.returncode}, controller {controller.returncode}", file=sys.stderr)
        return 1
    stats = json.loads(plant_out.strip().splitlines()[-1])
    result = {
        "rtt_median_us": stats["rtt_median_us"], "rtt_p99_us": stats["rtt_p99_us"], "rate_hz": stats["rate_hz"],
        "deadline_miss_pct": stats["deadline_miss_pct"], "target_rate_hz": args.rate_hz,
        "steps": stats["steps"], "commands": stats["commands"], "late_commands": stats["late_commands"],
        "controller": args.controller, "duration_s": args.duration_s, "cpus": os.cpu_count(),
        "loadavg_1min_at_start": round(load, 2), "python": platform.python_version(),
    }
    print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
