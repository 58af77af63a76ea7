"""Command line: ``python -m gp_trainer {dataset,train,evaluate,campaign,identify}``.

Typical use::

    python -m gp_trainer campaign --workers 2      # 9 Table 2 cases, Dask LocalCluster -> recordings/campaign/
    python -m gp_trainer campaign --scheduler tls://HOST:8786   # ... on an existing Dask cluster (TLS)
    python -m gp_trainer identify --workers 2      # 13 identification runs -> recordings/identification/
    python -m gp_trainer dataset                   # -> out/gp/dataset.npz
    python -m gp_trainer train                     # -> gp_model/models/in625_gp.json
    python -m gp_trainer evaluate --json           # metrics + out/gp/gp_scatter.png, gp_rollout.png

User errors (missing or bad files, too few samples, bad arguments) end with exit status 2 and a
one-line reason on stderr; nothing is half-written (every output is written atomically).
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, NoReturn

import numpy as np

from controller_node.process import process_mismatch
from controller_node.settings import ControllerSettings
from fe_node.frames import frame_ratio
from fe_node.part import EXAMPLE_STL, require_pyslm
from fe_node.scenarios import scenario
from gp_model import narx
from gp_model.build_up import ROLLOUT_HORIZON, rollout_horizon
from gp_model.errors import DatasetError, GPError
from gp_model.files import is_model_file
from gp_model.model import DEFAULT_RESTARTS, GPModel
from gp_model.narx import NarxGPModel, series_from_states
from gp_model.plan_feature import RemnantFeature
from gp_model.shipped import DEFAULT_MODEL_PATH, ONE_STEP_MODEL_PATH
from gp_trainer import dataset, synthetic
from gp_trainer.campaign import (
    IDENT_SETS,
    PART_IDENT_LAYERS,
    CampaignSettings,
    IdentifySettings,
    run_campaign,
    run_identification,
    select_ident_runs,
    summary_json,
)
from gp_trainer.dataset import load_samples, read_states
from gp_trainer.errors import CampaignError, LearnError
from gp_trainer.evaluate import evaluate, plot_narx
from gp_trainer.jobs import JobResult
from gp_trainer.learn import LearnSettings, design_from_record, learn, process_record, refit, retune
from gp_trainer.narx_fit import POWER_FORM_NAMES, candidate_of, evaluate_model, rollout_key, select_and_fit
from gp_trainer.provenance import REPO_ROOT
from gp_trainer.train import TrainSettings, train
from messages.cli import UsageError
from messages.config import build, load_toml
from messages.recording import run_config

PROG = "python -m gp_trainer"
DEFAULT_DATASET = Path("out/gp/dataset.npz")
DEFAULT_RECORDINGS = Path("recordings/campaign")
DEFAULT_PLOTS = Path("out/gp")
FE_SOURCE = "FE campaign: finite-element plant (fe_node) recordings, see dataset.recordings"
RECORDED_SOURCE = "recordings whose plant is not identified as the FE node, see dataset.recordings"
SYNTHETIC_SOURCE = "synthetic stand-in plant (gp_trainer.synthetic), NOT FE data"


class _Parser(argparse.ArgumentParser):
    """argparse with one-line errors and exit status 2."""

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {message}\n")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of :func:`main`."""
    parser = _Parser(prog=PROG,
                     description="Build the dataset, train and validate the melt-pool GP model (paper eq. 1-5, IV.A).",
                     formatter_class=argparse.ArgumentDefaultsHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)
    fmt = argparse.ArgumentDefaultsHelpFormatter

    p = sub.add_parser("dataset", formatter_class=fmt, help="build training samples from recordings")
    p.add_argument("recordings", nargs="*", type=Path,
                   help="MCAP recordings (default: table2-case*.mcap in --recordings-dir)")
    p.add_argument("--recordings-dir", type=Path, default=DEFAULT_RECORDINGS, help="campaign directory")
    p.add_argument("--synthetic", action="store_true",
                   help="use the synthetic stand-in plant (gp_trainer.synthetic) instead of recordings")
    p.add_argument("--out", type=Path, default=DEFAULT_DATASET, help="dataset file (.npz)")
    p.add_argument("--startup-fraction", type=float, default=0.5,
                   help="a track's pool is formed once its area reaches this fraction of the track median")
    p.add_argument("--min-samples", type=int, default=120, help="fewer usable samples is an error")

    p = sub.add_parser("train", formatter_class=fmt, help="select training points and fit the GP")
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET, help="dataset file from `dataset`")
    p.add_argument("--out", type=Path, default=ONE_STEP_MODEL_PATH, help="model file (JSON)")
    p.add_argument("--seed", type=int, default=0, help="seed of the point selection and optimiser restarts")
    p.add_argument("--n-train", type=int, default=100, help="training points")
    p.add_argument("--restarts", type=int, default=DEFAULT_RESTARTS, help="optimiser starts")
    p.add_argument(
        "--selection",
        choices=("variance", "maximin"),
        default="variance",
        help="training-point design: integrated-variance reduction after a maximin pilot fit, or maximin alone",
    )
    p.add_argument("--no-history", action="store_true",
                   help="the paper's four inputs (x, T, p, v) only, without the area change x[k] - x[k-1]")

    p = sub.add_parser(
        "evaluate",
        formatter_class=fmt,
        help="validate a model: the delay-aware one on held-out identification runs, a one-step one on the dataset",
    )
    _plant_option(p, None)
    p.add_argument("--model", type=Path, default=None,
                   help="model file (default: the --plant's delay-aware model; a delay-aware model is evaluated "
                        "on --recordings-dir, a one-step GP on --dataset)")
    p.add_argument("--recordings-dir", type=Path, default=None,
                   help="identification recordings (delay-aware model; default: the model's (learn) or the "
                        "--plant's)")
    p.add_argument("--dataset", type=Path, default=DEFAULT_DATASET, help="dataset file")
    p.add_argument("--plots-dir", type=Path, default=DEFAULT_PLOTS, help="where the PNG figures go")
    p.add_argument("--rollout-source", default="table2-case2", help="case of the multi-step forward simulation")
    p.add_argument("--json", action="store_true", help="print the metrics as JSON (last line)")
    p.add_argument("--no-identify", action="store_true",
                   help="a delay-aware model's held-out runs missing in --recordings-dir are an error (exit 2) "
                        "instead of being recorded first, as `identify --runs` would")
    p.add_argument("--runs", nargs="+", type=Path, default=None, metavar="RECORDING",
                   help="evaluate a delay-aware model on these MCAP recordings (any run on its process: simulated, "
                        "closed loop, or from hardware) instead of its held-out runs")

    p = sub.add_parser("narx", formatter_class=fmt,
                       help="select, fit and evaluate the delay-aware model (FIR + residual GP) of the preview MPC")
    _plant_option(p)
    p.add_argument("recordings", nargs="*", type=Path,
                   help="MCAP recordings (default: every complete run of the --plant's identification directory)")
    p.add_argument("--held-out", nargs="+", default=None,
                   help="recording stems held out for selection and evaluation (default: the --plant's)")
    p.add_argument("--out", type=Path, default=None,
                   help="model file (default: the --plant's model in gp_model/models/)")
    p.add_argument("--seed", type=int, default=0, help="seed of the GP point choice and optimiser restarts")
    p.add_argument("--structure-of", type=Path, default=None, metavar="MODEL",
                   help="fit the candidate a delay-aware model was selected as (its structure) instead of "
                        "selecting among all (default: select)")
    p.add_argument("--json", action="store_true", help="print the held-out metrics as JSON (last line)")

    p = sub.add_parser("campaign", formatter_class=fmt, help="record the Table 2 cases open loop (on Dask)",
                       description="Record the Table 2 cases open loop, each a launch.py run, on Dask distributed: "
                       "a local cluster of --workers processes, or an existing one (--scheduler).")
    p.add_argument("--cases", type=int, nargs="+", default=list(range(1, 10)), help="Table 2 case numbers")
    p.add_argument("--out-dir", type=Path, default=DEFAULT_RECORDINGS, help="recordings directory")
    _runner_options(p, "case")

    p = sub.add_parser(
        "identify",
        formatter_class=fmt,
        help="record the identification runs (random power staircases, closed-loop runs) on Dask",
        description="Record seeded random power-staircase runs (launch.py --controller none) and closed-loop "
        "runs, one MCAP each, on Dask distributed as `campaign`. "
        + " ".join(f"--plant {s.name}: {', '.join(r.name for r in s.runs)}." for s in IDENT_SETS.values()),
    )
    _plant_option(p)
    p.add_argument("--runs", nargs="+", metavar="NAME", default=argparse.SUPPRESS,
                   help="only these runs (default: all of the --plant's)")
    p.add_argument("--out-dir", type=Path, default=None, help="recordings directory (default: the --plant's)")
    _runner_options(p, "run")

    p = sub.add_parser(
        "learn", formatter_class=fmt, help="learn a process: operating point, identification runs, delay-aware model",
        description="Learn the delay-aware model of a process, on the plate or on a part: find the power that holds "
        "the set point along a track, record the identification runs designed around it (staircases, closed-loop "
        "runs, then the preview MPC with the stage-1 model) on Dask, select and fit the model by its held-out "
        "rollout, and write the model, its stage-1 model beside it, a JSON report (learn.json) and plots in "
        "--out-dir.")
    p.add_argument("--scenario", choices=("layer", "part"), default="layer",
                   help="layer: the runs are the plate's layer and double track; part: they build the first --layers "
                        "layers of --part")
    p.add_argument("--part", type=Path, default=None, metavar="STL",
                   help="--scenario part: the part (default: the example part)")
    p.add_argument("--layers", type=int, default=None,
                   help=f"--scenario part: layers each run builds (default {PART_IDENT_LAYERS})")
    p.add_argument("--extra-runs", type=Path, nargs="+", default=(), metavar="RECORDING",
                   help="recordings of other runs on the same process (e.g. another part's identification runs) "
                        "added to the training runs of both stages, not to the held-out ones")
    p.add_argument("--config", type=Path, required=True,
                   help="TOML file whose [plant] table is the process (launch.py's; [controller] sets the power "
                        "limits)")
    p.add_argument("--set-point-mm2", type=float, default=None,
                   help="target melt-pool area [mm²] (default: the [controller] table's, else "
                        f"{ControllerSettings.set_point_m2 * 1e6:g})")
    p.add_argument("--out", type=Path, default=LearnSettings.model_out, help="model file (JSON)")
    p.add_argument("--out-dir", type=Path, default=LearnSettings.out_dir,
                   help="recordings, report and plots (a re-run skips complete recordings)")
    p.add_argument("--seed", type=int, default=0, help="seed of the fits")
    p.add_argument("--structure-of", type=Path, default=None, metavar="MODEL",
                   help="fit the candidate a learned model was selected as (its structure) in both stages instead of "
                        "selecting among all (default: select)")
    p.add_argument("--frame-period-s", type=float, default=None, metavar="P",
                   help="learn at a camera's frame period P [s], a whole number of FE steps: the runs hold each "
                        "command over a frame and record every P/dt_s-th FE state ([plant] frame_period_s; "
                        "default: the FE step)")
    _runner_options(p, "run")

    p = sub.add_parser(
        "tune-pid", formatter_class=fmt, help="tune the PID baseline of a learned model on its training staircases",
        description="Fit a first-order-plus-dead-time model to the training power staircases of a model learned "
        "by `learn` (its provenance.design names them and their directory) and write the SIMC PI gains and the "
        "operating power into its provenance.controller, which launch.py gives every controller on that process "
        "(`learn` writes the same record).")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL_PATH,
                   help="model file (JSON), rewritten (default: the shipped model of the physical plant)")
    p.add_argument("--json", action="store_true", help="print the record as JSON")

    p = sub.add_parser(
        "refit", formatter_class=fmt, help="refit a learned model's selected candidate with the current code",
        description="Fit the candidate a model of `learn` was selected as (lags, output map, squares, p×T, "
        "feature lags, length-scale floor, smoothness prior, seed) again, on its training runs and scored on "
        "its held-out runs from the recordings directory its provenance.design names, keeping its design, "
        "process and controller records: a change of the model's definition on the same data, no new "
        "selection.")
    p.add_argument("--model", type=Path, default=DEFAULT_MODEL_PATH,
                   help="the learned model (default: the shipped model of the physical plant)")
    p.add_argument("--out", type=Path, default=None, help="where the refitted model goes (default: --model)")
    p.add_argument("--remnant-states", type=int, default=None,
                   help="fit the remnant terms over this many states after a turn, 0: none (default: as the model)")
    p.add_argument("--remnant-sources", type=int, default=RemnantFeature.n_sources,
                   help="previous-track states whose mean power scales the remnant terms (default %(default)s)")
    p.add_argument("--remnant-offsets", action="store_true", help="fit an offset per state besides the slope")
    p.add_argument("--drop", nargs="+", default=(), metavar="RUN",
                   help="leave these training runs out (a model that never saw their plans, e.g. for "
                        "bench_suite.py --model; give --out)")
    p.add_argument("--power-form", choices=POWER_FORM_NAMES, default=None,
                   help="the power lags' map and the GP's inputs: 'square' p² (the models of format 5), 'log1p' "
                        "log(1 + p/25 W), each with the GP's mean-power input; 'log1p-no-gp-power' without it "
                        "(default: as the model)")
    p.add_argument("--json", action="store_true", help="print the held-out metrics as JSON (last line)")
    return parser


