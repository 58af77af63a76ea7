"""Live view: serve a running loop over the Foxglove WebSocket protocol (``foxglove-sdk``).

The ``live`` node subscribes to every contract topic of its run and serves them to Foxglove on
``ws://127.0.0.1:8765`` (loopback by default). The channels are the MCAP recording's: the same
names (``/plant/state``, ``/controller/command``, ...), the same schemas (name and
``jsonschema`` bytes from :func:`messages.codec.json_schema`, as :mod:`messages.recorder`
writes them), message encoding ``json`` with the original JSON bytes as payload, and log time =
the message's **process time** (:func:`messages.recorder.log_time_ns`), so the shipped layout
``docs/foxglove-layout.json`` shows a live run exactly as it shows its recording.

It never slows the loop:

- zenoh callbacks only filter and enqueue: a topic no client is subscribed to is not even copied,
  and ``/plant/temperature`` images are decimated there to at most ``--image-max-hz`` per second
  of wall clock (images arriving sooner after the last one kept are skipped before their bytes
  are copied);
- the queue is bounded (``--queue-size``) and drops its oldest item when full, counting it;
- decoding and validation (schema, run id, publishing node — invalid messages are dropped and
  counted, as the recorder does) happen in the node's own loop;
- publishing to clients never blocks: the SDK keeps a bounded backlog per client and drops its
  oldest messages for a slow client;
- the loop takes what arrived in batches at most every 20 ms, and the process runs at niceness
  ``--nice`` (10), so the loop's own nodes get the CPU first when it is scarce.

It publishes no contract topic (no role), only its own start/end events and log lines. It ends
when the plant's liveliness token goes (after draining what already arrived, ``--drain-s``), or
on SIGINT/SIGTERM, with exit status 0; 2 for a bad command line or a port it cannot listen on
(one line naming ``--port``); 1 if the hub cannot be reached.

Run: ``python -m messages.live --run-id RUN --connect HUB [--port 8765]``, or
``python launch.py --live``; then open ``ws://127.0.0.1:8765`` in Foxglove (``docs/live.md``).

Access: the view serves on loopback by default. With a token in the environment
(:data:`TOKEN_ENV`, never on the command line, where other users could read it) a client must
put it in the URL it opens, ``ws://HOST:PORT/?token=TOKEN`` (Foxglove keeps the query when it
connects); others get HTTP 401. A ``--host`` other machines can reach needs the token. The token
is checked by a small TCP front (:class:`TokenGate`) of the Foxglove server, which then listens
on a loopback port of its own: it keeps other machines out, not other users of this one.
"""

from __future__ import annotations

import argparse
import contextlib
import hmac
import json
import os
import socket
import threading
import time
from collections import Counter, deque
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import parse_qs, urlsplit

from messages.bus import NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args, run_node
from messages.cli import ArgumentParser, UsageError, exit_usage, run_main
from messages.codec import MessageError, decode, json_schema
from messages.foxglove import LogLevel
from messages.hub import is_loopback_host
from messages.recorder import log_time_ns
from messages.topics import PLANT_TEMPERATURE, TOPICS, Topic, key_expr, message_node

NODE_NAME = "live"
DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
DEFAULT_IMAGE_MAX_HZ = 30.0
DEFAULT_QUEUE_SIZE = 4096
CLIENT_BACKLOG = 1024
"""Messages buffered per WebSocket client before the SDK drops that client's oldest ones."""
POLL_S = 0.1
BATCH_S = 0.02
"""Least time between two batches of the loop: at most 50 wake-ups a second, whatever the message rate."""
DEFAULT_NICE = 10
TOKEN_ENV = "MELTLOOP_LIVE_TOKEN"
"""Environment variable with the token a client must give (``?token=``); unset or empty: none."""
HEAD_TIMEOUT_S = 5.0
"""How long a client may take to send its HTTP upgrade request to the token gate."""
MAX_HEAD_BYTES = 16 * 1024


