"""Provenance of a run or artefact: code revision and package versions."""

from __future__ import annotations

import platform
import subprocess
from functools import cache
from importlib import metadata
from pathlib import Path

_PACKAGES = ("meltloop", "eclipse-zenoh", "numpy", "scipy", "scikit-fem", "cvxpy", "osqp", "mcap", "msgspec")
REPO_ROOT = Path(__file__).resolve().parent.parent


@cache
def git_revision() -> str:
    """Commit hash of the source tree (with ``-dirty`` if modified), or ``unknown``."""
    try:
        rev = subprocess.run(
            ["git", "describe", "--always", "--dirty", "--abbrev=40"],
            cwd=REPO_ROOT, capture_output=True, text=True, timeout=5, check=True,
        ).stdout.strip()
        return rev or "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


@cache
def package_versions() -> dict[str, str]:
    """Installed versions of the packages a run depends on, plus Python's."""
    versions = {"python": platform.python_version()}
    for name in _PACKAGES:
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return versions