def _plant_option(p: argparse.ArgumentParser, default: str | None = "plate") -> None:
    p.add_argument("--plant", choices=tuple(IDENT_SETS), default=default,
                   help="plate: the bare-plate scenarios (layer, double track); part: the part scenario "
                        "(powder, the example part); a process learned by `learn` is on neither"
                        + ("" if default else " (default: the shipped model of the physical plant, whose held-out "
                           "runs its provenance names)"))


def _runner_options(p: argparse.ArgumentParser, unit: str) -> None:
    """Options of the job runner (`campaign`, `identify`): where the runs execute and how."""

    where = p.add_mutually_exclusive_group()
    where.add_argument("--workers", type=int, default=argparse.SUPPRESS,
                       help=f"worker processes of the local Dask cluster, i.e. {unit}s run at the same time "
                       f"(default: {CampaignSettings.workers})")
    where.add_argument("--scheduler", metavar="tls://HOST:PORT", default=None,
                       help="run on this existing Dask cluster instead (TLS, credentials from Dask's configuration "
                       "distributed.comm.tls.*; workers must see this repository "
                       "and --out-dir at the same paths)")
    where.add_argument("--sequential", action="store_true",
                       help=f"no Dask: the {unit}s one after the other in this process")
    p.add_argument("--retries", type=int, default=1, help=f"a failed {unit} is run again this many times")
    p.add_argument("--timeout", type=float, default=None, help=f"wall-time limit per {unit} and attempt [s]")
    p.add_argument("--max-steps", type=int, default=None,
                   help=f"launch.py --max-steps for every {unit} (short test runs; use another --out-dir)")
    p.add_argument("--h-um", type=float, default=None,
                   help=f"launch.py --h-um for every {unit} (coarser mesh; use another --out-dir: a re-run refuses "
                   "recordings made on another mesh)")
    p.add_argument("--no-progress", action="store_true", help=f"no progress bar and no line per finished {unit}")
    p.add_argument("--json", action="store_true", help="print a JSON summary (last line)")


