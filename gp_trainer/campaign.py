"""The data campaign: the nine Table 2 cases run open loop, in parallel, each to its own MCAP.

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
"""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Any, Protocol

from gp_trainer.errors import CampaignError
from gp_trainer.provenance import REPO_ROOT

TABLE2_CASES = tuple(range(1, 10))
DEFAULT_IDENT_DIR = Path("recordings/identification")
STOP_GRACE_S = 30.0  # after a timeout: SIGINT, then SIGKILL if the launcher is still running


@dataclass(frozen=True)
class CampaignSettings:
    """What the campaign runs and where it writes.

    Attributes
    ----------
    cases : tuple[int, ...]
        Table 2 case numbers to run (1-9).
    out_dir : Path
        Directory of the recordings.
    workers : int
        Cases run at the same time (each is several processes; the FE plant dominates).
    launcher : Path
        The project's ``launch.py``.
    python : str
        Interpreter used to run the launcher.
    timeout_s : float or None
        Wall-time limit per case [s].
    controller : str
        launch.py's ``--controller``; ``none`` plays the scenario's profiles (module docstring).
    """

    cases: tuple[int, ...] = TABLE2_CASES
    out_dir: Path = Path("recordings/campaign")
    workers: int = 2
    launcher: Path = REPO_ROOT / "launch.py"
    python: str = sys.executable
    timeout_s: float | None = None
    controller: str = "none"


@dataclass(frozen=True)
class CaseResult:
    """Outcome of one case: ``status`` is ``skipped`` (already complete), ``ok`` or ``failed``."""

    case: int
    recording: str
    status: str
    wall_s: float
    detail: str


@dataclass(frozen=True)
class Job:
    """One recorded run of the launcher.

    Attributes
    ----------
    name : str
        Run id and recording stem (``<out_dir>/<name>.mcap``).
    scenario : str
        launch.py's ``--scenario``.
    plant : tuple[tuple[str, Any], ...]
        ``[plant]`` table (key, value pairs: numbers, booleans, strings). If not empty it is
        written to a TOML file in a temporary directory, passed as ``--config`` and removed
        after the run (the plant records its resolved scenario, profile included, in the MCAP).
    args : tuple[str, ...]
        Further launch.py arguments.
    controller : str or None
        launch.py's ``--controller`` for this job (None: the runner's, ``none`` by default).
    """

    name: str
    scenario: str
    plant: tuple[tuple[str, Any], ...] = ()
    args: tuple[str, ...] = ()
    controller: str | None = None


@dataclass(frozen=True)
class JobResult:
    """Outcome of one job: ``status`` is ``skipped`` (already complete), ``ok`` or ``failed``."""

    name: str
    recording: str
    status: str
    wall_s: float
    detail: str


class RunnerSettings(Protocol):
    """What :func:`run_jobs` needs (:class:`CampaignSettings`, :class:`IdentifySettings`)."""

    out_dir: Path
    workers: int
    launcher: Path
    python: str
    timeout_s: float | None
    controller: str


def scenario_name(case: int) -> str:
    """Scenario (and run id, recording stem) of Table 2 case ``case``, e.g. ``table2-case2``."""
    return f"table2-case{case}"


def case_job(case: int) -> Job:
    """The job of Table 2 case ``case``: its scenario, named after it, no config."""
    return Job(scenario_name(case), scenario_name(case))


def job_recording(settings: RunnerSettings, job: Job) -> Path:
    """Final recording of one job."""
    return settings.out_dir / f"{job.name}.mcap"


def recording_path(settings: CampaignSettings, case: int) -> Path:
    """Final recording of one case."""
    return job_recording(settings, case_job(case))


def recording_complete(path: Path) -> bool:
    """True if ``path`` exists and the recorder finished it with no message missing."""
    from messages.recording import is_complete

    return path.is_file() and is_complete(path)


def job_command(settings: RunnerSettings, job: Job, out: Path, config: Path | None = None) -> list[str]:
    """Command line that records ``job`` to ``out``, with ``--config config`` if given (the job's
    ``[plant]`` table as TOML). The launcher runs in the repository root: the runner passes
    absolute paths."""
    return [settings.python, str(settings.launcher), "--scenario", job.scenario,
            "--controller", job.controller or settings.controller,
            *(("--config", str(config)) if config is not None else ()), *job.args,
            "--no-progress", "--json", "--out", str(out), "--run-id", job.name]


def case_command(settings: CampaignSettings, case: int, out: Path) -> list[str]:
    """Command line that records one case to ``out``."""
    return job_command(settings, case_job(case), out)


