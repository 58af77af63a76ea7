"""Learning a process: ``python -m gp_trainer learn --config FILE.toml [--scenario part --part X.stl]``.

One command takes a process (a ``[plant]`` table, as ``launch.py --config`` takes it, on the plate or
on a part built layer by layer) to a delay-aware model of it:

1. **Operating point** (:func:`find_operating_power`): the power that holds the set point along a
   track, by regula falsi on the plant's steady area over a single track (a few short FE runs,
   :func:`fe_steady_area`), after checking that the set point is reachable within the controller's
   power limits.
2. **Runs** (:class:`gp_trainer.campaign.ProcessDesign`; on a part
   :class:`gp_trainer.campaign.PartDesign`): stage 1, open-loop staircases about the operating power
   and closed-loop runs at set points about the target; stage 2, the preview MPC with the stage-1
   model. Both on the campaign's runner (:func:`gp_trainer.campaign.run_jobs`:
   Dask, partial/complete recordings, a re-run skips complete ones).
3. **Fit** (:func:`gp_trainer.narx_fit.select_and_fit`: selection by the held-out 40-step rollout)
   after each stage, the held-out metrics and plots of the final model, and a JSON report.
4. **Controller record** (:func:`controller_record`, in the model's ``provenance.controller``): the
   operating power, from which every controller starts, and the PID baseline's gains tuned on the
   training staircases (:mod:`gp_trainer.pid_tuning`).

The functional core (:func:`find_operating_power`, :class:`~gp_trainer.campaign.ProcessDesign`) is
free of FE runs; :func:`learn` is the shell that runs them.
"""

from __future__ import annotations

import json
import math
import sys
from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any, Literal

import numpy as np

from controller_node.process import preview_steps
from gp_model.atomic import atomic_write
from gp_model.build_up import rollout_horizon
from gp_model.narx import NarxGPModel, RunSeries, series_from_states
from gp_model.plan_feature import RemnantFeature
from gp_trainer.campaign import PART_IDENT_LAYERS, IdentRun, PartDesign, ProcessDesign, run_jobs
from gp_trainer.dataset import read_states, recording_info
from gp_trainer.errors import CampaignError, LearnError
from gp_trainer.evaluate import plot_narx
from gp_trainer.jobs import RunnerSettings, job_recording
from gp_trainer.narx_fit import candidate_of, rollout_key, select_and_fit
from gp_trainer.pid_tuning import pid_record
from gp_trainer.provenance import REPO_ROOT

SEARCH_SCENARIO = "single-track"
"""The scenario of the operating-point search: one 5 mm track at the plant's speed."""
SEARCH_REL_TOL = 0.005
"""The search stops when the steady area is within this fraction of the set point."""
SEARCH_MAX_EVALUATIONS = 10
"""FE runs of the search at most (the bounds included)."""


@dataclass(frozen=True)
class OperatingPoint:
    """The power that holds a set point along a track.

    Attributes
    ----------
    power_w : float
        The operating power [W].
    area_m2 : float
        The plant's steady area at ``power_w`` [m²].
    set_point_m2 : float
        The set point [m²].
    evaluations : tuple[tuple[float, float], ...]
        Every (power [W], steady area [m²]) the search ran, in order.
    """

    power_w: float
    area_m2: float
    set_point_m2: float
    evaluations: tuple[tuple[float, float], ...]


