"""Start a meltloop run: recorder, controller and plant as separate processes over zenoh.

The options become a declarative node list; the launch service (:mod:`messages.launch.service`)
runs it behind an authenticating hub, and the run report (:mod:`controller_node.summary`) prints
the Table-4 line over the fixed window.
"""

from __future__ import annotations

import argparse
import functools
import json
import math
import sys
import time
from dataclasses import dataclass, fields, replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from controller_node.learning_state import parse_learning_state, plan_mismatch
from controller_node.node import load_model
from controller_node.process import process_mismatch, process_table
from controller_node.registry import CONTROLLERS, PREVIEW_CONTROLLERS
from controller_node.report import WINDOW_START_S, plot, read_trace
from controller_node.report import main as report_main
from controller_node.settings import ControllerSettings, merged_over
from controller_node.summary import comparison_table, summarise, table_line
from fe_node.commands import CommandPolicy
from fe_node.scenarios import NAMES, PART_NAMES, PART_POWER_W, Scenario, check_description, scenario
from gp_model.shipped import DEFAULT_MODEL_PATH, PART_MODEL_PATH, default_model_path
from messages.bus import BusSettings, StopFlag, zenoh_config
from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main
from messages.config import build, load_toml
from messages.launch.node import NodeSpec, load_node_list
from messages.launch.service import (
    LaunchService,
    RunFailed,
    free_loopback_endpoint,
    new_recording,
    reserve_recording,
    writable_recording,
)
from messages.live import DEFAULT_PORT, check_port

DEFAULT_CONTROLLER = "preview-mpc"
CONTROLLER_CHOICES = (*CONTROLLERS, "none")
NODE_OPTIONS = ("scenario", "part", "layers", "controller", "setpoint_mm2", "learning_state", "model", "max_steps",
                "h_um", "fallback", "command_timeout_s", "config", "compare", "live")  # refused with --nodes
DEFAULT_SETPOINT_MM2 = round(ControllerSettings.set_point_m2 * 1e6, 9)


@dataclass(frozen=True)
class RunOptions:
    """What one default run consists of (validated command-line options; SI inside the nodes).

    ``setpoint_mm2`` [mm²] is resolved once, on construction: the option, else the ``--config``
    ``[controller]`` table's, else the controller's default.
    """

    scenario: str = "layer"
    part: Path | None = None
    layers: int | None = None
    controller: str = DEFAULT_CONTROLLER
    setpoint_mm2: float | None = None
    config: Path | None = None
    max_steps: int | None = None
    h_um: float | None = None
    model: Path | None = None
    process: Path | None = None
    learning_state: Path | None = None
    fallback: str | None = None
    command_timeout_s: float | None = None
    live: int | None = None  # serve the run live over the Foxglove WebSocket protocol on this port

    def __post_init__(self) -> None:
        checks = [
            (self.controller in CONTROLLER_CHOICES, f"--controller: choose one of {', '.join(CONTROLLER_CHOICES)}"),
            (self.setpoint_mm2 is None or 0 < self.setpoint_mm2 < 0.5, "--setpoint-mm2 must be in (0, 0.5)"),
            (self.max_steps is None or self.max_steps >= 1, "--max-steps must be >= 1"),
            (self.part is None or self.scenario in PART_NAMES, "--part needs --scenario part or ident-part"),
            (self.part is None or self.part.is_file(), f"--part: file not found: {self.part}"),
            (self.layers is None or self.layers >= 1, "--layers must be >= 1"),
            (self.h_um is None or 0 < self.h_um <= 1000, "--h-um must be in (0, 1000] µm"),
            (self.fallback in (None, "safe", "hold"), "--fallback must be 'safe' or 'hold'"),
            (self.command_timeout_s is None or 0 < self.command_timeout_s <= 60,
             "--command-timeout-s must be in (0, 60]"),
            (self.config is None or self.config.is_file(), f"--config: file not found: {self.config}"),
            (self.live is None or 1 <= self.live <= 65535, "--live: the port must be in 1..65535"),
            (self.model is None or self.model.is_file(), f"--model: file not found: {self.model}"),
            (self.process is None or self.process.is_file(), f"--process: file not found: {self.process}"),
            (self.learning_state is None or self.controller == "preview-mpc",
             "--learning-state needs --controller preview-mpc"),
            (self.controller != "none" or (self.fallback is None and self.command_timeout_s is None),
             "--fallback and --command-timeout-s set how the plant treats a controller's commands; with "
             "--controller none there are none"),
        ]
        for ok, message in checks:
            if not ok:
                raise UsageError(message)
        if self.setpoint_mm2 is None:  # resolved once, here: the [controller] table's, else the default
            table = {k: v for k, v in load_toml(self.config).get("controller", {}).items() if k != "name"}
            settings = build(ControllerSettings, table, f"{self.config} [controller]")
            object.__setattr__(self, "setpoint_mm2", settings.set_point_m2 * 1e6)

    @property
    def plant_overrides(self) -> dict[str, Any]:
        """``--part``, ``--layers`` and ``--h-um`` as scenario overrides (as the plant node applies them)."""
        return {k: v for k, v in (("part_stl", self.part and str(self.part)), ("n_layers", self.layers),
                                  ("h_fine_m", self.h_um and self.h_um * 1e-6)) if v}

    @property
    def closed_loop(self) -> bool:
        """Whether a controller node takes part (``none``: the plant plays its own profile)."""
        return self.controller != "none"



