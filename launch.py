"""Start a meltloop run: recorder, controller and plant as separate processes over zenoh.

The run is a declarative list of :class:`NodeSpec` (module + arguments). The supervisor opens
the run's zenoh hub on loopback, spawns each node in order as its own process (never forking a
zenoh session), prefixes its output with ``[node]``, waits for its liveliness token before
starting the next, and ends the whole run when any node fails. Ctrl-C / SIGTERM stops the nodes
in reverse order with SIGINT, then SIGTERM, then SIGKILL, so the recorder finishes its MCAP
last and no process is left behind.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import socket
import subprocess
import sys
import threading
import time
import tomllib
from dataclasses import dataclass, field
from datetime import datetime, timezone
from pathlib import Path
from typing import Any, TextIO

from messages.bus import SUPERVISOR_ENV, BusSettings, zenoh_config
from messages.cli import ArgumentParser, UsageError, exit_usage
from messages.topics import liveliness_key

STOP_ESCALATION_S = (4.0, 3.0)  # wait after SIGINT, then after SIGTERM, before SIGKILL
FINISH_GRACE_S = 15.0  # how long the other nodes may take to end after the plant finished


@dataclass(frozen=True)
class NodeSpec:
    """One node of a run.

    Attributes
    ----------
    name : str
        Node name: the ``[name]`` output prefix and its liveliness token ``.../alive/<name>``.
    module : str
        Python module run as ``python -m module``.
    args : tuple of str
        Its arguments (the supervisor appends ``--run-id`` and ``--connect <hub>``).
    wait_ready : bool
        Wait for the node's liveliness token before starting the next node.
    main : bool
        The run is over when a main node exits 0 (the others then get time to end by themselves).
    """

    name: str
    module: str
    args: tuple[str, ...] = ()
    wait_ready: bool = True
    main: bool = False

    def __post_init__(self) -> None:
        if not self.name or not all(c.isalnum() or c in "_-." for c in self.name):
            raise UsageError(f"invalid node name {self.name!r}")
        if not self.module or not all(part.isidentifier() for part in self.module.split(".")):
            raise UsageError(f"invalid module {self.module!r} for node {self.name!r}")


@dataclass
class RunningNode:
    """A spawned node and the thread that relays its output."""

    spec: NodeSpec
    process: subprocess.Popen[str]
    relay: threading.Thread


@dataclass
class Supervisor:
    """Spawns, watches and stops the nodes of one run."""

    run_id: str
    hub: str
    out: TextIO = sys.stdout
    ready_timeout_s: float = 60.0
    nodes: list[RunningNode] = field(default_factory=list)
    _print_lock: threading.Lock = field(default_factory=threading.Lock)

    def say(self, text: str) -> None:
        """Print a supervisor line, ``[launch] ...``."""
        self._emit(f"[launch] {text}")

    def _emit(self, line: str) -> None:
        with self._print_lock:
            print(line, file=self.out, flush=True)

    def _relay(self, name: str, stream: TextIO) -> None:
        for line in stream:
            self._emit(f"[{name}] {line.rstrip()}")

    def spawn(self, spec: NodeSpec) -> RunningNode:
        """Start one node as its own process (own session, so the terminal's Ctrl-C reaches
        only the supervisor, which then stops the nodes in order)."""
        cmd = [sys.executable, "-u", "-m", spec.module, *spec.args, "--run-id", self.run_id, "--connect", self.hub]
        env = dict(os.environ, PYTHONUNBUFFERED="1", **{SUPERVISOR_ENV: str(os.getpid())})
        process = subprocess.Popen(
            cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
            text=True, bufsize=1, env=env, start_new_session=True,
        )
        relay = threading.Thread(target=self._relay, args=(spec.name, process.stdout), daemon=True)
        relay.start()
        node = RunningNode(spec, process, relay)
        self.nodes.append(node)
        self.say(f"started {spec.name} (pid {process.pid}): python -m {spec.module} {' '.join(spec.args)}")
        return node

    def wait_ready(self, session: Any, node: RunningNode, stop: threading.Event) -> None:
        """Block until the node's liveliness token appears.

        Raises
        ------
        RuntimeError
            If the node exits first, does not become ready in time, or a stop is requested.
        """
        deadline = time.monotonic() + self.ready_timeout_s
        key = liveliness_key(self.run_id, node.spec.name)
        while time.monotonic() < deadline and not stop.is_set():
            if node.process.poll() is not None:
                raise RuntimeError(f"node {node.spec.name} exited with status {node.process.returncode} before it was ready")
            if any(r.ok is not None for r in session.liveliness().get(key, timeout=0.5)):
                return
            stop.wait(0.05)
        if stop.is_set():
            raise RuntimeError("stopped while starting")
        raise RuntimeError(f"node {node.spec.name} not ready after {self.ready_timeout_s:.0f} s")

    def stop_all(self) -> None:
        """Stop every running node, last started first: SIGINT, then SIGTERM, then SIGKILL."""
        for node in reversed(self.nodes):
            proc = node.process
            for sig, wait_s in ((signal.SIGINT, STOP_ESCALATION_S[0]), (signal.SIGTERM, STOP_ESCALATION_S[1]), (signal.SIGKILL, 5.0)):
                if proc.poll() is not None:
                    break
                if sig != signal.SIGINT:
                    self.say(f"{node.spec.name} did not stop; sending {sig.name}")
                try:
                    proc.send_signal(sig)
                except ProcessLookupError:
                    break
                try:
                    proc.wait(timeout=wait_s)
                except subprocess.TimeoutExpired:
                    continue
        for node in self.nodes:
            node.relay.join(timeout=2.0)

    def run(self, specs: list[NodeSpec], stop: threading.Event) -> int:
        """Start ``specs`` in order, supervise until the run ends, stop everything; exit status."""
        import zenoh  # imported here: only the supervising process needs it, after argument parsing

        settings = BusSettings(run_id=self.run_id, connect=(), listen=(self.hub,))
        with zenoh.open(zenoh_config(settings)) as session:
            try:
                for spec in specs:
                    node = self.spawn(spec)
                    if spec.wait_ready:
                        self.wait_ready(session, node, stop)
                return self._supervise(stop)
            except RuntimeError as err:
                self.say(f"error: {err}; stopping the run")
                return 1
            finally:
                self.stop_all()

    def _supervise(self, stop: threading.Event) -> int:
        finished_at: float | None = None
        while True:
            if stop.is_set():
                self.say("interrupted; stopping the nodes")
                return 130
            for node in self.nodes:
                code = node.process.poll()
                if code not in (None, 0):
                    self.say(f"error: node {node.spec.name} exited with status {code}; stopping the run")
                    return 1
                if code == 0 and node.spec.main and finished_at is None:
                    finished_at = time.monotonic()
            if all(n.process.poll() == 0 for n in self.nodes):
                return 0
            if finished_at is not None and time.monotonic() - finished_at > FINISH_GRACE_S:
                late = [n.spec.name for n in self.nodes if n.process.poll() is None]
                self.say(f"error: {', '.join(late)} still running {FINISH_GRACE_S:.0f} s after the run finished")
                return 1
            stop.wait(0.05)


def free_loopback_endpoint() -> str:
    """A zenoh TCP endpoint on a currently free loopback port (the run's hub)."""
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return f"tcp/127.0.0.1:{s.getsockname()[1]}"


def load_node_list(path: Path) -> list[NodeSpec]:
    """Read a declarative node list: TOML with ``[[node]]`` tables (name, module, args, wait_ready, main)."""
    try:
        data = tomllib.loads(path.read_text())
    except FileNotFoundError:
        raise UsageError(f"node list not found: {path}") from None
    except tomllib.TOMLDecodeError as err:
        raise UsageError(f"{path}: invalid TOML: {err}") from None
    entries = data.get("node")
    if not isinstance(entries, list) or not entries:
        raise UsageError(f"{path}: expected one or more [[node]] tables")
    specs = []
    for entry in entries:
        unknown = set(entry) - {"name", "module", "args", "wait_ready", "main"}
        if unknown:
            raise UsageError(f"{path}: unknown node keys {sorted(unknown)}")
        try:
            specs.append(NodeSpec(
                name=entry["name"], module=entry["module"], args=tuple(str(a) for a in entry.get("args", [])),
                wait_ready=bool(entry.get("wait_ready", True)), main=bool(entry.get("main", False)),
            ))
        except KeyError as err:
            raise UsageError(f"{path}: node entry without {err.args[0]!r}") from None
    return specs


def default_recording(scenario: str, controller: str) -> Path:
    """``recordings/<date>-<scenario>-<controller>.mcap``."""
    stamp = datetime.now(timezone.utc).strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{stamp}-{scenario}-{controller}.mcap"


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``python launch.py``."""
    parser = ArgumentParser(
        prog="python launch.py",
        description=__doc__.split("\n\n")[0],
        formatter_class=argparse.ArgumentDefaultsHelpFormatter,
    )
    parser.add_argument("--nodes", type=Path, metavar="FILE", help="declarative node list (TOML [[node]] tables) replacing the default nodes")
    parser.add_argument("--out", type=Path, help="MCAP recording to write (default: recordings/<date>-<scenario>-<controller>.mcap)")
    parser.add_argument("--run-id", default=None, help="run identifier (default: derived from the recording name)")
    parser.add_argument("--hub", default=None, metavar="ENDPOINT", help="zenoh endpoint of the run's hub (default: a free loopback port)")
    parser.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    return parser


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python launch.py``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.nodes is None:
            raise UsageError("no default node list yet: pass --nodes FILE")
        specs = load_node_list(args.nodes)
        out = args.out or default_recording("custom", "nodes")
        run_id = args.run_id or out.stem.replace(" ", "_")[-64:]
        hub = args.hub or free_loopback_endpoint()
        BusSettings(run_id=run_id, connect=(hub,))
    except UsageError as err:
        return exit_usage(parser.prog, err)
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    supervisor = Supervisor(run_id=run_id, hub=hub)
    started = time.monotonic()
    status = supervisor.run([_with_out(s, out) for s in specs], stop)
    summary = {"status": status, "wall_s": round(time.monotonic() - started, 3), "recording": str(out)}
    if args.json:
        print(json.dumps(summary))
    return status


def _with_out(spec: NodeSpec, out: Path) -> NodeSpec:
    """Point the recorder node at the run's recording unless its arguments already name one."""
    if spec.module == "messages.recorder" and "--out" not in spec.args:
        return NodeSpec(spec.name, spec.module, spec.args + ("--out", str(out)), spec.wait_ready, spec.main)
    return spec


if __name__ == "__main__":
    sys.exit(main())
