"""The zenoh session helper shared by every node.

Defaults are secure and local: peer mode, listening on loopback only (an ephemeral port),
multicast scouting off, connecting to the run's hub endpoint (``launch.py`` opens the hub; by
hand, start one node with ``--listen tcp/127.0.0.1:7447``). Peers discover each other through
the hub by gossip and then talk directly.

``--low-latency`` switches a zenoh session to zenoh's low-latency unicast transport
(``transport/unicast/lowlatency``, which needs ``transport/unicast/qos/enabled = false``): the
thread that publishes writes the message to the socket itself instead of handing it to zenoh's
transmit thread, one thread wake-up less on each leg of the loop. It has no QoS priorities and no
fragmentation, and zenoh loses some messages above 32 KiB on it (measured, ``docs/node-contract.md``):
a node on it refuses to publish a message larger than :data:`LOW_LATENCY_MAX_BYTES` with a
:class:`~messages.codec.MessageError` instead. Both ends of a link must enable it, else zenoh
uses its default transport on that link. It suits a sensor ↔ controller loop; the FE node's
temperature images (up to 4 MiB) do not fit.

A :class:`NodeBus` owns one session for one node: typed publishers that validate and count
what they send, inboxes whose zenoh callbacks only enqueue raw bytes (decoding and validation
happen in the node's own loop), a liveliness token that says the node is ready, and start/end
:class:`~messages.types.RunEvent` messages carrying the per-topic publish counts the recorder
reconciles against. The session is always closed on exit (an unclosed session with declared
callbacks keeps the process alive).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import secrets
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import zenoh

from messages.auth import PASSWORD_ENV, USER_ENV, node_credentials
from messages.cli import UsageError
from messages.codec import MessageError, decode, encode, prepare
from messages.foxglove import Log, LogLevel, Timestamp
from messages.topics import LOG, RUN_EVENTS, Topic, key_expr, liveliness_key, message_node
from messages.types import RunEvent

DEFAULT_HUB = "tcp/127.0.0.1:7447"
DEFAULT_LISTEN = "tcp/127.0.0.1:0"
SUPERVISOR_ENV = "MELTLOOP_SUPERVISOR_PID"
REQUIRE_TIMEOUT_S = 60.0
LOW_LATENCY_MAX_BYTES = 32 * 1024
"""Largest message a session on zenoh's low-latency transport publishes [bytes] (it does not
fragment; 300 random sizes in 32-64 KiB lost 19 on loopback, 2 300 up to 32 KiB none)."""
SHARED_MEMORY = False
"""Whether meltloop's sessions (nodes, hub, the hub's node configurations) let zenoh pass messages
through shared memory: no. With it (zenoh's default) a message above 3 KiB between two processes on
one host, such as a temperature image, goes into shared memory, and zenoh has dropped such messages
silently when the receiver was descheduled for ~100 ms before mapping them (eclipse-zenoh/zenoh
issue 2628), a loss the recorder can only report. Over the socket the message is copied."""
GREATER_ZID_ONLY = '{peer: {to_router: "always", to_peer: "greater-zid"}}'
"""Gossip autoconnect strategy of a low-latency session: of two peers, only the one with the
greater zenoh id opens their link (:func:`zenoh_config`)."""
_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-")


def is_name(text: str) -> bool:
    """Whether ``text`` is a valid run id or node name: 1-64 letters, digits, ``_.-``, not starting with ``_.-``."""
    return 1 <= len(text) <= 64 and set(text) <= _NAME_CHARS and text[0] not in "_.-"


@dataclass(frozen=True)
class BusSettings:
    """Where a node's zenoh session listens and connects, and which run it belongs to.

    Attributes
    ----------
    run_id : str
        Run identifier (letters, digits, ``_.-``; at most 64), the key namespace.
    connect : tuple of str
        Zenoh endpoints to connect to (default: the hub on loopback).
    listen : tuple of str
        Zenoh endpoints to listen on (default: an ephemeral loopback port).
    zenoh_config : Path or None
        A zenoh JSON5 configuration file; when given it is the base, and explicit
        ``connect``/``listen`` options still override its endpoints.
    require : tuple of str
        Nodes that must be present before this node announces itself (:meth:`NodeBus.ready`).
        Seeing a node's liveliness token means its subscriptions (declared before the token)
        have reached this session, so nothing published afterwards is lost to it; a node that
        is recorded requires ``recorder`` for that reason.
    low_latency : bool
        Use zenoh's low-latency unicast transport (module docstring): fewer thread hops per
        message, no QoS, messages of at most :data:`LOW_LATENCY_MAX_BYTES`.
    """

    run_id: str = "default"
    connect: tuple[str, ...] = (DEFAULT_HUB,)
    listen: tuple[str, ...] = (DEFAULT_LISTEN,)
    zenoh_config: Path | None = None
    require: tuple[str, ...] = ()
    low_latency: bool = False

    def __post_init__(self) -> None:
        if not is_name(self.run_id):
            raise UsageError(f"invalid run id {self.run_id!r}: use 1-64 letters, digits, '_', '.', '-'")
        for endpoint in self.connect + self.listen:
            proto, sep, address = endpoint.partition("/")
            if not sep or not address or proto not in {"tcp", "udp", "tls", "quic", "unixsock-stream", "ws"}:
                raise UsageError(f"invalid zenoh endpoint {endpoint!r}: expected e.g. tcp/127.0.0.1:7447")
        if self.zenoh_config is not None and not self.zenoh_config.is_file():
            raise UsageError(f"zenoh config file not found: {self.zenoh_config}")
        for node in self.require:
            if not is_name(node):
                raise UsageError(f"invalid node name {node!r} for --require: use 1-64 letters, digits, '_', '.', '-'")


def add_bus_arguments(parser: argparse.ArgumentParser) -> None:
    """Add the options every node shares: ``--run-id --connect --listen --zenoh-config --require
    --low-latency``."""
    group = parser.add_argument_group("zenoh bus")
    group.add_argument("--run-id", default="default", help="run identifier, the key namespace (default: %(default)s)")
    group.add_argument(
        "--connect", action="append", metavar="ENDPOINT",
        help=f"zenoh endpoint to connect to; repeatable (default: {DEFAULT_HUB})",
    )
    group.add_argument(
        "--listen", action="append", metavar="ENDPOINT",
        help=f"zenoh endpoint to listen on; repeatable (default: {DEFAULT_LISTEN}, loopback only)",
    )
    group.add_argument("--zenoh-config", type=Path, metavar="FILE", help="zenoh JSON5 configuration file")
    group.add_argument(
        "--require", action="append", default=[], metavar="NODE",
        help="wait until this node of the run is present before announcing readiness; repeatable",
    )
    group.add_argument(
        "--low-latency", action="store_true",
        help="zenoh's low-latency transport: the publishing thread writes to the socket, no QoS; messages up to "
             f"{LOW_LATENCY_MAX_BYTES // 1024} KiB (for a sensor-controller loop; both ends must enable it)",
    )


def bus_settings_from_args(args: argparse.Namespace) -> BusSettings:
    """Build validated :class:`BusSettings` from parsed arguments (raises :class:`UsageError`)."""
    return BusSettings(
        run_id=args.run_id,
        connect=tuple(args.connect) if args.connect else (() if args.zenoh_config else (DEFAULT_HUB,)),
        listen=tuple(args.listen) if args.listen else (() if args.zenoh_config else (DEFAULT_LISTEN,)),
        zenoh_config=args.zenoh_config,
        require=tuple(args.require),
        low_latency=args.low_latency,
    )


def parse_node_arguments(parser: argparse.ArgumentParser,
                         argv: list[str] | None) -> tuple[argparse.Namespace, BusSettings]:
    """A node's command line: add the bus options (:func:`add_bus_arguments`) to ``parser``, parse
    ``argv`` and build the :class:`BusSettings` (raises :class:`UsageError`).

    Returns
    -------
    tuple[argparse.Namespace, BusSettings]
        The parsed arguments and the bus settings.
    """
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    return args, bus_settings_from_args(args)


def zenoh_config(settings: BusSettings, credentials: tuple[str, str] | None = None) -> zenoh.Config:
    """The zenoh configuration of a node.

    - a configuration file given: that file (explicit ``connect``/``listen`` still override);
    - ``credentials`` (user, password), as ``launch.py`` hands them to its nodes: a client of the
      run's authenticating hub (``settings.connect``), multicast off, listening nowhere;
    - neither: an unauthenticated peer on loopback with multicast off;
    - ``settings.low_latency``: zenoh's low-latency unicast transport on top (QoS off), and of
      two peers only the one with the greater zenoh id opens their link.
    """
    if settings.zenoh_config is not None:
        try:
            config = zenoh.Config.from_file(str(settings.zenoh_config))
        except Exception as err:  # zenoh raises its own error types
            raise UsageError(f"--zenoh-config {settings.zenoh_config}: cannot load: {err}") from None
    else:
        config = zenoh.Config()
        config.insert_json5("mode", '"client"' if credentials else '"peer"')
        config.insert_json5("scouting/multicast/enabled", "false")
        config.insert_json5("transport/shared_memory/enabled", json.dumps(SHARED_MEMORY))
    if settings.low_latency:
        config.insert_json5("transport/unicast/lowlatency", "true")
        config.insert_json5("transport/unicast/qos/enabled", "false")
        # of two peers that learn of each other by gossip, only one opens the link: with both
        # opening at once, 5 of 28 low-latency trials left a peer that never saw the other's token
        config.insert_json5("scouting/gossip/autoconnect_strategy", GREATER_ZID_ONLY)
    if credentials is not None:
        user, password = credentials
        config.insert_json5("transport/auth/usrpwd", json.dumps({"user": user, "password": password}))
    if settings.listen and credentials is None:
        config.insert_json5("listen/endpoints", json.dumps(list(settings.listen)))
    if settings.connect:
        config.insert_json5("connect/endpoints", json.dumps(list(settings.connect)))
    return config


def client_mode(config: zenoh.Config) -> bool:
    """Whether ``config`` makes the session a zenoh client (``launch.py``'s nodes, or a file):
    every message then crosses a router, a third process on its way."""
    return json.loads(config.get_json("mode")) == "client"


def low_latency(config: zenoh.Config) -> bool:
    """Whether ``config`` selects zenoh's low-latency unicast transport (by ``--low-latency`` or a file)."""
    return json.loads(config.get_json("transport/unicast/lowlatency")) is True


def open_session(settings: BusSettings, node: str, config: zenoh.Config | None = None) -> zenoh.Session:
    """Open ``node``'s zenoh session with the run credentials from the environment, if any
    (:mod:`messages.auth`); without them, say once that the session is unauthenticated.
    ``config``: the session's configuration if already built (default: :func:`zenoh_config`).

    Raises
    ------
    UsageError
        If the configuration file cannot be loaded.
    ConnectionError
        If the hub cannot be reached or refuses the credentials (one line, naming the endpoints).
    """
    credentials = node_credentials()
    if config is None:
        config = zenoh_config(settings, credentials)
    if credentials is None and settings.zenoh_config is None:
        print(f"warning: {node}: no run credentials ({USER_ENV}/{PASSWORD_ENV}); this zenoh session is "
              "unauthenticated (start the run with launch.py for per-node access control)", flush=True)
    try:
        return zenoh.open(config)
    except zenoh.ZError as err:
        where = ", ".join(settings.connect) or "the configured endpoints"
        reason = "refused or unreachable" if credentials else "unreachable"
        raise ConnectionError(f"{node}: cannot open a zenoh session to {where} ({reason}): "
                              f"{str(err).split(' at ')[0]}") from None


class _SignalRelay:
    """The process's one bridge from a signal handler to a :class:`threading.Event`.

    A Python signal handler runs on the main thread between two bytecodes, possibly while that
    thread holds the lock inside ``Event.wait``; calling ``Event.set`` there blocks forever on that
    lock. The handler therefore only writes a byte to a pipe (no lock taken) and this relay's
    thread, blocked on the pipe, sets the event of the current :class:`StopFlag`.
    """

    _instance: _SignalRelay | None = None

    def __init__(self) -> None:
        self.target: StopFlag | None = None
        self._open()

    def _open(self) -> None:
        self._read_fd, self._write_fd = os.pipe()
        os.set_blocking(self._write_fd, False)
        threading.Thread(target=self._relay, args=(self._read_fd,), name="stop-signal-relay", daemon=True).start()

    @classmethod
    def get(cls) -> _SignalRelay:
        if cls._instance is None:
            cls._instance = cls()
            os.register_at_fork(after_in_child=cls._instance._reopen_in_child)
        return cls._instance

    def _reopen_in_child(self) -> None:
        """A forked child gets a pipe and relay thread of its own (threads do not survive a fork, and
        a byte on the inherited pipe would stop the parent)."""
        os.close(self._read_fd)
        os.close(self._write_fd)
        self._open()

    def notify(self) -> None:
        """Wake the relay thread (async-signal safe: one non-blocking write)."""
        try:
            os.write(self._write_fd, b"\0")
        except BlockingIOError:  # the pipe is full of earlier wake-ups: one is enough
            pass

    def _relay(self, read_fd: int) -> None:
        while os.read(read_fd, 4096):
            if self.target is not None:
                self.target.set()


class StopFlag:
    """Set by SIGINT/SIGTERM, or when the supervising ``launch.py`` disappears.

    Installing the handlers also resets an inherited 'ignore SIGINT' disposition (a background
    process started from a non-interactive shell would otherwise ignore Ctrl-C). The handler takes
    no lock (see :class:`_SignalRelay`): a signal can land while the main thread waits here.
    """

    def __init__(self) -> None:
        self._event = threading.Event()
        self.signal_name: str | None = None
        self._signals = _SignalRelay.get()
        self._signals.target = self
        for sig in (signal.SIGINT, signal.SIGTERM):
            signal.signal(sig, self._handle)
        supervisor = os.environ.get(SUPERVISOR_ENV)
        if supervisor and supervisor.isdigit():
            threading.Thread(target=self._watch_parent, args=(int(supervisor),), daemon=True).start()

    def _handle(self, signum: int, _frame: Any) -> None:
        self.signal_name = signal.Signals(signum).name
        self._signals.notify()

    def _watch_parent(self, pid: int) -> None:
        while not self._event.wait(0.5):
            if os.getppid() != pid:
                self.signal_name = "supervisor gone"
                self._event.set()

    def set(self) -> None:
        """Request a stop from inside the node."""
        self._event.set()

    def is_set(self) -> bool:
        """Whether a stop was requested."""
        return self.signal_name is not None or self._event.is_set()

    def wait(self, timeout: float) -> bool:
        """Sleep up to ``timeout`` seconds, waking early on a stop request."""
        return self.is_set() or self._event.wait(timeout)


def wait_for_nodes(session: zenoh.Session, run_id: str, nodes: list[str], stop: StopFlag | threading.Event,
                   timeout_s: float, check: Callable[[], bool] | None = None) -> None:
    """Block until every node in ``nodes`` holds its liveliness token in run ``run_id``: the one
    readiness mechanism of nodes and of the launch service.

    ``check()`` is called between queries: it may raise to give up (e.g. a node process failed) or
    return ``True`` to end the wait (e.g. the node already finished with status 0, faster than its
    token could be seen).

    Raises
    ------
    TimeoutError
        If they are not all present within ``timeout_s`` (or a stop was requested).
    """
    missing = set(nodes)
    deadline = time.monotonic() + timeout_s
    while missing and not stop.is_set() and time.monotonic() < deadline:
        if check is not None and check():
            return
        for reply in session.liveliness().get(liveliness_key(run_id), timeout=0.5):
            if reply.ok is not None:
                missing.discard(str(reply.ok.key_expr).rsplit("/", 1)[-1])
        if missing:
            stop.wait(0.05)
    if missing and stop.is_set():
        raise TimeoutError(f"stopped while waiting for nodes: {', '.join(sorted(missing))}")
    if missing:
        raise TimeoutError(f"nodes not present after {timeout_s:.0f} s: {', '.join(sorted(missing))}")


class TopicPublisher:
    """Publishes validated messages of one topic and counts them."""

    def __init__(self, bus: NodeBus, topic: Topic, publisher: zenoh.Publisher) -> None:
        prepare(topic)
        self.topic = topic
        self._bus = bus
        self._publisher = publisher

    def put(self, msg: Any) -> float:
        """Encode (validating) and publish ``msg``; raises :class:`MessageError` if invalid, larger
        than its topic's limit (``Topic.max_bytes``: every receiver would drop it), or larger than
        the session's transport carries (:data:`LOW_LATENCY_MAX_BYTES`).

        Returns the monotonic time [s] at which the encoded message was handed to zenoh (a
        free-running plant times its round trips from there, as a bare ping-pong does).
        """
        if not isinstance(msg, self.topic.type):
            raise MessageError(f"{self.topic.channel} carries {self.topic.type.__name__}, not {type(msg).__name__}")
        payload = encode(msg)
        if len(payload) > self.topic.max_bytes:
            raise MessageError(f"{self.topic.channel}: a {len(payload)}-byte message exceeds the topic's "
                               f"{self.topic.max_bytes}-byte limit (every receiver would drop it); not published")
        if len(payload) > self._bus.max_payload_bytes:
            raise MessageError(f"{self.topic.channel}: a {len(payload)}-byte message exceeds the "
                               f"{self._bus.max_payload_bytes}-byte limit of zenoh's low-latency transport")
        t = time.monotonic()
        self._publisher.put(payload)
        self._bus.published[self.topic.suffix] = self._bus.published.get(self.topic.suffix, 0) + 1
        return t


class Inbox:
    """Messages of one topic received by a node, decoded in the node's loop.

    The zenoh callback only stamps the arrival time and appends the raw payload to a queue.
    :meth:`get`
    decodes and validates (including that the message's ``run_id`` is the run of its key);
    invalid payloads are dropped and counted in :attr:`n_invalid`, with the last reason kept in
    :attr:`last_error`. :attr:`received_t` is the arrival time of the message :meth:`get`
    returned last: a node that reads its inbox only at its own ticks still knows when each
    message came in.
    """

    subscriber: Any = None
    """The zenoh subscriber feeding this inbox (set when a :class:`NodeBus` declares it)."""

    def __init__(self, topic: Topic, run_id: str | None = None) -> None:
        prepare(topic)
        self.topic = topic
        self.run_id = run_id
        self._queue: queue.SimpleQueue[tuple[float, str, bytes]] = queue.SimpleQueue()
        self.n_invalid = 0
        self.last_error = ""
        self.received_t = 0.0

    def _on_sample(self, sample: zenoh.Sample) -> None:
        self._queue.put((time.monotonic(), str(sample.key_expr), sample.payload.to_bytes()))

    def get(self, timeout: float | None = None) -> Any | None:
        """Next valid message, waiting up to ``timeout`` s (``None``: do not wait); ``None`` if none."""
        deadline = None if timeout is None else time.monotonic() + timeout
        while True:
            try:
                if deadline is None:
                    t, key, payload = self._queue.get_nowait()
                else:
                    t, key, payload = self._queue.get(timeout=max(0.0, deadline - time.monotonic()))
            except queue.Empty:
                return None
            msg = self._valid(key, payload)
            if msg is not None:
                self.received_t = t
                return msg

    def _valid(self, key: str, payload: bytes) -> Any | None:
        """The decoded message if ``payload`` on ``key`` is a valid one of this inbox, else ``None`` (counted)."""
        try:
            msg = decode(self.topic, payload)
        except MessageError as err:
            self.n_invalid += 1
            self.last_error = str(err)
            return None
        if self.run_id is not None and getattr(msg, "run_id", self.run_id) != self.run_id:
            self.n_invalid += 1
            self.last_error = (
                f"{self.topic.channel}: run_id {msg.run_id!r} does not match the key's run {self.run_id!r}"
            )
            return None
        if self.topic.per_node and key.rpartition("/")[2] != message_node(msg):
            self.n_invalid += 1
            self.last_error = f"{self.topic.channel}: node {message_node(msg)!r} published under {key!r}"
            return None
        return msg

    def drain(self) -> Iterator[Any]:
        """Every valid message already queued, oldest first."""
        while (msg := self.get()) is not None:
            yield msg


class PolledInbox(Inbox):
    """Messages of one topic that the node's own loop polls for: zenoh queues them in its channel
    (no callback thread, nothing to wake) and :meth:`get` takes what has arrived, validated like
    :class:`Inbox`. :attr:`received_t` is when :meth:`get` took the message: its arrival while the
    node was polling, an upper bound of it otherwise. Read it from one thread only.
    """

    CAPACITY = 4096  # samples zenoh queues before its network thread waits for the reader

    def __init__(self, topic: Topic, run_id: str, session: zenoh.Session) -> None:
        super().__init__(topic, run_id)
        self.subscriber = session.declare_subscriber(key_expr(run_id, topic), zenoh.handlers.FifoChannel(self.CAPACITY))

    def get(self, timeout: float | None = None) -> Any | None:
        """Next valid message already arrived, or ``None``; ``timeout`` must be ``None`` (it never waits)."""
        if timeout is not None:
            raise TypeError("a PolledInbox never waits: poll get() from the node's loop")
        while (sample := self.subscriber.try_recv()) is not None:
            t = time.monotonic()
            msg = self._valid(str(sample.key_expr), sample.payload.to_bytes())
            if msg is not None:
                self.received_t = t
                return msg
        return None


class NewestInbox(PolledInbox):
    """Messages of one topic for a loop that answers only the newest one, without a callback.

    zenoh queues the samples in its own channel and :meth:`newest` blocks in zenoh (the GIL
    released, no poll) until one arrives: the network thread never waits for the GIL and the
    sample reaches the reading thread directly. :meth:`newest` then takes every sample already
    queued, validates them like :class:`Inbox` (invalid ones are dropped and counted) and
    returns the newest valid message with the number of older valid ones it replaced.
    :meth:`wake` makes a blocked :meth:`newest` return from another thread, e.g. on a stop
    request (a sample put with a random payload that never leaves this session). Read it from
    one thread only.
    """

    queued: bool = False
    """Whether the last :meth:`newest` with a poll window found a sample already waiting when the
    window opened (its arrival time is then only known to be earlier than :attr:`received_t`)."""

    def __init__(self, topic: Topic, run_id: str, session: zenoh.Session) -> None:
        super().__init__(topic, run_id, session)
        self._session = session
        self._key = key_expr(run_id, topic)
        self._wake_payload = secrets.token_bytes(16)

    def newest(self, block: bool = True, busy: bool = False,
               poll: tuple[float, float] | None = None) -> tuple[Any | None, int]:
        """(newest valid message, older valid ones skipped) of what has arrived; ``block``: wait until
        something arrives (else return at once); ``busy``: wait by polling zenoh's channel instead of
        sleeping in it (the thread keeps its core: no wake-up latency, a core spent); ``poll``
        (monotonic times [s] ``(start, end)``, with ``block``): sleep until ``start``, poll until
        ``end``, then sleep in zenoh (what arrives before ``start`` waits for it). Polling yields the
        core after each look (``sched_yield``): a thread waiting for it, e.g. the plant's when both
        share it, runs at once instead of after the poller's time slice.

        The message is ``None`` after a :meth:`wake`, when everything that arrived was invalid, or
        when nothing had arrived and ``block`` is false. :attr:`queued` tells whether a sample was
        already waiting when the poll window opened (it arrived at some unknown time before).
        """
        first, self.queued = None, False
        if block and busy:
            while (first := self.subscriber.try_recv()) is None:
                os.sched_yield()
        elif block and poll is not None:
            start, end = poll
            while (remaining := start - time.monotonic()) > 0:
                time.sleep(remaining)
            self.queued = (first := self.subscriber.try_recv()) is not None
            while first is None and time.monotonic() < end:
                os.sched_yield()
                first = self.subscriber.try_recv()
        if first is None:
            first = self.subscriber.recv() if block else self.subscriber.try_recv()
        if first is None:
            return None, 0
        samples = [first]
        while (sample := self.subscriber.try_recv()) is not None:
            samples.append(sample)
        t = time.monotonic()
        newest, n_valid = None, 0
        for sample in samples:
            payload = sample.payload.to_bytes()
            if payload == self._wake_payload:
                continue
            msg = self._valid(str(sample.key_expr), payload)
            if msg is not None:
                newest, n_valid, self.received_t = msg, n_valid + 1, t
        return newest, max(0, n_valid - 1)

    def wake(self) -> None:
        """Make a blocked :meth:`newest` return."""
        self._session.put(self._key, self._wake_payload, allowed_destination=zenoh.Locality.SESSION_LOCAL)

    def get(self, timeout: float | None = None) -> Any | None:
        raise TypeError("a NewestInbox is read with newest()")


@dataclass
class NodeBus:
    """One node's zenoh session: publishers, inboxes, readiness, logs and life-cycle events.

    Use as a context manager; on exit it publishes the ``end`` event with its publish counts,
    undeclares everything and closes the session.
    """

    node: str
    settings: BusSettings
    published: dict[str, int] = field(default_factory=dict)
    session: zenoh.Session | None = None
    _token: Any = None
    _declared: list[Any] = field(default_factory=list)
    _publishers: dict[str, TopicPublisher] = field(default_factory=dict)
    _end_detail: str = ""
    _last_time_s: float = 0.0
    max_payload_bytes: int | float = float("inf")
    """Largest message this session publishes [bytes]: :data:`LOW_LATENCY_MAX_BYTES` on the
    low-latency transport, else no limit of the bus's own (each topic still has its own)."""
    routed: bool = False
    """Whether every message of this session crosses a router (a zenoh client: :func:`client_mode`)."""

    def __enter__(self) -> NodeBus:
        zenoh.try_init_log_from_env()
        config = zenoh_config(self.settings, node_credentials())
        if low_latency(config):
            self.max_payload_bytes = LOW_LATENCY_MAX_BYTES
        self.routed = client_mode(config)
        self.session = open_session(self.settings, self.node, config)
        return self

    def __exit__(self, exc_type: Any, exc: Any, tb: Any) -> None:
        try:
            if self.session is not None and exc_type is None:
                self.event("end", time_s=self._last_time_s, detail=self._end_detail)
                time.sleep(0.05)  # let the end event leave before the links close
        finally:
            for entity in reversed(self._declared):
                try:
                    entity.undeclare()
                except Exception:  # already gone with the session
                    pass
            if self.session is not None:
                self.session.close()
                self.session = None

    @property
    def run_id(self) -> str:
        """The run this node belongs to."""
        return self.settings.run_id

    def publisher(self, topic: Topic) -> TopicPublisher:
        """A counted, validating publisher for ``topic`` (reliable, blocking on congestion, express).

        Every topic is express (never batched), so that a node's messages leave in the order it puts
        them and none waits in a batch when its session closes (docs/node-contract.md).
        """
        if topic.suffix not in self._publishers:
            assert self.session is not None
            pub = self.session.declare_publisher(
                key_expr(self.run_id, topic, self.node),
                congestion_control=zenoh.CongestionControl.BLOCK,
                reliability=zenoh.Reliability.RELIABLE,
                express=True,
            )
            self._declared.append(pub)
            self._publishers[topic.suffix] = TopicPublisher(self, topic, pub)
        return self._publishers[topic.suffix]

    def inbox(self, topic: Topic) -> Inbox:
        """Subscribe to ``topic`` of this run; messages queue until the node reads them."""
        return self._subscribe(Inbox(topic, self.run_id))

    def polled_inbox(self, topic: Topic) -> PolledInbox:
        """Subscribe to ``topic`` of this run for a loop that polls for it (:class:`PolledInbox`)."""
        return self._channel_inbox(PolledInbox, topic)

    def newest_inbox(self, topic: Topic) -> NewestInbox:
        """Subscribe to ``topic`` of this run for a loop that answers only the newest message
        (:class:`NewestInbox`: a blocking wait in zenoh, no callback, no queue hop)."""
        return self._channel_inbox(NewestInbox, topic)

    def _channel_inbox(self, kind: type[PolledInbox], topic: Topic) -> Any:
        assert self.session is not None
        box = kind(topic, self.run_id, self.session)
        self._declared.append(box.subscriber)
        return box

    def _subscribe(self, box: Inbox) -> Inbox:
        # zenoh-python runs a plain callback on a Python thread of its own, not on the network thread:
        # measured faster here than indirect=False, whose network thread must take the GIL itself
        assert self.session is not None
        box.subscriber = self.session.declare_subscriber(key_expr(self.run_id, box.topic), box._on_sample)
        self._declared.append(box.subscriber)
        return box

    def close_inbox(self, box: Inbox) -> None:
        """Undeclare ``box``'s subscriber: nothing more arrives in it. A callback :class:`Inbox`
        can still be read for what had arrived; a :class:`PolledInbox` cannot (read it first)."""
        self._declared.remove(box.subscriber)
        box.subscriber.undeclare()

    def subscribe_raw(self, key: str, callback: Any) -> None:
        """Subscribe ``callback(sample)`` to any key expression (e.g. the recorder's ``meltloop/<run>/**``).

        The callback runs on a zenoh thread: it must only enqueue.
        """
        assert self.session is not None
        self._declared.append(self.session.declare_subscriber(key, callback))

    def ready(self, *, time_s: float = 0.0, config: dict[str, Any] | None = None, total_steps: int | None = None,
              stop: StopFlag | threading.Event | None = None) -> None:
        """Announce readiness: wait for the required nodes, publish the ``start`` event, then
        declare the liveliness token.

        Raises
        ------
        TimeoutError
            If a node of ``settings.require`` is not present within ``REQUIRE_TIMEOUT_S``
            (or ``stop`` is set while waiting).
        """
        if self.settings.require:
            self.wait_for_nodes(list(self.settings.require), stop or threading.Event(), REQUIRE_TIMEOUT_S)
        self.event("start", time_s=time_s, config=config, total_steps=total_steps)
        assert self.session is not None
        self._token = self.session.liveliness().declare_token(liveliness_key(self.run_id, self.node))
        self._declared.append(self._token)

    def wait_for_nodes(self, nodes: list[str], stop: StopFlag | threading.Event, timeout_s: float) -> None:
        """Block until every node in ``nodes`` holds its liveliness token (:func:`wait_for_nodes`)."""
        assert self.session is not None
        wait_for_nodes(self.session, self.run_id, nodes, stop, timeout_s)

    def watch_presence(self, node: str) -> threading.Event:
        """An event set when ``node``'s liveliness token disappears (the node ended or died)."""
        assert self.session is not None
        gone = threading.Event()

        def on_change(sample: zenoh.Sample) -> None:
            if sample.kind == zenoh.SampleKind.DELETE:
                gone.set()

        sub = self.session.liveliness().declare_subscriber(liveliness_key(self.run_id, node), on_change)
        self._declared.append(sub)
        return gone

    def event(
        self,
        kind: str,
        *,
        time_s: float,
        config: dict[str, Any] | None = None,
        total_steps: int | None = None,
        detail: str = "",
    ) -> None:
        """Publish a :class:`RunEvent` of this node (``end`` carries the publish counts so far)."""
        self._last_time_s = max(self._last_time_s, time_s)
        pub = self.publisher(RUN_EVENTS)
        counts = dict(self.published)
        counts[RUN_EVENTS.suffix] = counts.get(RUN_EVENTS.suffix, 0) + 1  # this event itself
        pub.put(
            RunEvent(
                run_id=self.run_id,
                node=self.node,
                event=kind,  # type: ignore[arg-type]
                time_s=time_s,
                config_json=json.dumps(config, sort_keys=True, default=str) if config else "",
                total_steps=total_steps,
                published=counts if kind == "end" else {},
                detail=detail[:2000],
            )
        )

    def end_detail(self, detail: str) -> None:
        """Text carried by the ``end`` event published on exit (e.g. a summary)."""
        self._end_detail = detail

    def log(self, level: LogLevel, text: str, *, time_s: float = 0.0) -> None:
        """Publish a ``foxglove.Log`` line (process-time stamped) and mirror it on stderr."""
        self._last_time_s = max(self._last_time_s, time_s)
        self.publisher(LOG).put(
            Log(timestamp=Timestamp.from_seconds(time_s), level=level, message=text[:8000], name=self.node)
        )
        print(f"{level.name.lower()}: {text}", flush=True)


def single_threaded_blas() -> None:
    """Run every BLAS of this process on the calling thread (``threadpoolctl``), for the nodes of a
    fast loop (a free-running plant, the controller): call it before any numerical work.

    Their matrices are small, and with two or more threads OpenBLAS leaves its workers spinning for
    a while after each call: at the start of a fast loop they take the core the loop's own threads
    need, and its first steps miss their deadlines (``docs/realtime.md``, "The loop's first 200
    steps").
    """
    import threadpoolctl

    threadpoolctl.threadpool_limits(1, user_api="blas")


def run_node(prog: str, node: str, settings: BusSettings, body: Callable[[NodeBus], int]) -> int:
    """Run ``body(bus)`` inside ``node``'s :class:`NodeBus`: the one place a node main turns a
    session failure into one line and an exit status.

    Returns ``body``'s status; 2 (naming the key) for a zenoh configuration that cannot be
    loaded, 1 for a hub that cannot be reached, a required node that never appeared, or a message
    the node could not publish (e.g. too large for the low-latency transport).
    """
    from messages.cli import exit_error, exit_usage

    try:
        with NodeBus(node, settings) as bus:
            return body(bus)
    except UsageError as err:
        return exit_usage(prog, err)
    except (TimeoutError, ConnectionError, MessageError) as err:
        return exit_error(prog, err)
