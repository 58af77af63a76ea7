"""A process loads only the numerics it runs: a PID controller node and ``launch.py`` checking a
PID run start without numba, scipy (the plant's sparse algebra, the optimisers) or cvxpy (each test
process and every node of a run pays its imports at start)."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import REPO

HEAVY = ("numba", "scipy", "cvxpy", "gp_model.narx", "gp_model.model", "fe_node.solver")

BUILD_PID = """
import controller_node.node as node
from controller_node import ControllerSettings, make_controller
make_controller("pid", ControllerSettings(), node.load_model("pid", None))
"""
PREVIEW_MODEL = "from controller_node.registry import model_class\nmodel_class('preview-mpc')\n"


def loaded(code: str, modules: tuple[str, ...] = HEAVY) -> list[str]:
    """The ``modules`` (default :data:`HEAVY`) that ``code`` has imported, run in a fresh interpreter."""
    probe = f"{code}\nimport json, sys\nprint(json.dumps([m for m in {modules!r} if m in sys.modules]))\n"
    out = subprocess.run([sys.executable, "-c", probe], cwd=REPO, capture_output=True, text=True, check=True)
    return json.loads(out.stdout.splitlines()[-1])


@pytest.mark.parametrize("code", [BUILD_PID, "import launch", "import messages.recorder"])
def test_a_process_without_a_model_loads_no_model_numerics(code):
    assert loaded(code) == []


def test_the_preview_mpc_model_class_loads_them():
    """The check above can see a heavy import: naming the preview MPC's model class imports its module
    (without compiling: this module runs during the numba warm-up of ``tests/conftest.py``)."""
    assert {"numba", "gp_model.narx"} <= set(loaded(PREVIEW_MODEL))


def test_the_trainer_s_command_line_loads_no_optimiser_until_it_fits():
    """``python -m gp_trainer`` (its help, ``dataset``, ``evaluate``, ...) imports the PID tuning with ``learn``;
    its optimiser and filter (``scipy.optimize``, ``scipy.signal``: about a second of CPU) load when it fits."""
    assert loaded("import gp_trainer.cli", ("scipy.optimize", "scipy.signal")) == []
