"""Campaign jobs on Dask distributed: a ``LocalCluster`` by default, or an existing cluster.

:func:`gp_trainer.campaign.run_jobs` opens a client with :func:`dask_client` and hands the pending
jobs to :func:`run_on_dask`. Each job is one task, :func:`gp_trainer.jobs.run_job`, which
starts ``launch.py`` as a subprocess on the worker; the worker only waits for it. So:

* a local cluster has ``workers`` worker *processes* with one thread each: at most ``workers``
  launcher runs at a time, as the process pool did before;
* the local cluster talks TLS with throw-away credentials of this campaign
  (``Security.temporary()``): a process without them cannot reach its scheduler or workers,
  whose RPC runs pickled code;
* on an existing cluster (``--scheduler tls://HOST:PORT``; ``tcp://`` is refused) a worker runs as
  many jobs at a time as it has threads; the client's TLS credentials come from Dask's
  configuration (``distributed.comm.tls.ca-file``, ``distributed.comm.tls.client.cert`` and
  ``distributed.comm.tls.client.key``, e.g. ``DASK_DISTRIBUTED__COMM__TLS__CA_FILE=ca.pem``); the
  workers must have this project installed and see the repository, the interpreter and the output
  directory at the same paths as the client (a shared file system);
* a failed job (the launcher failed, or its worker died) is submitted again, under a new key, up
  to ``retries`` times; the results are collected by job name, so their order, and the dataset
  built from the recordings, does not depend on which job finished first;
* Ctrl-C cancels the tasks and sends SIGINT to this campaign's launchers on every worker, which
  stop their nodes in order.
"""

from __future__ import annotations

import contextlib
import logging
import re
import uuid
from collections.abc import Callable, Iterator
from typing import TYPE_CHECKING

from gp_trainer.errors import CampaignError
from gp_trainer.jobs import Job, JobResult, RunSpec, interrupt_running, job_recording, run_job

if TYPE_CHECKING:
    from distributed import Client

CONNECT_TIMEOUT_S = 10.0  # an unreachable --scheduler is reported after this long
_ADDRESS = re.compile(r"^(tcp|tls)://(\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9._-]+):(\d{1,5})$")
_TLS_KEYS = ("distributed.comm.tls.ca-file", "distributed.comm.tls.client.cert", "distributed.comm.tls.client.key")


def check_scheduler_address(address: str) -> str:
    """``address`` if it looks like ``tls://HOST:PORT``, else a one-line :class:`CampaignError`
    naming ``--scheduler`` (``tcp://`` too: anyone reaching such a scheduler runs code on its workers)."""
    match = _ADDRESS.match(address)
    if not match or not 0 < int(match.group(3)) < 65536:
        raise CampaignError(f"--scheduler must be tls://HOST:PORT (a Dask scheduler), got {address!r}")
    if match.group(1) != "tls":
        raise CampaignError(f"--scheduler {address}: refused, a Dask cluster must use TLS (tls://HOST:PORT): "
                            "over tcp:// anyone who reaches it can run code as its workers' user")
    return address


def client_security():
    """The TLS credentials for an existing cluster, from Dask's configuration (:data:`_TLS_KEYS`);
    a one-line :class:`CampaignError` naming the keys when they are not set."""
    from distributed.security import Security

    security = Security()
    if not (security.tls_ca_file and security.tls_client_cert and security.tls_client_key):
        raise CampaignError(f"--scheduler: no TLS credentials for the client; set {', '.join(_TLS_KEYS)} in Dask's "
                            "configuration (e.g. DASK_DISTRIBUTED__COMM__TLS__CA_FILE=ca.pem)")
    return security


