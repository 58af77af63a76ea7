"""MCAP recorder: its own process, one file per run, every contract topic of the run.

Channels are the contract topics (``/plant/state``, ``/controller/command``, ...), schema
encoding ``jsonschema`` (generated from :mod:`messages.types`), message encoding ``json`` — what
Foxglove plots directly. Time base: ``log_time`` is the message's **process time** (simulated
time for the FE plant, ``time_s`` or ``timestamp``), ``publish_time`` is the recorder's **wall
clock** (UNIX ns) on receipt. Metadata ``meltloop`` holds run id, code revision and package
versions; each node's resolved configuration (from its ``start`` event) is attached as
``config/<node>.json``; metadata ``meltloop.counts`` holds recorded, published, missing, extra
and dropped counts at the end.

What is recorded (:class:`Intake`): schema-valid messages of this run only, taken from a bounded
queue with a log rate per node (:class:`Arrivals`; what they drop is counted, ``queue_full``
and ``log_rate``); a state or command whose step is not newer than the last recorded one of its
topic, or more than :data:`MAX_STEPS_AHEAD` ahead of it, is dropped and counted. An ``end`` event counts only for a
node that sent a ``start`` and whose liveliness token disappears within the drain time of it
(:class:`RunTracker`); a second ``end`` of a node is dropped. At the end, published and
recorded counts are reconciled both ways, per publisher (:func:`reconcile`): a node answers for
its own events and log and, by its roles, for its role's topics (``--role``; by default a node
named like a role has that role); a count it claims for any other key is ignored and counted
(``foreign_count``), so that a node without a role cannot touch another node's reconciliation.

Crash safety: every :data:`FLUSH_PERIOD_S` the MCAP chunk is closed, the file flushed and
``fsync``-ed (never per message), so a killed recorder or a power cut loses at most that much;
``python -m messages.recording recover`` makes such a file whole again. A write error (full
disk, read-only file system) ends the recorder with one line, exit status 1, the file readable
up to the fault.

The file is created with mode 0600 (whatever the umask,
:data:`messages.recording.RECORDING_MODE`): a recording holds every node's configuration.
``--out`` refuses an existing file unless ``--overwrite`` is given.

Run: ``python -m messages.recorder --run-id RUN --out recordings/run.mcap``. It finishes the
file when every expected node has ended and every message it reported published has arrived
(or the drain time has passed), and on SIGINT/SIGTERM. ``complete = "true"`` only when every
node that started (expected or not) ended by its own end event, with nothing missing or extra; exit status 1 if messages
were missing or extra, or the file could not be written; 2 for a bad command line or an
unwritable ``--out``.
"""

from __future__ import annotations

import io
import json
import os
import queue
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable, Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any, BinaryIO

from mcap.writer import CompressionType, Writer

from messages.auth import ROLES
from messages.bus import NodeBus, StopFlag, parse_node_arguments, run_node
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main
from messages.codec import MessageError, decode, encode, json_schema
from messages.foxglove import Log, LogLevel, Timestamp
from messages.provenance import git_revision, package_versions
from messages.recording import create_recording
from messages.topics import (
    LASER_COMMAND,
    LOG,
    PLANT_STATE,
    RUN_EVENTS,
    TOPICS,
    Topic,
    key_suffix,
    message_node,
    run_prefix,
    split_key,
)
from messages.types import MAX_STEPS_AHEAD, RunEvent

NODE_NAME = "recorder"
STEP_TOPICS = (PLANT_STATE, LASER_COMMAND)
FLUSH_PERIOD_S = 0.5
"""Wall time [s] between chunk closes and file flushes (while messages arrive and when idle)."""
POLL_S = 0.05
BATCH_S = 0.002
"""After writing what had arrived, the recorder waits this long [s] before it looks again: it
wakes a few hundred times a second, not once per message (a 2 kHz loop sends ~5 000 a second)."""
MAX_WATCHES = 64
WARNINGS_LOGGED = 20
MAX_QUEUED_BYTES = 256 * 1024 * 1024
"""Largest backlog [bytes] between zenoh's callback and the recorder's loop, each message counted
with :data:`QUEUED_OVERHEAD_BYTES` more; a message arriving beyond it is dropped and counted
(``queue_full``)."""
QUEUED_OVERHEAD_BYTES = 256
LOG_RATE_PER_S = 200.0
LOG_BURST = 1000
"""Log lines of one node the recorder takes per second on average, and at once (a token bucket);
more are dropped and counted (``log_rate``), so that one node's flood cannot crowd out the run."""


