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
from datetime import UTC, datetime
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
    zenoh_config: Path | None = None
    out: TextIO = sys.stdout
    ready_timeout_s: float = 120.0
    progress: bool = False
    nodes: list[RunningNode] = field(default_factory=list)
    _print_lock: threading.Lock = field(default_factory=threading.Lock)
    _bar: Any = None
    _steps: list[int] = field(default_factory=lambda: [0, 0])  # [latest plant step, total steps]

    def _follow_progress(self, session: Any) -> None:
        """Subscribe (callbacks only store numbers) to the plant's steps and announced total."""
        from messages.codec import MessageError, decode
        from messages.topics import PLANT_STATE, RUN_EVENTS, key_expr

        def on_event(sample: Any) -> None:
            try:
                event = decode(RUN_EVENTS, sample.payload.to_bytes())
            except MessageError:
                return
            if event.event == "start" and event.total_steps:
                self._steps[1] = event.total_steps

        def on_state(sample: Any) -> None:
            try:
                self._steps[0] = max(self._steps[0], decode(PLANT_STATE, sample.payload.to_bytes()).step)
            except MessageError:
                pass

        session.declare_subscriber(key_expr(self.run_id, RUN_EVENTS), on_event)
        session.declare_subscriber(key_expr(self.run_id, PLANT_STATE), on_state)

    def _update_bar(self) -> None:
        step, total = self._steps
        if not total:
            return
        if self._bar is None:
            from tqdm import tqdm

            with self._print_lock:
                self._bar = tqdm(total=total, desc="[launch] steps", unit="step", file=sys.stderr, dynamic_ncols=True)
        self._bar.update(step - self._bar.n)

    def say(self, text: str) -> None:
        """Print a supervisor line, ``[launch] ...``."""
        self._emit(f"[launch] {text}")

    def _emit(self, line: str) -> None:
        with self._print_lock:
            if self._bar is not None:
                self._bar.write(line, file=self.out)
            else:
                print(line, file=self.out, flush=True)

    def _relay(self, name: str, stream: TextIO) -> None:
        for line in stream:
            self._emit(f"[{name}] {line.rstrip()}")

    def spawn(self, spec: NodeSpec) -> RunningNode:
        """Start one node as its own process (own session, so the terminal's Ctrl-C reaches
        only the supervisor, which then stops the nodes in order)."""
        cmd = [sys.executable, "-u", "-m", spec.module, *spec.args, "--run-id", self.run_id, "--connect", self.hub]
        if self.zenoh_config is not None:
            cmd += ["--zenoh-config", str(self.zenoh_config)]
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

        settings = BusSettings(run_id=self.run_id, connect=(), listen=(self.hub,), zenoh_config=self.zenoh_config)
        with zenoh.open(zenoh_config(settings)) as session:
            if self.progress:
                self._follow_progress(session)
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
                if self._bar is not None:
                    self._bar.close()
                    self._bar = None

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
            if self.progress:
                self._update_bar()
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


DEFAULT_CONTROLLER = "preview-mpc"
CONTROLLER_CHOICES = ("mpc", "preview-mpc", "pid", "feedforward", "open-loop", "none")
COMPARED = ("open-loop", "pid", "feedforward", "mpc", "preview-mpc")
DEFAULT_SETPOINT_MM2 = 0.063


@dataclass(frozen=True)
class RunOptions:
    """What one default run consists of (validated command-line options)."""

    scenario: str = "layer"
    controller: str = DEFAULT_CONTROLLER
    setpoint_mm2: float | None = None
    config: Path | None = None
    max_steps: int | None = None
    h_um: float | None = None
    model: Path | None = None
    learning_state: Path | None = None

    def __post_init__(self) -> None:
        if self.controller not in CONTROLLER_CHOICES:
            raise UsageError(f"unknown controller {self.controller!r}; choose one of {', '.join(CONTROLLER_CHOICES)}")
        if self.setpoint_mm2 is not None and not 0 < self.setpoint_mm2 < 0.5:
            raise UsageError(f"--setpoint-mm2 must be in (0, 0.5), got {self.setpoint_mm2}")
        if self.max_steps is not None and self.max_steps < 1:
            raise UsageError("--max-steps must be >= 1")
        if self.config is not None and not self.config.is_file():
            raise UsageError(f"config file not found: {self.config}")
        if self.model is not None and not self.model.is_file():
            raise UsageError(f"model file not found: {self.model}")
        if self.learning_state is not None and self.controller != "preview-mpc":
            raise UsageError("--learning-state needs --controller preview-mpc")

    @property
    def closed_loop(self) -> bool:
        """Whether a controller node takes part (``none``: the plant plays its own profile)."""
        return self.controller != "none"

    def setpoint(self) -> float:
        """The set point [mm²]: the option, else the [controller] table's, else the default."""
        if self.setpoint_mm2 is not None:
            return self.setpoint_mm2
        from messages.config import load_toml

        table = load_toml(self.config).get("controller", {})
        return float(table.get("set_point_m2", DEFAULT_SETPOINT_MM2 * 1e-6)) * 1e6