def _toml_value(key: str, value: Any) -> str:
    if not key or not set(key) <= set("abcdefghijklmnopqrstuvwxyzABCDEFGHIJKLMNOPQRSTUVWXYZ0123456789_-"):
        raise CampaignError(f"[plant] key {key!r}: not a bare TOML key")
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, int):
        return str(value)
    if isinstance(value, float):
        if not math.isfinite(value):
            raise CampaignError(f"[plant] {key}: not a finite number: {value}")
        return repr(value)
    if isinstance(value, str):
        return json.dumps(value)  # a TOML basic string
    raise CampaignError(f"[plant] {key}: unsupported value {value!r}")


def plant_toml(plant: tuple[tuple[str, Any], ...]) -> str:
    """A TOML document with one ``[plant]`` table (flat numbers, booleans and strings)."""
    return "[plant]\n" + "".join(f"{key} = {_toml_value(key, value)}\n" for key, value in plant)


class _Runner:
    """Runs job subprocesses and can interrupt all of them (Ctrl-C of the campaign)."""

    def __init__(self, settings: RunnerSettings) -> None:
        self.settings = settings
        self._procs: dict[str, subprocess.Popen[str]] = {}
        self._lock = threading.Lock()

    def run(self, job: Job) -> JobResult:
        if not job.plant:
            return self._run(job, None)
        with tempfile.TemporaryDirectory(prefix="meltloop-job-") as tmp:
            config = Path(tmp) / f"{job.name}.toml"
            config.write_text(plant_toml(job.plant))
            return self._run(job, config)

    def _run(self, job: Job, config: Path | None) -> JobResult:
        final = job_recording(self.settings, job)
        partial = final.with_name(f"{job.name}.partial.mcap")
        started = time.monotonic()
        proc = subprocess.Popen(job_command(self.settings, job, partial.absolute(), config), cwd=REPO_ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        with self._lock:
            self._procs[job.name] = proc
        try:
            stdout, stderr = proc.communicate(timeout=self.settings.timeout_s)
        except subprocess.TimeoutExpired:
            proc.send_signal(signal.SIGINT)  # let the launcher stop its nodes, then insist
            try:
                stdout, stderr = proc.communicate(timeout=STOP_GRACE_S)
            except subprocess.TimeoutExpired:
                proc.kill()
                stdout, stderr = proc.communicate()
            stderr += f"\ntimed out after {self.settings.timeout_s} s"
        finally:
            with self._lock:
                self._procs.pop(job.name, None)
        wall = time.monotonic() - started
        last_out = (stdout.strip().splitlines() or [""])[-1]
        last_err = (stderr.strip().splitlines() or [""])[-1]
        if proc.returncode == 0 and recording_complete(partial):
            os.replace(partial, final)
            return JobResult(job.name, str(final), "ok", wall, last_out)
        reason = last_err or last_out or "no output"
        return JobResult(job.name, str(partial), "failed", wall, f"exit status {proc.returncode}: {reason}")

    def interrupt(self) -> None:
        with self._lock:
            procs = list(self._procs.values())
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)  # the launcher stops its nodes in order


def _check_runner(settings: RunnerSettings) -> None:
    if settings.workers < 1:
        raise CampaignError(f"--workers must be at least 1, got {settings.workers}")
    if settings.timeout_s is not None and not settings.timeout_s > 0:
        raise CampaignError(f"--timeout must be > 0 s, got {settings.timeout_s}")
    if not settings.launcher.is_file():
        raise CampaignError(f"launcher not found: {settings.launcher}")


