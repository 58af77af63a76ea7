"""``benchmarks/turn_sensitivity.py --json``: the model's response to a pre-turn power change over the plant's."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from tests.conftest import REPO
from tests.plants import MODEL_PRESET


@pytest.mark.slow
def test_json_reports_the_model_to_plant_ratio():
    """On the double track's turn of the model's plant (the shipped model sees about a tenth of the
    plant's change)."""
    proc = subprocess.run([sys.executable, "benchmarks/turn_sensitivity.py", "--preset", MODEL_PRESET, "--scenario",
                           "double-track", "--turn", "0", "--json"], cwd=REPO, capture_output=True, text=True,
                          timeout=300)
    assert proc.returncode == 0, proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    plant, model = result["plant_darea_pct_turn_15_30"], result["model_darea_pct_turn_15_30"]
    assert plant < -1.0 and result["model_to_plant_ratio"] == pytest.approx(model / plant, abs=2e-3)