def check_config(opts: RunOptions) -> None:
    """Validate the scenario and the TOML configuration as the nodes will read them, before
    any node starts (raises :class:`UsageError` with the offending table and key)."""
    from controller_node.settings import ControllerSettings
    from fe_node.scenarios import NAMES, scenario
    from messages.config import build, load_toml

    if opts.scenario not in NAMES:
        raise UsageError(f"unknown scenario {opts.scenario!r}; choose one of {', '.join(NAMES)}")
    data = load_toml(opts.config)
    unknown = set(data) - {"plant", "controller"}
    if unknown:
        raise UsageError(f"{opts.config}: unknown table(s) {', '.join(sorted(unknown))}; expected [plant] and [controller]")
    try:
        scenario(opts.scenario, **data.get("plant", {}))
    except (ValueError, TypeError) as err:
        raise UsageError(f"{opts.config} [plant]: {err}") from None
    table = {k: v for k, v in data.get("controller", {}).items() if k != "name"}
    build(ControllerSettings, table, f"{opts.config} [controller]", set_point_m2=opts.setpoint() * 1e-6)


def default_nodes(opts: RunOptions, out: Path) -> list[NodeSpec]:
    """The declarative node list of a run: recorder, controller (unless ``none``), plant."""
    common = ("--config", str(opts.config)) if opts.config else ()
    plant_args = ["--scenario", opts.scenario, "--require", "recorder", *common]
    recorder_args = ["--out", str(out), "--expect", "plant"]
    nodes = [NodeSpec("recorder", "messages.recorder", tuple(recorder_args))]
    if opts.closed_loop:
        recorder_args += ["--expect", "controller"]
        nodes[0] = NodeSpec("recorder", "messages.recorder", tuple(recorder_args))
        controller_args = ["--controller", opts.controller, "--setpoint-mm2", repr(opts.setpoint()),
                           "--require", "recorder", *common]
        if opts.model:
            controller_args += ["--model", str(opts.model)]
        if opts.learning_state:
            controller_args += ["--learning-state", str(opts.learning_state)]
        nodes.append(NodeSpec("controller", "controller_node", tuple(controller_args)))
        plant_args += ["--require", "controller"]
    else:
        plant_args += ["--open-loop"]
    if opts.max_steps:
        plant_args += ["--max-steps", str(opts.max_steps)]
    if opts.h_um:
        plant_args += ["--h-um", repr(opts.h_um)]
    nodes.append(NodeSpec("plant", "fe_node", tuple(plant_args), main=True))
    return nodes


