"""benchmarks/power_sensitivity.py: the plant's and the model's change of the area after a power step, from
one settled state, and its usage errors."""

from __future__ import annotations

import subprocess
import sys

from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import power_sensitivity  # noqa: E402

from gp_model.narx import NarxGPModel  # noqa: E402
from gp_model.shipped import DEFAULT_MODEL_PATH  # noqa: E402


def test_a_power_step_grows_the_pool_of_the_plant_and_of_the_model():
    model = NarxGPModel.load(DEFAULT_MODEL_PATH)
    up = power_sensitivity.case("physical", model, 120.0, 30.0, 40, 30)
    down = power_sensitivity.case("physical", model, 120.0, -30.0, 40, 30)
    assert up["plant_darea_pct"] > 10.0 and down["plant_darea_pct"] < -10.0     # the plant's response, both ways
    assert up["model_darea_pct"] > 0.0 > down["model_darea_pct"]
    assert up["model_to_plant_ratio"] == round(up["model_darea_pct"] / up["plant_darea_pct"], 3)


def test_powers_beyond_the_bounds_are_a_usage_error():
    run = subprocess.run([sys.executable, "benchmarks/power_sensitivity.py", "--powers", "340", "--delta-w", "30"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "every power and power + step must lie in [0, 350] W" in run.stderr