def _runner_settings(args: argparse.Namespace) -> dict:
    """The runner fields of the campaign/identify settings from the command line."""

    if args.h_um is not None and not 0 < args.h_um <= 1000:
        raise CampaignError(f"--h-um must be in (0, 1000] µm, got {args.h_um}")
    if args.max_steps is not None and args.max_steps < 1:
        raise CampaignError(f"--max-steps must be >= 1, got {args.max_steps}")
    launch_args = (*(("--max-steps", str(args.max_steps)) if args.max_steps is not None else ()),
                   *(("--h-um", repr(args.h_um)) if args.h_um is not None else ()))
    return dict(out_dir=args.out_dir, workers=getattr(args, "workers", CampaignSettings.workers),
                scheduler=args.scheduler, sequential=args.sequential, retries=args.retries, timeout_s=args.timeout,
                launch_args=launch_args)


def _interrupted(command: str, out_dir: Path) -> int:
    """Ctrl-C: the running launchers were sent SIGINT (they stop their nodes); exit status 130."""
    print(f"{PROG} {command}: interrupted; the complete recordings in {out_dir} are kept and a re-run skips them",
          file=sys.stderr)
    return 130


def _report_failures(results: list, label: Callable[[Any], str]) -> None:
    """For every run that failed after its retries: which, exit status and the last lines of its output."""
    for r in results:
        if r.status != "failed":
            continue
        status = "no exit status (its worker died)" if r.exit_status is None else f"exit status {r.exit_status}"
        print(f"{label(r)} failed after {r.attempts} attempt(s), {status}; last lines of its output:",
              file=sys.stderr)
        for line in (r.output_tail or r.detail).splitlines():
            print(f"    {line}", file=sys.stderr)


