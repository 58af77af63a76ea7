"""Campaigns on Dask distributed: the same dataset, bit for bit, as in-process sequential runs;
retries and failure reports; --scheduler errors.

Every case is a real ``launch.py`` run (FE plant, recorder, hub) kept short with ``--max-steps``
and a coarse mesh, so that the default test set stays short.
"""

from __future__ import annotations

import contextlib
import dataclasses
import hashlib
import json
import socket
from pathlib import Path

import numpy as np
import pytest

from gp_trainer import cli, distributed
from gp_trainer.campaign import CampaignSettings, run_campaign, run_jobs, states_sha256
from gp_trainer.cli import main
from gp_trainer.dataset import DatasetSettings, build_samples, concatenate, read_states
from gp_trainer.jobs import Job
from tests.conftest import REPO
from tests.plants import BARE

SHORT = ("--h-um", "50")  # the coarsest mesh the beam allows


@pytest.fixture(scope="module")
def cluster():
    """One TLS ``LocalCluster`` of two worker processes for this module's campaigns on an existing
    cluster (``--scheduler``), as a user starts one: (scheduler address, worker addresses, the
    credentials a client sets with :func:`client_credentials`). The campaign's own cluster
    (``--workers``) has its own tests."""
    import logging

    from distributed import LocalCluster
    from distributed.security import Security

    security = Security.temporary()
    with LocalCluster(n_workers=2, threads_per_worker=1, dashboard_address=None, silence_logs=logging.ERROR,
                      security=security) as local:
        yield local.scheduler_address, set(local.scheduler_info["workers"]), security


def dataset_digest(recordings: list[Path]) -> str:
    """SHA-256 of the dataset's arrays (Z, y, source, step, track: dtype, shape and bytes), built
    from ``recordings`` in the given order as ``python -m gp_trainer dataset`` builds it."""
    settings = DatasetSettings(min_samples=1)
    samples = concatenate([build_samples(read_states(p), p.stem, settings)[0] for p in recordings], settings)
    digest = hashlib.sha256()
    for name in ("Z", "y", "source", "step", "track"):
        array = np.ascontiguousarray(getattr(samples, name))
        digest.update(f"{name}:{array.dtype.str}:{array.shape}".encode())
        digest.update(array.tobytes())
    return digest.hexdigest()


def _jobs(steps: tuple[int, ...]) -> list[Job]:
    """Table 2 cases 1..n on the bare plate with ``--max-steps`` per case: the first is the longest, so on
    two workers the cases finish in another order than they were submitted."""
    return [Job(f"table2-case{c}", f"table2-case{c}", plant=(("preset", BARE),), args=("--max-steps", str(n)))
            for c, n in enumerate(steps, 1)]


def _compare(tmp_path: Path, jobs: list[Job], launch_args: tuple[str, ...], cluster: tuple) -> None:
    base = CampaignSettings(out_dir=tmp_path / "sequential", sequential=True, launch_args=launch_args)
    local = run_jobs(jobs, base, progress=False)
    scheduler, workers, security = cluster
    with client_credentials(security):
        dask = run_jobs(jobs, dataclasses.replace(base, out_dir=tmp_path / "dask", sequential=False,
                                                  scheduler=scheduler), progress=False)
    assert [r.status for r in local] == [r.status for r in dask] == ["ok"] * len(jobs), [r.detail for r in dask]
    assert [r.name for r in dask] == [j.name for j in jobs]  # job order, whatever finished first
    assert {r.worker for r in local} == {"local"} and {r.worker for r in dask} <= workers
    assert [r.states_sha256 for r in local] == [r.states_sha256 for r in dask]
    paths = {name: [Path(r.recording) for r in results] for name, results in (("local", local), ("dask", dask))}
    assert dataset_digest(paths["local"]) == dataset_digest(paths["dask"])
    assert all(p.parent == tmp_path / "dask" and p.name == f"{j.name}.mcap" for p, j in zip(paths["dask"], jobs))
    assert sorted(p.name for p in (tmp_path / "dask").iterdir()) == sorted(f"{j.name}.mcap" for j in jobs)


def test_two_worker_cluster_gives_the_sequential_dataset_bit_for_bit(tmp_path, cluster):
    _compare(tmp_path, _jobs((30, 10)), SHORT, cluster)


@pytest.mark.slow
def test_full_campaign_on_two_workers_gives_the_sequential_dataset_bit_for_bit(tmp_path):
    """The nine Table 2 cases at full length and the default mesh (nine full FE runs: slow)."""
    sequential = run_campaign(CampaignSettings(out_dir=tmp_path / "sequential", sequential=True), progress=False)
    dask = run_campaign(CampaignSettings(out_dir=tmp_path / "dask", workers=2), progress=False)
    assert [r.status for r in sequential] == [r.status for r in dask] == ["ok"] * 9
    assert [r.states_sha256 for r in sequential] == [r.states_sha256 for r in dask]
    assert dataset_digest([Path(r.recording) for r in sequential]) == dataset_digest([Path(r.recording) for r in dask])