def log_time_ns(msg: Any) -> int:
    """Process time of a message in ns: ``time_s``, the Foxglove ``timestamp``, or the latest of a
    ``foxglove.SceneUpdate``'s entities (it has at least one)."""
    if hasattr(msg, "time_s"):
        return int(round(msg.time_s * 1e9))
    if hasattr(msg, "timestamp"):
        return msg.timestamp.to_ns()
    return max(entity.timestamp.to_ns() for entity in msg.entities)


class RecordingWriteError(Exception):
    """The output file cannot be written any more (full disk, read-only file system, ...)."""

    def __init__(self, path: Path, err: OSError) -> None:
        super().__init__(f"cannot write {path}: {err.strerror or err}")


class McapRecorder:
    """Writes contract messages of one run into one MCAP stream (no transport inside).

    Parameters
    ----------
    path : Path
        The file ``stream`` writes to (named in errors).
    run_id : str
        The run recorded.
    stream : binary file object
        Where the MCAP goes: ``path.open("wb")`` in production, a fault-injecting wrapper in tests.
    """

    def __init__(self, path: Path, run_id: str, stream: BinaryIO) -> None:
        self.path = path
        self.run_id = run_id
        self._stream = stream
        self.recorded: Counter[str] = Counter()
        self.failed = False
        self.finished = False
        self._last_flush = time.monotonic()
        with self._writing():
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
        self.flush()  # the header, channels and run metadata on disk at once: a recorder killed before its first
        #               periodic flush still leaves a readable recording, not an empty file

    @contextmanager
    def _writing(self) -> Iterator[None]:
        """Turn an ``OSError`` of the stream into :class:`RecordingWriteError`; no writing after one."""
        if self.failed:
            raise RecordingWriteError(self.path, OSError("an earlier write failed"))
        try:
            yield
        except OSError as err:
            self.failed = True
            raise RecordingWriteError(self.path, err) from None

    def write(self, topic: Topic, payload: bytes, msg: Any, publish_time_ns: int) -> None:
        """Append one validated message (its original JSON bytes) to the topic's channel."""
        with self._writing():
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
        with self._writing():
            self._writer.add_attachment(create_time=now, log_time=now, name=name, media_type=media_type, data=data)

    def log(self, level: LogLevel, text: str, time_s: float) -> None:
        """Write one of the recorder's own log lines to ``/log``."""
        msg = Log(timestamp=Timestamp.from_seconds(time_s), level=level, message=text[:8000], name=NODE_NAME)
        self.write(LOG, encode(msg), msg, time.time_ns())

    def flush(self) -> None:
        """Close the current chunk, flush the stream and ``fsync`` it, so that everything so far is on disk.

        ``mcap.writer.Writer.flush`` (public since mcap 1.2) finishes the chunk in progress and
        flushes the output stream; ``tests/test_recorder_crash.py`` fails if it stops doing so.
        """
        with self._writing():
            self._writer.flush()
            self._sync()
        self._last_flush = time.monotonic()

    def _sync(self) -> None:
        """``fsync`` the stream if it is a file (an in-memory stream in tests has no descriptor)."""
        try:
            fd = self._stream.fileno()
        except (AttributeError, io.UnsupportedOperation):
            return
        os.fsync(fd)

    def flush_due(self, now: float) -> None:
        """:meth:`flush` if :data:`FLUSH_PERIOD_S` has passed since the last one (``now``: monotonic s)."""
        if now - self._last_flush >= FLUSH_PERIOD_S:
            self.flush()

    def finish(self, summary: dict[str, str]) -> None:
        """Close the last chunk, then write the closing metadata and the MCAP summary; close the file.

        The ``meltloop.counts`` record comes after every message, so a file cut anywhere before
        its footer never holds a completeness record with messages missing behind it. After a
        write error only closes the stream (what reached the file stays recoverable).
        """
        if self.finished:
            return
        self.finished = True
        if self.failed:
            with suppress(OSError):
                self._stream.close()
            return
        with self._writing():
            self._writer.flush()  # the chunk in progress goes before the completeness record
            self._writer.add_metadata("meltloop.counts", summary)
            self._writer.finish()
            self._stream.flush()
            self._sync()
            self._stream.close()


