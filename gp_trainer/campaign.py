"""The data campaign: the nine Table 2 cases run open loop, in parallel on Dask, each to its own MCAP.

Every case is a separate run of the project's own entry point,

    python launch.py --scenario table2-caseN --controller none --no-progress --json
                     --out <dir>/table2-caseN.partial.mcap --run-id table2-caseN

so the data come through exactly the path a live run takes (plant → zenoh → recorder).
"Open loop" here means launch.py's ``--controller none``: no controller node, the plant plays
the case's own power/speed profile (constant, sinusoidal or staircase, Table 2).
``--controller open-loop`` is something else in launch.py, the paper's constant-power baseline
*controller*, which would overwrite the profiles and leave the GP without power/speed
excitation. A case
writes to ``*.partial.mcap`` and is renamed to ``table2-caseN.mcap`` only when the launcher
succeeded and the recorder marked the file complete; a re-run skips cases whose final
recording is complete. A failed case keeps its ``.partial.mcap`` for inspection.

The same runner records the identification runs (``python -m gp_trainer identify``): seeded
random power staircases of the ``ident-layer`` and ``ident-double-track`` scenarios
(:mod:`fe_node.scenarios`) at several mean powers, each ``launch.py --scenario ident-... --controller
none --config <tmp>/<name>.toml`` whose ``[plant]`` table carries ``ident_seed``,
``ident_mean_w`` and ``ident_amplitude_w`` (:data:`IDENT_RUNS`). In general a run is a
:class:`Job`: a name (run id and recording stem), a scenario, an optional ``[plant]`` table and
further launcher arguments.

Jobs run on Dask distributed (:mod:`gp_trainer.distributed`): a ``LocalCluster`` of
``workers`` worker processes (TLS) by default, or an existing TLS cluster (``scheduler``,
``tls://HOST:PORT``). A worker runs a job exactly as above, as a ``launch.py`` subprocess
(:func:`run_job`), so the plant, recorder and controller stay separate processes; the workers must
see the repository, the interpreter and the output directory at the same paths as this process.
The FE runs are lockstep and deterministic, run ids and paths depend only on the job, and results
come back in job order, so the recordings' plant states, and the dataset built from them, are
the same bit for bit whichever worker ran a job and in which order the jobs finished
(``tests/test_campaign_dask.py``). A failed job is retried once (``retries``), then reported;
the other jobs are kept.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any

from fe_node.presets import NAMES as PRESETS
from fe_node.presets import preset
from fe_node.scenarios import TRAINING_MESH, scenario
from fe_node.settings import Settings
from gp_model.shipped import PART_MODEL_PATH, PLATE_MODEL_PATH
from gp_trainer.distributed import check_scheduler_address, dask_client, run_on_dask
from gp_trainer.errors import CampaignError
from gp_trainer.jobs import (
    Job,
    JobResult,
    RunnerSettings,
    RunSpec,
    interrupt_running,
    job_command,
    job_recording,
    plant_toml,
    recording_complete,
    run_job,
)
from gp_trainer.provenance import REPO_ROOT
from messages.recording import read_messages, run_config

TABLE2_CASES = tuple(range(1, 10))
DEFAULT_IDENT_DIR = Path("recordings/identification")


@dataclass(frozen=True)
class CampaignSettings(RunnerSettings):
    """What the campaign runs and where it writes (the runner's fields as :class:`RunnerSettings`).

    Attributes
    ----------
    cases : tuple[int, ...]
        Table 2 case numbers to run (1-9).
    out_dir : Path
        Directory of the recordings.
    """

    cases: tuple[int, ...] = TABLE2_CASES
    out_dir: Path = Path("recordings/campaign")


@dataclass(frozen=True, kw_only=True)
class CaseResult(JobResult):
    """Outcome of one Table 2 case: the :class:`JobResult` of its job, with its case number."""

    case: int


def scenario_name(case: int) -> str:
    """Scenario (and run id, recording stem) of Table 2 case ``case``, e.g. ``table2-case2``."""
    return f"table2-case{case}"


def case_job(case: int) -> Job:
    """The job of Table 2 case ``case``: its scenario, named after it, no config."""
    return Job(scenario_name(case), scenario_name(case))


def recording_path(settings: CampaignSettings, case: int) -> Path:
    """Final recording of one case."""
    return job_recording(settings, case_job(case))


def requested_mesh_m(job: Job, settings: RunnerSettings) -> float:
    """The FE mesh size ``h_fine_m`` [m] a run of ``job`` asks for: the runner's ``--h-um`` (launch.py's
    option wins over the job's ``[plant]`` table), else the table's ``h_fine_m``, else the plant's default."""

    args = list(getattr(settings, "launch_args", ()))
    if "--h-um" in args:
        return float(args[args.index("--h-um") + 1]) * 1e-6
    return float(dict(job.plant).get("h_fine_m", Settings().h_fine_m))


PLANT_KEYS = tuple(sorted({key for name in PRESETS for key in preset(name)}))
"""The plant settings the presets set (:mod:`fe_node.presets`): a recording a re-run keeps has the job's."""


def check_recorded_plant(path: Path, job: Job, settings: RunnerSettings) -> None:
    """:class:`CampaignError` if the complete recording ``path``, which a re-run would keep, was made on
    another FE mesh than ``job`` asks for (e.g. an earlier ``--h-um 50`` run in the same ``--out-dir``),
    or on another plant (a :data:`PLANT_KEYS` setting differs, e.g. a bare-plate run kept by a run of
    the default plant)."""

    recorded_settings = run_config(path).get("plant", {}).get("settings", {})
    recorded = recorded_settings.get("h_fine_m")
    wanted = requested_mesh_m(job, settings)
    if recorded is not None and not math.isclose(recorded, wanted, rel_tol=1e-9):
        raise CampaignError(f"{path} was recorded on a {recorded * 1e6:g} µm mesh, this run asks for "
                            f"{wanted * 1e6:g} µm: use another --out-dir, or delete it to record it again")
    try:
        plant = scenario(job.scenario, **dict(job.plant)).settings
    except ValueError as err:
        raise CampaignError(f"job {job.name}: [plant] {err}") from None
    differs = [k for k in PLANT_KEYS if k in recorded_settings and recorded_settings[k] != getattr(plant, k)]
    if differs:
        key = differs[0]
        raise CampaignError(f"{path} was recorded on another plant ({key} {recorded_settings[key]!r}, this run asks "
                            f"for {getattr(plant, key)!r}): use another --out-dir, or delete it to record it again")


def case_command(settings: CampaignSettings, case: int, out: Path) -> list[str]:
    """Command line that records one case to ``out``."""
    return job_command(settings, case_job(case), out)


def run_spec(settings: RunnerSettings) -> RunSpec:
    """The :class:`RunSpec` of ``settings`` (output directory made absolute)."""
    return RunSpec(settings.out_dir.absolute(), settings.launcher.absolute(), settings.python, settings.timeout_s,
                   settings.controller, tuple(getattr(settings, "launch_args", ())))


def states_sha256(path: Path) -> str | None:
    """SHA-256 of a recording's ``/plant/state`` messages (msgspec JSON, in file order): what the
    dataset is built from, free of wall-clock times; equal for equal FE runs wherever they ran."""
    import msgspec


    digest = hashlib.sha256()
    try:
        for state in read_messages(path, "/plant/state"):
            digest.update(msgspec.json.encode(state))
    except ValueError:
        return None
    return digest.hexdigest()


def _check_runner(settings: RunnerSettings) -> None:
    scheduler = getattr(settings, "scheduler", None)
    if settings.workers < 1:
        raise CampaignError(f"--workers must be at least 1, got {settings.workers}")
    if getattr(settings, "retries", 1) < 0:
        raise CampaignError(f"--retries must be >= 0, got {settings.retries}")
    if settings.timeout_s is not None and not settings.timeout_s > 0:
        raise CampaignError(f"--timeout must be > 0 s, got {settings.timeout_s}")
    if scheduler is not None and getattr(settings, "sequential", False):
        raise CampaignError("--scheduler and --sequential exclude each other")
    if scheduler is not None:

        check_scheduler_address(scheduler)
    if not settings.launcher.is_file():
        raise CampaignError(f"launcher not found: {settings.launcher}")


class _Progress:
    """The tqdm bar over jobs and one line per finished (or retried) job, on stderr."""

    def __init__(self, total: int, initial: int, unit: str, enabled: bool) -> None:
        from tqdm import tqdm

        self.enabled = enabled
        self.bar = tqdm(total=total, initial=initial, unit=unit, disable=not enabled, file=sys.stderr)

    def __call__(self, result: JobResult, final: bool) -> None:
        if not self.enabled:
            return
        where = f", {result.worker}" if result.worker else ""
        if final:
            self.bar.write(f"{result.name}: {result.status} ({result.wall_s:.1f} s{where})"
                           + (f" after {result.attempts} attempts: {result.detail}" if result.status == "failed"
                              else ""), file=sys.stderr)
            self.bar.set_postfix_str(f"{result.name} {result.status}")
            self.bar.update()
        else:
            self.bar.write(f"{result.name}: failed ({result.wall_s:.1f} s{where}): {result.detail}; retrying",
                           file=sys.stderr)

    def close(self) -> None:
        self.bar.close()


def _run_sequential(jobs: list[Job], spec: RunSpec, retries: int, report: _Progress) -> dict[str, JobResult]:
    """Every job in this process, one after the other, in job order (no Dask)."""
    results = {}
    try:
        for job in jobs:
            for attempt in range(1, retries + 2):
                result = run_job(spec, job, attempt)
                final = result.status != "failed" or attempt > retries
                report(result, final)
                if final:
                    results[job.name] = result
                    break
    except KeyboardInterrupt:
        interrupt_running()
        raise
    return results


def run_jobs(jobs: list[Job] | tuple[Job, ...], settings: RunnerSettings, *, progress: bool = True,
             unit: str = "run") -> list[JobResult]:
    """Record every job that has no complete recording yet, on Dask distributed.

    Jobs run on a ``LocalCluster`` of ``settings.workers`` worker processes (one thread each, so
    one job per worker at a time), or on the cluster at ``settings.scheduler``
    (``tls://HOST:PORT``), or, with ``settings.sequential``, in this process one after the other
    without Dask. Each job is one ``launch.py`` subprocess started by the worker
    (:func:`run_job`). A failed job is run again up to ``settings.retries`` times (default once);
    it is reported failed only if every attempt failed, and the other jobs are kept either way.
    Results come back in job order, whatever order the jobs finished in.

    Parameters
    ----------
    jobs : sequence of Job
        Distinct names.
    settings : RunnerSettings
        Output directory, workers or scheduler, launcher, interpreter, timeout, controller.
    progress : bool
        Show a tqdm progress bar over jobs and one line per finished job (on stderr).
    unit : str
        Unit name of the progress bar.

    Returns
    -------
    list[JobResult]
        One per job, in job order; ``states_sha256`` is set for every complete recording.

    Raises
    ------
    CampaignError
        No or duplicate jobs, ``workers`` < 1, a missing launcher, a malformed or unreachable
        scheduler.
    """
    names = [j.name for j in jobs]
    if not jobs or len(set(names)) != len(names):
        raise CampaignError(f"need at least one job and distinct names, got {names}")
    _check_runner(settings)
    for job in jobs:
        plant_toml(job.plant, job.controller_table)  # a bad [plant] table is a usage error before anything runs
    spec = run_spec(settings)
    spec.out_dir.mkdir(parents=True, exist_ok=True)
    results = {j.name: JobResult(j.name, str(job_recording(settings, j)), "skipped", 0.0, "recording complete", 0)
               for j in jobs if recording_complete(job_recording(settings, j))}
    for job in (j for j in jobs if j.name in results):
        check_recorded_plant(Path(results[job.name].recording), job, settings)
    pending = [j for j in jobs if j.name not in results]
    retries = getattr(settings, "retries", 1)
    with contextlib.ExitStack() as stack:
        client = None
        if pending and not getattr(settings, "sequential", False):

            client = stack.enter_context(dask_client(getattr(settings, "scheduler", None), settings.workers))
        report = _Progress(len(jobs), len(results), unit, progress)  # after the cluster is up (or refused)
        stack.callback(report.close)
        if client is not None:
            results.update(run_on_dask(client, pending, spec, retries, report))
        elif pending:
            results.update(_run_sequential(pending, spec, retries, report))
    return [dataclasses.replace(results[n], states_sha256=states_sha256(Path(results[n].recording)))
            if results[n].status != "failed" else results[n] for n in names]


def run_campaign(settings: CampaignSettings = CampaignSettings(), *, progress: bool = True) -> list[CaseResult]:
    """Record every case of ``settings.cases`` that has no complete recording yet.

    Parameters
    ----------
    settings : CampaignSettings
    progress : bool
        Show a tqdm progress bar over cases (on stderr).

    Returns
    -------
    list[CaseResult]
        One per case, in case order (whatever order they finished in).

    Raises
    ------
    CampaignError
        Unknown case numbers, ``workers`` < 1, a missing launcher or a bad ``scheduler``.
    """
    bad = sorted(set(settings.cases) - set(TABLE2_CASES))
    if bad or not settings.cases:
        raise CampaignError(f"Table 2 cases are 1-9, got {list(settings.cases)}")
    _check_runner(settings)
    cases = list(dict.fromkeys(settings.cases))
    done = run_jobs([case_job(c) for c in cases], settings, progress=progress, unit="case")
    by_case = {c: CaseResult(case=c, **asdict(r)) for c, r in zip(cases, done)}
    return [by_case[c] for c in settings.cases]


@dataclass(frozen=True)
class IdentRun:
    """One identification run: a seeded random power staircase of an ``ident-*`` scenario."""

    scenario: str
    mean_w: float
    amplitude_w: float
    seed: int
    n_layers: int | None = None
    """Layers to build (``ident-part``; None: the scenario's default)."""
    plant: tuple[tuple[str, Any], ...] = ()
    """``[plant]`` table of the process (e.g. ``preset``), before the run's own keys."""
    tracks: tuple[int, float] | None = None
    """(tracks, track length [m]) of the plan (None: the scenario's)."""

    @property
    def name(self) -> str:
        """Run id and recording stem, e.g. ``ident-layer-p250-s2``, ``ident-layer-8x5mm-p174-s7``,
        ``ident-part-block_5mm-p60-s21`` (a part other than the example: its STL's stem)."""
        plan = "" if self.tracks is None else f"-{self.tracks[0]}x{self.tracks[1] * 1e3:g}mm"
        stl = dict(self.plant).get("part_stl")
        part = "" if stl is None else f"-{Path(stl).stem}"
        return f"{self.scenario}{part}{plan}-p{self.mean_w:g}-s{self.seed}"

    def job(self) -> Job:
        """The launcher job: the scenario with its ``[plant]`` ``ident_*`` (and ``n_layers``, plan) overrides."""
        layers = () if self.n_layers is None else (("n_layers", int(self.n_layers)),)
        plan = () if self.tracks is None else (("n_tracks", int(self.tracks[0])),
                                               ("track_length_m", float(self.tracks[1])))
        return Job(self.name, self.scenario, plant=_merged(self.plant, (
            ("ident_seed", int(self.seed)), ("ident_mean_w", float(self.mean_w)),
            ("ident_amplitude_w", float(self.amplitude_w)), *layers, *plan)))


def _merged(process: tuple[tuple[str, Any], ...], run: tuple[tuple[str, Any], ...]) -> tuple[tuple[str, Any], ...]:
    """The process's ``[plant]`` keys, then the run's (a run's key replaces the process's)."""
    own = dict(run)
    return tuple((k, v) for k, v in process if k not in own) + run


@dataclass(frozen=True)
class FeedbackRun:
    """A closed-loop identification run: one of the project's controllers at one set point.

    It excites what open-loop steps rarely reach: the power drop at every turnaround onto the hot
    previous track, the regime the preview MPC works in.
    """

    scenario: str
    controller: str
    setpoint_mm2: float
    n_layers: int | None = None
    """Layers to build (``part``; None: the scenario's default)."""
    hatch_m: float | None = None
    """Hatch spacing [m] (None: the scenario's)."""
    t0_k: float | None = None
    """Preheat [K] (None: the scenario's)."""
    model: str | None = None
    """The controller's model file, relative to the repository or absolute (None: its shipped model)."""
    plant: tuple[tuple[str, Any], ...] = ()
    """``[plant]`` table of the process (e.g. ``preset``), before the run's own keys."""
    nominal_power_w: float | None = None
    """``[controller] nominal_power_w`` [W] (None: the controller's default): the feed-forward baseline's
    power at the reference temperature."""

    @property
    def name(self) -> str:
        """Run id and recording stem, e.g. ``ident-mpc-layer-a0.058``, ``ident-preview-mpc-layer-a0.065-h90um-350K``,
        ``ident-pid-part-l_bracket_3mm-a0.063`` (a part other than the example: its STL's stem)."""
        plant = "" if self.hatch_m is None else f"-h{self.hatch_m * 1e6:g}um"
        plant += "" if self.t0_k is None else f"-{self.t0_k:g}K"
        stl = dict(self.plant).get("part_stl")
        part = "" if stl is None else f"-{Path(stl).stem}"
        return f"ident-{self.controller}-{self.scenario}{part}-a{self.setpoint_mm2:g}{plant}"

    def job(self) -> Job:
        """The launcher job: the scenario under the controller (with its ``[plant]`` overrides)."""
        layers = () if self.n_layers is None else ("--layers", str(int(self.n_layers)))
        model = () if self.model is None else ("--model", str(REPO_ROOT / self.model))
        plant = _merged(self.plant, tuple((k, float(v)) for k, v in (("hatch_m", self.hatch_m), ("t0_k", self.t0_k))
                                          if v is not None))
        if self.scenario == "layer":
            plant = _merged((("mesh", TRAINING_MESH),), plant)
        controller = () if self.nominal_power_w is None else (("nominal_power_w", float(self.nominal_power_w)),)
        return Job(self.name, self.scenario, plant=plant,
                   args=("--setpoint-mm2", repr(self.setpoint_mm2), *layers, *model), controller=self.controller,
                   controller_table=controller)


class _AboutOperatingPoint:
    """What a design of runs about an operating point shares (:class:`ProcessDesign`, :class:`PartDesign`):
    the checks of its scale, set points and powers as ratios of the target and of the operating power, and
    its runs in order."""

    operating_power_w: float
    setpoint_mm2: float
    power_ratios: tuple[float, ...]
    amplitude_ratio: float

    def _check(self) -> None:
        if not (math.isfinite(self.operating_power_w) and self.operating_power_w > 0):
            raise CampaignError(f"operating_power_w must be > 0 W, got {self.operating_power_w}")
        if not (math.isfinite(self.setpoint_mm2) and self.setpoint_mm2 > 0):
            raise CampaignError(f"set_point must be > 0 mm², got {self.setpoint_mm2}")
        if 1.0 not in self.power_ratios or not 0 <= self.amplitude_ratio < min(self.power_ratios):
            raise CampaignError("the staircases need the operating power among their means and levels >= 0 W")

    def _setpoint(self, ratio: float) -> float:
        return round(self.setpoint_mm2 * ratio, 4)

    def _power(self, ratio: float) -> float:
        return float(round(self.operating_power_w * ratio))

    def runs(self) -> tuple[IdentRun | FeedbackRun, ...]:
        """Stage 1, then stage 2."""
        return self.stage1_runs() + self.stage2_runs()


@dataclass(frozen=True)
class ProcessDesign(_AboutOperatingPoint):
    """The identification runs of a plate process, designed around its operating point.

    Stage 1: seeded random power staircases on the layer and the double track about the operating
    power (means ``power_ratios`` × it, amplitude ``amplitude_ratio`` × it), and with ``turn_tracks``
    on a layer of that many shorter tracks (more turnarounds, each after its own random pre-turn
    powers: what tells the model how power before a turn acts after it), a closed-loop controller
    on the double track and the layer at set points about the target (``*_setpoint_ratios`` × it) and
    the feed-forward baseline at the target. Stage 2: the preview MPC with the stage-1 model on the
    double track and the layer at set points about the target, at the default hatch and preheat and
    at two others (:data:`PREVIEW_VARIANTS`). The shipped bare-plate design (:data:`IDENT_RUNS`) is
    the instance at 250 W and 0.063 mm² with the one-step GP-MPC as its closed-loop controller.

    Attributes
    ----------
    operating_power_w : float
        The power that holds ``setpoint_mm2`` along a track [W] (:mod:`gp_trainer.learn`).
    setpoint_mm2 : float
        The target set point [mm²].
    stage1_model : str
        The preview MPC's model in the stage-2 runs (relative to the repository, or absolute).
    plant : tuple[tuple[str, Any], ...]
        ``[plant]`` table of the process (a preset and overrides), before each run's own keys.
    feedback_controller : str
        The stage-1 closed-loop controller (``pid``: needs no model of the process).
    feedforward_scenarios : tuple[str, ...]
        Scenarios of the feed-forward baseline's runs at the target.
    turn_tracks : tuple[int, float] or None
        (tracks, track length [m]) of the turnaround staircases (seeds 7-9; None: none).
    """

    operating_power_w: float
    setpoint_mm2: float
    stage1_model: str
    plant: tuple[tuple[str, Any], ...] = ()
    feedback_controller: str = "pid"
    feedforward_scenarios: tuple[str, ...] = ("double-track",)
    power_ratios: tuple[float, ...] = (0.8, 1.0, 1.2)
    amplitude_ratio: float = 0.24
    double_track_setpoint_ratios: tuple[float, ...] = (55 / 63, 1.0, 70 / 63)
    layer_setpoint_ratios: tuple[float, ...] = (58 / 63, 68 / 63)
    turn_tracks: tuple[int, float] | None = (8, 5e-3)

    def __post_init__(self) -> None:
        self._check()

    def stage1_runs(self) -> tuple[IdentRun | FeedbackRun, ...]:
        """Open-loop staircases (seeds 1-3 on the layer, 4-6 on the double track, 7-9 on the
        ``turn_tracks`` layer), then the closed-loop runs."""
        amplitude = self._power(self.amplitude_ratio)
        plans = (("ident-layer", 1, None), ("ident-double-track", 4, None)) + (
            () if self.turn_tracks is None else (("ident-layer", 7, self.turn_tracks),))
        staircases = tuple(IdentRun(scenario, self._power(ratio), amplitude, seed, plant=self.plant, tracks=tracks)
                           for scenario, first, tracks in plans
                           for seed, ratio in enumerate(self.power_ratios, first))
        feedback = tuple(FeedbackRun(scenario, self.feedback_controller, self._setpoint(ratio), plant=self.plant)
                         for scenario, ratios in (("double-track", self.double_track_setpoint_ratios),
                                                  ("layer", self.layer_setpoint_ratios)) for ratio in ratios)
        feedforward = tuple(FeedbackRun(scenario, "feedforward", self.setpoint_mm2, plant=self.plant,
                                        nominal_power_w=self.operating_power_w)
                            for scenario in self.feedforward_scenarios)
        return staircases + feedback + feedforward

    def stage2_runs(self) -> tuple[FeedbackRun, ...]:
        """The preview MPC with :attr:`stage1_model` (:data:`PREVIEW_VARIANTS`)."""
        return tuple(FeedbackRun(scenario, "preview-mpc", self._setpoint(ratio), hatch_m=hatch, t0_k=t0,
                                 model=self.stage1_model, plant=self.plant)
                     for scenario, ratio, hatch, t0 in PREVIEW_VARIANTS)

    def held_out(self) -> tuple[str, ...]:
        """Runs held out for selection and evaluation: the staircases at the operating power (layer and
        double track) and the closed-loop double track at the target."""
        at_power = [r.name for r in self.stage1_runs() if isinstance(r, IdentRun)
                    and r.mean_w == self._power(1.0)]
        closed = FeedbackRun("double-track", self.feedback_controller, self.setpoint_mm2).name
        return (*at_power, closed)


PART_IDENT_LAYERS = 4
"""Layers each identification run on a part builds (the example part's runs and :class:`PartDesign`'s default)."""


@dataclass(frozen=True)
class PartDesign(_AboutOperatingPoint):
    """The identification runs of a part (an STL built layer by layer), designed around its operating point.

    A small part holds its heat: it needs far less power than a single track of the same process. The
    PID baseline finds the part's power: it runs at set points about the target (``setpoint_ratios`` ×
    it), starting from the single track's operating power ``track_power_w``, and the median power of its
    run at the target is the part's operating power (:func:`gp_trainer.learn.median_power_w`). Stage 1:
    those PID runs and seeded random power staircases over the part's first ``n_layers`` layers (seeds
    1-3, means ``power_ratios`` × the part's operating power, amplitude ``amplitude_ratio`` × it). Stage 2:
    the preview MPC with the stage-1 model at two set points between the PID's (``preview_setpoint_ratios``).
    The shipped example part's runs (:data:`IDENT_PART_RUNS`) are of the same form.

    Attributes
    ----------
    operating_power_w : float
        The part's operating power [W]: the staircases' centre, and where every controller starts.
    setpoint_mm2 : float
        The target set point [mm²].
    stage1_model : str
        The preview MPC's model in the stage-2 runs (relative to the repository, or absolute).
    part_stl : str
        The part (an STL path, absolute or relative to the repository).
    n_layers : int
        Layers each run builds.
    plant : tuple[tuple[str, Any], ...]
        ``[plant]`` table of the process, before each run's own keys (``part_stl`` is added).
    track_power_w : float or None
        The power that holds the target along a single track [W], where the PID runs start (None: the
        operating power).
    """

    operating_power_w: float
    setpoint_mm2: float
    stage1_model: str
    part_stl: str
    n_layers: int = PART_IDENT_LAYERS
    plant: tuple[tuple[str, Any], ...] = ()
    track_power_w: float | None = None
    power_ratios: tuple[float, ...] = (0.6, 1.0, 1.4)
    amplitude_ratio: float = 0.4
    setpoint_ratios: tuple[float, ...] = (55 / 63, 1.0, 70 / 63)
    preview_setpoint_ratios: tuple[float, ...] = (60 / 63, 66 / 63)

    def __post_init__(self) -> None:
        self._check()
        if self.track_power_w is not None and not (math.isfinite(self.track_power_w) and self.track_power_w > 0):
            raise CampaignError(f"track_power_w must be > 0 W, got {self.track_power_w}")
        if not (isinstance(self.n_layers, int) and self.n_layers >= 1):
            raise CampaignError(f"layers must be an integer >= 1, got {self.n_layers}")

    @property
    def part_plant(self) -> tuple[tuple[str, Any], ...]:
        """The process's ``[plant]`` table with the part."""
        stl = Path(self.part_stl)
        return _merged(self.plant, (("part_stl", str(stl if stl.is_absolute() else REPO_ROOT / stl)),))

    def pid_runs(self) -> tuple[FeedbackRun, ...]:
        """The PID baseline at set points about the target, from :attr:`track_power_w`; the one at the
        target (:attr:`target_pid_run`) gives the part's operating power."""
        start = self.operating_power_w if self.track_power_w is None else self.track_power_w
        return tuple(FeedbackRun("part", "pid", self._setpoint(ratio), self.n_layers, plant=self.part_plant,
                                 nominal_power_w=start) for ratio in self.setpoint_ratios)

    @property
    def target_pid_run(self) -> FeedbackRun:
        """The PID run at the target set point."""
        return next(r for r in self.pid_runs() if r.setpoint_mm2 == self.setpoint_mm2)

    def stage1_runs(self) -> tuple[IdentRun | FeedbackRun, ...]:
        """The PID runs, then the staircases (seeds 1-3)."""
        amplitude = self._power(self.amplitude_ratio)
        return self.pid_runs() + tuple(IdentRun("ident-part", self._power(ratio), amplitude, seed, self.n_layers,
                                                plant=self.part_plant)
                                       for seed, ratio in enumerate(self.power_ratios, 1))

    def stage2_runs(self) -> tuple[FeedbackRun, ...]:
        """The preview MPC with :attr:`stage1_model`."""
        return tuple(FeedbackRun("part", "preview-mpc", self._setpoint(ratio), self.n_layers, model=self.stage1_model,
                                 plant=self.part_plant) for ratio in self.preview_setpoint_ratios)

    def held_out(self) -> tuple[str, ...]:
        """Runs held out for selection and evaluation: the staircase at the operating power and the PID
        run at the target."""
        at_power = [r.name for r in self.stage1_runs() if isinstance(r, IdentRun) and r.mean_w == self._power(1.0)]
        return (*at_power, self.target_pid_run.name)


PREVIEW_VARIANTS = (
    ("double-track", 58 / 63, None, None), ("double-track", 68 / 63, None, None),
    ("layer", 60 / 63, None, None), ("layer", 66 / 63, None, None),
    ("double-track", 60 / 63, 0.9e-4, 350.0), ("layer", 65 / 63, 0.9e-4, 350.0),
    ("double-track", 66 / 63, 1.1e-4, 450.0), ("layer", 61 / 63, 1.1e-4, 450.0))
"""(scenario, set point / target, hatch [m], preheat [K]) of the preview MPC's stage-2 runs: set points
between the stage-1 ones, at the default hatch and preheat and at two others (0.09 mm / 350 K,
0.11 mm / 450 K). They hold the controller's own pre-turn power profile, which random power steps
never show (the model's error after a turn came from it, ``docs/gp.md``)."""

PLATE_STAGE1_MODEL = "gp_model/models/in625_plate_narx_gp_stage1.json"
"""The bare plate's stage-1 model: ``narx`` over every plate run but the ``ident-preview-mpc-*`` ones, the
controller of those runs, so that the data do not depend on the model they train."""
PLATE_DESIGN = ProcessDesign(250.0, 0.063, PLATE_STAGE1_MODEL, (("preset", "bare-plate"),), feedback_controller="mpc",
                             feedforward_scenarios=("double-track", "layer"), turn_tracks=None)
"""The bare plate's runs: 250 W, 0.063 mm², the one-step GP-MPC in closed loop (its model is the plate's)."""
IDENT_RUNS = PLATE_DESIGN.runs()
PREVIEW_RUNS = PLATE_DESIGN.stage2_runs()

DEFAULT_PART_IDENT_DIR = Path("recordings/identification-part")
BLOCK_STL = "fe_node/parts/block_5mm.stl"
"""The second part of the part model's runs (relative to the repository)."""
IDENT_PART_RUNS = tuple(
    IdentRun("ident-part", mean, 40.0, seed, PART_IDENT_LAYERS) for mean, seed in ((60.0, 11), (100.0, 12), (140.0, 13))
) + tuple(FeedbackRun("part", "pid", a, PART_IDENT_LAYERS) for a in (0.055, 0.063, 0.07)) + tuple(
    IdentRun("ident-part", mean, 40.0, seed, 1, plant=(("part_stl", str(REPO_ROOT / BLOCK_STL)),))
    for mean, seed in ((60.0, 21), (100.0, 22), (140.0, 23)))
"""The runs for a model of the ``part`` scenario (powder on small parts: far less power than the
bare plate, 75 W median under PID at 0.063 mm²): on the example cylinder, random staircases at 60,
100, 140 W ± 40 W and the PID baseline at three set points, 4 layers each; on the 5 mm block
(:data:`BLOCK_STL`), the same three staircases over its first layer (6 508 states each)."""


@dataclass(frozen=True)
class IdentSet:
    """The identification runs of one plant, where they are recorded, which are held out for model
    selection and evaluation, and the model file ``narx`` writes from them.

    Attributes
    ----------
    name : str
        ``--plant`` of ``identify``, ``narx`` and ``evaluate``.
    runs : tuple[IdentRun | FeedbackRun, ...]
    out_dir : pathlib.Path
    held_out : tuple[str, ...]
        Recording stems (run names) held out.
    model_path : pathlib.Path
    """

    name: str
    runs: tuple[IdentRun | FeedbackRun, ...]
    out_dir: Path
    held_out: tuple[str, ...]
    model_path: Path


IDENT_SETS = {
    "plate": IdentSet("plate", IDENT_RUNS, DEFAULT_IDENT_DIR, PLATE_DESIGN.held_out(), PLATE_MODEL_PATH),
    "part": IdentSet("part", IDENT_PART_RUNS, DEFAULT_PART_IDENT_DIR,
                     ("ident-part-p100-s12", "ident-pid-part-a0.063"), PART_MODEL_PATH),
}
"""``plate``: the bare-plate scenarios (``layer``, ``double-track``; the default model);
``part``: the ``part`` scenario (powder, the shipped example part; the model ``launch.py
--scenario part`` uses)."""


@dataclass(frozen=True)
class IdentifySettings(RunnerSettings):
    """What ``identify`` runs and where it writes (the runner's fields as :class:`RunnerSettings`).

    Attributes
    ----------
    runs : tuple[IdentRun, ...]
        Default :data:`IDENT_RUNS`: 6 open-loop runs (ident-layer and ident-double-track at 200,
        250 and 300 W mean, 60 W amplitude, seeds 1-6) and 15 closed-loop runs: the one-step
        GP-MPC on the double track at 0.055, 0.063, 0.07 mm² and on the layer at 0.058, 0.068 mm²,
        the feed-forward baseline on both (its power does not depend on the set point), and the
        8 runs of the preview MPC with the stage-1 model (:data:`PREVIEW_RUNS`).
    """

    runs: tuple[IdentRun | FeedbackRun, ...] = IDENT_RUNS
    out_dir: Path = DEFAULT_IDENT_DIR


def select_ident_runs(
    names: list[str] | tuple[str, ...] | None, runs: tuple[IdentRun, ...] = IDENT_RUNS
) -> tuple[IdentRun, ...]:
    """The runs named in ``names`` (all of ``runs`` for ``None``), in the order of ``runs``.

    Raises
    ------
    CampaignError
        A name that is not one of ``runs``.
    """
    if names is None:
        return runs
    known = {r.name: r for r in runs}
    unknown = [n for n in names if n not in known]
    if unknown:
        raise CampaignError(f"unknown identification run(s) {', '.join(unknown)}; choose from {', '.join(known)}")
    return tuple(r for r in runs if r.name in set(names))


def identify_jobs(settings: IdentifySettings) -> list[Job]:
    """The launcher jobs of ``settings.runs``."""
    return [r.job() for r in settings.runs]


def run_identification(settings: IdentifySettings = IdentifySettings(), *, progress: bool = True) -> list[JobResult]:
    """Record every identification run of ``settings.runs`` that has no complete recording yet.

    Raises
    ------
    CampaignError
        No runs, duplicate names, ``workers`` < 1, a missing launcher or a bad ``scheduler``.
    """
    return run_jobs(identify_jobs(settings), settings, progress=progress)


def summary_json(results: list[CaseResult] | list[JobResult], key: str = "cases") -> str:
    """One-line JSON summary of a campaign (``key``: name of the per-run list)."""
    return json.dumps({
        "ok": sum(r.status == "ok" for r in results),
        "skipped": sum(r.status == "skipped" for r in results),
        "failed": sum(r.status == "failed" for r in results),
        key: [asdict(r) for r in results],
    })
