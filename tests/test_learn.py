"""Learning a process (``python -m gp_trainer learn``): operating point, run design, refusals, the layer check."""

from __future__ import annotations

import json
import tomllib
from pathlib import Path

import pytest

from controller_node.process import process_mismatch
from fe_node.scenarios import scenario
from gp_model.narx import NarxGPModel
from gp_model.shipped import DEFAULT_MODEL_PATH, PLATE_MODEL_PATH
from gp_trainer.campaign import IDENT_RUNS, PLATE_DESIGN, FeedbackRun, IdentRun, PartDesign, ProcessDesign
from gp_trainer.cli import main
from gp_trainer.errors import CampaignError, LearnError
from gp_trainer.jobs import plant_toml
from gp_trainer.learn import design_from_record, design_record, find_operating_power
from gp_trainer.provenance import REPO_ROOT
from messages.cli import UsageError


def synthetic_area(threshold_w: float = 60.0, gain_m2_per_w: float = 0.8e-9, curvature_w: float = 200.0):
    """A plant's steady area: no pool below a threshold power, then convex in power (plain regula falsi
    would keep one end of its bracket and crawl)."""
    calls = []

    def area(power_w: float) -> float:
        calls.append(power_w)
        excess = max(0.0, power_w - threshold_w)
        return gain_m2_per_w * excess * (1.0 + excess / curvature_w)

    return area, calls


@pytest.mark.parametrize("set_point_mm2", [0.02, 0.063, 0.15])
def test_operating_power_holds_the_set_point_in_a_few_runs(set_point_mm2):
    area, calls = synthetic_area()
    op = find_operating_power(area, set_point_mm2 * 1e-6, 0.0, 350.0)
    assert op.area_m2 == pytest.approx(set_point_mm2 * 1e-6, rel=0.005)
    assert area(op.power_w) == op.area_m2 and 60.0 < op.power_w < 350.0
    assert len(op.evaluations) == len(calls) - 1 <= 8  # the bound first, no run at 0 W
    assert op.evaluations[0] == (350.0, area(350.0))


def test_operating_power_with_a_lower_limit_evaluates_it():
    area, calls = synthetic_area()
    op = find_operating_power(area, 0.063e-6, 100.0, 300.0)
    assert calls[:2] == [300.0, 100.0] and op.area_m2 == pytest.approx(0.063e-6, rel=0.005)


@pytest.mark.parametrize("set_point_mm2, limits, bound", [(0.9, (0.0, 350.0), "power_max_w 350 W"),
                                                          (0.063, (0.0, 100.0), "power_max_w 100 W"),
                                                          (0.01, (100.0, 350.0), "power_min_w 100 W")])
def test_unreachable_set_point_is_refused_in_one_line_naming_set_point(set_point_mm2, limits, bound):
    area, _ = synthetic_area()
    with pytest.raises(LearnError, match=f"set_point {set_point_mm2:g} mm² is not reachable.*{bound}") as info:
        find_operating_power(area, set_point_mm2 * 1e-6, *limits)
    assert "\n" not in str(info.value)