class Admission:
    """Which schema-valid messages may be recorded: this run's, with possible steps.

    A state or command (:data:`STEP_TOPICS`) must be newer than the last admitted one of its
    topic and at most :data:`MAX_STEPS_AHEAD` ahead of it; before the first, the reference is
    step −1 (a run starts at step 0).
    """

    def __init__(self, run_id: str) -> None:
        self.run_id = run_id
        self.last_step: dict[str, int] = {t.suffix: -1 for t in STEP_TOPICS}

    def reason_to_drop(self, topic: Topic, msg: Any) -> str | None:
        """``None`` if ``msg`` may be recorded (and then takes its step as the topic's last), else the reason."""
        if getattr(msg, "run_id", self.run_id) != self.run_id:
            return "other_run"
        last = self.last_step.get(topic.suffix)
        if last is not None:
            if msg.step <= last:
                return "step_not_newer"
            if msg.step > last + MAX_STEPS_AHEAD:
                return "step_too_far_ahead"
            self.last_step[topic.suffix] = msg.step
        return None


@dataclass
class _PendingEnd:
    event: RunEvent
    received_s: float
    item: Any


@dataclass
class RunTracker:
    """Follows nodes' start/end events; an ``end`` counts only when the node's liveliness agrees.

    An ``end`` of a node that sent a ``start`` is held until the node's liveliness token is seen
    gone within ``drain_s`` of it (before or after); then the latest such ``end`` is confirmed
    and its publish counts taken, any other of the node is dropped as ``duplicate_end`` (as is
    every ``end`` after a confirmed one). An ``end`` held longer than ``drain_s`` with the
    token still there, or received more than ``drain_s`` after the token went, is dropped as
    ``unconfirmed_end``. Times are wall-clock seconds.

    Parameters
    ----------
    expected : tuple of str
        Nodes whose end finishes the run (none: every node that started).
    drain_s : float
        Largest time [s] between an ``end`` event and its node's token disappearing.
    own_node : str
        The recorder's name: its own ``start`` is recorded once, it never ends through an event.
    roles : dict of str to tuple of str
        Roles of the run's nodes (:data:`messages.auth.ROLES`); a node not listed has the role
        of its name, if that is a role, else none.
    """

    expected: tuple[str, ...]
    drain_s: float
    own_node: str = NODE_NAME
    roles: dict[str, tuple[str, ...]] = field(default_factory=dict)
    started: set[str] = field(default_factory=set)
    ended: dict[str, RunEvent] = field(default_factory=dict)
    gone_at: dict[str, float] = field(default_factory=dict)
    _pending: dict[str, list[_PendingEnd]] = field(default_factory=dict)

    def on_event(self, event: RunEvent, received_s: float, item: Any = None) -> str | None:
        """Take one life-cycle event; ``None`` if it is recorded now, ``"held"`` for an ``end``
        waiting for confirmation (``item`` comes back from :meth:`poll`), else the reason to drop it."""
        node = event.node
        if event.event == "start":
            if node in self.started:
                return "duplicate_start"
            self.started.add(node)
            return None
        if event.event == "fault":
            return None
        if node not in self.started or node == self.own_node:
            return "end_without_start"
        if node in self.ended:
            return "duplicate_end"
        self._pending.setdefault(node, []).append(_PendingEnd(event, received_s, item))
        return "held"

    def gone(self, node: str, at_s: float) -> None:
        """``node``'s liveliness token was seen gone at ``at_s`` (the first time counts)."""
        self.gone_at.setdefault(node, at_s)

    def poll(self, now_s: float) -> tuple[list[Any], list[str]]:
        """Decide held ``end`` events: the items of the confirmed ones, and the reasons of the dropped ones."""
        confirmed, dropped = [], []
        for node, held in list(self._pending.items()):
            gone = self.gone_at.get(node)
            if gone is None:
                expired = [h for h in held if now_s - h.received_s > self.drain_s]
                dropped += ["unconfirmed_end"] * len(expired)
                self._pending[node] = [h for h in held if h not in expired]
                continue
            matching = [h for h in held if abs(gone - h.received_s) <= self.drain_s]
            dropped += ["unconfirmed_end"] * (len(held) - len(matching))
            if matching:
                latest = max(matching, key=lambda h: h.received_s)
                self.ended[node] = latest.event
                confirmed.append(latest.item)
                dropped += ["duplicate_end"] * (len(matching) - 1)
            del self._pending[node]
        return confirmed, dropped

    def waiting_for(self) -> set[str]:
        """Nodes whose confirmed end is still needed (expected ones, or all started but the recorder)."""
        nodes = set(self.expected) or self.started - {self.own_node}
        return nodes - set(self.ended)

    def all_ended(self) -> bool:
        """Whether the run ended by its nodes' own (confirmed) end events: the recording may finish."""
        return bool(self.expected or self.started - {self.own_node}) and not self.waiting_for()

    def not_ended(self) -> set[str]:
        """Nodes that started (expected or not) without a confirmed end: while one is left, the run
        is not complete."""
        return self.started - {self.own_node} - set(self.ended) | self.waiting_for()

    def roles_of(self, node: str) -> tuple[str, ...]:
        """``node``'s roles: as given, else its name if that is a role, else none."""
        return self.roles.get(node, (node,) if node in ROLES else ())

    def owns(self, node: str, topic: Topic) -> bool:
        """Whether ``node`` answers for messages of ``topic``: its own per-node key, or a topic of its role."""
        return topic.per_node or topic.suffix.split("/")[0] in self.roles_of(node)

    def foreign_claims(self, event: RunEvent) -> list[str]:
        """The keys of an ``end`` event's counts that are not its node's own (ignored)."""
        return [suffix for suffix in event.published
                if suffix not in TOPICS or not self.owns(event.node, TOPICS[suffix])]

    def published(self) -> Counter[str]:
        """Per key suffix (:func:`messages.topics.key_suffix`), what the ended nodes reported
        published of their own keys."""
        total: Counter[str] = Counter()
        for node, event in self.ended.items():
            for suffix, n in event.published.items():
                if suffix in TOPICS and self.owns(node, TOPICS[suffix]):
                    total[key_suffix(TOPICS[suffix], node)] += n
        return total

    def settled(self, suffix: str) -> bool:
        """Whether every started node that may publish under key suffix ``suffix`` has a confirmed
        end (true when none started): only then can a recorded message be called extra."""
        topic, node = TOPICS.get(suffix), None
        if topic is None:
            base, _, node = suffix.rpartition("/")
            topic = TOPICS[base]
        publishers = {node} if topic.per_node else {n for n in self.started if self.owns(n, topic)}
        return not publishers & self.not_ended()


