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
import functools
import os
import socket
import sys
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

from messages.auth import RunCredentials
from messages.bus import SUPERVISOR_ENV, BusSettings, StopFlag, wait_for_nodes, zenoh_config
from messages.cli import UsageError
from messages.hub import router_config
from messages.launch.node import NodeProcess, NodeSpec
from messages.launch.progress import ProgressObserver


def free_loopback_endpoint() -> str:
    """A zenoh TCP endpoint on a currently free loopback port (the run's hub)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def new_recording(path: Path) -> Path:
    """A recording path (or, with no suffix, a folder) that no other run has: ``path``, else
    ``<stem>-2<suffix>``, ``-3``, … — created empty, atomically (``O_EXCL``, ``mkdir``), so that runs
    started in the same second never write one file. Usage error naming ``--out`` as
    :func:`writable_recording`."""
    writable_recording(path)
    candidate, n = path, 1
    while True:
        try:
            if path.suffix:
                os.close(os.open(candidate, os.O_CREAT | os.O_EXCL | os.O_WRONLY, 0o600))
            else:
                candidate.mkdir()
            return candidate
        except FileExistsError:
            n += 1
            candidate = path.with_name(f"{path.stem}-{n}{path.suffix}")
        except OSError as err:
            raise UsageError(f"--out {candidate}: cannot create it: {err.strerror or err}") from None


def reserve_recording(path: Path, overwrite: bool) -> Path:
    """``path``, created empty (mode 0600) unless it exists; an existing file only with
    ``overwrite`` (the recorder then replaces it). Usage error naming ``--out`` otherwise."""
    writable_recording(path)
    try:
        os.close(os.open(path, os.O_CREAT | os.O_WRONLY | (0 if overwrite else os.O_EXCL), 0o600))
    except FileExistsError:
        raise UsageError(f"--out {path}: exists; give --overwrite to replace it") from None
    except OSError as err:
        raise UsageError(f"--out {path}: cannot create it: {err.strerror or err}") from None
    return path


def writable_recording(path: Path) -> Path:
    """``path`` if its folder exists or can be made and is writable (else a usage error naming ``--out``)."""
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise UsageError(f"--out {path}: cannot create its folder: {err.strerror or err}") from None
    if not os.access(path.parent, os.W_OK | os.X_OK):
        raise UsageError(f"--out {path}: folder {path.parent} is not writable")
    return path


@dataclass
class Console:
    """The run's output: node and supervisor lines, one at a time, around the progress bar."""

    out: TextIO = sys.stdout
    observer: ProgressObserver | None = None
    _lock: threading.Lock = field(default_factory=threading.Lock)

    def emit(self, line: str) -> None:
        """Print one line."""
        with self._lock:
            if self.observer is not None:
                self.observer.writer(self._print)(line)
            else:
                self._print(line)

    def _print(self, line: str) -> None:
        print(line, file=self.out, flush=True)


def open_hub(stack: contextlib.ExitStack, run_id: str, endpoint: str, zenoh_file: Path | None,
             roles: dict[str, tuple[str, ...]] | None) -> tuple[Any, RunCredentials | None]:
    """Open the run's hub session (closed with ``stack``): with ``roles`` and no ``zenoh_file``,
    an authenticating router with fresh credentials for those nodes (:mod:`messages.hub`); else a
    plain session from ``zenoh_file`` or the loopback defaults.

    Raises
    ------
    RunFailed
        If the hub cannot listen on ``endpoint``.
    """
    import zenoh

    credentials = None
    if roles is not None and zenoh_file is None:
        credentials = stack.enter_context(RunCredentials(run_id, roles))
        config = router_config(credentials, endpoint)
    else:
        config = zenoh_config(BusSettings(run_id=run_id, connect=(), listen=(endpoint,), zenoh_config=zenoh_file))
    try:
        return stack.enter_context(zenoh.open(config)), credentials
    except zenoh.ZError as err:
        raise RunFailed(f"cannot open the run's hub on {endpoint}: {str(err).split(' at ')[0]}") from None


def verdict(codes: list[tuple[str, int | None, bool]], finished_at: float | None, now_s: float,
            grace_s: float) -> tuple[int | None, float | None, str]:
    """One look at a run's nodes, given as (name, exit status or None, main).

    Returns the run's exit status (``None``: go on), when a main node finished (monotonic s) and,
    for a failure, why: any node failing fails the run; the run is done when every node ended
    with 0; after a main node finished, the others get ``grace_s`` to end by themselves.
    """
    for name, code, main in codes:
        if code not in (None, 0):
            return 1, finished_at, f"node {name} exited with status {code}"
        if code == 0 and main and finished_at is None:
            finished_at = now_s
    if all(code == 0 for _, code, _ in codes):
        return 0, finished_at, ""
    if finished_at is not None and now_s - finished_at > grace_s:
        late = [name for name, code, _ in codes if code is None]
        return 1, finished_at, f"{', '.join(late)} still running {grace_s:.0f} s after the run finished"
    return None, finished_at, ""


