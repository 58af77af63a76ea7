"""CI installs the tested versions: ``constraints.txt`` pins the whole dependency closure."""

from __future__ import annotations

import re
import runpy
import shlex
import tomllib

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

from tests.conftest import REPO


def pins() -> dict[str, str]:
    lines = [line for line in (REPO / "constraints.txt").read_text().splitlines() if line and not line.startswith("#")]
    assert all(re.fullmatch(r"[a-z0-9-]+==[^=\s]+", line) for line in lines), lines
    return dict(line.split("==") for line in lines)


def test_constraints_pin_every_dependency_within_the_declared_bounds():
    pinned = pins()
    needed = runpy.run_path(str(REPO / ".ci" / "constraints.py"))["closure"]()
    assert "meltloop" not in pinned
    assert sorted(set(needed) - set(pinned)) == []
    project = tomllib.loads((REPO / "pyproject.toml").read_text())["project"]
    declared = [*project["dependencies"], *(r for extra in project["optional-dependencies"].values() for r in extra)]
    for line in declared:
        req = Requirement(line)
        assert req.specifier.contains(pinned[canonicalize_name(req.name)], prereleases=True), (line, pinned)


def test_ci_installs_with_the_constraints():
    installs = [shlex.split(line) for line in (REPO / ".ci" / "run").read_text().splitlines()
                if "pip install" in line and "-e" in line]
    assert installs and all("-c" in cmd and cmd[cmd.index("-c") + 1] == "constraints.txt" for cmd in installs)
