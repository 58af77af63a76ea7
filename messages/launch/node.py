"""One node of a run: its declarative spec and the process that runs it.

Like ros2/launch's ``ExecuteLocal``: one object per process that spawns it, relays its output
with a ``[name]`` prefix, and stops it by escalating SIGINT -> SIGTERM -> SIGKILL after named
timeouts, with a log line on each escalation.
"""

from __future__ import annotations

import contextlib
import os
import shlex
import shutil
import signal
import subprocess
import sys
import threading
import time
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from messages.auth import ROLES
from messages.bus import is_name
from messages.cli import UsageError


@dataclass(frozen=True)
class NodeSpec:
    """One node of a run.

    Attributes
    ----------
    name : str
        Node name: the ``[name]`` output prefix, its zenoh user and its liveliness token
        ``.../alive/<name>``.
    module : str
        Python module run as ``python -u -m module`` (empty when ``command`` is given).
    args : tuple of str
        Its arguments (the launch service appends ``--run-id <run> --connect <hub>``).
    wait_ready : bool
        Wait for the node's liveliness token before starting the next node.
    main : bool
        The run is over when a main node exits 0 (the others then get time to end by themselves).
    roles : tuple of str
        What it may publish besides its own events and log, and what it may read
        (:data:`messages.auth.ROLES`, :data:`messages.auth.READS`): ``plant`` publishes the
        ``plant/...`` topics and reads the commands, ``controller`` publishes the
        ``controller/...`` topics and reads the plant state and run events, ``recorder`` and
        ``live`` read everything. Default: the name, if it is a role; without a role a node
        reads no topic.
    command : tuple of str
        Any executable and its first arguments, instead of ``module``: a name is looked up on
        ``PATH``, a path with a ``/`` is taken relative to the working directory.
    """

    name: str
    module: str = ""
    args: tuple[str, ...] = ()
    wait_ready: bool = True
    main: bool = False
    roles: tuple[str, ...] = ()
    command: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not is_name(self.name):
            raise UsageError(f"invalid node name {self.name!r}")
        if not self.module and not self.command:
            raise UsageError(f"node {self.name!r} without 'module' or 'command' (give exactly one)")
        if self.module and self.command:
            raise UsageError(f"node {self.name!r} has both 'module' and 'command' (give exactly one)")
        if self.module and not all(part.isidentifier() for part in self.module.split(".")):
            raise UsageError(f"invalid module {self.module!r} for node {self.name!r}")
        if self.command and shutil.which(self.command[0]) is None:
            raise UsageError(f"node {self.name!r}: 'command' executable {self.command[0]!r} not found "
                             "or not executable")
        if not set(self.roles) <= set(ROLES):
            raise UsageError(f"invalid roles {list(self.roles)} for node {self.name!r}; "
                             f"choose among {', '.join(ROLES)}")
        if not self.roles and self.name in ROLES:
            object.__setattr__(self, "roles", (self.name,))

    def argv(self, run_id: str, hub: str) -> list[str]:
        """The node's full command line, with the arguments the launch service appends."""
        head = list(self.command) if self.command else [sys.executable, "-u", "-m", self.module]
        return [*head, *self.args, "--run-id", run_id, "--connect", hub]


_KEY_TYPES = {"name": str, "module": str, "args": list, "wait_ready": bool, "main": bool, "roles": list,
              "command": list}
_KIND_NAMES = {str: "a string", list: "a list of strings", bool: "true or false"}


def load_node_list(path: Path) -> list[NodeSpec]:
    """Read a declarative node list: TOML with ``[[node]]`` tables (the fields of :class:`NodeSpec`).

    Raises
    ------
    UsageError
        One line naming the file, the node and the offending key.
    """
    try:
        entries = tomllib.loads(path.read_text()).get("node")
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UsageError(f"--nodes {path}: {getattr(err, 'strerror', None) or err}") from None
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise UsageError(f"--nodes {path}: expected one or more [[node]] tables")
    specs = []
    for entry in entries:
        if unknown := sorted(set(entry) - set(_KEY_TYPES)):
            raise UsageError(f"--nodes {path}: unknown node keys {unknown}; known: {sorted(_KEY_TYPES)}")
        if "name" not in entry:
            raise UsageError(f"--nodes {path}: node entry without 'name'")
        where = f"--nodes {path}: node {entry['name']!r}"
        for key, value in entry.items():
            kind = _KEY_TYPES[key]
            if not isinstance(value, kind) or (kind is list and not all(isinstance(v, str) for v in value)):
                raise UsageError(f"{where}: {key!r} must be {_KIND_NAMES[kind]}")
        if "command" in entry and not (entry["command"] and entry["command"][0]):
            raise UsageError(f"{where}: 'command' must name an executable")
        try:
            specs.append(NodeSpec(name=entry["name"], module=entry.get("module", ""),
                                  args=tuple(entry.get("args", ())), wait_ready=entry.get("wait_ready", True),
                                  main=entry.get("main", False), roles=tuple(entry.get("roles", ())),
                                  command=tuple(entry.get("command", ()))))
        except UsageError as err:
            raise UsageError(f"--nodes {path}: {err}") from None
    return specs