def find_operating_power(steady_area_m2: Callable[[float], float], set_point_m2: float, power_min_w: float,
                         power_max_w: float, *, rel_tol: float = SEARCH_REL_TOL,
                         max_evaluations: int = SEARCH_MAX_EVALUATIONS) -> OperatingPoint:
    """The power in ``[power_min_w, power_max_w]`` whose steady area is ``set_point_m2``.

    ``steady_area_m2(p)`` is the plant's steady melt-pool area [m²] at the constant power ``p`` [W],
    non-decreasing in ``p``. The search evaluates the upper bound, then the lower one (an area of 0
    at 0 W is taken without a run), then narrows the bracket by regula falsi (Illinois) until the
    area is within ``rel_tol`` of the set point or ``max_evaluations`` runs were made; it returns
    the evaluated power closest to the set point.

    Raises
    ------
    LearnError
        The set point lies outside the areas the power limits reach (naming ``set_point``), or bad
        limits.
    """
    if not (math.isfinite(set_point_m2) and set_point_m2 > 0):
        raise LearnError(f"set_point must be > 0 mm², got {set_point_m2 * 1e6:g}")
    if not 0 <= power_min_w < power_max_w or not math.isfinite(power_max_w):
        raise LearnError(f"power limits must satisfy 0 <= power_min_w < power_max_w, got {power_min_w:g}, "
                         f"{power_max_w:g} W")
    evaluations: list[tuple[float, float]] = []

    def area(power_w: float) -> float:
        value = float(steady_area_m2(power_w))
        evaluations.append((float(power_w), value))
        return value

    hi, a_hi = power_max_w, area(power_max_w)
    if a_hi < set_point_m2:
        raise LearnError(f"set_point {set_point_m2 * 1e6:g} mm² is not reachable: the plant's steady area at the "
                         f"controller's power_max_w {power_max_w:g} W is {a_hi * 1e6:.4g} mm²")
    lo, a_lo = power_min_w, (0.0 if power_min_w == 0 else area(power_min_w))
    if a_lo > set_point_m2:
        raise LearnError(f"set_point {set_point_m2 * 1e6:g} mm² is not reachable: the plant's steady area at the "
                         f"controller's power_min_w {power_min_w:g} W is {a_lo * 1e6:.4g} mm²")
    side = 0
    while len(evaluations) < max_evaluations:
        f_lo, f_hi = a_lo - set_point_m2, a_hi - set_point_m2
        power = hi if f_hi == f_lo else (lo * f_hi - hi * f_lo) / (f_hi - f_lo)
        power = min(max(power, lo + 1e-3 * (hi - lo)), hi - 1e-3 * (hi - lo))
        value = area(power)
        if abs(value / set_point_m2 - 1.0) <= rel_tol:
            break
        if value < set_point_m2:
            lo, a_lo = power, value
            if side == -1:  # Illinois: the end that stayed twice is pulled halfway to the set point
                a_hi = set_point_m2 + 0.5 * (a_hi - set_point_m2)
            side = -1
        else:
            hi, a_hi = power, value
            if side == 1:
                a_lo = set_point_m2 + 0.5 * (a_lo - set_point_m2)
            side = 1
    power, value = min(evaluations, key=lambda e: abs(e[1] - set_point_m2))
    return OperatingPoint(power, value, set_point_m2, tuple(evaluations))


def median_power_w(recording: Path) -> float:
    """The median power [W] a controller applied over a recorded run (every state after the first)."""
    return float(np.median([s.power_w for s in read_states(recording)[1:]]))


def fe_steady_area(plant: dict[str, Any], scenario_name: str = SEARCH_SCENARIO) -> Callable[[float], float]:
    """``steady_area_m2(power_w)`` of the FE plant ``plant`` (a ``[plant]`` table): the mean area [m²]
    over the last fifth of a single track at that constant power (:func:`fe_node.driver.quasi_steady`)."""
    from fe_node.driver import quasi_steady, run_open_loop
    from fe_node.scenarios import scenario

    def steady_area_m2(power_w: float) -> float:
        return quasi_steady(run_open_loop(scenario(scenario_name, **{**plant, "power_w": float(power_w)})))[
            "area_mm2"] * 1e-6

    return steady_area_m2


