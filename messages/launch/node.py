"""One node of a run: its declarative spec and the process that runs it.

Like ros2/launch's ``ExecuteLocal``: one object per process that spawns it, relays its output
with a ``[name]`` prefix, and stops it by escalating SIGINT -> SIGTERM -> SIGKILL after named
timeouts, with a log line on each escalation.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import threading
import tomllib
from collections.abc import Callable, Mapping
from dataclasses import dataclass, fields
from pathlib import Path

from messages.auth import ROLES
from messages.cli import UsageError

_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_.-")


@dataclass(frozen=True)
class NodeSpec:
    """One node of a run.

    Attributes
    ----------
    name : str
        Node name: the ``[name]`` output prefix, its zenoh user and its liveliness token
        ``.../alive/<name>``.
    module : str
        Python module run as ``python -m module``.
    args : tuple of str
        Its arguments (the launch service appends ``--run-id <run> --connect <hub>``).
    wait_ready : bool
        Wait for the node's liveliness token before starting the next node.
    main : bool
        The run is over when a main node exits 0 (the others then get time to end by themselves).
    roles : tuple of str
        What it may publish besides its own events and log (:data:`messages.auth.ROLES`):
        ``plant`` the ``plant/...`` topics, ``controller`` the ``controller/...`` topics.
        Default: the name, if it is a role.
    """

    name: str
    module: str
    args: tuple[str, ...] = ()
    wait_ready: bool = True
    main: bool = False
    roles: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if not self.name or not set(self.name) <= _NAME_CHARS or self.name[0] in "_.-":
            raise UsageError(f"invalid node name {self.name!r}")
        if not self.module or not all(part.isidentifier() for part in self.module.split(".")):
            raise UsageError(f"invalid module {self.module!r} for node {self.name!r}")
        if not set(self.roles) <= set(ROLES):
            raise UsageError(f"invalid roles {list(self.roles)} for node {self.name!r}; "
                             f"choose among {', '.join(ROLES)}")
        if not self.roles and self.name in ROLES:
            object.__setattr__(self, "roles", (self.name,))

    def command(self, run_id: str, hub: str) -> list[str]:
        """The node's command line, with the arguments the launch service appends."""
        return [sys.executable, "-u", "-m", self.module, *self.args, "--run-id", run_id, "--connect", hub]


def load_node_list(path: Path) -> list[NodeSpec]:
    """Read a declarative node list: TOML with ``[[node]]`` tables (the fields of :class:`NodeSpec`)."""
    try:
        entries = tomllib.loads(path.read_text()).get("node")
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise UsageError(f"--nodes {path}: {getattr(err, 'strerror', None) or err}") from None
    if not isinstance(entries, list) or not entries or not all(isinstance(e, dict) for e in entries):
        raise UsageError(f"--nodes {path}: expected one or more [[node]] tables")
    known = {f.name for f in fields(NodeSpec)}
    specs = []
    for entry in entries:
        if set(entry) - known:
            raise UsageError(f"--nodes {path}: unknown node keys {sorted(set(entry) - known)}; known: {sorted(known)}")
        if missing := [k for k in ("name", "module") if k not in entry]:
            raise UsageError(f"--nodes {path}: node entry without {missing[0]!r}")
        specs.append(NodeSpec(name=entry["name"], module=entry["module"],
                              args=tuple(str(a) for a in entry.get("args", [])),
                              wait_ready=bool(entry.get("wait_ready", True)), main=bool(entry.get("main", False)),
                              roles=tuple(entry.get("roles", ()))))
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
        process = subprocess.Popen(
            spec.command(run_id, hub), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, env={**os.environ, "PYTHONUNBUFFERED": "1", **env}, start_new_session=True,
        )
        relay = threading.Thread(target=_relay, args=(spec.name, process.stdout, emit), daemon=True)
        relay.start()
        say(f"started {spec.name} (pid {process.pid}): python -m {spec.module} "
            f"{' '.join(spec.args + ('--run-id', run_id, '--connect', hub))}")
        return cls(spec, process, relay, say)

    @property
    def name(self) -> str:
        """The node's name."""
        return self.spec.name

    def poll(self) -> int | None:
        """The exit status, or ``None`` while running."""
        return self.process.poll()

    def stop(self) -> None:
        """Stop the node: SIGINT, then SIGTERM, then SIGKILL, each after its timeout."""
        escalation = ((signal.SIGINT, self.sigint_timeout_s), (signal.SIGTERM, self.sigterm_timeout_s),
                      (signal.SIGKILL, 5.0))
        for sig, wait_s in escalation:
            if self.process.poll() is not None:
                break
            if sig != signal.SIGINT:
                self.say(f"{self.name} did not stop within its timeout; sending {sig.name}")
            try:
                self.process.send_signal(sig)
                self.process.wait(timeout=wait_s)
            except ProcessLookupError:
                break
            except subprocess.TimeoutExpired:
                continue
        self.relay.join(timeout=2.0)


def _relay(name: str, stream, emit: Callable[[str], None]) -> None:
    for line in stream:
        emit(f"[{name}] {line.rstrip()}")