class RunFailed(RuntimeError):
    """The run could not start or a node failed: reported in one line, exit status 1."""


@dataclass
class LaunchService:
    """Spawns, watches and stops the nodes of one run.

    ``hub``: the endpoint the hub listens on and every node connects to; ``zenoh_config``: a file
    for the hub and every node, which then defines security; ``authenticate``: per-run
    credentials and access control (default); ``ready_timeout_s`` / ``finish_grace_s`` [s]: how
    long a node may take to become ready / the others to end after a main node finished.
    """

    run_id: str
    hub: str
    zenoh_config: Path | None = None
    authenticate: bool = True
    ready_timeout_s: float = 120.0
    finish_grace_s: float = 15.0
    progress: bool = False
    console: Console = field(default_factory=lambda: Console())
    nodes: list[NodeProcess] = field(default_factory=list)

    def say(self, text: str) -> None:
        """Print a supervisor line, ``[launch] ...``."""
        self.console.emit(f"[launch] {text}")

    def run(self, specs: list[NodeSpec], stop: StopFlag) -> int:
        """Start ``specs`` in order, supervise until the run ends, stop everything; returns 0 (ended
        normally), 1 (a node failed), 130/143 (stopped by SIGINT/SIGTERM). Raises :class:`RunFailed`
        if the hub cannot be opened."""
        with contextlib.ExitStack() as stack:
            session, credentials = open_hub(stack, self.run_id, self.hub, self.zenoh_config,
                                            {s.name: s.roles for s in specs} if self.authenticate else None)
            self.say(f"hub {self.hub}: " + ("authenticating router, per-node access control" if credentials
                                             else "no generated credentials"))
            if self.progress:
                self.console.observer = ProgressObserver(session, self.run_id)
                stack.callback(self.console.observer.close)
            stack.callback(self.stop_all)
            try:
                for spec in specs:
                    env = {SUPERVISOR_ENV: str(os.getpid()), **(credentials.env(spec.name) if credentials else {})}
                    node = NodeProcess.spawn(spec, self.run_id, self.hub, env, self.console.emit, self.say)
                    self.nodes.append(node)
                    if spec.wait_ready:
                        wait_for_nodes(session, self.run_id, [node.name], stop, self.ready_timeout_s,
                                       functools.partial(self._finished_before_ready, node))
                return self._supervise(stop)
            except (RunFailed, ChildProcessError) as err:
                self.say(f"error: {err}; stopping the run")
                return 1
            except TimeoutError as err:
                if stop.is_set():
                    return self._stopped(stop)
                self.say(f"error: {err}; stopping the run")
                return 1

    def _finished_before_ready(self, node: NodeProcess) -> bool:
        """The readiness wait's check for ``node``: whether it already ended with status 0; raises
        :class:`ChildProcessError` if it, or a node started before it without a wait for its readiness,
        ended with another status meanwhile (``node`` may wait for that one)."""
        for other in self.nodes:
            if other is not node and not other.spec.wait_ready:
                code = other.process.poll()
                if code not in (None, 0):
                    raise ChildProcessError(f"node {other.name} exited with status {code} while the launch waited "
                                            f"for {node.name} to be ready")
        return node.finished_before_ready()

    def _stopped(self, stop: StopFlag) -> int:
        self.say(f"{stop.signal_name or 'stop requested'}; stopping the nodes")
        return 143 if stop.signal_name == "SIGTERM" else 130

    def _supervise(self, stop: StopFlag) -> int:
        finished_at: float | None = None
        while not stop.is_set():
            codes = [(n.name, n.poll(), n.spec.main) for n in self.nodes]
            status, finished_at, reason = verdict(codes, finished_at, time.monotonic(), self.finish_grace_s)
            if status is not None:
                if reason:
                    self.say(f"error: {reason}; stopping the run")
                return status
            if self.console.observer is not None:
                self.console.observer.poll()
            stop.wait(0.05)
        return self._stopped(stop)

    def stop_all(self) -> None:
        """Stop every running node, last started first."""
        for node in reversed(self.nodes):
            node.stop()
