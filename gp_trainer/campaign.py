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
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from concurrent.futures import ThreadPoolExecutor, as_completed
from dataclasses import asdict, dataclass
from pathlib import Path

from gp_trainer.errors import CampaignError
from gp_trainer.provenance import REPO_ROOT

TABLE2_CASES = tuple(range(1, 10))
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


def scenario_name(case: int) -> str:
    """Scenario (and run id, recording stem) of Table 2 case ``case``, e.g. ``table2-case2``."""
    return f"table2-case{case}"


def recording_path(settings: CampaignSettings, case: int) -> Path:
    """Final recording of one case."""
    return settings.out_dir / f"{scenario_name(case)}.mcap"


def recording_complete(path: Path) -> bool:
    """True if ``path`` exists and the recorder finished it with no message missing."""
    from messages.recording import is_complete

    return path.is_file() and is_complete(path)


def case_command(settings: CampaignSettings, case: int, out: Path) -> list[str]:
    """Command line that records one case to ``out``."""
    return [settings.python, str(settings.launcher), "--scenario", scenario_name(case), "--controller",
            settings.controller, "--no-progress", "--json", "--out", str(out), "--run-id", scenario_name(case)]


class _Runner:
    """Runs case subprocesses and can interrupt all of them (Ctrl-C of the campaign)."""

    def __init__(self, settings: CampaignSettings) -> None:
        self.settings = settings
        self._procs: dict[int, subprocess.Popen[str]] = {}
        self._lock = threading.Lock()

    def run(self, case: int) -> CaseResult:
        final = recording_path(self.settings, case)
        partial = final.with_name(f"{scenario_name(case)}.partial.mcap")
        started = time.monotonic()
        proc = subprocess.Popen(case_command(self.settings, case, partial), cwd=REPO_ROOT,
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        with self._lock:
            self._procs[case] = proc
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
                self._procs.pop(case, None)
        wall = time.monotonic() - started
        last_out = (stdout.strip().splitlines() or [""])[-1]
        last_err = (stderr.strip().splitlines() or [""])[-1]
        if proc.returncode == 0 and recording_complete(partial):
            os.replace(partial, final)
            return CaseResult(case, str(final), "ok", wall, last_out)
        reason = last_err or last_out or "no output"
        return CaseResult(case, str(partial), "failed", wall, f"exit status {proc.returncode}: {reason}")

    def interrupt(self) -> None:
        with self._lock:
            procs = list(self._procs.values())
        for proc in procs:
            if proc.poll() is None:
                proc.send_signal(signal.SIGINT)  # the launcher stops its nodes in order


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
    from tqdm import tqdm

    bad = sorted(set(settings.cases) - set(TABLE2_CASES))
    if bad or not settings.cases:
        raise CampaignError(f"Table 2 cases are 1-9, got {list(settings.cases)}")
    if settings.workers < 1:
        raise CampaignError(f"--workers must be at least 1, got {settings.workers}")
    if not settings.launcher.is_file():
        raise CampaignError(f"launcher not found: {settings.launcher}")
    settings.out_dir.mkdir(parents=True, exist_ok=True)
    results = {c: CaseResult(c, str(recording_path(settings, c)), "skipped", 0.0, "recording complete")
               for c in settings.cases if recording_complete(recording_path(settings, c))}
    pending = [c for c in settings.cases if c not in results]
    runner = _Runner(settings)
    with tqdm(total=len(settings.cases), initial=len(results), unit="case", disable=not progress) as bar, \
            ThreadPoolExecutor(max_workers=settings.workers) as pool:
        futures = {pool.submit(runner.run, c): c for c in pending}
        try:
            for future in as_completed(futures):
                result = future.result()
                results[result.case] = result
                bar.set_postfix_str(f"case {result.case} {result.status}")
                bar.update()
        except KeyboardInterrupt:
            for future in futures:
                future.cancel()
            runner.interrupt()
            raise
    return [results[c] for c in settings.cases]


def summary_json(results: list[CaseResult]) -> str:
    """One-line JSON summary of a campaign."""
    return json.dumps({
        "ok": sum(r.status == "ok" for r in results),
        "skipped": sum(r.status == "skipped" for r in results),
        "failed": sum(r.status == "failed" for r in results),
        "cases": [asdict(r) for r in results],
    })