@dataclass(frozen=True)
class LearnSettings(RunnerSettings):
    """What ``learn`` learns and where it writes (the runner's fields as :class:`RunnerSettings`).

    Attributes
    ----------
    plant : tuple[tuple[str, Any], ...]
        The process's ``[plant]`` table.
    set_point_m2 : float
        The target set point [m²].
    power_min_w, power_max_w : float
        The controller's power limits [W].
    model_out : Path
        The final model; the stage-1 model goes beside it (:attr:`stage1_out`).
    search_plant : tuple[tuple[str, Any], ...]
        Extra ``[plant]`` keys of the operating-point search only (e.g. a coarser mesh in tests).
    seed : int
        Seed of the fits.
    part_stl : Path or None
        The part (``--scenario part --part``): the runs build its first ``n_layers`` layers
        (:class:`~gp_trainer.campaign.PartDesign`). None: a plate process
        (:class:`~gp_trainer.campaign.ProcessDesign`).
    n_layers : int
        Layers each run on the part builds.
    extra_runs : tuple[Path, ...]
        Recordings of other runs on the same process (e.g. another part's identification runs) added to the
        training runs of both stages, never to the held-out ones; recorded as ``provenance.extra_runs``.
    structure_of : Path or None
        A learned model whose selected candidate (:func:`~gp_trainer.narx_fit.candidate_of`: lags, output
        map, squares, p×T, feature, length-scale floor, smoothness prior, power form, remnant) both stages
        fit, instead of selecting among every candidate: a new process learned in the structure of a known
        one, at a fraction of the fitting time. None: select.
    """

    plant: tuple[tuple[str, Any], ...] = ()
    set_point_m2: float = 0.063e-6
    power_min_w: float = 0.0
    power_max_w: float = 350.0
    model_out: Path = Path("out/learn/narx_gp.json")
    out_dir: Path = Path("recordings/learn")
    search_plant: tuple[tuple[str, Any], ...] = field(default=())
    seed: int = 0
    structure_of: Path | None = None
    part_stl: Path | None = None
    n_layers: int = PART_IDENT_LAYERS
    extra_runs: tuple[Path, ...] = ()

    @property
    def stage1_out(self) -> Path:
        """The stage-1 model: ``<model>_stage1.json`` beside the model."""
        return self.model_out.with_name(f"{self.model_out.stem}_stage1{self.model_out.suffix}")

    @property
    def report_out(self) -> Path:
        """The JSON report, in the recordings directory."""
        return self.out_dir / "learn.json"


def _series(recordings_dir: Path, runs) -> list[RunSeries]:
    return [series_from_states(read_states(recordings_dir / f"{r.name}.mcap"), r.name) for r in runs]


def controller_record(recordings_dir: Path, design: ProcessDesign | PartDesign) -> dict[str, Any]:
    """The model's ``provenance.controller``: ``nominal_power_w``, the operating power [W] (the power
    at laser-on and during the build-up of every controller on this process), and ``pid``, the PID
    baseline tuned on the design's training staircases of the scenarios' own plans (not the held-out
    ones, nor the turnaround staircases, whose short tracks are mostly turnarounds) by
    :func:`gp_trainer.pid_tuning.pid_record`; on a process observed at a camera's frame period
    (``[plant] frame_period_s``) also ``preview``, the preview MPC's sample counts at that period
    (:func:`controller_node.process.preview_steps`)."""
    held = set(design.held_out())
    staircases = [r for r in design.stage1_runs()
                  if isinstance(r, IdentRun) and r.tracks is None and r.name not in held]
    record = {"nominal_power_w": design.operating_power_w,
              "pid": pid_record(_series(recordings_dir, staircases), design.setpoint_mm2 * 1e-6,
                                part=isinstance(design, PartDesign))}
    if frame_period_s := dict(design.plant).get("frame_period_s"):
        record["preview"] = preview_steps(float(frame_period_s))
    return record


def process_record(paths: list[Path]) -> dict[str, Any]:
    """The process of the FE plant that recorded ``paths`` (``material``, ``powder_layer_m`` [m]) from
    their recorded configuration; :class:`DatasetError` naming the key if they differ."""
    from gp_model.errors import DatasetError

    found: dict[str, set] = {"material": set(), "powder_layer_m": set()}
    for path in paths:
        plant = recording_info(path)["config"].get("plant") or {}
        settings = (plant.get("settings") or {}) if isinstance(plant, dict) else {}
        material = settings.get("material")
        found["material"].add(material.get("name") if isinstance(material, dict) else None)
        found["powder_layer_m"].add(settings.get("powder_layer_m"))
    record = {}
    for key, values in found.items():
        values.discard(None)
        if len(values) > 1:
            raise DatasetError(f"the recordings are of different {key}: {', '.join(map(str, sorted(values)))}")
        record[key] = values.pop() if values else None
    return record