def check_config(opts: RunOptions) -> None:
    """Validate scenario and TOML configuration as the nodes will read them (:class:`UsageError` naming the key)."""
    if opts.scenario not in NAMES:
        raise UsageError(f"--scenario: unknown {opts.scenario!r}; choose one of {', '.join(NAMES)}")
    data = load_toml(opts.config)
    unknown = set(data) - {"plant", "controller"}
    if unknown:
        raise UsageError(f"{opts.config}: unknown table(s) {', '.join(sorted(unknown))}; expected [plant], "
                         "[controller]")
    try:
        plant = run_scenario(opts)
        check_description(plant)
    except (ValueError, TypeError) as err:
        raise UsageError(f"{opts.config} [plant]: {err}" if opts.config else str(err)) from None
    model = load_model(opts.controller, opts.model or default_model(opts))  # refused here, before any node starts
    table = {k: v for k, v in data.get("controller", {}).items() if k != "name"}
    process = process_model(opts) if opts.closed_loop else None
    table = merged_over(process_table(process), table) if process else table  # as the controller node merges them
    plant_speed = float(plant.profile.command(0)[1])
    settings = build(ControllerSettings, table, f"{opts.config} [controller]", set_point_m2=opts.setpoint_mm2 * 1e-6,
                     nominal_speed_m_s=None if "nominal_speed_m_s" in table else plant_speed)
    if opts.closed_loop:
        check_within_plant(settings, f"{opts.config} [controller]")
        if not math.isclose(settings.nominal_speed_m_s, plant_speed, rel_tol=0.01):
            raise UsageError(f"{opts.config} [controller] nominal_speed_m_s: {settings.nominal_speed_m_s:g} m/s, but "
                             f"the plant scans at {plant_speed:g} m/s ([plant] speed_m_s); a controller commands its "
                             "nominal speed, so the plant would change speed after its first step (leave it out: "
                             "launch.py passes the plant's)")
    if opts.controller in PREVIEW_CONTROLLERS:
        check_process(model, plant, settings, opts.config)
    if opts.learning_state is not None and opts.learning_state.is_file():
        check_learning_state(opts.learning_state, model, settings,
                             plant.layer_plans[0] if plant.layer_plans else plant.plan)


def check_learning_state(path: Path, model, settings: ControllerSettings, plan) -> None:
    """:class:`UsageError` unless ``path`` holds learning the preview MPC on ``model`` can start from
    (:func:`controller_node.learning_state.parse_learning_state`; a missing file starts afresh) on the
    scan plan ``plan`` (the run's first layer: :func:`~controller_node.learning_state.plan_mismatch`)."""
    try:
        doc = json.loads(path.read_bytes())
        parse_learning_state(doc, model.sample_period_s, settings.preview.turn_learning_steps,
                             len(model.turn_profile_k))
        if (reason := plan_mismatch(doc, plan.path_lengths)) is not None:
            raise ValueError(reason)
    except json.JSONDecodeError as err:
        raise UsageError(f"--learning-state {path}: not JSON ({err})") from None
    except (OSError, ValueError) as err:
        raise UsageError(f"--learning-state {path}: {' '.join(str(err).split())}") from None