def test_design_scales_the_runs_to_the_operating_point_and_the_set_point():
    design = ProcessDesign(130.0, 0.07, "models/stage1.json", (("preset", "physical"), ("t0_k", 320.0)))
    stage1, stage2 = design.stage1_runs(), design.stage2_runs()
    staircases = [r for r in stage1 if isinstance(r, IdentRun)]
    assert [(r.scenario, r.mean_w, r.amplitude_w, r.seed) for r in staircases] == [
        ("ident-layer", 104.0, 31.0, 1), ("ident-layer", 130.0, 31.0, 2), ("ident-layer", 156.0, 31.0, 3),
        ("ident-double-track", 104.0, 31.0, 4), ("ident-double-track", 130.0, 31.0, 5),
        ("ident-double-track", 156.0, 31.0, 6), ("ident-layer", 104.0, 31.0, 7), ("ident-layer", 130.0, 31.0, 8),
        ("ident-layer", 156.0, 31.0, 9)]
    turns = staircases[6:]   # the turnaround staircases: 8 tracks of 5 mm, 7 turns each
    assert [r.name for r in turns] == ["ident-layer-8x5mm-p104-s7", "ident-layer-8x5mm-p130-s8",
                                       "ident-layer-8x5mm-p156-s9"]
    assert all(dict(r.job().plant)["n_tracks"] == 8 and dict(r.job().plant)["track_length_m"] == 5e-3 for r in turns)
    assert all("n_tracks" not in dict(r.job().plant) for r in staircases[:6])
    closed = [r for r in stage1 if isinstance(r, FeedbackRun)]
    assert [(r.controller, r.scenario, r.setpoint_mm2) for r in closed] == [
        ("pid", "double-track", 0.0611), ("pid", "double-track", 0.07), ("pid", "double-track", 0.0778),
        ("pid", "layer", 0.0644), ("pid", "layer", 0.0756), ("feedforward", "double-track", 0.07)]
    assert [r.setpoint_mm2 for r in stage2] == [0.0644, 0.0756, 0.0667, 0.0733, 0.0667, 0.0722, 0.0733, 0.0678]
    for run in design.runs():  # the process's [plant] table in every run, a run's own keys over it
        job = run.job()
        plant = tomllib.loads(plant_toml(job.plant, job.controller_table))
        own_t0_k = run.t0_k if isinstance(run, FeedbackRun) and run.t0_k is not None else 320.0
        assert plant["plant"]["preset"] == "physical" and plant["plant"]["t0_k"] == own_t0_k
        # every run on one mesh, the uniform one: the closed-loop runs on the layer too (its default is multi-level)
        assert scenario(run.scenario, **plant["plant"]).settings.mesh == "uniform"
    assert closed[-1].job().controller_table == (("nominal_power_w", 130.0),)
    assert all(r.job().args[-2:] == ("--model", str(REPO_ROOT / "models/stage1.json")) for r in stage2)
    held = design.held_out()
    assert held == ("ident-layer-p130-s2", "ident-double-track-p130-s5", "ident-layer-8x5mm-p130-s8",
                    "ident-pid-double-track-a0.07")
    assert set(held) < {r.name for r in stage1}
    # the default layer at the target set point is in no run (the closed-loop figure there is off the training set)
    assert not [r for r in design.runs() if isinstance(r, FeedbackRun) and r.scenario == "layer"
                and r.setpoint_mm2 == design.setpoint_mm2]
    assert design_from_record(json.loads(json.dumps(design_record(design, Path("rec"))))) == (design, Path("rec"))
    older = {k: v for k, v in design_record(design, Path("rec")).items() if k != "turn_tracks"}
    assert design_from_record(older)[0].turn_tracks is None      # a record from before the turnaround staircases
    with pytest.raises(CampaignError, match="operating_power_w"):
        ProcessDesign(0.0, 0.063, "m.json")


def test_the_plate_design_is_the_shipped_plate_runs():
    assert PLATE_DESIGN.runs() == IDENT_RUNS
    assert [r.name for r in IDENT_RUNS][:6] == [
        "ident-layer-p200-s1", "ident-layer-p250-s2", "ident-layer-p300-s3",
        "ident-double-track-p200-s4", "ident-double-track-p250-s5", "ident-double-track-p300-s6"]
    assert PLATE_DESIGN.held_out() == ("ident-layer-p250-s2", "ident-double-track-p250-s5",
                                       "ident-mpc-double-track-a0.063")