FLAKY_LAUNCHER = '''
import subprocess, sys
from pathlib import Path
args = sys.argv[1:]
name = args[args.index("--run-id") + 1]
partial = Path(args[args.index("--out") + 1])
if name == "table2-case1":  # always fails
    print("solver diverged at step 3", file=sys.stderr)
    print("last words of case 1", file=sys.stderr)
    sys.exit(7)
if name == "table2-case2" and not partial.with_suffix(".tried").exists():  # fails once
    partial.with_suffix(".tried").write_text("1")
    print("transient failure", file=sys.stderr)
    sys.exit(3)
run = subprocess.run([sys.executable, {launcher!r}, *args], capture_output=True, text=True)
sys.stdout.write(run.stdout)
sys.stderr.write(run.stderr)
with partial.with_suffix(".launched").open("a") as log:  # the real launcher's exit status, a line per run
    log.write(f"{{run.returncode}}\\n")
sys.exit(run.returncode)
'''
"""The campaign's launcher in :func:`test_failed_case_is_retried_once_then_reported_and_the_others_kept`:
case 1 always fails, case 2 fails once; otherwise it runs the real launcher and logs its exit status
to ``<name>.partial.launched``."""


def launched(out: Path, case: int) -> list[int]:
    """Exit statuses of the real launcher's runs of ``case`` under :data:`FLAKY_LAUNCHER`, in order."""
    log = out / f"table2-case{case}.partial.launched"
    return [int(line) for line in log.read_text().split()] if log.exists() else []


def test_failed_case_is_retried_once_then_reported_and_the_others_kept(tmp_path, monkeypatch, capsys, cluster):
    """A failed attempt is retried once, and only a failed one: case 1 fails twice and is reported,
    case 2 fails once and then succeeds, case 3 succeeds. The successes are real runs; should case 3's
    fail on its own (a loaded machine), the campaign must retry it: its attempts are checked against
    the launcher's own record of its runs."""
    launcher = tmp_path / "flaky_launch.py"
    launcher.write_text(FLAKY_LAUNCHER.format(launcher=str(REPO / "launch.py")))
    original = run_campaign
    monkeypatch.setattr(cli, "run_campaign",
                        lambda settings, progress: original(dataclasses.replace(settings, launcher=launcher),
                                                            progress=progress))
    out = tmp_path / "out"
    argv = ["campaign", "--cases", "1", "2", "3", "--max-steps", "10", *SHORT, "--out-dir", str(out), "--json"]
    with client_credentials(cluster[2]):
        assert main([*argv, "--scheduler", cluster[0]]) == 1
    captured = capsys.readouterr()
    summary = json.loads(captured.out.strip().splitlines()[-1])
    cases = {c["case"]: c for c in summary["cases"]}
    runs = {c: launched(out, c) for c in (2, 3)}
    detail = (runs, captured.err[-3000:])
    assert runs[2] == [0] and runs[3][-1:] == [0] and 0 not in runs[3][:-1], detail  # each ends at a success
    assert (summary["ok"], summary["failed"]) == (2, 1) and list(cases) == [1, 2, 3], detail
    assert (cases[1]["status"], cases[1]["attempts"], cases[1]["exit_status"]) == ("failed", 2, 7)
    assert cases[1]["output_tail"].splitlines()[-2:] == ["solver diverged at step 3", "last words of case 1"]
    assert (cases[2]["status"], cases[2]["attempts"]) == ("ok", 2), detail
    assert (cases[3]["status"], cases[3]["attempts"]) == ("ok", len(runs[3])), detail
    assert (out / "table2-case2.mcap").is_file() and (out / "table2-case3.mcap").is_file()
    assert (out / "table2-case1.partial.mcap").exists() is False  # the fake never wrote one
    err = captured.err
    assert "case 1 failed after 2 attempt(s), exit status 7; last lines of its output:" in err
    assert "    last words of case 1" in err
    assert "table2-case2: failed" in err and "retrying" in err  # the progress line of the first attempt
    for c in (2, 3):
        assert f"table2-case{c}: ok (" in err  # one progress line per finished case
    # a re-run skips the complete cases and tries the failed one again (twice)
    assert main([*argv, "--no-progress", "--sequential"]) == 1  # (the skip comes before any runner)
    again = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert [c["status"] for c in again["cases"]] == ["failed", "skipped", "skipped"]
    assert again["cases"][1]["states_sha256"] == states_sha256(out / "table2-case2.mcap") is not None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@contextlib.contextmanager