def _case_number(path: Path) -> tuple[int, str]:
    match = re.search(r"case(\d+)", path.stem)
    return (int(match.group(1)) if match else sys.maxsize, path.name)


def _recorded_source(recordings: list[dict]) -> str:
    """:data:`FE_SOURCE` if every recording's plant config is the FE node's (it has a mesh), else generic."""
    def is_fe(info: dict) -> bool:
        plant = (info.get("config") or {}).get("plant") or {}
        return isinstance(plant, dict) and "nodes" in plant and "settings" in plant
    return FE_SOURCE if recordings and all(is_fe(r) for r in recordings) else RECORDED_SOURCE


def _dataset(args: argparse.Namespace) -> int:
    settings = dataset.DatasetSettings(startup_fraction=args.startup_fraction, min_samples=args.min_samples)
    if not 0.0 < settings.startup_fraction <= 1.0:
        raise DatasetError(f"--startup-fraction must be in (0, 1], got {settings.startup_fraction}")
    parts, reports, recordings = [], [], []
    if args.synthetic:
        if args.recordings:
            raise DatasetError("give recordings or --synthetic, not both")
        sources = {f"table2-case{c}": synthetic.table2_case(c, noise_rel=0.002, seed=c) for c in range(1, 10)}
        recordings = [{"name": "synthetic stand-in plant (gp_trainer.synthetic), NOT FE data", "noise_rel": 0.002}]
        data_source = SYNTHETIC_SOURCE
    else:
        paths = args.recordings or sorted(args.recordings_dir.glob("table2-case*.mcap"), key=_case_number)
        paths = [p for p in paths if not p.name.endswith(".partial.mcap")]
        if not paths:
            raise DatasetError(f"no recordings given and none in {args.recordings_dir} (run `{PROG} campaign`)")
        sources = {p.stem: dataset.read_states(p) for p in paths}
        recordings = [dataset.recording_info(p) for p in paths]
        data_source = _recorded_source(recordings)
    for name, states in sources.items():
        samples, report = dataset.build_samples(states, name, settings)
        parts.append(samples)
        reports.append(report)
        print(report.summary())
    samples = dataset.concatenate(parts, settings)
    meta = {"data_source": data_source, "recordings": recordings, "reports": [asdict(r) for r in reports],
            "settings": asdict(settings)}
    out = dataset.save_samples(args.out, samples, meta)
    dropped = sum(r.dropped_startup + r.dropped_no_pool + r.dropped_gap for r in reports)
    print(f"{len(samples)} samples from {len(reports)} sources ({dropped} pairs dropped) -> {out}")
    return 0