def test_a_part_design_builds_the_part_about_its_operating_point():
    """``learn --scenario part``: the PID from the single track's power at set points about the target,
    staircases over the part's layers at 0.6/1/1.4 × the part's operating power, the preview MPC with the
    stage-1 model; the part in every run; the design survives the model's provenance record."""
    stl = "fe_node/parts/l_bracket_3mm.stl"
    design = PartDesign(70.0, 0.063, "models/stage1.json", stl, 2, (("preset", "physical"),), track_power_w=168.0)
    stage1, stage2 = design.stage1_runs(), design.stage2_runs()
    assert [r.name for r in stage1] == [f"ident-pid-part-l_bracket_3mm-a{a}" for a in ("0.055", "0.063", "0.07")] + [
        f"ident-part-l_bracket_3mm-p{p}-s{s}" for p, s in ((42, 1), (70, 2), (98, 3))]
    assert design.pid_runs() == stage1[:3] and design.target_pid_run == stage1[1]
    assert {r.amplitude_w for r in stage1 if isinstance(r, IdentRun)} == {28.0}
    assert [(r.controller, r.setpoint_mm2) for r in stage2] == [("preview-mpc", 0.06), ("preview-mpc", 0.066)]
    for run in design.runs():
        job = run.job()
        plant = tomllib.loads(plant_toml(job.plant, job.controller_table))["plant"]
        assert plant["part_stl"] == str(REPO_ROOT / stl) and plant["preset"] == "physical"
        layers = plant.get("n_layers") if isinstance(run, IdentRun) else int(job.args[job.args.index("--layers") + 1])
        assert layers == 2
    assert all(r.job().controller_table == (("nominal_power_w", 168.0),) for r in design.pid_runs())
    assert all(r.job().args[-2:] == ("--model", str(REPO_ROOT / "models/stage1.json")) for r in stage2)
    assert design.held_out() == ("ident-part-l_bracket_3mm-p70-s2", "ident-pid-part-l_bracket_3mm-a0.063")
    assert set(design.held_out()) < {r.name for r in stage1}
    assert design_from_record(json.loads(json.dumps(design_record(design, Path("rec"))))) == (design, Path("rec"))
    for bad in ({"n_layers": 0}, {"operating_power_w": -1.0}, {"track_power_w": 0.0}):
        with pytest.raises(CampaignError):
            PartDesign(**{"operating_power_w": 70.0, "setpoint_mm2": 0.063, "stage1_model": "m.json",
                          "part_stl": stl, **bad})


@pytest.mark.parametrize("argv, says", [
    (["--part", "fe_node/parts/l_bracket_3mm.stl"], "--part needs --scenario part"),
    (["--layers", "2"], "--layers needs --scenario part"),
    (["--scenario", "part", "--part", "no_such.stl"], "--part no_such.stl"),
    (["--scenario", "part", "--layers", "0"], "--layers 0"),
])
def test_learn_on_a_part_refuses_bad_part_options_in_one_line(tmp_path, capsys, argv, says):
    config = _config(tmp_path, "[plant]\n")
    status = main(["learn", "--config", str(config), "--out", str(tmp_path / "m.json"), "--out-dir",
                   str(tmp_path / "rec"), "--no-progress", *argv])
    err = capsys.readouterr().err
    assert status == 2 and says in err and err.count("\n") == 1, err
    assert not (tmp_path / "m.json").exists() and not (tmp_path / "rec").exists()


def _config(tmp_path: Path, text: str) -> Path:
    path = tmp_path / "process.toml"
    path.write_text(text)
    return path


@pytest.mark.parametrize("text, argv, key", [
    ('[plant]\npreset = "physical"\n[controller]\npower_max_w = 20.0\nnominal_power_w = 10.0\n', [], "set_point"),
    ('[plant]\npreset = "physical"\n', ["--set-point-mm2", "-1"], "set_point"),
    ('[plant]\nno_such_key = 1\n', [], "no_such_key"),
    ('[plant]\n[controller]\npower_max_w = -5.0\n', [], "power"),
    ('[plant]\n[other]\n', [], "other"),
    ('[plant]\n', ["--h-um", "100"], "h_fine_m"),
    ('[plant]\n', ["--structure-of", str(REPO_ROOT / "README.md")], "--structure-of: model file"),
    ('[plant]\n', ["--structure-of", str(REPO_ROOT / "gp_model/models/in625_narx_gp_1ms.json")],
     "learned at a sample period of 0.001 s"),
])
def test_learn_refuses_in_one_line_with_exit_2_naming_the_key(tmp_path, capsys, text, argv, key):
    config = _config(tmp_path, text)
    status = main(["learn", "--config", str(config), "--out", str(tmp_path / "m.json"), "--out-dir",
                   str(tmp_path / "rec"), "--h-um", "50", "--no-progress", *argv])
    err = capsys.readouterr().err
    assert status == 2 and key in err and err.count("\n") == 1 and err.startswith("python -m gp_trainer learn:")
    assert not (tmp_path / "m.json").exists() and not (tmp_path / "rec").exists()


def _model_of_layer(tmp_path: Path, powder_layer_m: float) -> Path:
    doc = json.loads(PLATE_MODEL_PATH.read_text())
    doc["provenance"]["process"] = {**doc["provenance"].get("process", {}), "powder_layer_m": powder_layer_m}
    path = tmp_path / "model.json"
    path.write_text(json.dumps(doc))
    return path