def retune(model_path: Path) -> dict[str, Any]:
    """Write :func:`controller_record` into the model at ``model_path`` from the recordings and design its
    ``provenance.design`` names (``python -m gp_trainer tune-pid``); the record."""
    model = NarxGPModel.load(model_path)
    design, recordings_dir = design_from_record(model.provenance.get("design") or {})
    recordings_dir = recordings_dir if recordings_dir.is_absolute() else REPO_ROOT / recordings_dir
    model.provenance["controller"] = controller_record(recordings_dir, design)
    model.save(model_path)
    return model.provenance["controller"]


def refit(model_path: Path, out: Path, remnant: RemnantFeature | None | Literal["keep"] = "keep",
          drop: Sequence[str] = (), power_form: tuple[str, bool] | None = None) -> dict[str, Any]:
    """Refit a learned model with the current code (``python -m gp_trainer refit``): the candidate it was
    selected as (:func:`~gp_trainer.narx_fit.candidate_of`), its seed and GP points, on its training runs in
    their recorded order and scored on its design's held-out runs, all read from the recordings directory
    its ``provenance.design`` names; written to ``out`` with its design, process and controller records.
    For a change of the model's definition (e.g. the turnaround feature's extent) on the same data without
    a new selection; ``remnant`` replaces the candidate's remnant terms (None: none; "keep": the model's);
    ``drop`` names training runs to leave out (a model that never saw their plans, to be judged off its
    training set), recorded as ``provenance.dropped_runs``; ``power_form`` replaces its (power map, GP's
    mean-power input) (:data:`~gp_trainer.narx_fit.POWER_FORM_NAMES`; None: the model's). Returns the
    held-out row.

    Raises
    ------
    LearnError
        A name in ``drop`` is not one of the model's training runs.
    """
    old = NarxGPModel.load(model_path)
    design, recordings_dir = design_from_record(old.provenance.get("design") or {})
    recordings_dir = recordings_dir if recordings_dir.is_absolute() else REPO_ROOT / recordings_dir
    names = list(old.provenance.get("runs") or [])
    if unknown := [n for n in drop if n not in names]:
        raise LearnError(f"--drop: {', '.join(unknown)} not among the model's training runs ({', '.join(names)})")
    names = [n for n in names if n not in drop]
    held_names = list(design.held_out())
    extra = {Path(p).stem: Path(p) for p in old.provenance.get("extra_runs", [])}
    series = [series_from_states(read_states(extra.get(n, recordings_dir / f"{n}.mcap")), n)
              for n in names + held_names]
    train, held = series[:len(names)], series[len(names):]
    provenance = {key: old.provenance[key] for key in ("design", "process", "controller", "extra_runs")
                  if key in old.provenance}
    dropped = [*old.provenance.get("dropped_runs", []), *drop]
    if dropped:
        provenance["dropped_runs"] = dropped
    candidate = list(candidate_of(old))
    if remnant != "keep":
        candidate[-1] = remnant
    if power_form is not None:
        candidate[-2] = tuple(power_form)
    model, best, _ = select_and_fit(train, held, seed=int(old.provenance.get("seed", 0)),
                                    n_train=int(old.provenance.get("n_train", 150)), provenance=provenance,
                                    candidates=[tuple(candidate)])
    model.save(out)
    return best


def _fit(settings: LearnSettings, design: ProcessDesign | PartDesign, runs, out: Path, provenance: dict[str, Any]
         ) -> tuple[NarxGPModel, dict[str, Any], list[RunSeries]]:
    """Select and fit the model on ``runs`` but the design's held-out ones, write it to ``out``; the model,
    its held-out row and the held-out runs."""
    series = _series(settings.out_dir, runs)
    held_names = set(design.held_out())
    held = [r for r in series if r.name in held_names]
    train = [r for r in series if r.name not in held_names]
    train += [series_from_states(read_states(path), path.stem) for path in settings.extra_runs]
    paths = [job_recording(settings, r.job()) for r in runs] + list(settings.extra_runs)
    record = {**provenance, "process": {**process_record(paths), "plant": dict(settings.plant)}}
    if settings.extra_runs:
        record["extra_runs"] = [str(path) for path in settings.extra_runs]
    candidates = None if settings.structure_of is None else [candidate_of(NarxGPModel.load(settings.structure_of))]
    if candidates is not None:
        record["structure_of"] = str(settings.structure_of)
    model, best, _ = select_and_fit(train, held, seed=settings.seed, provenance=record, candidates=candidates,
                                    workers=1 if settings.sequential else settings.workers)
    model.save(out)
    return model, best, held


