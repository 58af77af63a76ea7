"""Test node: republishes every valid message of run ``--run-id`` on run ``<run-id>-echo``
(with that run id).

Each message is decoded (validated) and re-encoded, so a round trip through this process
checks the whole codec across a process boundary.
"""

from __future__ import annotations

import sys

import msgspec

from messages.bus import BusSettings, NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args
from messages.cli import ArgumentParser
from messages.codec import encode
from messages.topics import TOPICS, key_expr, message_node


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="echo")
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    settings = bus_settings_from_args(args)
    stop = StopFlag()
    out_settings = BusSettings(run_id=settings.run_id + "-echo", connect=settings.connect, listen=settings.listen)
    with NodeBus("echo", settings) as bus, NodeBus("echo-out", out_settings) as out:
        inboxes = [bus.inbox(t) for t in TOPICS.values()]
        pubs = {t.suffix: out.publisher(t) for t in TOPICS.values()}
        out.ready()
        bus.ready()
        while not stop.is_set():
            idle = True
            for box in inboxes:
                for msg in box.drain():
                    if hasattr(msg, "run_id"):  # now a message of the echo run
                        msg = msgspec.structs.replace(msg, run_id=out_settings.run_id)
                    if box.topic.per_node:  # forwarded under the node it names, as that node sent it
                        out.session.put(key_expr(out.run_id, box.topic, message_node(msg)), encode(msg))
                    else:
                        pubs[box.topic.suffix].put(msg)
                    idle = False
            if idle:
                stop.wait(0.002)
    return 0


if __name__ == "__main__":
    sys.exit(main())