def test_a_model_of_another_powder_layer_is_refused_naming_it(tmp_path):
    from launch import RunOptions, check_config

    model = NarxGPModel.load(_model_of_layer(tmp_path, 40e-6))
    assert model.powder_layer_m == 40e-6
    assert "powder layer is 0 µm but the model was identified on 40 µm" in process_mismatch(model, powder_layer_m=0.0)
    assert process_mismatch(model, powder_layer_m=40e-6) is None
    assert process_mismatch(NarxGPModel.load(PLATE_MODEL_PATH), powder_layer_m=40e-6) is None  # not recorded
    config = _config(tmp_path, "[plant]\npowder_layer_m = 5e-5\n")
    with pytest.raises(UsageError, match=r"\[plant\] powder_layer_m: the plant's powder layer is 50 µm") as info:
        check_config(RunOptions(controller="preview-mpc", model=tmp_path / "model.json", config=config))
    assert "\n" not in str(info.value)


def test_launch_picks_the_model_of_the_plants_layer(tmp_path):
    from launch import RunOptions, default_model

    bare = _config(tmp_path, '[plant]\npreset = "bare-plate"\n')
    physical = tmp_path / "physical.toml"
    physical.write_text('[plant]\npreset = "physical"\n')
    assert default_model(RunOptions(controller="preview-mpc", config=bare)) == PLATE_MODEL_PATH
    assert default_model(RunOptions(controller="preview-mpc", config=physical)) is None  # the shipped default
    assert default_model(RunOptions(controller="pid", config=bare)) is None
    assert NarxGPModel.load(DEFAULT_MODEL_PATH).powder_layer_m == 25e-6  # the shipped model: the physical layer


@pytest.mark.slow
def test_learn_end_to_end_on_a_short_coarse_case(tmp_path, capsys):
    """``learn`` on the bare plate, every run cut to 80 steps on a 50 µm mesh: operating point, both
    stages, the model with its stage-1 model, the report and the plots; a re-run skips every run."""
    config = _config(tmp_path, '[plant]\npreset = "bare-plate"\n')
    argv = ["learn", "--config", str(config), "--out", str(tmp_path / "m.json"), "--out-dir", str(tmp_path / "rec"),
            "--h-um", "50", "--max-steps", "80", "--no-progress", "--json"]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["status"] == "ok" and 150.0 < report["operating_point"]["power_w"] < 350.0
    assert len(report["runs"]) == 23 and all(r["status"] == "ok" for r in report["runs"])
    model = NarxGPModel.load(tmp_path / "m.json")
    assert model.powder_layer_m == 0.0 and model.provenance["design"]["held_out"] == report["held_out"]
    same_runs = NarxGPModel.load(tmp_path / "m_stage1.json").provenance["runs"] == model.provenance["runs"]
    assert same_runs is (report["model_stage"] == 1)
    assert all(Path(p).is_file() for p in report["plots"].values())
    assert json.loads((tmp_path / "rec" / "learn.json").read_text())["metrics"] == report["metrics"]
    assert main(argv) == 0
    assert {r["status"] for r in json.loads(capsys.readouterr().out.strip().splitlines()[-1])["runs"]} == {"skipped"}


@pytest.mark.slow
def test_learn_end_to_end_on_a_part(tmp_path, capsys):
    """``learn --scenario part --part STL --layers 1`` in the structure of the shipped part model, every run cut
    to 150 steps on a 50 µm mesh: the PID's median power at the target is the part's operating power, the
    staircases are about it, both stages fit; ``evaluate`` rebuilds the design from the model."""
    from gp_model.shipped import PART_MODEL_PATH

    config = _config(tmp_path, "[plant]\n")
    out = tmp_path / "m.json"
    argv = ["learn", "--config", str(config), "--scenario", "part", "--part", "fe_node/parts/l_bracket_3mm.stl",
            "--layers", "1", "--structure-of", str(PART_MODEL_PATH), "--out", str(out), "--out-dir",
            str(tmp_path / "rec"), "--h-um", "50", "--max-steps", "150", "--no-progress", "--json"]
    assert main(argv) == 0
    report = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert report["status"] == "ok" and len(report["runs"]) == 8
    from gp_trainer.learn import median_power_w

    part = report["part_operating_point"]
    assert part["power_w"] == median_power_w(tmp_path / "rec" / f"{part['from_run']}.mcap")
    design, _ = design_from_record(NarxGPModel.load(out).provenance["design"])
    assert design.operating_power_w == round(part["power_w"]) and design.track_power_w == round(
        report["operating_point"]["power_w"])
    assert [r for r in design.runs() if isinstance(r, IdentRun)][1].mean_w == design.operating_power_w
    assert main(["evaluate", "--model", str(out), "--json", "--plots-dir", str(tmp_path / "plots")]) == 0
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["r2"] == report["metrics"]["r2"]