@dataclass(frozen=True)
class LiveSettings:
    """What the live node serves and how (validated command-line options)."""

    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    image_max_hz: float = DEFAULT_IMAGE_MAX_HZ
    queue_size: int = DEFAULT_QUEUE_SIZE
    plant: str = "plant"
    drain_s: float = 0.05
    nice: int = DEFAULT_NICE
    token: str = field(default="", repr=False)

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise UsageError(f"--port must be in 0..65535 (0: any free port), got {self.port}")
        if not self.image_max_hz > 0:
            raise UsageError(f"--image-max-hz must be > 0, got {self.image_max_hz}")
        if self.queue_size < 1:
            raise UsageError(f"--queue-size must be >= 1, got {self.queue_size}")
        if not 0 <= self.drain_s <= 60:
            raise UsageError(f"--drain-s must be in [0, 60], got {self.drain_s}")
        if not self.host:
            raise UsageError("--host must not be empty")
        if not 0 <= self.nice <= 19:
            raise UsageError(f"--nice must be in 0..19, got {self.nice}")
        if not self.token and not is_loopback_host(self.host):
            raise UsageError(f"--host {self.host}: other machines can reach the view, so it needs a token: set "
                             f"{TOKEN_ENV} (clients then open ws://HOST:PORT/?token=TOKEN)")


def check_port(port: int, host: str = "127.0.0.1") -> None:
    """Refuse a port already taken on ``host`` before a run starts (:class:`UsageError` naming ``--live``)."""
    import socket

    with socket.socket() as sock:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
        try:
            sock.bind((host, port))
        except OSError as err:
            raise UsageError(f"--live {port}: cannot serve on {host}:{port}: {err.strerror or err}") from None


def schema_bytes(topic: Topic) -> bytes:
    """The ``jsonschema`` data of ``topic``'s channel, byte for byte what the recorder writes."""
    return json.dumps(json_schema(topic)).encode()


class DropOldestQueue:
    """A bounded queue filled by zenoh callbacks and emptied by the node's loop.

    When full, appending drops the oldest item. :attr:`dropped` is exact: everything put that
    was neither taken nor is still queued.
    """

    def __init__(self, size: int) -> None:
        self._items: deque[Any] = deque(maxlen=size)
        self._wake = threading.Event()
        self.n_put = 0
        self.n_taken = 0

    def put(self, item: Any) -> None:
        """Append ``item`` (from a zenoh thread); never blocks."""
        self._items.append(item)
        self.n_put += 1
        if not self._wake.is_set():
            self._wake.set()

    def take_all(self, timeout: float) -> list[Any]:
        """Everything queued, oldest first, waiting up to ``timeout`` s for something."""
        self._wake.wait(timeout)
        self._wake.clear()  # before draining: an item put from now on sets it again
        taken = []
        while True:
            try:
                taken.append(self._items.popleft())
            except IndexError:
                break
        self.n_taken += len(taken)
        return taken

    def wake(self) -> None:
        """End a :meth:`take_all` wait early (e.g. the run ended)."""
        self._wake.set()

    def __len__(self) -> int:
        return len(self._items)

    @property
    def dropped(self) -> int:
        """Items dropped because the queue was full."""
        return max(0, self.n_put - self.n_taken - len(self._items))


class RateGate:
    """Lets at most one event through per ``1 / max_hz`` s of ``clock`` (wall clock by default)."""

    def __init__(self, max_hz: float, clock: Any = time.monotonic) -> None:
        self.period_s = 1.0 / max_hz
        self._clock = clock
        self._last: float | None = None
        self.n_skipped = 0

    def admit(self) -> bool:
        """Whether the event now passes (and then restarts the period)."""
        now = self._clock()
        if self._last is not None and now - self._last < self.period_s:
            self.n_skipped += 1
            return False
        self._last = now
        return True


def _port_error(settings: LiveSettings, reason: str) -> UsageError:
    if "in use" in reason.lower():
        reason = "address already in use (another live view? choose another --port, 0 for any free one)"
    return UsageError(f"--port {settings.port}: cannot serve on {settings.host}:{settings.port}: {reason}")


