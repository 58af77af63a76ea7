"""MCAP recorder: its own process, one file per run, every contract topic of the run.

Channels are the contract topics (``/plant/state``, ``/controller/command``, ...), schema
encoding ``jsonschema`` (generated from :mod:`messages.types`), message encoding ``json`` — what
Foxglove plots directly. Time base: ``log_time`` is the message's **process time** (simulated
time for the FE plant, ``time_s`` or ``timestamp``), ``publish_time`` is the recorder's **wall
clock** (UNIX ns) on receipt. Metadata ``meltloop`` holds run id, code revision and package
versions; each node's resolved configuration (from its ``start`` event) is attached as
``config/<node>.json``; metadata ``meltloop.counts`` holds recorded, invalid and published
counts at the end.

Run: ``python -m messages.recorder --run-id RUN --out recordings/run.mcap``. It finishes the
file when every expected node has sent its ``end`` event and every message it reported
published has arrived, and on SIGINT/SIGTERM. Exit status 1 if messages were missing.
"""

from __future__ import annotations

import json
import queue
import sys
import time
from collections import Counter
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from messages.bus import NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args
from messages.cli import ArgumentParser, UsageError, exit_usage
from messages.codec import MessageError, decode, encode, json_schema
from messages.foxglove import Log, LogLevel, Timestamp
from messages.provenance import git_revision, package_versions
from messages.topics import LOG, RUN_EVENTS, TOPICS, Topic, run_prefix, topic_for_key
from messages.types import RunEvent

NODE_NAME = "recorder"


def log_time_ns(msg: Any) -> int:
    """Process time of a message in ns: ``time_s`` or the Foxglove ``timestamp``."""
    if hasattr(msg, "time_s"):
        return int(round(msg.time_s * 1e9))
    return msg.timestamp.to_ns()


class McapRecorder:
    """Writes contract messages of one run into one MCAP file (no transport inside)."""

    def __init__(self, path: Path, run_id: str) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self.path = path
        self.run_id = run_id
        self._stream: BinaryIO = path.open("wb")
        self._writer = Writer(self._stream, compression=CompressionType.ZSTD)
        self._writer.start(profile="", library="meltloop")
        self._channels: dict[str, int] = {}
        for topic in TOPICS.values():
            schema_id = self._writer.register_schema(
                name=topic.schema_name, encoding="jsonschema", data=json.dumps(json_schema(topic)).encode()
            )
            self._channels[topic.suffix] = self._writer.register_channel(
                topic=topic.channel, message_encoding="json", schema_id=schema_id
            )
        self.recorded: Counter[str] = Counter()
        self._writer.add_metadata(
            "meltloop",
            {
                "run_id": run_id,
                "git_revision": git_revision(),
                "started_utc": datetime.now(UTC).isoformat(),
                "log_time": "process (simulated) time since the start of the run",
                "publish_time": "recorder wall clock on receipt, UNIX epoch",
                **{f"version.{k}": v for k, v in package_versions().items()},
            },
        )
        self.finished = False

    def write(self, topic: Topic, payload: bytes, msg: Any, publish_time_ns: int) -> None:
        """Append one validated message (its original JSON bytes) to the topic's channel."""
        self._writer.add_message(
            channel_id=self._channels[topic.suffix],
            log_time=log_time_ns(msg),
            data=payload,
            publish_time=publish_time_ns,
            sequence=self.recorded[topic.suffix],
        )
        self.recorded[topic.suffix] += 1

    def attach(self, name: str, data: bytes, media_type: str = "application/json") -> None:
        """Add an attachment (e.g. a node's resolved configuration)."""
        now = time.time_ns()
        self._writer.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=data)

    def log(self, level: LogLevel, text: str, time_s: float) -> None:
        """Write one of the recorder's own log lines to ``/log``."""
        msg = Log(timestamp=Timestamp.from_seconds(time_s), level=level, message=text, name=NODE_NAME)
        self.write(LOG, encode(msg), msg, time.time_ns())

    def finish(self, summary: dict[str, str]) -> None:
        """Write the closing metadata and the MCAP summary; close the file."""
        if self.finished:
            return
        self._writer.add_metadata("meltloop.counts", summary)
        self._writer.finish()
        self._stream.close()
        self.finished = True