@pytest.mark.parametrize("rollouts, chosen", [((30.0, 25.0), 2), ((25.0, 30.0), 1)])
def test_the_model_is_the_stage_that_predicts_the_held_out_runs_better(monkeypatch, tmp_path, rollouts, chosen):
    """Stage 2 adds the preview MPC's closed-loop runs; where they make the held-out 40-step rollout worse,
    the stage-1 fit is written as the model (``model_stage`` 1, stage 2's figures kept as ``stage2``)."""
    from gp_trainer import learn as learn_module
    from gp_trainer.jobs import JobResult
    from gp_trainer.learn import LearnSettings

    class Fitted:
        sample_period_s = 5e-5

        def __init__(self, stage):
            self.stage = stage

        def save(self, out):
            Path(out).write_text(json.dumps({"stage": self.stage}))

    fits = iter((1, 2))

    def fit(settings, design, runs, out, provenance):
        stage = next(fits)
        Fitted(stage).save(out)
        return Fitted(stage), {"rollout_h40_mape_pct": rollouts[stage - 1]}, []

    monkeypatch.setattr(learn_module, "fe_steady_area", lambda plant: lambda p: 0.063e-6 * p / 200.0)
    monkeypatch.setattr(learn_module, "run_jobs",
                        lambda jobs, *a, **k: [JobResult(j.name, "rec.mcap", "ok", 0.0, "") for j in jobs])
    monkeypatch.setattr(learn_module, "controller_record", lambda directory, design: {})
    monkeypatch.setattr(learn_module, "_fit", fit)
    monkeypatch.setattr(learn_module.NarxGPModel, "load",
                        lambda path: Fitted(json.loads(Path(path).read_text())["stage"]))
    monkeypatch.setattr(learn_module, "plot_narx", lambda model, held, out_dir: {})
    settings = LearnSettings(model_out=tmp_path / "m.json", out_dir=tmp_path / "rec", sequential=True)
    report = learn_module.learn(settings, progress=False, log=lambda m: None)
    assert report["status"] == "ok" and report["model_stage"] == chosen
    assert json.loads((tmp_path / "m.json").read_text())["stage"] == chosen
    assert report["metrics"]["rollout_h40_mape_pct"] == min(rollouts)
    assert ("stage2" in report) is (chosen == 1)


@pytest.mark.parametrize("part", [False, True])
def test_a_failed_run_ends_learn_with_a_written_report_naming_it_and_no_model(monkeypatch, tmp_path, part):
    """A run that fails (on a part: one of the PID runs that set the operating power; on the plate: a stage-1
    run) ends ``learn`` before any fit: the report says ``failed``, names the run, lists every run once, and
    no model is written."""
    from gp_trainer import learn as learn_module
    from gp_trainer.jobs import JobResult
    from gp_trainer.learn import LearnSettings

    def run_jobs(jobs, *a, **k):
        return [JobResult(j.name, "rec.mcap", "failed" if i == 1 else "ok", 0.0, "") for i, j in enumerate(jobs)]

    monkeypatch.setattr(learn_module, "fe_steady_area", lambda plant: lambda p: 0.063e-6 * p / 200.0)
    monkeypatch.setattr(learn_module, "run_jobs", run_jobs)
    monkeypatch.setattr(learn_module, "_fit", lambda *a: pytest.fail("a fit after a failed run"))
    stl = REPO_ROOT / "fe_node" / "parts" / "l_bracket_3mm.stl"
    settings = LearnSettings(model_out=tmp_path / "m.json", out_dir=tmp_path / "rec", sequential=True,
                             part_stl=stl if part else None)
    report = learn_module.learn(settings, progress=False, log=lambda m: None)
    first = (PartDesign(200.0, 0.063, "s1.json", str(stl)).pid_runs() if part
             else ProcessDesign(200.0, 0.063, "s1.json").stage1_runs())
    assert report["status"] == "failed" and report["failed"] == [first[1].name]
    names = [r["name"] for r in report["runs"]]
    assert len(names) == len(set(names)) == len(first)
    written = json.loads(settings.report_out.read_text())
    assert (written["status"], written["failed"], written["runs"]) == ("failed", report["failed"], report["runs"])
    assert not (tmp_path / "m.json").exists()