def design_record(design: ProcessDesign | PartDesign, recordings_dir: Path) -> dict[str, Any]:
    """The design as the model's ``provenance.design`` records it (what ``evaluate`` rebuilds it from)."""
    if isinstance(design, PartDesign):
        return {"operating_power_w": design.operating_power_w, "setpoint_mm2": design.setpoint_mm2,
                "stage1_model": design.stage1_model, "plant": dict(design.plant), "part_stl": design.part_stl,
                "n_layers": design.n_layers, "track_power_w": design.track_power_w,
                "held_out": list(design.held_out()), "recordings_dir": str(recordings_dir)}
    return {"operating_power_w": design.operating_power_w, "setpoint_mm2": design.setpoint_mm2,
            "stage1_model": design.stage1_model, "plant": dict(design.plant),
            "feedback_controller": design.feedback_controller,
            "feedforward_scenarios": list(design.feedforward_scenarios),
            "turn_tracks": None if design.turn_tracks is None else list(design.turn_tracks),
            "held_out": list(design.held_out()),
            "recordings_dir": str(recordings_dir)}


def design_from_record(record: dict[str, Any]) -> tuple[ProcessDesign | PartDesign, Path]:
    """The design and recordings directory a model's ``provenance.design`` records (a part's if it names
    ``part_stl``)."""
    try:
        if "part_stl" in record:
            return PartDesign(float(record["operating_power_w"]), float(record["setpoint_mm2"]),
                              str(record["stage1_model"]), str(record["part_stl"]), int(record["n_layers"]),
                              tuple(dict(record["plant"]).items()),
                              None if record.get("track_power_w") is None else float(record["track_power_w"])
                              ), Path(record["recordings_dir"])
        design = ProcessDesign(float(record["operating_power_w"]), float(record["setpoint_mm2"]),
                               str(record["stage1_model"]), tuple(dict(record["plant"]).items()),
                               str(record["feedback_controller"]), tuple(record["feedforward_scenarios"]),
                               turn_tracks=None if record.get("turn_tracks") is None
                               else (int(record["turn_tracks"][0]), float(record["turn_tracks"][1])))
        return design, Path(record["recordings_dir"])
    except (KeyError, TypeError, ValueError) as err:
        raise CampaignError(f"the model's provenance.design is incomplete ({err})") from None


def _stage(jobs_of, settings: LearnSettings, report: dict[str, Any], progress: bool,
           log: Callable[[str], None]) -> bool:
    """Run ``jobs_of``, add their results to ``report["runs"]`` (once per run) and return whether all succeeded;
    if not, the report is marked ``failed`` with the failed runs and written."""
    results = run_jobs([r.job() for r in jobs_of], settings, progress=progress)
    for r in results:
        log(f"{r.name}: {r.status} ({r.wall_s:.1f} s) {r.recording}")
    done = {r["name"] for r in report.get("runs", [])}
    report.setdefault("runs", []).extend(asdict(r) for r in results if r.name not in done)
    if failed := [r.name for r in results if r.status == "failed"]:
        report.update(status="failed", failed=failed)
        _write_report(settings.report_out, report)
        return False
    return True