class TokenGate:
    """A TCP front of a WebSocket server: admits a client whose HTTP upgrade request targets a URL
    with ``token=<token>`` in its query, then relays the bytes both ways unchanged; any other
    client gets ``401 Unauthorized``.

    Raises
    ------
    OSError
        If it cannot listen on ``host:port``.
    """

    def __init__(self, host: str, port: int, token: str, inner_port: int) -> None:
        self._token = token.encode()
        self._inner_port = inner_port
        family = socket.AF_INET6 if ":" in host else socket.AF_INET
        self._listener = socket.create_server((host.strip("[]"), port), family=family)
        self.port: int = self._listener.getsockname()[1]
        self._open: set[socket.socket] = set()
        self._lock = threading.Lock()
        threading.Thread(target=self._accept, name="token-gate", daemon=True).start()

    def admits(self, head: bytes) -> bool:
        """Whether the request ``head`` (request line and headers) carries the token."""
        parts = head.split(b"\r\n", 1)[0].decode("latin-1").split(" ")
        target = parts[1] if len(parts) == 3 else ""
        given = parse_qs(urlsplit(target).query).get("token", [""])[0]
        return hmac.compare_digest(given.encode(), self._token)

    def _accept(self) -> None:
        while True:
            try:
                client, _ = self._listener.accept()
            except OSError:  # closed by stop()
                return
            threading.Thread(target=self._serve, args=(client,), daemon=True).start()

    def _serve(self, client: socket.socket) -> None:
        with self._lock:
            self._open.add(client)
        inner: socket.socket | None = None
        try:
            client.settimeout(HEAD_TIMEOUT_S)
            head = b""
            while b"\r\n\r\n" not in head and len(head) <= MAX_HEAD_BYTES:
                chunk = client.recv(4096)
                if not chunk:
                    return
                head += chunk
            if not self.admits(head):
                client.sendall(b"HTTP/1.1 401 Unauthorized\r\nContent-Length: 0\r\nConnection: close\r\n\r\n")
                return
            client.settimeout(None)
            inner = socket.create_connection(("127.0.0.1", self._inner_port))
            with self._lock:
                self._open.add(inner)
            inner.sendall(head)
            threading.Thread(target=_relay_bytes, args=(inner, client), daemon=True).start()
            _relay_bytes(client, inner)
        except OSError:
            pass
        finally:
            for sock in (client, inner):
                if sock is not None:
                    with self._lock:
                        self._open.discard(sock)
                    sock.close()

    def stop(self) -> None:
        """Stop listening and close every relayed connection."""
        self._listener.close()
        with self._lock:
            for sock in self._open:
                with contextlib.suppress(OSError):
                    sock.shutdown(socket.SHUT_RDWR)


def _relay_bytes(source: socket.socket, target: socket.socket) -> None:
    """Copy ``source`` to ``target`` until either closes; then shut both down."""
    try:
        while chunk := source.recv(65536):
            target.sendall(chunk)
    except OSError:
        pass
    finally:
        for sock in (source, target):
            with contextlib.suppress(OSError):
                sock.shutdown(socket.SHUT_RDWR)


class LiveServer:
    """The Foxglove WebSocket server and one channel per contract topic, in a context of its own;
    with a token, behind a :class:`TokenGate` (the server itself then on a free loopback port).

    Raises
    ------
    UsageError
        If the server cannot listen on ``host:port`` (one line naming ``--port``).
    """

    def __init__(self, settings: LiveSettings, name: str) -> None:
        import foxglove

        self._context = foxglove.Context()
        # the channels exist before the server listens: a client that connects at once sees them all
        self.channels: dict[str, Any] = {
            topic.suffix: foxglove.Channel(
                topic.channel,
                schema=foxglove.Schema(name=topic.schema_name, encoding="jsonschema", data=schema_bytes(topic)),
                message_encoding="json",
                context=self._context,
            )
            for topic in TOPICS.values()
        }
        host, port = ("127.0.0.1", 0) if settings.token else (settings.host, settings.port)
        try:
            self.server = foxglove.start_server(name=name, host=host, port=port,
                                                context=self._context, message_backlog_size=CLIENT_BACKLOG)
        except RuntimeError as err:
            raise _port_error(settings, str(err).removeprefix("FoxgloveError: ")) from None
        self.gate: TokenGate | None = None
        if settings.token:
            try:
                self.gate = TokenGate(settings.host, settings.port, settings.token, self.server.port)
            except OSError as err:
                self.server.stop()
                raise _port_error(settings, err.strerror or str(err)) from None

    @property
    def port(self) -> int:
        """The port clients connect to (the chosen one when ``--port 0``)."""
        return self.gate.port if self.gate is not None else self.server.port

    def watched(self, topic: Topic) -> bool:
        """Whether a client is subscribed to ``topic``'s channel."""
        return self.channels[topic.suffix].has_sinks()

    def publish(self, topic: Topic, payload: bytes, log_time_ns: int) -> None:
        """Send one message to the subscribed clients (never blocks)."""
        self.channels[topic.suffix].log(payload, log_time=log_time_ns)

    def stop(self) -> None:
        """Close the channels and stop the server (clients are disconnected)."""
        for channel in self.channels.values():
            channel.close()
        if self.gate is not None:
            self.gate.stop()
        self.server.stop()