@dataclass
class NodeProcess:
    """A spawned node: its process, the thread relaying its output, and how it is stopped.

    Attributes
    ----------
    sigint_timeout_s, sigterm_timeout_s : float
        How long the node may take to stop after SIGINT, then after SIGTERM, before the next
        signal [s].
    """

    spec: NodeSpec
    process: subprocess.Popen[str]
    relay: threading.Thread
    say: Callable[[str], None]
    sigint_timeout_s: float = 4.0
    sigterm_timeout_s: float = 3.0

    @classmethod
    def spawn(cls, spec: NodeSpec, run_id: str, hub: str, env: Mapping[str, str],
              emit: Callable[[str], None], say: Callable[[str], None]) -> NodeProcess:
        """Start the node in its own process session (so a terminal's Ctrl-C reaches only the
        supervisor, which then stops the nodes in order); ``env`` is added to the environment."""
        argv = spec.argv(run_id, hub)
        process = subprocess.Popen(
            argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1", **env}, start_new_session=True,
        )
        relay = threading.Thread(target=_relay, args=(spec.name, process.stdout, emit), daemon=True)
        relay.start()
        say(f"started {spec.name} (pid {process.pid}): {shlex.join(argv)}")
        return cls(spec, process, relay, say)

    @property
    def name(self) -> str:
        """The node's name."""
        return self.spec.name

    def poll(self) -> int | None:
        """The exit status, or ``None`` while running."""
        return self.process.poll()

    def finished_before_ready(self) -> bool:
        """Whether the node has already ended with status 0 (a short run can finish before its
        liveliness token is seen); raise :class:`ChildProcessError` if it ended with another status
        while the launch waited for it to be ready."""
        code = self.process.poll()
        if code not in (None, 0):
            raise ChildProcessError(f"node {self.name} exited with status {code} before it was ready")
        return code == 0

    def stop(self) -> None:
        """Stop the node's process group (the node and anything it started, e.g. a wrapper script's
        children): SIGINT, then SIGTERM, then SIGKILL, each after its timeout, while any of the
        group is left."""
        escalation = ((signal.SIGINT, self.sigint_timeout_s), (signal.SIGTERM, self.sigterm_timeout_s),
                      (signal.SIGKILL, 5.0))
        for sig, wait_s in escalation:
            if not self._group_left():
                break
            if sig != signal.SIGINT:
                self.say(f"{self.name} did not stop within its timeout; sending {sig.name}")
            try:
                os.killpg(self.process.pid, sig)  # its own session: the group id is its pid
            except ProcessLookupError:
                break
            if self._wait_group(wait_s):
                break
        self.relay.join(timeout=2.0)

    def _group_left(self) -> bool:
        """Whether any process of the node's group is still running (the node is reaped first)."""
        self.process.poll()
        return group_running(self.process.pid)

    def _wait_group(self, timeout_s: float) -> bool:
        """Wait up to ``timeout_s`` [s] for the whole group to end; whether it did."""
        deadline = time.monotonic() + timeout_s
        with contextlib.suppress(subprocess.TimeoutExpired):
            self.process.wait(timeout=timeout_s)
        while self._group_left():
            if time.monotonic() >= deadline:
                return False
            time.sleep(0.02)
        return True


def group_running(pgid: int) -> bool:
    """Whether process group ``pgid`` has a process that is not a zombie (an orphan that has
    ended but is not reaped yet counts as ended; without ``/proc``, any member counts)."""
    proc = Path("/proc")
    if not proc.is_dir():
        try:
            os.killpg(pgid, 0)
        except ProcessLookupError:
            return False
        return True
    for entry in proc.iterdir():
        if not entry.name.isdigit():
            continue
        try:
            fields = (entry / "stat").read_text().rpartition(")")[2].split()
        except OSError:
            continue
        if int(fields[2]) == pgid and fields[0] != "Z":  # fields after "(comm)": state, ppid, pgrp
            return True
    return False


def _relay(name: str, stream, emit: Callable[[str], None]) -> None:
    for line in stream:
        emit(f"[{name}] {line.rstrip()}")