def test_extra_runs_join_the_training_runs_of_a_stage_never_the_held_out(monkeypatch, tmp_path, capsys):
    """``learn --extra-runs R ...``: other runs of the process (another part's) are fitted with the design's
    training runs, the held-out runs stay the design's; the paths go to the process check and the provenance;
    a missing recording is one line, exit 2."""
    from types import SimpleNamespace

    from gp_trainer import learn as learn_module
    from gp_trainer.learn import LearnSettings

    seen = {}

    class Saved:
        def save(self, out):
            return out

    def select(train, held, **kwargs):
        seen.update(train=[r.name for r in train], held=[r.name for r in held], provenance=kwargs["provenance"])
        return Saved(), {}, []

    monkeypatch.setattr(learn_module, "_series", lambda directory, runs: [SimpleNamespace(name=r.name) for r in runs])
    monkeypatch.setattr(learn_module, "read_states", lambda path: path.stem)
    monkeypatch.setattr(learn_module, "series_from_states", lambda states, name: SimpleNamespace(name=name))
    monkeypatch.setattr(learn_module, "job_recording", lambda settings, job: tmp_path / f"{job.name}.mcap")
    monkeypatch.setattr(learn_module, "process_record", lambda paths: seen.setdefault("paths", paths) and {})
    monkeypatch.setattr(learn_module, "select_and_fit", select)
    design = PartDesign(70.0, 0.063, "m.json", "fe_node/parts/l_bracket_3mm.stl", 2)
    extra = (tmp_path / "ident-part-block_5mm-p60-s21.mcap", tmp_path / "ident-part-p60-s11.mcap")
    learn_module._fit(LearnSettings(extra_runs=extra, sequential=True), design, design.stage1_runs(),
                      tmp_path / "m.json", {})
    own = [r.name for r in design.stage1_runs() if r.name not in design.held_out()]
    assert seen["train"] == own + ["ident-part-block_5mm-p60-s21", "ident-part-p60-s11"]
    assert sorted(seen["held"]) == sorted(design.held_out()) and seen["paths"][-2:] == list(extra)
    assert seen["provenance"]["extra_runs"] == [str(p) for p in extra]
    config = _config(tmp_path, "[plant]\n")
    status = main(["learn", "--config", str(config), "--out", str(tmp_path / "m2.json"), "--out-dir",
                   str(tmp_path / "rec"), "--no-progress", "--extra-runs", str(tmp_path / "none.mcap")])
    err = capsys.readouterr().err
    assert status == 2 and "--extra-runs: no recording" in err and err.count("\n") == 1
    assert not (tmp_path / "rec").exists()


def test_selection_in_forked_workers_gives_the_same_model(monkeypatch):
    """``select_and_fit`` with workers fits each candidate in a forked process: the same table and model."""
    import dataclasses

    from gp_trainer import narx_fit
    from tests.test_preview import synthetic_run

    monkeypatch.setattr(narx_fit, "STRUCTURES", ((8, 5),))
    monkeypatch.setattr(narx_fit, "FORMS", (("identity", False, False), ("log", False, False)))
    monkeypatch.setattr(narx_fit, "LENGTH_SCALE_FLOORS", (2.0,))
    monkeypatch.setattr(narx_fit, "FEATURES", ((False, 0),))
    monkeypatch.setattr(narx_fit, "SMOOTHINGS", (0.0, 0.1))
    runs = [dataclasses.replace(synthetic_run(s, n=200), speed_m_s=0.8) for s in range(4)]
    one = narx_fit.select_and_fit(runs[:3], runs[3:], n_train=40)
    two = narx_fit.select_and_fit(runs[:3], runs[3:], n_train=40, workers=2)
    assert len(one[2]) == 4 and one[1] == two[1] and one[2] == two[2]
    assert one[0].to_dict() == two[0].to_dict()
    assert one[1]["rollout_h40_mape_pct"] == min(r["rollout_h40_mape_pct"] for r in one[2])