class Forwarder:
    """From zenoh samples to Foxglove messages: the callbacks' and the loop's halves, with counts."""

    def __init__(self, server: LiveServer, run_id: str, queue_size: int, image_max_hz: float) -> None:
        self.server = server
        self.run_id = run_id
        self.queue = DropOldestQueue(queue_size)
        self.images = RateGate(image_max_hz)
        self.sent: Counter[str] = Counter()
        self.invalid: Counter[str] = Counter()
        self.unwatched = 0
        self.last_error = ""

    def callback(self, topic: Topic) -> Any:
        """The zenoh callback of ``topic``: filter cheaply, copy, enqueue; nothing else."""
        server, queue, images = self.server, self.queue, self.images

        def on_sample(sample: Any) -> None:
            if not server.watched(topic):
                self.unwatched += 1
                return
            if topic is PLANT_TEMPERATURE and not images.admit():
                return
            key = str(sample.key_expr) if topic.per_node else ""
            queue.put((topic, key, sample.payload.to_bytes()))

        return on_sample

    def forward(self, topic: Topic, key: str, payload: bytes) -> int | None:
        """Decode and check one queued message, then publish it; its log time [ns], ``None`` if it was
        dropped as invalid."""
        try:
            msg = decode(topic, payload)
            if getattr(msg, "run_id", self.run_id) != self.run_id:
                raise MessageError(f"{topic.channel}: run_id {msg.run_id!r} is not the run {self.run_id!r}")
            if topic.per_node and key.rpartition("/")[2] != message_node(msg):
                raise MessageError(f"{topic.channel}: node {message_node(msg)!r} published under {key!r}")
        except MessageError as err:
            self.invalid[topic.channel] += 1
            self.last_error = str(err)
            return None
        log_time = log_time_ns(msg)
        self.server.publish(topic, payload, log_time)
        self.sent[topic.channel] += 1
        return log_time

    def summary(self) -> str:
        """Counts for the node's last log line and ``end`` event."""
        sent = ", ".join(f"{ch} {n}" for ch, n in sorted(self.sent.items())) or "nothing"
        return (f"sent {sent}; {self.images.n_skipped} images decimated, {self.queue.dropped} dropped "
                f"(queue full), {sum(self.invalid.values())} invalid, {self.unwatched} not watched; "
                f"{time.process_time():.2f} s CPU")


