"""Shared fixtures: a loopback zenoh hub and helpers to run nodes as real processes."""

from __future__ import annotations

import os
import subprocess
import sys
import uuid
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parent.parent


def free_endpoint() -> str:
    from launch import free_loopback_endpoint

    return free_loopback_endpoint()


@pytest.fixture
def run_id() -> str:
    return "t" + uuid.uuid4().hex[:10]


@pytest.fixture
def hub() -> str:
    """A fresh loopback endpoint for this test's hub."""
    return free_endpoint()


def spawn(module: str, *args: str, cwd: Path = REPO) -> subprocess.Popen[str]:
    """Start ``python -m module args`` in its own process (own session), output captured."""
    return subprocess.Popen(
        [sys.executable, "-u", "-m", module, *args],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), start_new_session=True,
    )


def finish(proc: subprocess.Popen[str], timeout: float = 30) -> tuple[int, str]:
    """Wait for a process; kill it if it outlives ``timeout``. Returns (status, output)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"process did not end in {timeout} s; output:\n{out}") from None
    return proc.returncode, out