def test_the_pid_is_tuned_on_the_training_staircases_of_the_scenarios_own_plans(monkeypatch):
    """Not on the held-out staircases, nor on the turnaround staircases (8 tracks of 5 mm: mostly turns,
    where a first-order model of the power's response along a track fits nothing)."""
    from gp_trainer import learn as learn_module

    seen = {}
    monkeypatch.setattr(learn_module, "_series", lambda directory, runs: [r.name for r in runs])
    monkeypatch.setattr(learn_module, "pid_record", lambda series, set_point_m2, **kw: seen.setdefault("runs", series))
    record = learn_module.controller_record(Path("rec"), ProcessDesign(130.0, 0.07, "m.json"))
    assert seen["runs"] == ["ident-layer-p104-s1", "ident-layer-p156-s3", "ident-double-track-p104-s4",
                            "ident-double-track-p156-s6"]
    assert record["nominal_power_w"] == 130.0


def test_learning_in_the_structure_of_a_model_fits_only_its_candidate(monkeypatch, tmp_path):
    """``learn --structure-of M``: each stage's fit is the one candidate M was selected as
    (:func:`~gp_trainer.narx_fit.candidate_of`), recorded in the provenance; without it, every candidate."""
    from gp_trainer import learn as learn_module
    from gp_trainer.learn import LearnSettings
    from gp_trainer.narx_fit import candidate_of

    seen = []

    class Saved:
        def save(self, out):
            return out

    def select(train, held, **kwargs):
        seen.append((kwargs["candidates"], kwargs["provenance"].get("structure_of")))
        return Saved(), {}, []

    monkeypatch.setattr(learn_module, "_series", lambda directory, runs: [])
    monkeypatch.setattr(learn_module, "job_recording", lambda settings, job: tmp_path / "none.mcap")
    monkeypatch.setattr(learn_module, "process_record", lambda paths: {})
    monkeypatch.setattr(learn_module, "select_and_fit", select)
    design = ProcessDesign(130.0, 0.07, "m.json")
    for structure in (DEFAULT_MODEL_PATH, None):
        settings = LearnSettings(structure_of=structure, sequential=True)
        learn_module._fit(settings, design, design.stage1_runs(), tmp_path / "m.json", {})
    assert seen[0] == ([candidate_of(NarxGPModel.load(DEFAULT_MODEL_PATH))], str(DEFAULT_MODEL_PATH))
    assert seen[1] == (None, None)


def test_refitting_a_selected_model_fits_the_candidate_it_was_selected_as(monkeypatch):
    """``candidate_of`` reads back the candidate a selection kept (lags, output map, squares, p × T,
    length-scale floor, λ, no remnant terms): fitting only that candidate on the same runs gives the same
    model; with remnant terms, ``candidate_of`` reads them back too."""
    import dataclasses

    from gp_model.plan_feature import RemnantFeature
    from gp_trainer import narx_fit
    from tests.test_preview import synthetic_run

    monkeypatch.setattr(narx_fit, "STRUCTURES", ((8, 5),))
    monkeypatch.setattr(narx_fit, "FORMS", (("identity", False, False), ("log", True, True)))
    monkeypatch.setattr(narx_fit, "LENGTH_SCALE_FLOORS", (0.5, 2.0))
    monkeypatch.setattr(narx_fit, "FEATURES", ((False, 0),))
    monkeypatch.setattr(narx_fit, "SMOOTHINGS", (0.0, 0.1))
    runs = [dataclasses.replace(synthetic_run(s, n=200), speed_m_s=0.8) for s in range(4)]
    model, row, table = narx_fit.select_and_fit(runs[:3], runs[3:], n_train=40)
    candidate = narx_fit.candidate_of(model)
    assert candidate == ((8, 5), (row["output"], row["quadratic"], row["interaction"]), (False, 0),
                         row["length_scale_floor"], row["smoothing"], narx_fit.POWER_FORM, None)
    assert (row["power_map"], row["gp_power_input"]) == narx_fit.POWER_FORM == ("log1p", True)
    again, again_row, again_table = narx_fit.select_and_fit(runs[:3], runs[3:], n_train=40, candidates=[candidate])
    assert len(table) == 8 and len(again_table) == 1 and again_row == row
    assert again.to_dict() == model.to_dict()
    remnant = RemnantFeature(n_states=12, n_sources=5)
    with_remnant = narx_fit.select_and_fit(runs[:3], runs[3:], n_train=40, candidates=[(*candidate[:-1], remnant)])[0]
    assert narx_fit.candidate_of(with_remnant) == (*candidate[:-1], remnant)