def _train(args: argparse.Namespace) -> int:
    if args.n_train < 10 or args.restarts < 1:
        raise DatasetError("--n-train must be at least 10 and --restarts at least 1")
    samples, meta = load_samples(args.dataset)
    meta = {**meta, "file": args.dataset.name}
    model = train(samples, meta, TrainSettings(n_train=args.n_train, seed=args.seed, n_restarts=args.restarts,
                                               selection=args.selection, history=not args.no_history))
    out = model.save(args.out)
    print(f"{model} log ML = {model.log_marginal_likelihood:.3f} -> {out}")
    return 0


def _evaluate_narx(args: argparse.Namespace) -> int:
    """Held-out metrics of a delay-aware model (the keys of the one-step evaluation plus
    ``rollout_h40_mape_pct`` and ``coverage_95_pct``) and its plots: on the held-out runs of the process
    its ``provenance.design`` records (``learn``), else on those of ``--plant``."""

    model = NarxGPModel.load(args.model)
    if args.runs is not None:
        return _evaluate_narx_on(model, args)
    record = model.provenance.get("design")
    if record is not None:
        design, default_dir = design_from_record(record)
        runs, held_out, plant = design.runs(), design.held_out(), None
        command = (f"{PROG} learn (the model's process, provenance.design) --out-dir "
                   f"{args.recordings_dir or default_dir}")
    else:
        ident = IDENT_SETS[args.plant or "plate"]
        runs, held_out, default_dir, plant = ident.runs, ident.held_out, ident.out_dir, ident.name
    recordings_dir = args.recordings_dir or default_dir
    paths = [recordings_dir / f"{name}.mcap" for name in held_out]
    missing = [p.stem for p in paths if not p.is_file()]
    if plant is not None:
        command = f"{PROG} identify --plant {plant} --runs {' '.join(missing)} --out-dir {recordings_dir}"
    if missing and args.no_identify:
        raise DatasetError(f"held-out identification recordings missing in {recordings_dir} "
                           f"({', '.join(missing)}): run `{command}`")
    if missing and (status := _identify_held_out(runs, missing, recordings_dir, command)) != 0:
        return status
    held = [series_from_states(read_states(p), p.stem) for p in paths]
    result = evaluate_model(model, held)
    result.update(plot_narx(model, held, args.plots_dir))
    case2 = DEFAULT_RECORDINGS / f"{args.rollout_source}.mcap"
    result["rollout_case2_mape_pct"] = None
    on_plate = plant == "plate"  # the Table 2 cases run on the bare plate; another plant's model skips them
    if on_plate and case2.is_file():  # the paper's Fig. 4b: the whole case predicted from its powers and measured T
        run = series_from_states(read_states(case2), case2.stem)
        mean, _ = model.predict_run(run)
        y, keep = run.area_m2[1:], (np.arange(1, len(run)) >= 20) & (run.area_m2[1:] > 0)
        result["rollout_case2_mape_pct"] = float(100.0 * np.mean(np.abs(mean[keep] - y[keep]) / y[keep]))
    elif on_plate:
        print(f"warning: no {case2} (run `{PROG} campaign`): no case-2 rollout", file=sys.stderr)
    if args.json:
        print(json.dumps(result))
    else:
        print(
            f"R² = {result['r2']:.5f}, MAPE = {result['mape_pct']:.3f} % on {result['n_valid']} held-out samples; "
            f"{rollout_horizon(model.sample_period_s)}-step rollout MAPE = "
            f"{result[rollout_key(model.sample_period_s)]:.3f} %; "
            f"95 % coverage {result['coverage_95_pct']:.1f} %"
        )
        if result["n_turnaround"]:
            print(f"turnaround windows ({result['n_turnaround']} samples): MAPE {result['mape_turnaround_pct']:.2f} %, "
                  f"coverage {result['coverage_95_turnaround_pct']:.1f} %; along the tracks: MAPE "
                  f"{result['mape_along_pct']:.2f} %, coverage {result['coverage_95_along_pct']:.1f} %")
    return 0


