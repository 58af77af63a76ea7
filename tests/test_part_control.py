"""Control of a part: its identification runs, its model and what launch.py gives its controller."""
from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from controller_node.settings import ControllerSettings
from fe_node.scenarios import PART_POWER_W, scenario
from gp_model.narx import NarxGPModel
from gp_model.shipped import PART_MODEL_PATH, PLATE_MODEL_PATH
from gp_trainer.campaign import BLOCK_STL, IDENT_PART_RUNS, IDENT_RUNS, IDENT_SETS, FeedbackRun, IdentRun
from gp_trainer.cli import main as gp_main
from gp_trainer.jobs import plant_toml
from gp_trainer.provenance import REPO_ROOT
from launch import RunOptions, default_nodes


def _controller_args(opts: RunOptions, tmp_path: Path) -> list[str]:
    nodes = {n.name: n for n in default_nodes(opts, tmp_path / "run.mcap")}
    return list(nodes["controller"].args)


def _value(args: list[str], flag: str) -> str | None:
    return args[args.index(flag) + 1] if flag in args else None


def test_part_identification_runs_build_four_layers_and_hold_out_named_runs():
    open_loop = [r for r in IDENT_PART_RUNS if isinstance(r, IdentRun)]
    feedback = [r for r in IDENT_PART_RUNS if isinstance(r, FeedbackRun)]
    assert [r.name for r in open_loop] == ["ident-part-p60-s11", "ident-part-p100-s12", "ident-part-p140-s13",
                                           "ident-part-block_5mm-p60-s21", "ident-part-block_5mm-p100-s22",
                                           "ident-part-block_5mm-p140-s23"]
    assert [r.name for r in feedback] == ["ident-pid-part-a0.055", "ident-pid-part-a0.063", "ident-pid-part-a0.07"]
    for run in open_loop:
        plant = tomllib.loads(plant_toml(run.job().plant))["plant"]
        block = {"part_stl": str(REPO_ROOT / BLOCK_STL)} if "block" in run.name else {}
        assert plant == {"ident_seed": run.seed, "ident_mean_w": run.mean_w, "ident_amplitude_w": 40.0,
                         "n_layers": 1 if block else 4, **block}
    assert (REPO_ROOT / BLOCK_STL).is_file()
    for run in feedback:
        assert run.job().args == ("--setpoint-mm2", repr(run.setpoint_mm2), "--layers", "4")
        assert run.job().controller == "pid" and run.job().scenario == "part"
    assert all("n_layers" not in dict(r.job().plant) for r in IDENT_RUNS if isinstance(r, IdentRun))
    for ident in IDENT_SETS.values():      # every held-out name is a run of its set (a typo would hold out nothing)
        assert set(ident.held_out) < {r.name for r in ident.runs}
    assert IDENT_SETS["plate"].model_path == PLATE_MODEL_PATH and IDENT_SETS["part"].model_path == PART_MODEL_PATH
    assert IDENT_SETS["part"].out_dir != IDENT_SETS["plate"].out_dir