def check_process(model, plant, settings: ControllerSettings, config: Path | None) -> None:
    """:class:`UsageError` naming the setting unless the plant is the process the preview MPC's
    ``model`` was identified on (:func:`controller_node.process.process_mismatch`): the speed of its
    first state (the scenario's), the speed the controller commands after it, its sample period, its
    material and its powder layer thickness."""

    file = f"{config} " if config else ""
    checks = ((f"{file}[plant] speed_m_s", {"speed_m_s": plant.profile.command(0)[1]}),
              (f"{file}[controller] nominal_speed_m_s", {"speed_m_s": settings.nominal_speed_m_s}),
              (f"{file}[plant] {'frame_period_s' if plant.settings.frame_period_s else 'dt_s'}",
               {"sample_period_s": plant.settings.sample_period_s}),
              (f"{file}[plant] material", {"material": plant.settings.material.name}),
              (f"{file}[plant] powder_layer_m", {"powder_layer_m": plant.settings.powder_layer_m}))
    for where, value in checks:
        if (reason := process_mismatch(model, **value)) is not None:
            raise UsageError(f"{where}: {reason}")


def check_within_plant(settings: ControllerSettings, where: str) -> None:
    """:class:`UsageError` unless the controller's power bounds and speed lie within the bounds the
    plant node starts with (:class:`fe_node.commands.CommandPolicy`'s): the plant would drop every
    command outside them."""
    plant = CommandPolicy()
    if not plant.power_min_w <= settings.power_min_w < settings.power_max_w <= plant.power_max_w:
        raise UsageError(f"{where}: power bounds [{settings.power_min_w:g}, {settings.power_max_w:g}] W must lie "
                         f"within the plant's [{plant.power_min_w:g}, {plant.power_max_w:g}] W (it drops any command "
                         "outside them)")
    if not plant.speed_min_m_s <= settings.nominal_speed_m_s <= plant.speed_max_m_s:
        raise UsageError(f"{where}: nominal_speed_m_s {settings.nominal_speed_m_s:g} m/s must lie within the plant's "
                         f"[{plant.speed_min_m_s:g}, {plant.speed_max_m_s:g}] m/s")


def run_scenario(opts: RunOptions) -> Scenario:
    """The run's plant scenario (``--scenario``, ``[plant]`` and the node options), built once for the
    same values (a part's is sliced by PySLM); ``ValueError``/``TypeError`` for a bad configuration."""
    overrides = {**load_toml(opts.config).get("plant", {}), **opts.plant_overrides}
    return _scenario(opts.scenario, json.dumps(overrides, sort_keys=True))


@functools.cache
def _scenario(name: str, overrides_json: str) -> Scenario:
    return scenario(name, **json.loads(overrides_json))


def plant_model(opts: RunOptions) -> Path | None:
    """The shipped model of the run's plant: the part model (``gp_model.shipped.PART_MODEL_PATH``) on a
    part scenario, else the model of the plate's powder layer (``gp_model.shipped.default_model_path``);
    ``None`` when the configuration is bad (check_config names the key)."""
    if opts.scenario in PART_NAMES:
        return PART_MODEL_PATH
    if opts.scenario not in NAMES:
        return None
    try:
        plant = run_scenario(opts)
    except (ValueError, TypeError):
        return None
    return default_model_path(plant.settings.powder_layer_m)


def process_model(opts: RunOptions) -> Path | None:
    """The learned model of the run's process, whose record every controller starts from: ``--process``,
    else ``--model``, else :func:`plant_model`."""
    return opts.process or opts.model or plant_model(opts)


def default_model(opts: RunOptions) -> Path | None:
    """The model of a controller on the delay-aware model if it is not its default: :func:`plant_model`."""
    if opts.controller not in PREVIEW_CONTROLLERS:
        return None
    path = plant_model(opts)
    return None if path == DEFAULT_MODEL_PATH else path


