"""benchmarks/mesh_convergence.py: the plant's pool area at h and h / 2 over the power range, and its usage errors."""

from __future__ import annotations

import json
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
    coarse, fine = c["meshes"]                                            # per mesh, the finest last
    assert (coarse["h_um"], fine["h_um"]) == (25.0, 12.5) and fine["error_vs_finest_pct"] == 0.0
    assert (coarse["area_mm2"], coarse["jitter_pct"]) == (c["area_mm2_h"], c["jitter_pct_h"])
    assert coarse["error_vs_finest_pct"] == c["mesh_convergence_pct"]
    assert 0 < coarse["keyhole_depth_um"] < fine["keyhole_depth_um"]     # 60 W: 3.5 and 7.5 µm, under-resolved
    assert 3000 < coarse["peak_temperature_k"] < fine["peak_temperature_k"] <= 3494.0   # capped at keyhole onset


def test_config_sets_the_plant_over_the_preset(monkeypatch, capsys):
    """``--config``'s [plant] table reaches every case (here: keyhole and evaporation off), with the refinements."""
    seen = []

    def case(settings, power_w, track_m, refinements):
        seen.append((settings.keyhole, settings.evaporation, settings.powder_layer_m, power_w, refinements))
        return {"power_w": power_w, "mesh_convergence_pct": 0.0, "meshes": []}

    monkeypatch.setattr(mesh_convergence, "case", case)
    monkeypatch.setattr(sys, "argv", ["mesh_convergence.py", "--config", str(REPO / "docs/physical-conduction.toml"),
                                      "--powers", "60", "--refinements", "4", "2", "--json"])
    mesh_convergence.main()
    assert seen == [(False, False, 25e-6, 60.0, (2, 4))]
    record = json.loads(capsys.readouterr().out.splitlines()[-1])
    assert record["config"].endswith("physical-conduction.toml") and record["refinements"] == [2, 4]


@pytest.mark.parametrize(("args", "message"), [
    (["--track-mm", "0.5"], "--track-mm: the track must be longer"),
    (["--config", str(REPO / "pyproject.toml")], "--config: " + str(REPO / "pyproject.toml") + ": unknown table(s)"),
    (["--refinements", "4"], "--refinements: divisors of h in [2, 8], 2 among them"),
    (["--refinements", "2", "16"], "--refinements: divisors of h in [2, 8], 2 among them"),
])
def test_usage_errors_exit_2_naming_the_option(args, message, monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["mesh_convergence.py", *args])
    with pytest.raises(SystemExit) as exit_:
        mesh_convergence.main()
    assert exit_.value.code == 2 and message in capsys.readouterr().err


def test_a_bad_plant_key_is_a_usage_error_naming_it(tmp_path, monkeypatch, capsys):
    config = tmp_path / "bad.toml"
    config.write_text("[plant]\nno_such_key = 1\n")
    monkeypatch.setattr(sys, "argv", ["mesh_convergence.py", "--config", str(config)])
    with pytest.raises(SystemExit) as exit_:
        mesh_convergence.main()
    assert exit_.value.code == 2 and f"--config {config} [plant]: unknown scenario override 'no_such_key'" in \
        capsys.readouterr().err