def reconcile(published: Counter[str], recorded: Counter[str], settled: Callable[[str], bool]) -> tuple[dict, dict]:
    """Per key suffix, messages published but not recorded (missing) and recorded but not published (extra).

    Keys are :func:`messages.topics.key_suffix` values: a role topic (``plant/state``) or a node's
    own key (``log/plant``), so that one publisher's loss cannot hide behind another's messages.

    Parameters
    ----------
    published : Counter
        What the ended nodes reported in their ``end`` events, of their own keys.
    recorded : Counter
        Recorded messages of other nodes (not the recorder's own start event and logs), or a lost
        message could hide behind one of the recorder's.
    settled : callable
        Whether every node that may publish under a key has ended; if not, its recorded messages
        have no complete published count to match and are not called extra (the run is
        incomplete anyway).
    """
    missing = {k: n - recorded[k] for k, n in sorted(published.items()) if recorded[k] < n}
    return missing, {k: n - published[k] for k, n in sorted(recorded.items()) if n > published[k] and settled(k)}


def by_topic(counts: Counter[str]) -> Counter[str]:
    """Counts per key suffix summed per topic suffix (``log/plant`` and ``log/controller`` into ``log``)."""
    total: Counter[str] = Counter()
    for suffix, n in counts.items():
        total[suffix if suffix in TOPICS else suffix.rpartition("/")[0]] += n
    return total