def default_recording(scenario: str, controller: str) -> Path:
    """``recordings/<date>-<scenario>-<controller>.mcap``."""
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return Path("recordings") / f"{stamp}-{scenario}-{controller}.mcap"


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``python launch.py``."""
    parser = ArgumentParser(
        prog="python launch.py",
        description=__doc__.split("\n\n")[0],
        epilog="With no options: the paper's MPC test — 4 x 10 mm bidirectional IN625 layer, hatch 0.1 mm, "
        "800 mm/s, nominal 250 W — under GP-MPC, recorded to recordings/.",
    )
    parser.add_argument("--scenario", default="layer", help="plant scenario: layer, single-track, double-track, table2-case1..9")
    parser.add_argument("--controller", default=DEFAULT_CONTROLLER, help=f"one of {', '.join(CONTROLLER_CHOICES)} ('none': the plant plays the scenario's open-loop profile)")
    parser.add_argument("--setpoint-mm2", type=float, help=f"melt-pool area set point [mm²] (default {DEFAULT_SETPOINT_MM2})")
    parser.add_argument("--config", type=Path, help="TOML run configuration: [plant] and [controller] tables of settings")
    parser.add_argument(
        "--learning-state",
        type=Path,
        metavar="FILE",
        help="preview-mpc learns over layers: start from FILE if it exists, write what this run learned to it",
    )
    parser.add_argument("--model", type=Path, help="model file (default: the shipped one of the controller: gp_trainer/models/in625_narx_gp.json for preview-mpc, in625_gp.json for mpc and feedforward)")
    parser.add_argument("--max-steps", type=int, help="end the run after this many plant steps")
    parser.add_argument("--h-um", type=float, help="fine FE element size [µm]")
    parser.add_argument("--out", type=Path, help="MCAP recording to write (with --compare: the output folder)")
    parser.add_argument("--json", action="store_true", help="print a JSON summary as the last line")
    parser.add_argument("--compare", action="store_true", help="run open-loop, pid, feedforward and mpc on the same plant; write a table and a figure")
    parser.add_argument("--report", type=Path, metavar="RECORDING", help="only compute the Table 4 metrics and figure of an existing recording")
    parser.add_argument("--nodes", type=Path, metavar="FILE", help="declarative node list (TOML [[node]] tables) replacing the default nodes")
    parser.add_argument("--run-id", default=None, help="run identifier (default: derived from the recording name)")
    parser.add_argument("--hub", default=None, metavar="ENDPOINT", help="zenoh endpoint of the run's hub (default: a free loopback port)")
    parser.add_argument("--zenoh-config", type=Path, metavar="FILE", help="zenoh JSON5 configuration for the hub and every node (e.g. docs/zenoh-acl.json5)")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar (it is shown only on a terminal anyway)")
    return parser


def launch(specs: list[NodeSpec], out: Path, run_id: str | None, hub: str | None, progress: bool,
           zenoh_config: Path | None = None) -> tuple[int, float]:
    """Run one list of nodes to its end; returns (exit status, wall time [s])."""
    run_id = run_id or "".join(c if c.isalnum() or c in "_.-" else "_" for c in out.stem)[-64:].lstrip("_.-")
    BusSettings(run_id=run_id, connect=(hub or "tcp/127.0.0.1:7447",))  # validates
    stop = threading.Event()
    for sig in (signal.SIGINT, signal.SIGTERM):
        signal.signal(sig, lambda *_: stop.set())
    supervisor = Supervisor(run_id=run_id, hub=hub or free_loopback_endpoint(), zenoh_config=zenoh_config, progress=progress)
    started = time.monotonic()
    status = supervisor.run([_with_out(s, out) for s in specs], stop)
    return status, time.monotonic() - started


def _summarise(out: Path, opts: RunOptions, status: int, wall_s: float) -> dict[str, Any]:
    """JSON-able summary of a default run: completeness and, closed loop, the Table-4 metrics
    over the fixed window (``controller_node.report``); ``complete`` is false for a run that did
    not finish or whose recording cannot be read."""
    from controller_node.report import metrics, read_trace, recording_completeness
    from messages.recording import RecordingError

    summary: dict[str, Any] = {"status": status, "wall_s": round(wall_s, 2), "recording": str(out),
                               "scenario": opts.scenario, "controller": opts.controller}
    try:
        trace = read_trace(out)
        done = recording_completeness(out, int(trace.time_s.size))
    except RecordingError as err:
        summary.update(error=str(err), complete=False, incomplete_reason=f"unreadable recording: {err}")
        return summary
    summary.update(steps=int(trace.time_s.size - 1), complete=done.complete, incomplete_reason=done.reason)
    if opts.closed_loop:
        try:
            m = metrics(trace, opts.setpoint())
        except ValueError as err:
            summary["error"] = str(err)
            return summary
        summary.update(setpoint_mm2=m.setpoint_mm2, window_start_s=m.window_start_s,
                       overshoot_pct=round(m.overshoot_pct, 2), undershoot_pct=round(m.undershoot_pct, 2),
                       steady_rmse_pct=round(m.steady_rmse_pct, 2),
                       rmse_turnaround_pct=_round(m.rmse_turnaround_pct), rmse_along_pct=_round(m.rmse_along_pct),
                       turnaround_share_pct=_round(m.turnaround_share_pct, 1),
                       n_turnaround=m.n_turnaround, n_along=m.n_along)
    return summary


def _round(value: float | None, digits: int = 2) -> float | None:
    return None if value is None else round(value, digits)


def _cell(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"


def _print_table(summary: dict[str, Any]) -> None:
    """Print a run's Table-4 line, or ``INCOMPLETE (<reason>)`` for a run that did not finish."""
    run = f"[launch] {summary['controller']} on {summary['scenario']}:"
    if summary.get("complete") is False:
        print(f"{run} INCOMPLETE ({summary['incomplete_reason']})")
    elif "steady_rmse_pct" in summary:
        print(f"{run} set point {summary['setpoint_mm2']:.4f} mm² | "
              f"max overshoot {summary['overshoot_pct']:.1f} % | max undershoot {summary['undershoot_pct']:.1f} % | "
              f"steady-state RMSE {summary['steady_rmse_pct']:.2f} % | "
              f"turnaround RMSE {_cell(summary['rmse_turnaround_pct'])} % ({summary['n_turnaround']} states) | "
              f"along-track RMSE {_cell(summary['rmse_along_pct'])} % ({summary['n_along']} states) | "
              f"window from {summary['window_start_s'] * 1e3:g} ms after laser-on | "
              f"{summary['steps']} steps in {summary['wall_s']:.1f} s")
    print(f"[launch] recording: {summary['recording']}")