@contextlib.contextmanager
def dask_client(scheduler: str | None, workers: int) -> Iterator[Client]:
    """A Dask client: of the TLS cluster at ``scheduler``, or of a new ``LocalCluster`` of ``workers``
    worker processes (one thread each, no dashboard, no memory limit: the memory is the
    launcher's, outside the worker; TLS with throw-away credentials), closed on exit.

    Raises
    ------
    CampaignError
        ``scheduler`` is malformed, not ``tls://``, without client credentials, unreachable within
        :data:`CONNECT_TIMEOUT_S` or has no worker.
    """
    try:
        from distributed import Client, LocalCluster
        from distributed.security import Security
    except ImportError:
        raise CampaignError("Dask distributed is not installed (pip install 'dask[distributed]'); "
                            "--sequential runs without it") from None
    if scheduler is None:
        try:
            security = Security.temporary()
        except ImportError:
            raise CampaignError("the local Dask cluster's TLS needs the cryptography package (pip install "
                                "cryptography); --sequential runs without it") from None
        with LocalCluster(n_workers=workers, threads_per_worker=1, processes=True, dashboard_address=None,
                          memory_limit=0, silence_logs=logging.ERROR, security=security) as cluster, \
                Client(cluster, security=security) as client:
            yield client
        return
    check_scheduler_address(scheduler)
    security = client_security()
    try:
        client = Client(scheduler, security=security, timeout=f"{CONNECT_TIMEOUT_S}s")
    except (OSError, TimeoutError) as exc:
        reason = " ".join(str(exc).split()) or type(exc).__name__
        raise CampaignError(f"--scheduler {scheduler}: no Dask scheduler reachable within "
                            f"{CONNECT_TIMEOUT_S:g} s ({reason[:200]})") from None
    with client:
        try:
            client.wait_for_workers(1, timeout=CONNECT_TIMEOUT_S)
        except (OSError, TimeoutError):
            raise CampaignError(f"--scheduler {scheduler}: the cluster has no worker "
                                f"(none joined within {CONNECT_TIMEOUT_S:g} s)") from None
        yield client


def run_on_dask(client: Client, jobs: list[Job], spec: RunSpec, retries: int,
                report: Callable[[JobResult, bool], None]) -> dict[str, JobResult]:
    """Run ``jobs`` as tasks on ``client``'s cluster; a failed one again, up to ``retries`` times.

    ``report(result, final)`` is called for every attempt as it finishes (``final`` false when it
    will be retried). Returns the final result of every job, by name.
    """
    from distributed import as_completed

    campaign = uuid.uuid4().hex[:8]  # keys unique on a shared cluster; never in a result
    attempts: dict[str, tuple[Job, int]] = {}
    live: dict[str, object] = {}  # futures not yet finished

    def submit(job: Job, attempt: int):
        future = client.submit(run_job, spec, job, attempt, key=f"meltloop-{job.name}-{campaign}-{attempt}",
                               pure=False, retries=0)
        attempts[future.key] = (job, attempt)
        live[future.key] = future
        return future

    results: dict[str, JobResult] = {}
    running = as_completed([submit(job, 1) for job in jobs])
    try:
        for future in running:
            job, attempt = attempts.pop(future.key)
            live.pop(future.key, None)
            try:
                result = future.result()
            except Exception as exc:  # the worker died (KilledWorker), the task was lost, ...
                reason = " ".join(f"{type(exc).__name__}: {exc}".split())
                partial = job_recording(spec, job).with_name(f"{job.name}.partial.mcap")
                result = JobResult(job.name, str(partial), "failed", 0.0, f"not run to the end: {reason}",
                                   attempt, None, "", reason)
            future.release()
            final = result.status != "failed" or attempt > retries
            report(result, final)
            if final:
                results[job.name] = result
            else:
                running.add(submit(job, attempt + 1))
    except KeyboardInterrupt:
        client.cancel(list(live.values()))
        partials = [str(job_recording(spec, j).with_name(f"{j.name}.partial.mcap")) for j in jobs]
        with contextlib.suppress(Exception):
            client.run(interrupt_running, partials)
        raise
    return results
