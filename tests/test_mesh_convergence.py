"""benchmarks/mesh_convergence.py: the plant's pool area at h and h / 2 over the power range, and its usage errors."""

from __future__ import annotations

import subprocess
import sys

import pytest

from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import mesh_convergence  # noqa: E402

from fe_node.presets import preset  # noqa: E402
from fe_node.settings import Settings  # noqa: E402


def test_the_record_compares_the_pool_at_h_and_at_half_of_it():
    """At 60 W on the default plant (25 and 12.5 µm): two different meshes, the difference in % of the fine
    one's area, and a steady pool on the fine mesh."""
    c = mesh_convergence.case(Settings(**preset("physical")), 60.0, 1.2e-3)
    assert c["n_states"] >= 4 and c["area_mm2_h"] > 0 and c["area_mm2_h2"] > 0
    assert c["area_mm2_h"] != c["area_mm2_h2"]
    expected = 100 * (c["area_mm2_h"] - c["area_mm2_h2"]) / c["area_mm2_h2"]
    assert c["mesh_convergence_pct"] == pytest.approx(expected, abs=0.05)      # (the areas are rounded)
    assert 0 <= c["jitter_pct_h2"] < 2.0


def test_a_track_too_short_for_a_window_is_a_usage_error():
    run = subprocess.run([sys.executable, "benchmarks/mesh_convergence.py", "--track-mm", "0.5"],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "--track-mm: the track must be longer" in run.stderr