def compare(opts: RunOptions, folder: Path, hub: str | None, progress: bool,
            zenoh_config: Path | None = None) -> tuple[int, dict[str, Any]]:
    """Run every compared controller on the same plant; write ``comparison.md`` and ``comparison.png``.

    Stops at the first run that fails, does not finish or has no metrics (status 1 unless the
    run's own status says otherwise)."""
    from controller_node.report import (
        TURNAROUND_STEPS,
        WINDOW_START_S,
        plot,
        read_trace,
    )

    folder.mkdir(parents=True, exist_ok=True)
    rows, traces = [], {}
    for name in COMPARED:
        run_opts = RunOptions(opts.scenario, name, opts.setpoint(), opts.config, opts.max_steps, opts.h_um, opts.model)
        out = folder / f"{opts.scenario}-{name}.mcap"
        status, wall_s = launch(default_nodes(run_opts, out), out, None, hub, progress, zenoh_config)
        summary = _summarise(out, run_opts, status, wall_s)
        _print_table(summary)
        if status != 0 or summary.get("complete") is not True or "steady_rmse_pct" not in summary:
            return status or 1, {"failed": name, **summary}
        rows.append(summary)
        traces[name] = read_trace(out)
    lines = [("| controller | max overshoot [%] | max undershoot [%] | steady-state RMSE [%] | turnaround RMSE [%] "
              "| along-track RMSE [%] | wall time [s] |"),
             "|---|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['controller']} | {r['overshoot_pct']:.1f} | {r['undershoot_pct']:.1f} | {r['steady_rmse_pct']:.2f} "
              f"| {_cell(r['rmse_turnaround_pct'])} | {_cell(r['rmse_along_pct'])} | {r['wall_s']:.1f} |" for r in rows]
    heading = (f"Scenario `{opts.scenario}`, set point {opts.setpoint():.4f} mm². Every figure in % of the set point, "
               f"over one fixed window for every controller: from {WINDOW_START_S * 1e3:g} ms after laser-on to the "
               f"end of the run; turnaround = the first {TURNAROUND_STEPS} states of every track after the first, "
               "along-track = the rest of the window.")
    table = folder / "comparison.md"
    table.write_text(heading + "\n\n" + "\n".join(lines) + "\n")
    figure = plot(traces, opts.setpoint(), folder / "comparison.png")
    print(heading)
    print("\n".join(lines))
    return 0, {"table": str(table), "figure": str(figure), "window_start_s": WINDOW_START_S, "runs": rows}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python launch.py``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.report:
            from controller_node.report import main as report_main

            return report_main([str(args.report), "--json"] + (["--setpoint-mm2", str(args.setpoint_mm2)] if args.setpoint_mm2 else []))
        opts = RunOptions(args.scenario, args.controller, args.setpoint_mm2, args.config, args.max_steps, args.h_um, args.model,
                          args.learning_state)
        if args.nodes is not None:
            specs = load_node_list(args.nodes)
        else:
            check_config(opts)
            specs = None
        if args.hub is not None:
            BusSettings(connect=(args.hub,))
        if args.run_id is not None:
            BusSettings(run_id=args.run_id)
        if args.zenoh_config is not None:
            BusSettings(zenoh_config=args.zenoh_config)
    except UsageError as err:
        return exit_usage(parser.prog, err)
    progress = not args.no_progress and sys.stderr.isatty()  # a bar only on a terminal, not in logs
    if args.compare:
        folder = args.out or Path("recordings") / f"{datetime.now(UTC):%Y%m%d-%H%M%S}-compare-{opts.scenario}"
        status, result = compare(opts, folder, args.hub, progress, args.zenoh_config)
        if args.json:
            print(json.dumps(result))
        return status
    out = args.out or default_recording(opts.scenario, opts.controller)
    status, wall_s = launch(specs or default_nodes(opts, out), out, args.run_id, args.hub, progress, args.zenoh_config)
    summary = _summarise(out, opts, status, wall_s) if specs is None else {"status": status, "wall_s": round(wall_s, 2), "recording": str(out)}
    if specs is None:
        _print_table(summary)
        if status == 0 and summary.get("complete") is False:
            status = 1  # the supervisor saw a normal end, but the run did not finish
            summary["status"] = status
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
