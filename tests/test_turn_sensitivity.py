"""``benchmarks/turn_sensitivity.py --json``: the model's response to a pre-turn power change over the plant's."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
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
    early = result["model_darea_pct_turn_1_7"] / result["plant_darea_pct_turn_1_7"]
    assert result["model_to_plant_ratio_turn_1_7"] == pytest.approx(early, abs=2e-3)


def test_the_windows_average_the_states_after_the_turn_they_name():
    """``window_means``: the mean change over the states ``first``..``last`` after the turn (both included) of the
    plant and the model, their ratio; None for an empty window or a plant that did not change there."""
    sys.path.insert(0, str(REPO / "benchmarks"))
    from turn_sensitivity import window_means

    after = np.arange(-3, 9)                   # states 1..12 after a snapshot taken 4 states before the turn
    plant = np.where(after >= 1, -2.0, 0.0) - np.where(after == 7, 2.0, 0.0)
    model = 0.5 * plant + np.where(after == 8, 100.0, 0.0)
    assert window_means(plant, model, after, 1, 7) == pytest.approx((-16 / 7, -8 / 7, 0.5))
    assert window_means(plant, model, after, 15, 30) == (None, None, None)
    assert window_means(plant, model, after, -3, -1) == (0.0, 0.0, None)