def run_jobs(jobs: list[Job] | tuple[Job, ...], settings: RunnerSettings, *, progress: bool = True,
             unit: str = "run") -> list[JobResult]:
    """Record every job that has no complete recording yet, ``settings.workers`` at a time.

    Parameters
    ----------
    jobs : sequence of Job
        Distinct names.
    settings : RunnerSettings
        Output directory, workers, launcher, interpreter, timeout, controller.
    progress : bool
        Show a tqdm progress bar over jobs (on stderr).
    unit : str
        Unit name of the progress bar.

    Returns
    -------
    list[JobResult]
        One per job, in job order.

    Raises
    ------
    CampaignError
        No or duplicate jobs, ``workers`` < 1 or a missing launcher.
    """
    from tqdm import tqdm

    names = [j.name for j in jobs]
    if not jobs or len(set(names)) != len(names):
        raise CampaignError(f"need at least one job and distinct names, got {names}")
    _check_runner(settings)
    for job in jobs:
        plant_toml(job.plant)  # a bad [plant] table is a usage error before anything runs
    settings.out_dir.mkdir(parents=True, exist_ok=True)
    results = {j.name: JobResult(j.name, str(job_recording(settings, j)), "skipped", 0.0, "recording complete")
               for j in jobs if recording_complete(job_recording(settings, j))}
    pending = [j for j in jobs if j.name not in results]
    runner = _Runner(settings)
    with tqdm(total=len(jobs), initial=len(results), unit=unit, disable=not progress) as bar, \
            ThreadPoolExecutor(max_workers=settings.workers) as pool:
        futures = {pool.submit(runner.run, j): j for j in pending}
        try:
            for future in as_completed(futures):
                result = future.result()
                results[result.name] = result
                bar.set_postfix_str(f"{result.name} {result.status}")
                bar.update()
        except KeyboardInterrupt:
            for future in futures:
                future.cancel()
            runner.interrupt()
            raise
    return [results[n] for n in names]


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
        One per case, in case order.

    Raises
    ------
    CampaignError
        Unknown case numbers, ``workers`` < 1 or a missing launcher.
    """
    bad = sorted(set(settings.cases) - set(TABLE2_CASES))
    if bad or not settings.cases:
        raise CampaignError(f"Table 2 cases are 1-9, got {list(settings.cases)}")
    _check_runner(settings)
    cases = list(dict.fromkeys(settings.cases))
    done = run_jobs([case_job(c) for c in cases], settings, progress=progress, unit="case")
    by_case = {c: CaseResult(c, r.recording, r.status, r.wall_s, r.detail) for c, r in zip(cases, done)}
    return [by_case[c] for c in settings.cases]


@dataclass(frozen=True)
class IdentRun:
    """One identification run: a seeded random power staircase of an ``ident-*`` scenario."""

    scenario: str
    mean_w: float
    amplitude_w: float
    seed: int

    @property
    def name(self) -> str:
        """Run id and recording stem, e.g. ``ident-layer-p250-s2``."""
        return f"{self.scenario}-p{self.mean_w:g}-s{self.seed}"

    def job(self) -> Job:
        """The launcher job: the scenario with its ``[plant]`` ``ident_*`` overrides."""
        return Job(self.name, self.scenario, plant=(("ident_seed", int(self.seed)),
                                                    ("ident_mean_w", float(self.mean_w)),
                                                    ("ident_amplitude_w", float(self.amplitude_w))))


@dataclass(frozen=True)
class FeedbackRun:
    """A closed-loop identification run: one of the project's controllers at one set point.

    It excites what open-loop steps rarely reach: the power drop at every turnaround onto the hot
    previous track, the regime the preview MPC works in.
    """

    scenario: str
    controller: str
    setpoint_mm2: float

    @property
    def name(self) -> str:
        """Run id and recording stem, e.g. ``ident-mpc-layer-a0.058``."""
        return f"ident-{self.controller}-{self.scenario}-a{self.setpoint_mm2:g}"

    def job(self) -> Job:
        """The launcher job: the scenario under the controller."""
        return Job(self.name, self.scenario, args=("--setpoint-mm2", repr(self.setpoint_mm2)),
                   controller=self.controller)


IDENT_RUNS = tuple(
    IdentRun(scenario, mean, 60.0, seed)
    for scenario, seeds in (("ident-layer", (1, 2, 3)), ("ident-double-track", (4, 5, 6)))
    for mean, seed in zip((200.0, 250.0, 300.0), seeds)
) + tuple(FeedbackRun("double-track", "mpc", a) for a in (0.055, 0.063, 0.07)) + tuple(
    FeedbackRun("layer", "mpc", a) for a in (0.058, 0.068)) + tuple(
    FeedbackRun(scenario, "feedforward", 0.063) for scenario in ("double-track", "layer"))


@dataclass(frozen=True)
class IdentifySettings:
    """What ``identify`` runs and where it writes (fields as :class:`CampaignSettings`).

    Attributes
    ----------
    runs : tuple[IdentRun, ...]
        Default :data:`IDENT_RUNS`: 6 open-loop runs (ident-layer and ident-double-track at 200,
        250 and 300 W mean, 60 W amplitude, seeds 1-6) and 7 closed-loop runs: the one-step
        GP-MPC on the double track at 0.055, 0.063, 0.07 mm² and on the layer at 0.058, 0.068 mm²,
        and the feed-forward baseline on both (its power does not depend on the set point).
    """

    runs: tuple[IdentRun | FeedbackRun, ...] = IDENT_RUNS
    out_dir: Path = DEFAULT_IDENT_DIR
    workers: int = 2
    launcher: Path = REPO_ROOT / "launch.py"
    python: str = sys.executable
    timeout_s: float | None = None
    controller: str = "none"


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
        No runs, duplicate names, ``workers`` < 1 or a missing launcher.
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