@dataclass
class Accepted:
    """A message to write: its topic, original bytes, decoded form and receipt time (UNIX ns)."""

    topic: Topic
    payload: bytes
    msg: Any
    received_ns: int


class Intake:
    """What the recorder does with each received sample, without any I/O.

    :meth:`receive` returns the messages to write now; :meth:`poll` the ``end`` events confirmed
    since. Everything dropped is counted per reason in :attr:`dropped`; the first
    :data:`WARNINGS_LOGGED` reasons are queued in :attr:`warnings` for the recorder's log.
    """

    def __init__(self, run_id: str, tracker: RunTracker) -> None:
        self.run_id = run_id
        self.tracker = tracker
        self.admission = Admission(run_id)
        self.dropped: Counter[str] = Counter()
        self.invalid: Counter[str] = Counter()
        self.from_nodes: Counter[str] = Counter()
        self.warnings: list[str] = []
        self.last_time_s = 0.0

    def _drop(self, reason: str, text: str, n: int = 1) -> list[Accepted]:
        if sum(self.dropped.values()) < WARNINGS_LOGGED:
            self.warnings.append(f"dropped ({reason}): {text}")
        self.dropped[reason] += n
        return []

    def dropped_on_arrival(self, dropped: Counter[tuple[str, str]]) -> None:
        """Count what :class:`Arrivals` dropped before it reached :meth:`receive`: (reason, node) -> n."""
        for (reason, node), n in sorted(dropped.items()):
            self._drop(reason, f"{n} message(s)" + (f" of node {node!r}" if node else ""), n)

    def _accept(self, item: Accepted) -> list[Accepted]:
        node = message_node(item.msg)
        if node != self.tracker.own_node:
            self.from_nodes[key_suffix(item.topic, node)] += 1
        self.last_time_s = max(self.last_time_s, log_time_ns(item.msg) / 1e9)
        return [item]

    def receive(self, key: str, payload: bytes, received_ns: int) -> list[Accepted]:
        """Decide one sample of the run's key space; returns what to write now."""
        found = split_key(self.run_id, key)
        if found is None:
            return self._drop("unknown_key", key[:200])
        topic, key_node = found
        try:
            msg = decode(topic, payload)
        except MessageError as err:
            self.invalid[topic.suffix] += 1
            return self._drop("invalid", str(err))
        if topic.per_node and message_node(msg) != key_node:
            return self._drop("node_mismatch", f"{topic.channel}: node {message_node(msg)!r} published under {key!r}")
        reason = self.admission.reason_to_drop(topic, msg)
        if reason is not None:
            step = getattr(msg, "step", None)
            return self._drop(reason, f"{topic.channel} run_id={getattr(msg, 'run_id', None)!r} step={step}")
        item = Accepted(topic, payload, msg, received_ns)
        if topic is LOG and msg.name == self.tracker.own_node:
            return self._drop("claims_recorder", f"{topic.channel} log named {msg.name!r}")
        if topic is RUN_EVENTS:
            reason = self.tracker.on_event(msg, received_ns / 1e9, item)
            if reason == "held":
                return []
            if reason is not None:
                return self._drop(reason, f"{msg.event} event of node {msg.node!r}")
        return self._accept(item)

    def poll(self, now_s: float) -> list[Accepted]:
        """The ``end`` events confirmed by now (to write), counting the ones dropped unconfirmed."""
        confirmed, dropped = self.tracker.poll(now_s)
        for reason in dropped:
            self._drop(reason, "end event not matched by its node's liveliness token disappearing")
        for item in confirmed:
            for suffix in self.tracker.foreign_claims(item.msg):
                self._drop("foreign_count", f"end event of {item.msg.node!r} counts {suffix[:64]!r}, not a key of "
                           "its own: ignored")
        return [accepted for item in confirmed for accepted in self._accept(item)]

    def summary(self, stopped_by: str | None) -> tuple[dict[str, str], str]:
        """The closing ``meltloop.counts`` metadata (without ``recorded``) and, if incomplete, why."""
        published = self.tracker.published()
        ended = self.tracker.all_ended()  # else the recording was stopped first: nothing is settled
        missing, extra = reconcile(published, self.from_nodes, lambda key: ended and self.tracker.settled(key))
        reasons = []
        if stopped_by:
            reasons.append(f"stopped by {stopped_by}")
        elif not_ended := self.tracker.not_ended():
            reasons.append(f"no confirmed end of {', '.join(sorted(not_ended))}")
        if missing:
            reasons.append(f"messages published but not recorded: {missing}")
        if extra:
            reasons.append(f"messages recorded but not published: {extra}")
        counts = {
            "complete": "false" if reasons else "true",
            "incomplete_reason": "; ".join(reasons),
            "stopped_by": stopped_by or "run end",
            "published": json.dumps(dict(by_topic(published)), sort_keys=True),
            "missing": json.dumps(missing, sort_keys=True),
            "extra": json.dumps(extra, sort_keys=True),
            "dropped": json.dumps(dict(self.dropped), sort_keys=True),
            "invalid_dropped": json.dumps(dict(self.invalid), sort_keys=True),
            "unknown_keys_dropped": str(self.dropped["unknown_key"]),
        }
        return counts, "; ".join(r for r in reasons if not r.startswith("stopped by"))