def plant_speed(opts: RunOptions) -> float | None:
    """The scan speed [m/s] of the plant's first step (the scenario's, or ``[plant] speed_m_s``), which every
    controller commands (power-only control) unless ``[controller] nominal_speed_m_s`` is set (check_config
    refuses one that differs); ``None`` when the configuration is bad (check_config names the key)."""
    if "nominal_speed_m_s" in load_toml(opts.config).get("controller", {}) or opts.scenario not in NAMES:
        return None
    try:
        plant = run_scenario(opts)
    except (ValueError, TypeError):
        return None
    return float(plant.profile.command(0)[1])


def part_nominal_power(opts: RunOptions, process: Path | None = None) -> float | None:
    """On a part scenario, every controller starts from the part's open-loop power (the scenario's,
    ``fe_node.scenarios.PART_POWER_W`` or ``[plant] power_w``) unless ``[controller]
    nominal_power_w`` is set or the process record of the model ``process`` has one (a part learned by
    ``gp_trainer learn --scenario part``: its operating power); ``None`` elsewhere (the controller's own
    default)."""
    if opts.scenario not in PART_NAMES:
        return None
    data = load_toml(opts.config)
    if "nominal_power_w" in data.get("controller", {}):
        return None
    if process is not None and process_table(process).get("nominal_power_w") is not None:
        return None
    return float(data.get("plant", {}).get("power_w", PART_POWER_W))


def default_nodes(opts: RunOptions, out: Path) -> list[NodeSpec]:
    """The declarative node list of a run: recorder, controller (unless ``none``), plant."""
    common = ["--config", str(opts.config)] if opts.config else []
    plant = ["--scenario", opts.scenario, "--require", "recorder", *common]
    recorder = ["--out", str(out), "--overwrite", "--expect", "plant"]  # out: reserved or checked by main
    nodes = []
    if opts.closed_loop:
        recorder += ["--expect", "controller"]
        controller = ["--controller", opts.controller, "--setpoint-mm2", repr(opts.setpoint_mm2), "--require",
                      "recorder", *common]
        model = opts.model or default_model(opts)
        controller += ["--model", str(model)] if model else []
        process = process_model(opts)
        controller += ["--process", str(process)] if process else []
        nominal = part_nominal_power(opts, process)
        controller += ["--nominal-power-w", repr(nominal)] if nominal is not None else []
        speed = plant_speed(opts)
        controller += ["--nominal-speed-m-s", repr(speed)] if speed is not None else []
        controller += ["--learning-state", str(opts.learning_state)] if opts.learning_state else []
        # started beside the plant, which waits for it (--require): their start-ups overlap
        nodes.append(NodeSpec("controller", "controller_node", tuple(controller), wait_ready=False))
        plant += ["--require", "controller"]
    else:
        plant += ["--open-loop"]
    optional = {"--max-steps": opts.max_steps, "--h-um": opts.h_um, "--fallback": opts.fallback,
                "--command-timeout-s": opts.command_timeout_s, "--part": opts.part, "--layers": opts.layers}
    plant += [item for flag, value in optional.items() if value is not None for item in (flag, str(value))]
    if opts.live is not None:  # the plant waits for it (every state served), the recorder for its end
        recorder, plant = recorder + ["--expect", "live"], plant + ["--require", "live"]
        nodes.insert(0, NodeSpec("live", "messages.live", ("--require", "recorder", "--port", str(opts.live)),
                                 wait_ready=False))
    return [NodeSpec("recorder", "messages.recorder", tuple(recorder)), *nodes,
            NodeSpec("plant", "fe_node", tuple(plant), main=True)]