def _evaluate_narx_on(model: NarxGPModel, args: argparse.Namespace) -> int:
    """``evaluate --runs``: the held-out metrics of :func:`gp_trainer.narx_fit.evaluate_model` on the given
    recordings; ``training_runs`` names those that are among the model's training runs (in-sample)."""
    runs = []
    for path in args.runs:
        run = series_from_states(read_states(path), path.stem)
        settings = run_config(path).get("plant", {}).get("settings", {})   # none in a hardware node's recording
        why = process_mismatch(model, run.speed_m_s, run.sample_period_s, settings.get("material", {}).get("name"),
                               settings.get("powder_layer_m"))
        if why is not None:
            raise DatasetError(f"--runs {path.name}: {why}")
        runs.append(run)
    result = evaluate_model(model, runs)
    trained = set(model.provenance.get("runs", []))
    result["runs"] = result.pop("held_out")
    result["training_runs"] = [r.name for r in runs if r.name in trained]

    def pct(key: str, sign: str = "") -> str:
        return "n/a" if result[key] is None else f"{result[key]:{sign}.2f} %"

    print(json.dumps(result) if args.json else
          f"on {len(runs)} recording(s), {result['n_valid']} samples: one-step MAPE {pct('mape_pct')} "
          f"(turnarounds {pct('mape_turnaround_pct')}, bias {pct('bias_turnaround_pct', '+')}; "
          f"along {pct('mape_along_pct')}, bias {pct('bias_along_pct', '+')}); bias after the turns by "
          f"{result['after_turn_bin_states']} states: "
          + " ".join("n/a" if b is None else f"{b:+.1f}" for b in result["bias_after_turn_pct"]) + " %")
    return 0


def _identify_held_out(runs: tuple, names: list[str], out_dir: Path, command: str) -> int:
    """Record the held-out identification runs ``names`` of ``runs`` into ``out_dir`` (what ``command``
    does, on a local Dask cluster); 0 when all are complete, else the status to exit with."""
    print(f"{PROG} evaluate: recording the held-out runs first ({', '.join(names)}): {command}", file=sys.stderr)
    settings = IdentifySettings(runs=select_ident_runs(names, runs), out_dir=out_dir)
    try:
        results = run_identification(settings)
    except KeyboardInterrupt:
        return _interrupted("evaluate", out_dir)
    _report_failures(results, lambda r: r.name)
    return 1 if any(r.status == "failed" for r in results) else 0


def _evaluate(args: argparse.Namespace) -> int:
    args.model = args.model or (DEFAULT_MODEL_PATH if args.plant is None else IDENT_SETS[args.plant].model_path)
    if is_model_file(args.model, narx.FORMAT_NAME):
        return _evaluate_narx(args)
    if args.runs is not None:
        raise DatasetError(f"--runs: {args.model} is a one-step model; --runs evaluates a delay-aware one")
    model = GPModel.load(args.model)
    samples, _ = load_samples(args.dataset)
    result = evaluate(model, samples, args.plots_dir, rollout_source=args.rollout_source)
    if result["n_train_found"] < model.n_train:
        print(f"warning: only {result['n_train_found']} of the model's {model.n_train} training points are in "
              f"{args.dataset}; the model was trained on other data", file=sys.stderr)
    if result["rollout_case2_mape_pct"] is None:
        print(f"warning: no samples of {args.rollout_source!r} in {args.dataset}: no rollout", file=sys.stderr)
    if args.json:
        print(json.dumps(result))
    else:
        rollout = result["rollout_case2_mape_pct"]
        print(f"R² = {result['r2']:.5f}, MAPE = {result['mape_pct']:.3f} % on {result['n_valid']} held-out samples "
              f"({result['n_train']} training); rollout {args.rollout_source}: "
              + ("n/a" if rollout is None else f"MAPE = {rollout:.3f} %"))
    return 0


def _run_and_report(args: argparse.Namespace, run: Callable, settings: Any, label: Callable[[Any], str],
                    key: str) -> int:
    """Run the campaign or the identification (``run(settings)``): a line per job, the failures, the JSON
    summary under ``key`` with ``--json``; the exit status."""
    try:
        results = run(settings, progress=not args.no_progress)
    except KeyboardInterrupt:
        return _interrupted(args.command, settings.out_dir)
    for r in results:
        print(f"{label(r)}: {r.status} ({r.wall_s:.1f} s) {r.recording} {r.detail}".rstrip())
    _report_failures(results, label)
    if args.json:
        print(summary_json(results, key=key))
    return 1 if any(r.status == "failed" for r in results) else 0


def _campaign(args: argparse.Namespace) -> int:
    settings = CampaignSettings(cases=tuple(args.cases), **_runner_settings(args))
    return _run_and_report(args, run_campaign, settings, lambda r: f"case {r.case}", "cases")