class _Presence:
    """Liveliness watches of the run's nodes, turned into :meth:`RunTracker.gone` calls.

    Expected nodes are watched from the start, other nodes once they sent a ``start``, at most
    :data:`MAX_WATCHES` in all (forged starts under many names must not exhaust the session; an
    unwatched node's ``end`` is never confirmed, so the run is then incomplete, never forged).
    """

    def __init__(self, bus: Any, tracker: RunTracker) -> None:
        self._bus = bus
        self._tracker = tracker
        self._watches = {node: bus.watch_presence(node) for node in tracker.expected}

    def update(self, now_s: float) -> None:
        """Watch newly started nodes; report every node whose token is gone (at ``now_s``, wall s)."""
        if len(self._watches) < MAX_WATCHES and len(self._tracker.started) > len(self._watches):
            for node in sorted(self._tracker.started - set(self._watches) - {self._tracker.own_node}):
                if len(self._watches) < MAX_WATCHES:
                    self._watches[node] = self._bus.watch_presence(node)
        for node, gone in self._watches.items():
            if gone.is_set():
                self._tracker.gone(node, now_s)


class Arrivals:
    """What zenoh's callback hands the recorder's loop: bounded, with a log rate per node.

    :meth:`put` (the callback; it only enqueues) drops a log line of a node over its
    :data:`LOG_RATE_PER_S` / :data:`LOG_BURST` token bucket (``log_rate``; nodes beyond the
    :data:`MAX_WATCHES` th share one bucket) and any message that would take the backlog over
    ``max_bytes`` (``queue_full``), counting each; :meth:`take` returns everything queued, in
    order; :meth:`take_dropped` the drop counts since its last call, by (reason, node).

    Parameters
    ----------
    run_id : str
        The run (whose log keys are rate-limited).
    max_bytes : int
        Largest backlog [bytes], :data:`MAX_QUEUED_BYTES` by default.
    clock : callable
        Monotonic time [s] of the log rate.
    """

    def __init__(self, run_id: str, max_bytes: int = MAX_QUEUED_BYTES,
                 clock: Callable[[], float] = time.monotonic) -> None:
        self.max_bytes = max_bytes
        self._clock = clock
        self._items: queue.SimpleQueue[tuple[str, bytes, int]] = queue.SimpleQueue()
        self._bytes = 0
        self._lock = threading.Lock()
        self._log_keys = f"{run_prefix(run_id)[:-2]}{LOG.suffix}/"
        self._buckets: dict[str, tuple[float, float]] = {}
        self._dropped: Counter[tuple[str, str]] = Counter()

    def _log_allowed(self, node: str, now_s: float) -> bool:
        if node not in self._buckets and len(self._buckets) >= MAX_WATCHES:
            node = "*"
        tokens, then = self._buckets.get(node, (float(LOG_BURST), now_s))
        tokens = min(float(LOG_BURST), tokens + (now_s - then) * LOG_RATE_PER_S)
        self._buckets[node] = (tokens - 1.0, now_s) if tokens >= 1.0 else (tokens, now_s)
        return tokens >= 1.0

    def put(self, key: str, payload: bytes, received_ns: int) -> None:
        """Queue one sample (zenoh's callback), unless a bound drops it."""
        size = len(payload) + QUEUED_OVERHEAD_BYTES
        with self._lock:
            if key.startswith(self._log_keys):
                node = key[len(self._log_keys):]
                if not self._log_allowed(node, self._clock()):
                    self._dropped[("log_rate", node if node in self._buckets else "*")] += 1
                    return
            if self._bytes + size > self.max_bytes:
                self._dropped[("queue_full", "")] += 1
                return
            self._bytes += size
            self._items.put((key, payload, received_ns))

    def take(self, timeout_s: float) -> list[tuple[str, bytes, int]]:
        """Everything queued, in order, after waiting up to ``timeout_s`` [s] for the first item."""
        try:
            items = [self._items.get(timeout=timeout_s)]
        except queue.Empty:
            return []
        while True:
            try:
                items.append(self._items.get_nowait())
            except queue.Empty:
                break
        with self._lock:
            self._bytes -= sum(len(payload) + QUEUED_OVERHEAD_BYTES for _, payload, _ in items)
        return items

    def take_dropped(self) -> Counter[tuple[str, str]]:
        """Drops since the last call, by (reason, node; empty for ``queue_full``)."""
        with self._lock:
            dropped, self._dropped = self._dropped, Counter()
        return dropped