def build_parser() -> argparse.ArgumentParser:
    """Command-line interface of ``python launch.py``."""
    p = ArgumentParser(prog="python launch.py", description=__doc__.split("\n\n")[0], epilog="With no options: a 4 x "
                       f"10 mm IN625 layer, hatch 0.1 mm, 800 mm/s, under {DEFAULT_CONTROLLER}, into recordings/.")
    add = p.add_argument
    add("--scenario", help="plant scenario: layer, single-track, double-track, table2-case1..9, ...")
    add("--part", type=Path, metavar="STL", help="--scenario part: the STL to slice and build (default: the example)")
    add("--layers", type=int, help="layers to build (--scenario part: default all of the part's)")
    add("--controller", help=f"{DEFAULT_CONTROLLER} (default) or one of {', '.join(CONTROLLER_CHOICES)} "
        "('none': the plant plays the scenario's open-loop profile)")
    add("--setpoint-mm2", type=float, help=f"melt-pool area set point [mm²] (default {DEFAULT_SETPOINT_MM2:g})")
    add("--config", type=Path, help="TOML run configuration: [plant] and [controller] tables of settings")
    add("--learning-state", type=Path, metavar="FILE", help="preview-mpc: start from FILE's learning, write this run's")
    add("--model", type=Path, help="model file of mpc, feedforward or preview-mpc (default: the controller's shipped "
                                   "model in gp_model/models/; refused with --compare)")
    add("--process", type=Path, metavar="MODEL",
        help="a model learned by `python -m gp_trainer learn` whose recorded operating power and PID tuning every "
             "controller starts from (default: --model, else the shipped model of the plant)")
    add("--max-steps", type=int, help="end the run after this many plant steps")
    add("--h-um", type=float, help="fine FE element size [µm]")
    add("--fallback", help="what the plant applies when the controller is gone or late: safe (default) or hold")
    add("--command-timeout-s", type=float, help="the plant falls back after this long without a command [s]")
    add("--out", type=Path, help="MCAP recording to write (with --compare: the output folder); refused if it exists")
    add("--overwrite", action="store_true", help="replace the --out recording(s) if they exist")
    add("--json", action="store_true", help="print a JSON summary as the last line")
    add("--compare", action="store_true", help=f"run {', '.join(CONTROLLERS)} on the same plant; table and figure")
    add("--report", type=Path, metavar="RECORDING", help="only the Table 4 metrics and figure of a recording")
    add("--nodes", type=Path, metavar="FILE", help="TOML node list replacing the default nodes (docs/launch.md)")
    add("--run-id", help="run identifier (default: derived from the recording name)")
    add("--hub", metavar="ENDPOINT", help="zenoh endpoint of the run's hub (default: a free loopback port)")
    add("--zenoh-config", type=Path, metavar="FILE", help="zenoh JSON5 file for hub and nodes (no per-run credentials)")
    add("--live", nargs="?", type=int, const=DEFAULT_PORT, metavar="PORT", help="also serve the run live to Foxglove "
        f"on ws://127.0.0.1:{DEFAULT_PORT} or PORT (docs/live.md)")
    add("--no-progress", action="store_true", help="no progress bar (it is shown only on a terminal anyway)")
    return p


def launch(specs: list[NodeSpec], out: Path, run_id: str | None, hub: str | None, progress: bool,
           zenoh_file: Path | None = None) -> tuple[int, float]:
    """Run one list of nodes to its end; returns (exit status, wall time [s])."""
    run_id = run_id or "".join(c if c.isalnum() or c in "_.-" else "_" for c in out.stem)[-64:].lstrip("_.-")
    specs = [replace(s, args=s.args + ("--out", str(out), "--overwrite"))  # out: reserved or checked by main
             if s.module == "messages.recorder" and "--out" not in s.args else s for s in specs]
    roles = tuple(f"--role={s.name}={','.join(s.roles)}" for s in specs if s.module != "messages.recorder")
    specs = [replace(s, args=s.args + roles) if s.module == "messages.recorder" else s for s in specs]
    service = LaunchService(run_id, hub or free_loopback_endpoint(), zenoh_file, progress=progress)
    started = time.monotonic()
    try:
        status = service.run(specs, StopFlag())
    except RunFailed as err:
        status = exit_error("python launch.py", err)
    if out.exists() and out.stat().st_size == 0:  # reserved (new_recording), but no recorder ever wrote it
        out.unlink()
    return status, time.monotonic() - started