def _repo_relative(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it, else absolute."""
    path = path.absolute()
    return str(path.relative_to(REPO_ROOT) if path.is_relative_to(REPO_ROOT) else path)


def learn(settings: LearnSettings, *, progress: bool = True,
          log: Callable[[str], None] = lambda m: print(m, file=sys.stderr)) -> dict[str, Any]:
    """Learn the process of ``settings``: operating point, stage-1 runs and fit, stage-2 runs and fit,
    held-out evaluation, plots and the report (also written to :attr:`LearnSettings.report_out`).

    Returns
    -------
    dict
        The report: ``status`` (``ok``, or ``failed`` with the runs that failed, and no model),
        ``operating_point`` (on a part also ``part_operating_point``), ``runs``, ``held_out``, ``stage1`` and
        ``metrics`` (the model's held-out metrics), ``model_stage``: the stage whose fit predicts the held-out
        runs better (its 40-step rollout) is the model (2 unless stage 2's closed-loop runs made it worse; then
        ``stage2`` holds stage 2's metrics), paths.
    """
    plant = dict(settings.plant)
    log(f"operating point: searching the power that holds {settings.set_point_m2 * 1e6:g} mm² on a single track")
    op = find_operating_power(fe_steady_area({**plant, **dict(settings.search_plant)}), settings.set_point_m2,
                              settings.power_min_w, settings.power_max_w)
    log(f"operating point: {op.power_w:.1f} W gives {op.area_m2 * 1e6:.4g} mm² ({len(op.evaluations)} FE runs)")
    stage1_name = _repo_relative(settings.stage1_out)
    report: dict[str, Any] = {
        "operating_point": {**asdict(op), "power_fraction_of_max": op.power_w / settings.power_max_w,
                            "power_min_w": settings.power_min_w, "power_max_w": settings.power_max_w}}
    if settings.part_stl is None:
        design = ProcessDesign(float(round(op.power_w)), round(settings.set_point_m2 * 1e6, 6), stage1_name,
                               tuple(plant.items()))
    else:
        design = PartDesign(float(round(op.power_w)), round(settings.set_point_m2 * 1e6, 6), stage1_name,
                            _repo_relative(settings.part_stl), settings.n_layers, tuple(plant.items()),
                            track_power_w=float(round(op.power_w)))
        if not _stage(design.pid_runs(), settings, report, progress, log):
            return report
        target = design.target_pid_run.name
        part_power = median_power_w(settings.out_dir / f"{target}.mcap")
        design = replace(design, operating_power_w=float(round(part_power)))
        report["part_operating_point"] = {"power_w": part_power, "from_run": target,
                                          "track_power_w": design.track_power_w}
        log(f"part operating point: {part_power:.1f} W, the PID's median power in {target}")
    report.update({
        "plant": plant, "part_stl": None if settings.part_stl is None else str(settings.part_stl),
        "n_layers": None if settings.part_stl is None else settings.n_layers,
        "set_point_mm2": design.setpoint_mm2, "held_out": list(design.held_out()),
        "model": str(settings.model_out), "stage1_model": str(settings.stage1_out),
        "recordings_dir": str(settings.out_dir)})
    provenance = {"design": design_record(design, settings.out_dir)}
    stages = ((design.stage1_runs(), design.stage1_runs(), settings.stage1_out, "stage1"),
              (design.stage2_runs(), design.runs(), settings.model_out, "metrics"))
    for stage, (record, fit_on, out, key) in enumerate(stages, 1):
        if not _stage(record, settings, report, progress, log):
            return report
        if stage == 1:
            provenance["controller"] = controller_record(settings.out_dir, design)
        extra = f" and {len(settings.extra_runs)} extra runs" if settings.extra_runs else ""
        log(f"stage {stage}: selecting and fitting the model on {len(fit_on)} runs{extra}")
        model, report[key], held = _fit(settings, design, fit_on, out, provenance)
        horizon = rollout_horizon(model.sample_period_s)
        log(f"stage {stage}: held-out {horizon}-step rollout {report[key][rollout_key(model.sample_period_s)]:.2f} % "
            f"-> {out}")
    key = rollout_key(model.sample_period_s)
    report["model_stage"] = 2
    if report["stage1"][key] < report["metrics"][key]:  # stage 2's closed-loop runs made the held-out prediction worse
        report["stage2"], report["metrics"], report["model_stage"] = report["metrics"], report["stage1"], 1
        model = NarxGPModel.load(settings.stage1_out)
        model.save(settings.model_out)
        log(f"the stage-1 model predicts the held-out runs better: it is the model -> {settings.model_out}")
    report["plots"] = plot_narx(model, held, settings.out_dir)
    report["status"] = "ok"
    _write_report(settings.report_out, report)
    return report


def _write_report(path: Path, report: dict[str, Any]) -> None:
    atomic_write(path, lambda handle: handle.write(json.dumps(report, indent=1).encode()))
