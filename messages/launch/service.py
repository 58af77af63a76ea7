"""The launch service: one run's hub, its nodes in order, supervision until the run ends.

The hub is a zenoh session of the supervising process, listening on the run's endpoint. By
default it is an authenticating **router**: the run gets fresh credentials
(:class:`messages.auth.RunCredentials`), each node its own identity through the environment,
and the hub's access control lets each node publish only its own keys. Nodes are started in
order, each waited for (its liveliness token, :func:`messages.bus.wait_for_nodes`) before the
next; the run ends when a main node exits 0 and the others follow, when any node fails, or on a
stop request; then every node is stopped, last started first.
"""

from __future__ import annotations

import contextlib
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TextIO

from messages.auth import RunCredentials
from messages.bus import SUPERVISOR_ENV, BusSettings, StopFlag, wait_for_nodes, zenoh_config
from messages.cli import UsageError
from messages.launch.node import NodeProcess, NodeSpec
from messages.launch.progress import ProgressObserver


def free_loopback_endpoint() -> str:
    """A zenoh TCP endpoint on a currently free loopback port (the run's hub)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def writable_recording(path: Path) -> Path:
    """``path`` if its folder exists or can be made and is writable (else a usage error naming ``--out``)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {path}: cannot create its folder: {err.strerror or err}") from None
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise UsageError(f"--out {path}: folder {path.parent} is not writable")
    return path


class RunFailed(RuntimeError):
    """The run could not start or a node failed: reported in one line, exit status 1."""


@dataclass
class LaunchService:
    """Spawns, watches and stops the nodes of one run.

    Attributes
    ----------
    run_id : str
        The run's key namespace.
    hub : str
        zenoh endpoint the hub listens on and every node connects to.
    zenoh_config : Path or None
        A zenoh configuration file for the hub and every node; it then defines security
        (no generated credentials).
    authenticate : bool
        Per-run credentials and access control (default). Off: an open peer hub on loopback.
    ready_timeout_s : float
        How long a node may take to become ready [s].
    finish_grace_s : float
        How long the other nodes may take to end after a main node finished [s].
    """

    run_id: str
    hub: str
    zenoh_config: Path | None = None
    authenticate: bool = True
    ready_timeout_s: float = 120.0
    finish_grace_s: float = 15.0
    progress: bool = False
    out: TextIO = sys.stdout
    nodes: list[NodeProcess] = field(default_factory=list)
    _lock: threading.Lock = field(default_factory=threading.Lock)
    _observer: ProgressObserver | None = None

    def say(self, text: str) -> None:
        """Print a supervisor line, ``[launch] ...``."""
        self._emit(f"[launch] {text}")

    def _emit(self, line: str) -> None:
        with self._lock:
            if self._observer is not None:
                self._observer.writer(self._print)(line)
            else:
                self._print(line)

    def _print(self, line: str) -> None:
        print(line, file=self.out, flush=True)

    def run(self, specs: list[NodeSpec], stop: StopFlag) -> int:
        """Start ``specs`` in order, supervise until the run ends, stop everything.

        Returns 0 (run ended normally), 1 (a node failed), or 128 + the signal number of a
        stop request (130 SIGINT, 143 SIGTERM).

        Raises
        ------
        RunFailed
            If the hub cannot be opened.
        """
        import zenoh

        with contextlib.ExitStack() as stack:
            credentials = None
            if self.authenticate and self.zenoh_config is None:
                credentials = stack.enter_context(RunCredentials(self.run_id, {s.name: s.roles for s in specs}))
            config = zenoh_config(BusSettings(run_id=self.run_id, connect=(), listen=(self.hub,),
                                              zenoh_config=self.zenoh_config))
            if credentials is not None:
                config.insert_json5("mode", '"router"')
                for key, value in credentials.hub_settings().items():
                    config.insert_json5(key, value)
            try:
                session = stack.enter_context(zenoh.open(config))
            except zenoh.ZError as err:
                raise RunFailed(f"cannot open the run's hub on {self.hub}: {str(err).split(' at ')[0]}") from None
            self.say(f"hub {self.hub}: " + ("authenticating router, per-node access control" if credentials
                                             else "no generated credentials"))
            if self.progress:
                self._observer = ProgressObserver(session, self.run_id)
                stack.callback(self._observer.close)
            stack.callback(self.stop_all)
            try:
                for spec in specs:
                    env = {SUPERVISOR_ENV: str(os.getpid()), **(credentials.env(spec.name) if credentials else {})}
                    node = NodeProcess.spawn(spec, self.run_id, self.hub, env, self._emit, self.say)
                    self.nodes.append(node)
                    if spec.wait_ready:
                        self._wait_ready(session, node, stop)
                return self._supervise(stop)
            except RunFailed as err:
                self.say(f"error: {err}; stopping the run")
                return 1
            except TimeoutError as err:
                if stop.is_set():
                    return self._stopped(stop)
                self.say(f"error: {err}; stopping the run")
                return 1

    def _wait_ready(self, session, node: NodeProcess, stop: StopFlag) -> None:
        def check() -> None:
            if node.poll() is not None:
                raise RunFailed(f"node {node.name} exited with status {node.poll()} before it was ready")

        wait_for_nodes(session, self.run_id, [node.name], stop, self.ready_timeout_s, check)

    def _stopped(self, stop: StopFlag) -> int:
        self.say(f"{stop.signal_name or 'stop requested'}; stopping the nodes")
        return 143 if stop.signal_name == "SIGTERM" else 130

    def _supervise(self, stop: StopFlag) -> int:
        finished_at: float | None = None
        while True:
            if stop.is_set():
                return self._stopped(stop)
            for node in self.nodes:
                code = node.poll()
                if code not in (None, 0):
                    self.say(f"error: node {node.name} exited with status {code}; stopping the run")
                    return 1
                if code == 0 and node.spec.main and finished_at is None:
                    finished_at = time.monotonic()
            if all(n.poll() == 0 for n in self.nodes):
                return 0
            if finished_at is not None and time.monotonic() - finished_at > self.finish_grace_s:
                late = [n.name for n in self.nodes if n.poll() is None]
                self.say(f"error: {', '.join(late)} still running {self.finish_grace_s:.0f} s after the run finished")
                return 1
            if self._observer is not None:
                self._observer.poll()
            stop.wait(0.05)

    def stop_all(self) -> None:
        """Stop every running node, last started first."""
        for node in reversed(self.nodes):
            node.stop()