def test_refit_refuses_a_model_without_a_design_in_one_line(tmp_path, capsys):
    """``refit`` needs the design a model of ``learn`` records (its runs and their directory): the bare
    plate's model of ``narx`` has none, a missing file is not a model, remnant terms need ≥ 1 source; exit 2,
    one line, nothing written."""
    for model, says, extra in ((PLATE_MODEL_PATH, "provenance.design", []), (tmp_path / "none.json", "none.json", []),
                               (PLATE_MODEL_PATH, "RemnantFeature.n_sources", ["--remnant-states", "8",
                                                                             "--remnant-sources", "0"])):
        status = main(["refit", "--model", str(model), "--out", str(tmp_path / "m.json"), *extra])
        err = capsys.readouterr().err
        assert status == 2 and says in err and err.count("\n") == 1 and err.startswith("python -m gp_trainer refit:")
        assert not (tmp_path / "m.json").exists()


def test_refit_can_leave_out_training_runs_and_records_them(monkeypatch, tmp_path, capsys):
    """``refit --drop RUN ...``: a model that never saw those runs' plans (judged off its training set by
    ``bench_suite.py --model``): the named runs are not fitted, the held-out ones stay, the names go to
    ``provenance.dropped_runs``; a name that is no training run, or no ``--out``, is one line, exit 2."""
    from gp_trainer import learn as learn_module

    seen = {}

    class Saved:
        def save(self, out):
            seen["out"] = out

    def select(train, held, **kwargs):
        seen.update(train=train, held=held, provenance=kwargs["provenance"])
        return Saved(), {"r2": 1.0}, []

    monkeypatch.setattr(learn_module, "read_states", lambda path: path.stem)
    monkeypatch.setattr(learn_module, "series_from_states", lambda states, name: name)
    monkeypatch.setattr(learn_module, "select_and_fit", select)
    runs = NarxGPModel.load(DEFAULT_MODEL_PATH).provenance["runs"]
    drop = ("ident-layer-p139-s1", "ident-pid-layer-a0.058")
    learn_module.refit(DEFAULT_MODEL_PATH, tmp_path / "m.json", drop=drop)
    assert seen["train"] == [r for r in runs if r not in drop] and len(seen["train"]) == len(runs) - 2
    assert "ident-layer-p174-s2" in seen["held"] and seen["provenance"]["dropped_runs"] == list(drop)
    for argv, says in ((["--drop", "nope", "--out", str(tmp_path / "x.json")], "--drop: nope not among"),
                       (["--drop", drop[0]], "--drop needs --out")):
        assert main(["refit", *argv]) == 2
        err = capsys.readouterr().err
        assert says in err and err.count("\n") == 1 and not (tmp_path / "x.json").exists()


def test_refit_takes_another_power_form(monkeypatch, tmp_path):
    """``refit --power-form F`` fits the model's candidate with F's (power map, GP's mean-power input) and
    nothing else changed; without it the candidate keeps the model's own form."""
    import shutil

    from gp_trainer import learn as learn_module
    from gp_trainer import narx_fit

    seen = []

    class Saved:
        def save(self, out):
            shutil.copy(DEFAULT_MODEL_PATH, out)

    def select(train, held, **kwargs):
        seen.append(kwargs["candidates"][0])
        return Saved(), {"r2": 1.0, "rollout_h40_mape_pct": 1.0}, []

    monkeypatch.setattr(learn_module, "read_states", lambda path: path.stem)
    monkeypatch.setattr(learn_module, "series_from_states", lambda states, name: name)
    monkeypatch.setattr(learn_module, "select_and_fit", select)
    own = narx_fit.candidate_of(NarxGPModel.load(DEFAULT_MODEL_PATH))
    learn_module.refit(DEFAULT_MODEL_PATH, tmp_path / "a.json")
    assert main(["refit", "--power-form", "log1p-no-gp-power", "--out", str(tmp_path / "b.json")]) == 0
    assert main(["refit", "--power-form", "square", "--out", str(tmp_path / "c.json")]) == 0
    assert seen[0] == own and own[-2] == ("log1p", True)
    assert seen[1] == (*own[:-2], ("log1p", False), own[-1]) and seen[2] == (*own[:-2], ("square", True), own[-1])