class RunTracker:
    """Follows nodes' start/end events and reconciles published against recorded counts."""

    def __init__(self, expected_nodes: tuple[str, ...]) -> None:
        self.expected = set(expected_nodes)
        self.started: set[str] = set()
        self.ended: set[str] = set()
        self.published: Counter[str] = Counter()

    def on_event(self, event: RunEvent) -> None:
        """Take one life-cycle event into account."""
        if event.event == "start":
            self.started.add(event.node)
        elif event.event == "end":
            self.ended.add(event.node)
            self.published.update(event.published)

    def all_ended(self) -> bool:
        """Whether every expected node (or, with none expected, every started node) has ended."""
        waiting_for = self.expected or self.started
        return bool(waiting_for) and waiting_for <= self.ended

    def missing(self, recorded: Counter[str]) -> dict[str, int]:
        """Per topic, how many reported-published messages were not recorded.

        ``recorded`` must count only messages of the tracked nodes (not the recorder's own
        events and logs), or a lost message could hide behind one of the recorder's.
        """
        return {t: n - recorded[t] for t, n in self.published.items() if recorded[t] < n}


def record(recorder: McapRecorder, bus: NodeBus, stop: StopFlag, tracker: RunTracker, drain_s: float,
           config: dict[str, Any]) -> int:
    """Receive everything under the run's prefix until the run ends; returns the exit status."""
    inbox: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()
    bus.subscribe_raw(run_prefix(bus.run_id), lambda s: inbox.put((str(s.key_expr), s.payload.to_bytes(), time.time_ns())))
    bus.ready(config=config)
    invalid: Counter[str] = Counter()
    from_nodes: Counter[str] = Counter()  # recorded messages of other nodes (what their end events count)
    unknown = 0
    last_time_s = 0.0
    end_since: float | None = None
    while True:
        try:
            key, payload, wall_ns = inbox.get(timeout=0.05)
        except queue.Empty:
            if stop.is_set():
                break
            if tracker.all_ended():
                end_since = end_since or time.monotonic()
                if not tracker.missing(from_nodes) or time.monotonic() - end_since > drain_s:
                    break
            continue
        topic = topic_for_key(bus.run_id, key)
        if topic is None:
            unknown += 1
            continue
        try:
            msg = decode(topic, payload)
        except MessageError as err:
            invalid[topic.suffix] += 1
            if sum(invalid.values()) <= 20:
                recorder.log(LogLevel.WARNING, f"dropped invalid message: {err}", last_time_s)
            continue
        recorder.write(topic, payload, msg, wall_ns)
        if getattr(msg, "node", getattr(msg, "name", None)) != NODE_NAME:
            from_nodes[topic.suffix] += 1
        last_time_s = max(last_time_s, log_time_ns(msg) / 1e9)
        if topic is RUN_EVENTS:
            if msg.node != NODE_NAME:
                tracker.on_event(msg)
            if msg.event == "start" and msg.config_json:
                recorder.attach(f"config/{msg.node}.json", msg.config_json.encode())
    missing = tracker.missing(from_nodes)
    status = 0
    if missing:
        recorder.log(LogLevel.ERROR, f"messages published but not recorded: {missing}", last_time_s)
        print(f"error: messages published but not recorded: {missing}", file=sys.stderr, flush=True)
        status = 1
    recorder.finish(
        {
            "complete": "true" if not missing and tracker.all_ended() else "false",
            "stopped_by": stop.signal_name or "run end",
            "recorded": json.dumps(dict(recorder.recorded), sort_keys=True),
            "published": json.dumps(dict(tracker.published), sort_keys=True),
            "invalid_dropped": json.dumps(dict(invalid), sort_keys=True),
            "unknown_keys_dropped": str(unknown),
        }
    )
    total = sum(recorder.recorded.values())
    print(f"recorded {total} messages to {recorder.path} ({sum(invalid.values())} invalid dropped)", flush=True)
    return status


def default_path(run_id: str) -> Path:
    """``recordings/<UTC date-time>-<run id>.mcap``."""
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{stamp}-{run_id}.mcap"


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.recorder``."""
    parser = ArgumentParser(prog="python -m messages.recorder", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="MCAP file to write (default: recordings/<date>-<run id>.mcap)")
    parser.add_argument(
        "--expect", action="append", default=[], metavar="NODE",
        help="finish once these nodes have ended (default: once every node that started has ended)",
    )
    parser.add_argument("--drain-s", type=float, default=3.0, help="how long to wait for late messages after the last end event")
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    try:
        settings = bus_settings_from_args(args)
        path = args.out or default_path(settings.run_id)
        if path.suffix != ".mcap":
            raise UsageError(f"--out must name a .mcap file, got {path}")
        if args.drain_s < 0:
            raise UsageError("--drain-s must be >= 0")
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = StopFlag()
    recorder = McapRecorder(path, settings.run_id)
    try:
        with NodeBus(NODE_NAME, settings) as bus:
            config = {"out": str(path), "expect": args.expect, "drain_s": args.drain_s}
            return record(recorder, bus, stop, RunTracker(tuple(args.expect)), args.drain_s, config)
    finally:
        recorder.finish({"complete": "false", "stopped_by": "error"})


if __name__ == "__main__":
    sys.exit(main())