def test_ident_part_scenario_is_a_seeded_staircase_over_every_layer():
    pytest.importorskip("pyslm")

    a = scenario("ident-part", ident_seed=12, ident_mean_w=100.0, ident_amplitude_w=40.0, n_layers=2)
    b = scenario("ident-part", ident_seed=12, ident_mean_w=100.0, ident_amplitude_w=40.0, n_layers=2)
    assert a.profile == b.profile and len(a.layer_plans) == 2
    steps = sum(round(p.total_length / (0.8 * a.settings.dt_s)) for p in a.layer_plans)
    levels = [a.profile.command(k)[0] for k in range(steps)]
    assert 60.0 <= min(levels) and max(levels) <= 140.0 and len(set(levels)) > 10   # new levels to the last layer
    assert len(set(levels[steps // 2:])) > 5
    assert scenario("part", n_layers=1).profile.command(5)[0] == PART_POWER_W
    with pytest.raises(ValueError, match="ident_seed"):
        scenario("part", ident_seed=1)
    with pytest.raises(ValueError, match="ident_seed"):
        scenario("ident-part", ident_seed=1, power_w=90.0)


def test_launch_gives_a_part_run_the_part_model_and_power(tmp_path):
    args = _controller_args(RunOptions(scenario="part"), tmp_path)
    assert _value(args, "--model") == str(PART_MODEL_PATH)
    assert float(_value(args, "--nominal-power-w")) == PART_POWER_W
    pid = _controller_args(RunOptions(scenario="part", controller="pid"), tmp_path)
    assert _value(pid, "--model") is None and float(_value(pid, "--nominal-power-w")) == PART_POWER_W
    layer = _controller_args(RunOptions(scenario="layer"), tmp_path)
    assert "--nominal-power-w" not in layer  # the model of the default plant's layer:
    bare = scenario("layer").settings.powder_layer_m == 0     # the plate's without powder, else the shipped default
    assert _value(layer, "--model") == (str(PLATE_MODEL_PATH) if bare else None)
    config = tmp_path / "c.toml"
    config.write_text("[plant]\npower_w = 80.0\n")
    assert float(_value(_controller_args(RunOptions(scenario="part", config=config), tmp_path),
                        "--nominal-power-w")) == 80.0
    config.write_text("[controller]\nnominal_power_w = 120.0\n")   # the user's own nominal power is kept
    own = _controller_args(RunOptions(scenario="part", config=config), tmp_path)
    assert "--nominal-power-w" not in own
    other = tmp_path / "m.json"
    other.write_text("{}")
    assert _value(_controller_args(RunOptions(scenario="part", model=other), tmp_path), "--model") == str(other)
    learned = tmp_path / "learned.json"     # a part learned by `learn --scenario part`: it starts from its own power
    doc = json.loads(PART_MODEL_PATH.read_text())
    doc["provenance"]["controller"] = {"nominal_power_w": 133.0, "pid": {"kp_w": 54.0, "ki_w": 2.9, "kd_w": 0.0}}
    learned.write_text(json.dumps(doc))
    for controller in ("preview-mpc", "pid"):
        args = _controller_args(RunOptions(scenario="part", controller=controller, model=learned), tmp_path)
        assert _value(args, "--process") == str(learned) and "--nominal-power-w" not in args


def test_controller_node_applies_nominal_power_and_no_part_specific_settings(tmp_path):
    from controller_node.node import build_parser, settings_from_args

    parse = build_parser().parse_args
    settings = settings_from_args(parse(["--nominal-power-w", "100", "--setpoint-mm2", "0.06"]))
    assert settings.nominal_power_w == 100.0 and settings.set_point_m2 == pytest.approx(0.06e-6)
    assert settings.preview == ControllerSettings().preview   # a part runs the layer's preview settings
    assert settings_from_args(parse([])) == ControllerSettings()


def test_shipped_part_model_was_fitted_on_part_runs():
    model = NarxGPModel.load(PART_MODEL_PATH)
    assert model.sample_period_s == pytest.approx(50e-6)
    runs = set(model.provenance["runs"])
    assert runs and all(name.startswith(("ident-part-", "ident-pid-part-")) for name in runs)
    assert runs.isdisjoint(IDENT_SETS["part"].held_out)


def test_evaluate_part_without_recordings_says_which_command_to_run(tmp_path, capsys):
    assert gp_main(["evaluate", "--plant", "part", "--recordings-dir", str(tmp_path), "--no-identify"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "identify --plant part" in err and "ident-part-p100-s12" in err


def test_identify_part_without_pyslm_is_one_line_before_any_run(tmp_path, monkeypatch, capsys):
    import importlib.util

    find_spec = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "pyslm" else find_spec(name, *a))
    assert gp_main(["identify", "--plant", "part", "--out-dir", str(tmp_path), "--no-progress"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and "needs PySLM" in err and "--plant part" in err
    assert not any(tmp_path.iterdir())                               # no run was started


def test_narx_in_the_structure_of_a_model_fits_only_its_candidate(monkeypatch, tmp_path, capsys):
    """``narx --structure-of M`` fits the one candidate M was selected as, recorded in the provenance; a file
    that is no delay-aware model is refused in one line (exit 2)."""
    from types import SimpleNamespace

    from gp_trainer import cli
    from gp_trainer.narx_fit import candidate_of

    seen = []

    def select(train, held, **kwargs):
        seen.append((kwargs["candidates"], kwargs["provenance"].get("structure_of")))
        return NarxGPModel.load(PART_MODEL_PATH), {"quadratic": False, "interaction": False}, []

    monkeypatch.setattr(cli, "read_states", lambda path: path)
    monkeypatch.setattr(cli, "series_from_states", lambda states, name: SimpleNamespace(name=name,
                                                                                       sample_period_s=5e-5))
    monkeypatch.setattr(cli, "process_record", lambda paths: {})
    monkeypatch.setattr(cli, "select_and_fit", select)
    runs = [str(tmp_path / "ident-part-p60-s11.mcap"), str(tmp_path / "ident-part-p100-s12.mcap")]
    out = str(tmp_path / "m.json")
    assert gp_main(["narx", "--plant", "part", *runs, "--out", out, "--structure-of", str(PART_MODEL_PATH)]) == 0
    assert gp_main(["narx", "--plant", "part", *runs, "--out", out]) == 0
    assert seen == [([candidate_of(NarxGPModel.load(PART_MODEL_PATH))], str(PART_MODEL_PATH)), (None, None)]
    capsys.readouterr()
    assert gp_main(["narx", "--plant", "part", *runs, "--out", out, "--structure-of", str(tmp_path / "no.json")]) == 2
    assert "--structure-of" in capsys.readouterr().err