def _identify(args: argparse.Namespace) -> int:
    ident = IDENT_SETS[args.plant]
    if ident.name == "part":  # every run would fail on it: say so once, before starting any
        try:
            require_pyslm()
        except ValueError as err:
            raise CampaignError(f"--plant part: {err}") from None
    args.out_dir = args.out_dir or ident.out_dir
    settings = IdentifySettings(runs=select_ident_runs(getattr(args, "runs", None), ident.runs),
                                **_runner_settings(args))
    return _run_and_report(args, run_identification, settings, lambda r: r.name, "runs")


def _narx(args: argparse.Namespace) -> int:
    ident = IDENT_SETS[args.plant]
    held_out = args.held_out or ident.held_out
    paths = args.recordings or sorted((REPO_ROOT / ident.out_dir).glob("*.mcap"))
    paths = [p for p in paths if not p.name.endswith(".partial.mcap")]
    if not paths:
        raise DatasetError(f"no recordings given and none in {ident.out_dir} "
                           f"(run `{PROG} identify --plant {ident.name}`)")
    runs = [series_from_states(read_states(p), p.stem) for p in paths]
    held = [r for r in runs if r.name in held_out]
    train = [r for r in runs if r.name not in held_out]
    if not held or not train:
        raise DatasetError("need both training and held-out runs; "
                           f"held out {[r.name for r in held]} of {[r.name for r in runs]}")
    process = {**process_record(paths), "plant": ident.name}
    provenance, candidates = {"process": process}, None
    if args.structure_of is not None:
        try:
            structure = _check_structure(args.structure_of, train[0].sample_period_s)
        except UsageError as err:
            raise DatasetError(str(err)) from None
        candidates = [candidate_of(structure)]
        provenance["structure_of"] = str(args.structure_of)
    model, best, table = select_and_fit(train, held, seed=args.seed, provenance=provenance, candidates=candidates)
    out = model.save(args.out or ident.model_path)
    for row in table:
        print(f"lags p {row['n_power_lags']:2d}, T {row['n_temperature_lags']:2d}, output {row['output']:8s}, "
              f"squares {row['quadratic']!s:5s}, p×T {row['interaction']!s:5s}, ℓ >= {row['length_scale_floor']}, "
              f"λ {row['smoothing']:g}: "
              f"{ROLLOUT_HORIZON}-step rollout {row[f'rollout_h{ROLLOUT_HORIZON}_mape_pct']:.2f} %, "
              f"one-step MAPE {row['mape_pct']:.2f} %, coverage {row['coverage_95_pct']:.1f} %")
    print(
        f"selected: {model.n_power_lags} power and {model.n_temperature_lags} temperature lags, output "
        f"{model.output}, squares {best['quadratic']}, p×T {best['interaction']}, "
        f"forecast persistence {model.forecast_persistence} -> {out}"
    )
    if args.json:
        print(json.dumps({k: v for k, v in best.items()}))
    return 0


def _tune_pid(args: argparse.Namespace) -> int:
    record = retune(args.model)
    pid = record["pid"]
    print(f"PID kp_w = {pid['kp_w']:.4g} W, ki_w = {pid['ki_w']:.4g} W/step, kd_w = 0 W from "
          f"{len(pid['runs'])} staircases; nominal power {record['nominal_power_w']:g} W -> {args.model}",
          file=sys.stderr)
    if args.json:
        print(json.dumps(record))
    return 0


def _refit(args: argparse.Namespace) -> int:
    out = args.out or args.model
    try:
        remnant = "keep" if args.remnant_states is None else None if args.remnant_states == 0 else RemnantFeature(
            n_states=args.remnant_states, n_sources=args.remnant_sources, offsets=args.remnant_offsets)
    except ValueError as exc:
        raise DatasetError(f"--remnant-states/--remnant-sources: {exc}") from None
    if args.drop and args.out is None:
        raise LearnError("--drop needs --out (the model without those runs is not the one it was refitted from)")
    best = refit(args.model, out, remnant, tuple(args.drop),
                 None if args.power_form is None else POWER_FORM_NAMES[args.power_form])
    key = rollout_key(NarxGPModel.load(out).sample_period_s)
    print(f"refitted {args.model} -> {out}: held-out R² {best['r2']:.3f}, {key} {best[key]:.2f} %", file=sys.stderr)
    if args.json:
        print(json.dumps(best))
    return 0


def _check_structure(path: Path, period_s: float) -> NarxGPModel:
    """The delay-aware model at ``path``; :class:`UsageError` naming ``--structure-of`` unless it is one
    learned at ``period_s`` [s]."""
    try:
        model = NarxGPModel.load(path)
    except (GPError, OSError, ValueError) as err:
        raise UsageError(f"--structure-of: {' '.join(str(err).split())}") from None
    if not math.isclose(model.sample_period_s, period_s, rel_tol=1e-9):
        raise UsageError(f"--structure-of {path}: learned at a sample period of {model.sample_period_s:g} s, "
                         f"this process's is {period_s:g} s")
    return model


