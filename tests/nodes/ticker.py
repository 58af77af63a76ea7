"""A minimal plant-like test node: publishes ``MeltPoolState`` at a fixed rate.

``python -m tests.nodes.ticker --steps N --rate-hz R [--require NODE]``; ``--steps 0`` runs until
stopped. Used by the launch and recorder tests in place of the FE node.
"""

from __future__ import annotations

import sys

from messages import LogLevel, MeltPoolState
from messages.bus import NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args
from messages.cli import ArgumentParser
from messages.topics import PLANT_STATE


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="ticker")
    parser.add_argument("--steps", type=int, default=0)
    parser.add_argument("--rate-hz", type=float, default=200.0)
    parser.add_argument("--name", default="ticker")
    parser.add_argument("--fail-at", type=int, default=-1, help="exit 3 at this step")
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    stop = StopFlag()
    with NodeBus(args.name, bus_settings_from_args(args)) as bus:
        pub = bus.publisher(PLANT_STATE)
        bus.ready(config={"steps": args.steps}, total_steps=args.steps or None, stop=stop)
        step = 0
        while not stop.is_set() and (args.steps == 0 or step < args.steps):
            if step == args.fail_at:
                print("failing on purpose", flush=True)
                return 3
            t = step * 50e-6
            pub.put(MeltPoolState(
                run_id=bus.run_id, step=step, time_s=t, laser_x_mm=step * 0.04, laser_y_mm=0.0, scan_dir_x=1.0,
                scan_dir_y=0.0, track=0, area_mm2=0.07, t_ahead_k=400.0, power_w=250.0, speed_mm_s=800.0,
            ))
            if step % 50 == 0:
                bus.log(LogLevel.INFO, f"step {step}", time_s=t)
            step += 1
            stop.wait(1.0 / args.rate_hz)
        print(f"published {step} states", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
