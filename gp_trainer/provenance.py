"""Code version recorded in model files: git revision of the tree and library versions."""

from __future__ import annotations

import platform
import subprocess
from functools import cache
from importlib import metadata
from pathlib import Path
from typing import Any

REPO_ROOT = Path(__file__).resolve().parent.parent


def _git(*args: str) -> str | None:
    try:
        result = subprocess.run(["git", *args], cwd=REPO_ROOT, capture_output=True, text=True, timeout=10, check=True)
    except (OSError, subprocess.SubprocessError):
        return None
    return result.stdout.strip()


@cache
def code_version() -> dict[str, Any]:
    """Revision of the source tree and versions of the numerical libraries.

    ``gp_trainer_modified`` tells whether ``gp_trainer/`` or ``gp_model/`` (excluding the shipped
    model files) differs from the revision; uncommitted changes elsewhere in the tree do not count, and
    re-training does not change it, so a fixed seed gives a byte-identical model file.
    """
    status = _git("status", "--porcelain", "--", "gp_trainer", "gp_model", ":(exclude)gp_model/models")
    versions = {"python": platform.python_version()}
    for name in ("numpy", "scipy"):
        try:
            versions[name] = metadata.version(name)
        except metadata.PackageNotFoundError:
            versions[name] = "not installed"
    return {
        "git_revision": _git("rev-parse", "HEAD") or "unknown",
        "gp_trainer_modified": None if status is None else bool(status),
        "versions": versions,
    }