def serve(bus: NodeBus, server: LiveServer, settings: LiveSettings, stop: StopFlag) -> int:
    """Forward the run's messages to the Foxglove clients until the plant goes or a stop is requested."""
    forwarder = Forwarder(server, bus.run_id, settings.queue_size, settings.image_max_hz)
    for topic in TOPICS.values():
        bus.subscribe_raw(key_expr(bus.run_id, topic), forwarder.callback(topic))
    plant_gone = bus.watch_presence(settings.plant)
    threading.Thread(target=lambda: (plant_gone.wait(), forwarder.queue.wake()), daemon=True).start()
    config = {"host": settings.host, "port": server.port, "image_max_hz": settings.image_max_hz,
              "queue_size": settings.queue_size, "plant": settings.plant, "drain_s": settings.drain_s,
              "nice": settings.nice, "client_backlog": CLIENT_BACKLOG, "token_required": bool(settings.token)}
    bus.ready(config=config, stop=stop)
    query = f"/?token=${TOKEN_ENV}" if settings.token else ""
    print(f"serving run {bus.run_id} on ws://{settings.host}:{server.port}{query} (Foxglove WebSocket; "
          f"images <= {settings.image_max_hz:g} Hz)", flush=True)
    last_time_ns = 0
    gone_at: float | None = None
    reported_drops = reported_invalid = False
    timeout_s = POLL_S
    while not stop.is_set():
        batch = forwarder.queue.take_all(timeout_s)
        for topic, key, payload in batch:
            last_time_ns = max(last_time_ns, forwarder.forward(topic, key, payload) or 0)
        if batch and gone_at is None:
            time.sleep(BATCH_S)  # let messages gather: few wake-ups of this process while the loop runs
        if forwarder.queue.dropped and not reported_drops:
            reported_drops = True
            bus.log(LogLevel.WARNING, f"live view falling behind: {forwarder.queue.dropped} messages dropped "
                    "(queue full); further drops are only counted", time_s=last_time_ns / 1e9)
        if forwarder.invalid and not reported_invalid:
            reported_invalid = True
            bus.log(LogLevel.WARNING, f"invalid message dropped: {forwarder.last_error} (further ones are only "
                    "counted)", time_s=last_time_ns / 1e9)
        if plant_gone.is_set():
            gone_at = gone_at or time.monotonic()
            timeout_s = settings.drain_s - (time.monotonic() - gone_at)
            if timeout_s <= 0 and not len(forwarder.queue):
                break
            timeout_s = max(timeout_s, 0.0)
    reason = "stopped" if stop.is_set() else f"plant {settings.plant!r} went away"
    summary = f"{reason}; {forwarder.summary()}"
    bus.log(LogLevel.INFO, summary, time_s=last_time_ns / 1e9)
    bus.end_detail(summary)
    return 0


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``python -m messages.live``."""
    parser = ArgumentParser(prog="python -m messages.live", description=__doc__.split("\n\n")[0])
    parser.add_argument("--host", default=DEFAULT_HOST,
                        help="address to serve on (default: %(default)s, this machine only; another one needs "
                             f"a token in {TOKEN_ENV}, which clients give as ws://HOST:PORT/?token=TOKEN)")
    parser.add_argument("--port", type=int, default=DEFAULT_PORT,
                        help="WebSocket port (default: %(default)s; 0: any free port, printed)")
    parser.add_argument("--image-max-hz", type=float, default=DEFAULT_IMAGE_MAX_HZ,
                        help="most /plant/temperature images sent per second of wall clock (default: %(default)g)")
    parser.add_argument("--queue-size", type=int, default=DEFAULT_QUEUE_SIZE,
                        help="messages held between the zenoh callbacks and the loop; the oldest is dropped "
                             "when full (default: %(default)s)")
    parser.add_argument("--plant", default="plant",
                        help="node whose end (liveliness token gone) ends the live view (default: %(default)s)")
    parser.add_argument("--nice", type=int, default=DEFAULT_NICE,
                        help="scheduling niceness of this process, so that the loop's nodes get the CPU first "
                             "(default: %(default)s; 0: as the other nodes)")
    parser.add_argument("--drain-s", type=float, default=0.05,
                        help="after the plant ended, forward what still arrives for this long [s] (default: "
                             "%(default)s)")
    add_bus_arguments(parser)
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.live``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        bus_settings = bus_settings_from_args(args)
        settings = LiveSettings(args.host, args.port, args.image_max_hz, args.queue_size, args.plant, args.drain_s,
                                args.nice, os.environ.get(TOKEN_ENV, ""))
        os.nice(settings.nice)  # before any thread starts: zenoh's and the server's threads inherit it
        server = LiveServer(settings, f"meltloop {bus_settings.run_id}")
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = StopFlag()
    try:
        return run_node(parser.prog, NODE_NAME, bus_settings, lambda bus: serve(bus, server, settings, stop))
    finally:
        server.stop()


if __name__ == "__main__":
    run_main(main)