def compare(opts: RunOptions, folder: Path, args: argparse.Namespace, progress: bool) -> tuple[int, dict[str, Any]]:
    """Run every compared controller on one plant (stop at the first failure); ``comparison.md`` and ``.png``."""
    rows, traces = [], {}
    for name in CONTROLLERS:
        run_opts = RunOptions(**{**vars(opts), "controller": name, "learning_state": None})
        out = writable_recording(folder / f"{opts.scenario}-{name}.mcap")
        status, wall_s = launch(default_nodes(run_opts, out), out, None, args.hub, progress, args.zenoh_config)
        summary = summarise(out, opts.scenario, name, status, wall_s)
        print(table_line(summary))
        if status != 0 or summary.get("complete") is not True or "steady_rmse_pct" not in summary:
            return status or 1, {"failed": name, **summary}
        rows.append(summary)
        traces[name] = read_trace(out)
    table = folder / "comparison.md"
    table.write_text(comparison_table(opts.scenario, opts.setpoint_mm2, rows))
    print(table.read_text())
    figure = plot(traces, opts.setpoint_mm2, folder / "comparison.png")
    return 0, {"table": str(table), "figure": str(figure), "window_start_s": WINDOW_START_S, "runs": rows}


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python launch.py``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    try:
        if args.report:
            setpoint = ["--setpoint-mm2", str(args.setpoint_mm2)] if args.setpoint_mm2 else []
            return report_main([str(args.report), "--json", *setpoint])
        if args.compare and (given := [f"--{k.replace('_', '-')}" for k in ("controller", "model", "learning_state")
                                       if getattr(args, k) is not None]):
            raise UsageError(f"{', '.join(given)} cannot be combined with --compare (it runs every controller, each "
                             "with its own model)")
        opts = RunOptions(**{f.name: getattr(args, f.name) for f in fields(RunOptions)}
                          | {"scenario": args.scenario or "layer", "controller": args.controller or DEFAULT_CONTROLLER})
        specs = load_node_list(args.nodes) if args.nodes is not None else None
        if specs is None:
            check_config(opts)
            if opts.live is not None:
                check_port(opts.live)
        elif given := [f"--{k.replace('_', '-')}" for k in NODE_OPTIONS if getattr(args, k) not in (None, False)]:
            raise UsageError(f"{', '.join(given)} cannot be combined with --nodes (give them to the nodes in the list)")
        zenoh_config(BusSettings(run_id=args.run_id or "default", connect=(args.hub,) if args.hub else (),
                                 zenoh_config=args.zenoh_config))  # validates, and loads a --zenoh-config file
        stamp = f"{datetime.now(UTC):%Y%m%d-%H%M%S}"
        if args.compare:
            if args.out:
                folder = args.out
                writable_recording(folder / "comparison.md")
                taken = [p for name in CONTROLLERS if (p := folder / f"{opts.scenario}-{name}.mcap").exists()]
                if taken and not args.overwrite:
                    raise UsageError(f"--out {taken[0]}: exists; give --overwrite to replace it")
            else:
                folder = new_recording(Path("recordings") / f"{stamp}-compare-{opts.scenario}")
        else:
            name = "nodes" if specs else f"{opts.scenario}-{opts.controller}"
            default = Path("recordings") / f"{stamp}-{name}.mcap"
            if args.out is not None and (args.out.suffix != ".mcap" or args.out.is_dir()):
                raise UsageError(f"--out {args.out}: must name a .mcap file (a folder only with --compare)")
            out = reserve_recording(args.out, args.overwrite) if args.out else new_recording(default)
    except UsageError as err:
        return exit_usage(parser.prog, err)
    progress = not args.no_progress and sys.stderr.isatty()  # a bar only on a terminal, not in logs
    if args.compare:
        status, result = compare(opts, folder, args, progress)
        if args.json:
            print(json.dumps(result))
        return status
    status, wall_s = launch(specs or default_nodes(opts, out), out, args.run_id, args.hub, progress, args.zenoh_config)
    summary = {"status": status, "wall_s": round(wall_s, 2), "recording": str(out)}
    if specs is None and out.exists():  # (no recording: the run failed before its recorder started, said above)
        summary = summarise(out, opts.scenario, opts.controller, status, wall_s)
        print(table_line(summary))
        print(f"[launch] recording: {out}")
        if status == 0 and summary.get("complete") is False:
            status = summary["status"] = 1  # the nodes ended normally, but the run did not finish
    if args.json:
        print(json.dumps(summary))
    return status


if __name__ == "__main__":
    run_main(main)