def record(recorder: McapRecorder, bus: NodeBus, stop: StopFlag, tracker: RunTracker, drain_s: float,
           config: dict[str, Any]) -> int:
    """Receive everything under the run's prefix until the run ends; returns the exit status.

    The run ends when the expected nodes (else every node that started) have ended; then the
    recorder waits up to ``drain_s`` more for messages still missing and for the end of any
    other node that started.

    zenoh's callback only enqueues (:class:`Arrivals`: bounded, a log rate per node); the loop
    takes all that has arrived at each wake-up and, after writing it, waits :data:`BATCH_S`
    before it looks again.

    ``bus`` needs ``run_id``, ``subscribe_raw``, ``watch_presence`` and ``ready`` only (a fake in
    the in-process tests).
    """
    inbox = Arrivals(bus.run_id)
    bus.subscribe_raw(run_prefix(bus.run_id),
                      lambda s: inbox.put(str(s.key_expr), s.payload.to_bytes(), time.time_ns()))
    intake = Intake(bus.run_id, tracker)
    presence = _Presence(bus, tracker)
    bus.ready(config=config)
    end_since: float | None = None
    try:
        while not stop.is_set():
            accepted = [item for sample in inbox.take(POLL_S) for item in intake.receive(*sample)]
            intake.dropped_on_arrival(inbox.take_dropped())
            presence.update(time.time())
            for item in accepted + intake.poll(time.time()):
                recorder.write(item.topic, item.payload, item.msg, item.received_ns)
                if item.topic is RUN_EVENTS and item.msg.event == "start" and item.msg.config_json:
                    recorder.attach(f"config/{item.msg.node}.json", item.msg.config_json.encode())
            for text in intake.warnings:
                recorder.log(LogLevel.WARNING, text, intake.last_time_s)
            intake.warnings.clear()
            recorder.flush_due(time.monotonic())
            if accepted:
                time.sleep(BATCH_S)
            if accepted or not tracker.all_ended():
                continue
            end_since = end_since or time.monotonic()
            missing, _ = reconcile(tracker.published(), intake.from_nodes, lambda _key: False)
            if not (missing or tracker.not_ended()) or time.monotonic() - end_since > drain_s:
                break
        intake.dropped_on_arrival(inbox.take_dropped())
        counts, problem = intake.summary(stop.signal_name if stop.is_set() else None)
        if problem:
            recorder.log(LogLevel.ERROR, problem, intake.last_time_s)
            print(f"error: {problem}", file=sys.stderr, flush=True)
        recorder.finish({**counts, "recorded": json.dumps(dict(recorder.recorded), sort_keys=True)})
    except RecordingWriteError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        recorder.finish({})
        return 1
    dropped = ", ".join(f"{reason} {n}" for reason, n in sorted(intake.dropped.items())) or "none"
    print(f"recorded {sum(recorder.recorded.values())} messages to {recorder.path} "
          f"(complete: {counts['complete']}; dropped: {dropped})", flush=True)
    return 1 if problem else 0