def client_credentials(security):
    """Dask's configuration of a client's TLS credentials, as a user sets it for ``--scheduler``."""
    import dask

    with dask.config.set({"distributed.comm.tls.ca-file": security.tls_ca_file,
                          "distributed.comm.tls.client.cert": security.tls_client_cert,
                          "distributed.comm.tls.client.key": security.tls_client_key}):
        yield


@pytest.mark.parametrize("address, credentials, message", [
    ("localhost:8786", True, "--scheduler must be tls://HOST:PORT"),
    ("tls://127.0.0.1", True, "--scheduler must be tls://HOST:PORT"),
    ("tls://127.0.0.1:99999", True, "--scheduler must be tls://HOST:PORT"),
    ("tcp://127.0.0.1:8786", True, "refused, a Dask cluster must use TLS (tls://HOST:PORT)"),
    (None, False, "no TLS credentials for the client; set distributed.comm.tls.ca-file"),
    (None, True, "no Dask scheduler reachable within 1.5 s"),
])
def test_bad_or_unreachable_scheduler_is_a_one_line_error_exit_2(tmp_path, monkeypatch, capsys, address, credentials,
                                                                 message):
    from distributed.security import Security

    monkeypatch.setattr(distributed, "CONNECT_TIMEOUT_S", 1.5)
    address = address or f"tls://127.0.0.1:{_free_port()}"
    with client_credentials(Security.temporary() if credentials else Security()):
        status = main(["campaign", "--cases", "1", "--scheduler", address, "--out-dir", str(tmp_path / "o")])
    assert status == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("python -m gp_trainer campaign: error: --scheduler")
    assert message in err[0]
    assert not (tmp_path / "o").exists() or not any((tmp_path / "o").iterdir())


def test_the_local_cluster_refuses_a_client_without_its_credentials():
    """The campaign's cluster talks TLS with its own throw-away credentials: a client with none,
    with other ones, or over plain TCP gets no connection to the scheduler (whose RPC runs pickled code)."""
    from distributed import Client
    from distributed.security import Security

    with distributed.dask_client(None, 1) as client:
        address = client.scheduler.address
        assert address.startswith("tls://") and client.submit(int, "7").result() == 7
        for attempt in (dict(address=address, security=Security.temporary()),
                        dict(address=address.replace("tls://", "tcp://", 1)),
                        dict(address=address)):
            with pytest.raises((OSError, TypeError)), Client(**attempt, timeout="3s"):
                pass


def test_workers_and_scheduler_exclude_each_other(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["identify", "--workers", "2", "--scheduler", "tls://127.0.0.1:8786", "--out-dir", str(tmp_path)])
    assert info.value.code == 2 and "--scheduler: not allowed with argument --workers" in capsys.readouterr().err


def test_a_rerun_on_another_mesh_does_not_keep_the_recordings_of_the_first(tmp_path):
    """A complete recording is kept by a re-run only if it was made on the mesh and the plant the re-run
    asks for: an earlier ``--h-um 50`` run in the same ``--out-dir`` is not silently taken as a 25 µm
    one, nor a bare-plate run as one of the default plant."""
    from gp_trainer.errors import CampaignError

    jobs = [Job("table2-case1", "table2-case1", plant=(("preset", BARE),), args=("--max-steps", "5"))]
    coarse = CampaignSettings(out_dir=tmp_path, sequential=True, launch_args=SHORT)
    assert [r.status for r in run_jobs(jobs, coarse, progress=False)] == ["ok"]
    assert [r.status for r in run_jobs(jobs, coarse, progress=False)] == ["skipped"]
    with pytest.raises(CampaignError, match=r"table2-case1\.mcap was recorded on a 50 µm mesh, this run asks for "
                                            r"25 µm: use another --out-dir"):
        run_jobs(jobs, dataclasses.replace(coarse, launch_args=()), progress=False)
    with pytest.raises(CampaignError, match="recorded on a 50 µm mesh, this run asks for 40 µm"):
        run_jobs([Job("table2-case1", "table2-case1", plant=(("preset", BARE), ("h_fine_m", 40e-6)),
                      args=("--max-steps", "5"))],
                 dataclasses.replace(coarse, launch_args=()), progress=False)
    with pytest.raises(CampaignError, match=r"table2-case1\.mcap was recorded on another plant \(absorptivity 0\.4, "
                                            r"this run asks for 0\.\d+\): use another --out-dir"):  # the default plant
        run_jobs([Job("table2-case1", "table2-case1", args=("--max-steps", "5"))], coarse, progress=False)
