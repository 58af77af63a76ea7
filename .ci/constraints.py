"""Print ``constraints.txt``: the installed version of every distribution meltloop needs with all
its extras, directly or not (meltloop itself excluded), after a header saying how to update it.

Run in an environment where the tests pass: ``python .ci/constraints.py > constraints.txt``.
"""

from __future__ import annotations

import tomllib
from importlib.metadata import PackageNotFoundError, distribution
from pathlib import Path

from packaging.requirements import Requirement
from packaging.utils import canonicalize_name

PYPROJECT = Path(__file__).resolve().parent.parent / "pyproject.toml"
HEADER = """\
# The versions CI installs (.ci/run: pip install -c constraints.txt -e ".[test]"): every
# distribution meltloop[test,part] needs, directly or not, as installed when the tests last passed.
# To update: upgrade what you want, run the tests, then `python .ci/constraints.py > constraints.txt`."""


def closure(pyproject: Path = PYPROJECT) -> dict[str, str]:
    """Canonical name -> installed version of every distribution the project of ``pyproject``
    requires with all its extras, recursively (the project's own list from ``pyproject``, the
    others' from their installed metadata), with environment markers evaluated here."""
    project = tomllib.loads(pyproject.read_text())["project"]
    own = [*project["dependencies"], *(r for extra in project["optional-dependencies"].values() for r in extra)]
    found: dict[str, str] = {}
    pending: list[tuple[str, list[str], tuple[str, ...]]] = [(project["name"], own, ())]
    while pending:
        name, requires, wanted = pending.pop()
        for line in requires:
            req = Requirement(line)
            if req.marker is not None and not any(req.marker.evaluate({"extra": e}) for e in wanted or ("",)):
                continue
            key = canonicalize_name(req.name)
            if key in found or key == canonicalize_name(project["name"]):
                continue
            try:
                dist = distribution(req.name)
            except PackageNotFoundError:
                raise SystemExit(f"{req.name} (required by {name}) is not installed") from None
            found[key] = dist.version
            pending.append((req.name, dist.requires or [], tuple(req.extras)))
    return found


if __name__ == "__main__":
    print(HEADER)
    for name, version in sorted(closure().items()):
        print(f"{name}=={version}")
