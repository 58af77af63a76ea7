"""One recorded run of the launcher: the job, running it in this process (as a Dask worker does) and its result.

:func:`run_job` starts ``launch.py`` as a subprocess in the repository root and waits for it;
:mod:`gp_trainer.campaign` runs many jobs, in turn or on Dask (:mod:`gp_trainer.distributed`).
"""

from __future__ import annotations

import ctypes
import json
import math
import os
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from gp_trainer.errors import CampaignError
from gp_trainer.provenance import REPO_ROOT
from messages.recording import is_complete

STOP_GRACE_S = 30.0  # after a timeout: SIGINT, then SIGKILL if the launcher is still running
OUTPUT_TAIL_LINES = 15  # of a failed run's output, kept in its result


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
    controller_table : tuple[tuple[str, Any], ...]
        ``[controller]`` table (key, value pairs), written to the same TOML file as ``plant``.
    """

    name: str
    scenario: str
    plant: tuple[tuple[str, Any], ...] = ()
    args: tuple[str, ...] = ()
    controller: str | None = None
    controller_table: tuple[tuple[str, Any], ...] = ()


@dataclass(frozen=True)
class JobResult:
    """Outcome of one job.

    Attributes
    ----------
    name : str
    recording : str
        The final recording, or the ``.partial.mcap`` a failed run left.
    status : str
        ``skipped`` (already complete), ``ok`` or ``failed`` (every attempt failed).
    wall_s : float
        Wall time of the last attempt [s].
    detail : str
        The launcher's last output line; for a failure ``exit status N: <last line>``.
    attempts : int
        Launcher runs (0 for skipped; 2 for a failure retried once).
    exit_status : int or None
        The launcher's exit status of the last attempt (None: it never ran or its worker died).
    worker : str
        Dask worker address of the last attempt (``local`` without Dask).
    output_tail : str
        Last lines of the launcher's merged stdout/stderr of a failed attempt.
    states_sha256 : str or None
        :func:`states_sha256` of a complete recording.
    """

    name: str
    recording: str
    status: str
    wall_s: float
    detail: str
    attempts: int = 1
    exit_status: int | None = None
    worker: str = ""
    output_tail: str = ""
    states_sha256: str | None = None


def job_recording(settings: RunnerSettings | RunSpec, job: Job) -> Path:
    """Final recording of one job."""
    return settings.out_dir / f"{job.name}.mcap"


def recording_complete(path: Path) -> bool:
    """True if ``path`` exists and the recorder finished it with no message missing."""
    return path.is_file() and is_complete(path)


def job_command(settings: RunnerSettings | RunSpec, job: Job, out: Path, config: Path | None = None) -> list[str]:
    """Command line that records ``job`` to ``out``, with ``--config config`` if given (the job's
    ``[plant]`` table as TOML), then the job's and the settings' further arguments; ``out`` (the
    job's partial recording, left by an earlier attempt) is overwritten. The launcher runs in the
    repository root: the runner passes absolute paths."""
    return [settings.python, str(settings.launcher), "--scenario", job.scenario,
            "--controller", job.controller or settings.controller,
            *(("--config", str(config)) if config is not None else ()), *job.args,
            *getattr(settings, "launch_args", ()), "--no-progress", "--json", "--out", str(out), "--overwrite",
            "--run-id", job.name]


@dataclass(frozen=True)
class RunSpec:
    """What a worker needs to record a job: absolute paths, so a Dask worker in another working
    directory (or on another machine sharing the file system) writes where the campaign would."""

    out_dir: Path
    launcher: Path
    python: str
    timeout_s: float | None
    controller: str
    launch_args: tuple[str, ...] = ()


_RUNNING: dict[str, subprocess.Popen[str]] = {}  # partial recording -> launcher process, in this process
_RUNNING_LOCK = threading.Lock()


def _tail(text: str, lines: int = OUTPUT_TAIL_LINES) -> str:
    return "\n".join(text.rstrip().splitlines()[-lines:])


def _worker_name() -> str:
    try:
        from distributed import get_worker

        return get_worker().address
    except (ImportError, ValueError):
        return "local"


def run_job(spec: RunSpec, job: Job, attempt: int = 1) -> JobResult:
    """Record one job now, in this process (a Dask worker runs exactly this).

    The launcher runs as a subprocess in the repository root (its nodes are separate processes
    as in any run) and writes ``<name>.partial.mcap``, renamed to ``<name>.mcap`` when it
    succeeded and the recorder marked the file complete. Never raises for a failed run: the
    result says ``failed`` with the exit status and the last lines of the launcher's output.
    """
    started = time.monotonic()
    final = job_recording(spec, job)
    partial = final.with_name(f"{job.name}.partial.mcap")
    worker = _worker_name()
    try:
        if not job.plant and not job.controller_table:
            returncode, output = _launch(spec, job, partial, None)
        else:
            with tempfile.TemporaryDirectory(prefix="meltloop-job-") as tmp:
                config = Path(tmp) / f"{job.name}.toml"
                config.write_text(plant_toml(job.plant, job.controller_table))
                returncode, output = _launch(spec, job, partial, config)
    except (OSError, CampaignError) as exc:  # e.g. the interpreter or launcher is missing on this worker
        return JobResult(job.name, str(partial), "failed", time.monotonic() - started,
                         f"could not start the launcher on {worker}: {exc}", attempt, None, worker, str(exc))
    wall = time.monotonic() - started
    last = (output.strip().splitlines() or [""])[-1]
    if returncode == 0 and recording_complete(partial):
        os.replace(partial, final)
        return JobResult(job.name, str(final), "ok", wall, last, attempt, 0, worker, "")
    if returncode == 0:
        last = f"the recording {partial.name} is not complete; {last}".rstrip("; ")
    return JobResult(job.name, str(partial), "failed", wall, f"exit status {returncode}: {last or 'no output'}",
                     attempt, returncode, worker, _tail(output))


def _parent_death_sigint() -> Callable[[], None] | None:
    """On Linux, a ``preexec_fn`` asking the kernel to send the launcher SIGINT when the thread
    that started it dies (a killed Dask worker or campaign): the launcher then stops its nodes
    instead of running on, orphaned, while the job is run again elsewhere. None elsewhere."""
    if not sys.platform.startswith("linux"):
        return None
    try:
        prctl = ctypes.CDLL(None, use_errno=True).prctl
    except (OSError, AttributeError):
        return None
    pr_set_pdeathsig, sigint = ctypes.c_int(1), ctypes.c_ulong(signal.SIGINT)  # built before fork

    def preexec() -> None:
        prctl(pr_set_pdeathsig, sigint)

    return preexec


_PARENT_DEATH_SIGINT = _parent_death_sigint()


def _launch(spec: RunSpec, job: Job, partial: Path, config: Path | None) -> tuple[int, str]:
    """Run the launcher to the end (or the timeout): exit status and its merged stdout/stderr."""
    partial.parent.mkdir(parents=True, exist_ok=True)
    proc = subprocess.Popen(job_command(spec, job, partial, config), cwd=REPO_ROOT, stdout=subprocess.PIPE,
                            stderr=subprocess.STDOUT, text=True, preexec_fn=_PARENT_DEATH_SIGINT)
    with _RUNNING_LOCK:
        _RUNNING[str(partial)] = proc
    try:
        output, _ = proc.communicate(timeout=spec.timeout_s)
    except subprocess.TimeoutExpired:
        proc.send_signal(signal.SIGINT)  # let the launcher stop its nodes, then insist
        try:
            output, _ = proc.communicate(timeout=STOP_GRACE_S)
        except subprocess.TimeoutExpired:
            proc.kill()
            output, _ = proc.communicate()
        output += f"\ntimed out after {spec.timeout_s} s"
    finally:
        with _RUNNING_LOCK:
            _RUNNING.pop(str(partial), None)
    return proc.returncode, output


def interrupt_running(partials: list[str] | None = None) -> int:
    """SIGINT to the launchers this process runs (those writing ``partials``, or all): the
    launcher stops its nodes in order. Returns how many were signalled."""
    with _RUNNING_LOCK:
        procs = [p for key, p in _RUNNING.items() if partials is None or key in partials]
    for proc in procs:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
    return len(procs)


@dataclass(frozen=True)
class RunnerSettings:
    """How and where jobs run (:func:`gp_trainer.campaign.run_jobs`); the campaign's and the
    identification's settings extend it with what they run.

    Attributes
    ----------
    out_dir : Path
        Directory of the recordings.
    workers : int
        Worker processes of the local Dask cluster, i.e. jobs run at the same time (each is
        several processes; the FE plant dominates).
    launcher : Path
        The project's ``launch.py``.
    python : str
        Interpreter used to run the launcher.
    timeout_s : float or None
        Wall-time limit per job [s].
    controller : str
        launch.py's ``--controller``; ``none`` plays the scenario's profiles (:mod:`gp_trainer.campaign`).
    scheduler : str or None
        Address of an existing Dask scheduler (``tls://HOST:PORT``); None: a ``LocalCluster`` of
        ``workers`` worker processes started for the campaign.
    sequential : bool
        No Dask: the jobs run in this process, one after the other (the reference of the
        bit-for-bit comparison, and a fallback).
    retries : int
        A failed job is run again this many times before it is reported failed.
    launch_args : tuple[str, ...]
        Further launch.py arguments for every job (e.g. ``--max-steps 40 --h-um 50``).
    """

    out_dir: Path = Path("recordings")
    workers: int = 2
    launcher: Path = REPO_ROOT / "launch.py"
    python: str = sys.executable
    timeout_s: float | None = None
    controller: str = "none"
    scheduler: str | None = None
    sequential: bool = False
    retries: int = 1
    launch_args: tuple[str, ...] = ()


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


def plant_toml(plant: tuple[tuple[str, Any], ...], controller: tuple[tuple[str, Any], ...] = ()) -> str:
    """A TOML document with a ``[plant]`` table and, if ``controller`` is given, a ``[controller]`` table
    (flat numbers, booleans and strings)."""
    def table(name: str, pairs: tuple[tuple[str, Any], ...]) -> str:
        return f"[{name}]\n" + "".join(f"{key} = {_toml_value(key, value)}\n" for key, value in pairs)
    return table("plant", plant) + (table("controller", controller) if controller else "")