def default_path(run_id: str) -> Path:
    """``recordings/<UTC date-time>-<run id>.mcap``, made unique (:func:`messages.launch.service.new_recording`)."""
    from messages.launch.service import new_recording

    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return new_recording(Path("recordings") / f"{stamp}-{run_id}.mcap")


def open_output(path: Path, overwrite: bool) -> BinaryIO:
    """Create ``path``'s folder and the file (:func:`messages.recording.create_recording`: mode
    0600); an existing file only with ``overwrite``.

    Raises
    ------
    UsageError
        Naming ``--out``: the file exists (without ``overwrite``) or cannot be written.
    """
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {path}: cannot write: {err.strerror or err}") from None
    try:
        return create_recording(path, overwrite)
    except FileExistsError:
        raise UsageError(f"--out {path}: exists; give --overwrite to replace it") from None
    except OSError as err:
        raise UsageError(f"--out {path}: cannot write: {err.strerror or err}") from None


def parse_roles(items: list[str]) -> dict[str, tuple[str, ...]]:
    """``--role NODE=ROLE[,ROLE]`` options as node -> roles (``NODE=``: none).

    Raises
    ------
    UsageError
        Naming the malformed option or unknown role.
    """
    roles = {}
    for item in items:
        node, sep, names = item.partition("=")
        given = tuple(r for r in names.split(",") if r)
        if not sep or not node or not set(given) <= set(ROLES):
            raise UsageError(f"--role {item!r}: expected NODE=ROLE[,ROLE] with roles among {', '.join(ROLES)}")
        roles[node] = given
    return roles


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.recorder``."""
    parser = ArgumentParser(prog="python -m messages.recorder", description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, help="MCAP file to write (default: recordings/<date>-<run id>.mcap)")
    parser.add_argument("--overwrite", action="store_true", help="replace --out if it exists (else refused)")
    parser.add_argument(
        "--expect", action="append", default=[], metavar="NODE",
        help="finish once these nodes have ended (default: once every node that started has ended)",
    )
    parser.add_argument(
        "--role", action="append", default=[], metavar="NODE=ROLE[,ROLE]",
        help="roles of a node, whose counts of those topics it answers for (default: a node named like a role "
             f"has it: {', '.join(ROLES)})",
    )
    parser.add_argument("--drain-s", type=float, default=3.0,
                        help="how long to wait for late messages and for an ending node's liveliness token to go")
    try:
        args, settings = parse_node_arguments(parser, argv)
        if not 0 <= args.drain_s <= 60:
            raise UsageError(f"--drain-s must be >= 0 and at most 60 s, got {args.drain_s}")
        if args.out is not None and args.out.suffix != ".mcap":
            raise UsageError(f"--out must name a .mcap file, got {args.out}")
        roles = parse_roles(args.role)
        path = args.out or default_path(settings.run_id)
        stream = open_output(path, overwrite=args.overwrite or args.out is None)  # the default is reserved, ours
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = StopFlag()
    try:
        recorder = McapRecorder(path, settings.run_id, stream)
    except RecordingWriteError as err:
        print(f"error: {err}", file=sys.stderr, flush=True)
        return 1
    config = {"out": str(path), "expect": args.expect, "drain_s": args.drain_s, "roles": roles}
    tracker = RunTracker(tuple(args.expect), args.drain_s, roles=roles)
    try:
        return run_node(parser.prog, NODE_NAME, settings,
                        lambda bus: record(recorder, bus, stop, tracker, args.drain_s, config))
    finally:
        with suppress(RecordingWriteError):
            recorder.finish({"complete": "false", "stopped_by": "error", "incomplete_reason": "recorder error"})


if __name__ == "__main__":
    run_main(main)