def _learn_part(args: argparse.Namespace, plant: dict) -> dict:
    """The part fields of :class:`LearnSettings` (``part_stl``, ``n_layers``) from ``--scenario part --part
    --layers``; :class:`UsageError` naming the option."""
    if args.scenario != "part":
        for option, value in (("--part", args.part), ("--layers", args.layers)):
            if value is not None:
                raise UsageError(f"{option} needs --scenario part")
        return {}
    stl = Path(args.part or EXAMPLE_STL)
    layers = PART_IDENT_LAYERS if args.layers is None else args.layers
    try:
        require_pyslm()
        scenario("part", **plant, part_stl=str(stl), n_layers=layers)
    except (ValueError, TypeError) as err:
        raise UsageError(f"--scenario part --part {stl} --layers {layers}: {err}") from None
    return {"part_stl": stl, "n_layers": layers}


def _learn(args: argparse.Namespace) -> int:
    try:
        data = load_toml(args.config)
        unknown = sorted(set(data) - {"plant", "controller"})
        if unknown:
            raise UsageError(f"{args.config}: unknown table(s) {', '.join(unknown)}; expected [plant], [controller]")
        plant = data.get("plant", {})
        search = {} if args.h_um is None else {"h_fine_m": args.h_um * 1e-6}
        try:
            plant_settings = scenario("layer", **plant, **search).settings
        except (ValueError, TypeError) as err:
            raise UsageError(f"{args.config} [plant]: {err}") from None
        if args.frame_period_s is not None:
            try:
                frame_ratio(args.frame_period_s, plant_settings.dt_s)
            except ValueError as err:
                raise UsageError(str(err)) from None
            plant = {**plant, "frame_period_s": args.frame_period_s}
        period_s = args.frame_period_s or plant_settings.sample_period_s
        table = {k: v for k, v in data.get("controller", {}).items() if k != "name"}
        overrides = {} if args.set_point_mm2 is None else {"set_point_m2": args.set_point_mm2 * 1e-6}
        if args.set_point_mm2 is not None and not (math.isfinite(args.set_point_mm2) and args.set_point_mm2 > 0):
            raise UsageError(f"--set-point-mm2 (set_point) must be > 0, got {args.set_point_mm2}")
        controller = build(ControllerSettings, table, f"{args.config} [controller]", **overrides)
        if args.structure_of is not None:
            _check_structure(args.structure_of, period_s)
        part = _learn_part(args, plant)
        if missing := [str(p) for p in args.extra_runs if not p.is_file()]:
            raise UsageError(f"--extra-runs: no recording {', '.join(missing)}")
    except UsageError as err:
        raise LearnError(str(err)) from None
    settings = LearnSettings(plant=tuple(plant.items()), set_point_m2=controller.set_point_m2,
                             power_min_w=controller.power_min_w, power_max_w=controller.power_max_w,
                             model_out=args.out, search_plant=tuple(search.items()), seed=args.seed,
                             structure_of=args.structure_of, extra_runs=tuple(args.extra_runs), **part,
                             **_runner_settings(args))
    try:
        report = learn(settings, progress=not args.no_progress,
                       log=(lambda m: None) if args.no_progress else (lambda m: print(m, file=sys.stderr)))
    except KeyboardInterrupt:
        return _interrupted("learn", settings.out_dir)
    failed = [r for r in report["runs"] if r["status"] == "failed"]
    _report_failures([JobResult(**r) for r in failed], lambda r: r.name)
    if report["status"] == "ok":
        m = report["metrics"]
        print(f"operating point {report['operating_point']['power_w']:.1f} W; held-out R² = {m['r2']:.4f}, "
              f"MAPE = {m['mape_pct']:.2f} %, {rollout_horizon(period_s)}-step rollout "
              f"{m[rollout_key(period_s)]:.2f} % -> {settings.model_out}"
              f" (report {settings.report_out})")
    if args.json:
        print(json.dumps(report))
    return 0 if report["status"] == "ok" else 1


def main(argv: Sequence[str] | None = None) -> int:
    """Run one sub-command; return the exit status (2 for user errors, with a one-line reason)."""
    parser = build_parser()
    args = parser.parse_args(argv)
    command = {"dataset": _dataset, "train": _train, "evaluate": _evaluate, "campaign": _campaign, "narx": _narx,
               "identify": _identify, "learn": _learn, "tune-pid": _tune_pid,
               "refit": _refit}[args.command]
    try:
        return command(args)
    except GPError as exc:
        print(f"{PROG} {args.command}: error: {' '.join(str(exc).split())}", file=sys.stderr)
        return 2
