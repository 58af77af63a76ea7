"""Identification runs: ident-* scenarios (seeded random power staircases) and ``gp_trainer identify``."""

from __future__ import annotations

import json
import math
import subprocess
import sys
import tomllib
from pathlib import Path

import numpy as np
import pytest

from fe_node.scenarios import IDENT_DEFAULTS, IDENT_HOLD_STEPS, TRAINING_MESH, scenario
from gp_model.shipped import PLATE_MODEL_PATH
from gp_trainer.campaign import (
    IDENT_RUNS,
    PLATE_STAGE1_MODEL,
    FeedbackRun,
    IdentifySettings,
    IdentRun,
    ProcessDesign,
    identify_jobs,
    run_identification,
    select_ident_runs,
)
from gp_trainer.cli import main
from gp_trainer.errors import CampaignError
from gp_trainer.jobs import job_command, job_recording, plant_toml
from gp_trainer.learn import design_record
from gp_trainer.provenance import REPO_ROOT

REPO = Path(__file__).resolve().parent.parent
IDENT = ("ident-layer", "ident-double-track")


def _steps(sc) -> int:
    """Steps of the run (as the plant counts them: plan length at the constant speed)."""
    return math.ceil(sc.plan.total_length / (sc.profile.speed_m_s.range()[0] * sc.settings.dt_s) - 1e-9)


def _holds(sc) -> np.ndarray:
    """Hold lengths [steps] of the staircase's levels (the last one ends with the run)."""
    starts = np.array(sc.profile.power_w.times_s) / sc.settings.dt_s
    np.testing.assert_allclose(starts, np.round(starts), atol=1e-9)  # levels change on step boundaries
    return np.diff(np.round(starts).astype(int))


@pytest.mark.parametrize("name", IDENT)
def test_profile_is_deterministic_per_seed_and_differs_across_seeds(name):
    a, b = scenario(name, ident_seed=7), scenario(name, ident_seed=7)
    assert a.profile == b.profile
    other = scenario(name, ident_seed=8).profile.power_w
    assert other.values != a.profile.power_w.values and other.times_s != a.profile.power_w.times_s
    assert scenario(name).profile == scenario(name, ident_seed=IDENT_DEFAULTS["ident_seed"]).profile
    powers = [a.profile.command(k)[0] for k in range(_steps(a))]
    assert len(set(powers)) >= 8  # a staircase, not a constant


@pytest.mark.parametrize("name", IDENT)
@pytest.mark.parametrize("mean, amp, seed", [(250.0, 60.0, 0), (200.0, 60.0, 1), (300.0, 60.0, 3), (100.0, 100.0, 9),
                                             (150.0, 0.0, 2)])
def test_levels_and_holds_stay_in_their_ranges(name, mean, amp, seed):
    sc = scenario(name, ident_seed=seed, ident_mean_w=mean, ident_amplitude_w=amp)
    values = np.array(sc.profile.power_w.values)
    assert np.all((values >= mean - amp) & (values <= mean + amp))
    holds = _holds(sc)
    lo, hi = IDENT_HOLD_STEPS
    assert (lo, hi) == (3, 30) and np.all((holds >= lo) & (holds <= hi))
    n = _steps(sc)
    assert sc.profile.power_w.times_s[-1] < n * sc.settings.dt_s  # the last level starts inside the run
    assert n - round(sc.profile.power_w.times_s[-1] / sc.settings.dt_s) <= hi  # ... and no longer before its end
    powers = np.array([sc.profile.command(k) for k in range(n)])
    assert np.all((powers[:, 0] >= mean - amp) & (powers[:, 0] <= mean + amp)) and np.all(powers[:, 1] == 0.8)
    if amp > 0 and name == "ident-layer":  # 1000 steps: the holds and levels spread over their ranges
        assert holds.min() <= 6 and holds.max() >= 26 and np.ptp(values) > amp


def test_geometry_speed_and_dt():
    layer, ident = scenario("layer"), scenario("ident-layer")
    assert ident.plan == layer.plan and len(ident.plan.tracks) == 4 and ident.plan.lengths == pytest.approx([10e-3] * 4)
    double = scenario("ident-double-track")
    assert double.plan == scenario("double-track").plan and double.plan.lengths == pytest.approx([5e-3] * 2)
    assert _steps(ident) == 1000 and _steps(double) == 250
    fine = scenario("ident-double-track", dt_s=25e-6)  # holds count steps of the settings' dt
    assert fine.profile.dt_s == 25e-6 and _steps(fine) == 500
    assert np.all((_holds(fine) >= 3) & (_holds(fine) <= 30)) and fine.profile.power_w.times_s[-1] >= 470 * 25e-6
    # the same draws: a longer run extends a shorter one's staircase
    short = scenario("ident-double-track", ident_seed=3).profile.power_w
    long = scenario("ident-layer", ident_seed=3).profile.power_w
    assert long.values[:len(short.values)] == short.values and long.times_s[:len(short.times_s)] == short.times_s
    assert scenario("ident-layer", power_w=200.0).profile.command(123)[0] == 200.0  # power_w still means constant


@pytest.mark.parametrize("name, kw, key", [
    ("ident-layer", dict(ident_seed=-1), "ident_seed"),
    ("ident-layer", dict(ident_seed=1.5), "ident_seed"),
    ("ident-layer", dict(ident_seed=True), "ident_seed"),
    ("ident-layer", dict(ident_amplitude_w=-1.0), "ident_amplitude_w"),
    ("ident-layer", dict(ident_mean_w=50.0), "ident_mean_w"),  # 50 - 60 < 0
    ("ident-double-track", dict(ident_mean_w=100.0, ident_amplitude_w=150.0), "ident_mean_w"),
    ("ident-layer", dict(ident_mean_w=float("nan")), "ident_mean_w"),
    ("ident-layer", dict(ident_amplitude_w="60"), "ident_amplitude_w"),
    ("layer", dict(ident_seed=1), "ident_seed"),  # ident-* scenarios only
    ("table2-case2", dict(ident_mean_w=250.0), "ident_mean_w"),
    ("ident-layer", dict(ident_seed=2, power_w=250.0), "ident_seed"),
])
def test_bad_overrides_raise_one_line_value_error_naming_the_key(name, kw, key):
    with pytest.raises(ValueError, match=key) as info:
        scenario(name, **kw)
    assert "\n" not in str(info.value)


def test_identify_jobs_are_the_default_runs_with_their_command_lines(tmp_path):
    open_loop = [r for r in IDENT_RUNS if isinstance(r, IdentRun)]
    feedback = [r for r in IDENT_RUNS if isinstance(r, FeedbackRun)]
    assert [r.name for r in open_loop] == [
        "ident-layer-p200-s1", "ident-layer-p250-s2", "ident-layer-p300-s3",
        "ident-double-track-p200-s4", "ident-double-track-p250-s5", "ident-double-track-p300-s6"]
    assert [r.name for r in feedback] == [
        "ident-mpc-double-track-a0.055", "ident-mpc-double-track-a0.063", "ident-mpc-double-track-a0.07",
        "ident-mpc-layer-a0.058", "ident-mpc-layer-a0.068",
        "ident-feedforward-double-track-a0.063", "ident-feedforward-layer-a0.063",
        "ident-preview-mpc-double-track-a0.058", "ident-preview-mpc-double-track-a0.068",
        "ident-preview-mpc-layer-a0.06", "ident-preview-mpc-layer-a0.066",
        "ident-preview-mpc-double-track-a0.06-h90um-350K", "ident-preview-mpc-layer-a0.065-h90um-350K",
        "ident-preview-mpc-double-track-a0.066-h110um-450K", "ident-preview-mpc-layer-a0.061-h110um-450K"]
    assert IdentifySettings().out_dir == Path("recordings/identification") and IdentifySettings().workers == 2
    settings = IdentifySettings(out_dir=tmp_path, python="PY", launcher=Path("/repo/launch.py"))
    jobs = identify_jobs(settings)
    assert len(jobs) == 21
    for run, job in zip(open_loop, jobs):
        out, config = tmp_path / f"{job.name}.partial.mcap", tmp_path / "cfg.toml"
        assert job_recording(settings, job) == tmp_path / f"{run.name}.mcap"
        assert job_command(settings, job, out, config) == [
            "PY", "/repo/launch.py", "--scenario", run.scenario, "--controller", "none", "--config", str(config),
            "--no-progress", "--json", "--out", str(out), "--overwrite", "--run-id", run.name]
        assert dict(job.plant) == {"preset": "bare-plate", "ident_seed": run.seed, "ident_mean_w": run.mean_w,
                                   "ident_amplitude_w": 60.0}
        assert tomllib.loads(plant_toml(job.plant)) == {"plant": dict(job.plant)}
    for run, job in zip(feedback[:7], jobs[6:]):
        out = tmp_path / f"{job.name}.partial.mcap"
        nominal = {"nominal_power_w": 250.0} if run.controller == "feedforward" else {}  # the plate's operating power
        on_layer = {"mesh": TRAINING_MESH} if run.scenario == "layer" else {}     # (the layer's default is multi-level)
        assert dict(job.controller_table) == nominal and dict(job.plant) == {"preset": "bare-plate", **on_layer}
        config = tmp_path / "cfg.toml"
        assert job_command(settings, job, out, config) == [
            "PY",
            "/repo/launch.py",
            "--scenario",
            run.scenario,
            "--controller",
            run.controller,
            "--config",
            str(config),
            "--setpoint-mm2",
            repr(run.setpoint_mm2),
            "--no-progress",
            "--json",
            "--out",
            str(out),
            "--overwrite",
            "--run-id",
            run.name,
        ]
    for run, job in zip(feedback[7:], jobs[13:]):  # the preview MPC (stage-1 model), some at another hatch/preheat
        out, config = tmp_path / f"{job.name}.partial.mcap", tmp_path / "cfg.toml"
        command = job_command(settings, job, out, config)
        assert command[command.index("--model") + 1] == str(REPO_ROOT / PLATE_STAGE1_MODEL)
        assert dict(job.plant) == {"preset": "bare-plate", **({} if run.hatch_m is None else
                                                              {"hatch_m": run.hatch_m, "t0_k": run.t0_k}),
                                   **({"mesh": TRAINING_MESH} if run.scenario == "layer" else {})}
    assert (REPO_ROOT / PLATE_STAGE1_MODEL).is_file()
    assert [(r.scenario, r.mean_w, r.seed) for r in open_loop] == [
        ("ident-layer", 200.0, 1), ("ident-layer", 250.0, 2), ("ident-layer", 300.0, 3),
        ("ident-double-track", 200.0, 4), ("ident-double-track", 250.0, 5), ("ident-double-track", 300.0, 6)]
    assert select_ident_runs(["ident-double-track-p200-s4", "ident-layer-p300-s3"]) == (IDENT_RUNS[2], IDENT_RUNS[3])
    with pytest.raises(CampaignError, match="unknown identification run"):
        select_ident_runs(["ident-layer-p999-s1"])


def test_per_run_toml_is_accepted_by_the_launcher_and_reproduces_the_profile(tmp_path):
    from launch import RunOptions, check_config

    run = IDENT_RUNS[4]
    path = tmp_path / "run.toml"
    path.write_text(plant_toml(run.job().plant))
    check_config(RunOptions(scenario=run.scenario, controller="none", config=path))  # as launch.py validates it
    plant = tomllib.loads(path.read_text())["plant"]
    assert scenario(run.scenario, **plant).profile == scenario(
        run.scenario, ident_seed=run.seed, ident_mean_w=run.mean_w, ident_amplitude_w=run.amplitude_w).profile
    assert scenario(run.scenario, **plant).settings.powder_layer_m == 0.0  # the bare plate's runs pin their plant


FAILING_LAUNCHER = '''
import sys
from pathlib import Path
args = sys.argv[1:]
Path(args[args.index("--out") + 1]).write_bytes(b"half a recording")
print(Path(args[args.index("--config") + 1]).read_text().replace("\\n", " | "), file=sys.stderr)
sys.exit(1)
'''


def test_failed_run_keeps_its_partial_recording(tmp_path):
    launcher = tmp_path / "fake_launch.py"
    launcher.write_text(FAILING_LAUNCHER)
    settings = IdentifySettings(runs=select_ident_runs(["ident-layer-p250-s2"]), out_dir=tmp_path / "ident",
                                launcher=launcher, python=sys.executable)
    (result,) = run_identification(settings, progress=False)  # on a LocalCluster of 2 workers, retried once
    assert result.status == "failed" and "exit status 1" in result.detail and "ident_seed = 2" in result.detail
    assert (result.attempts, result.exit_status) == (2, 1) and "ident_seed = 2" in result.output_tail
    assert Path(result.recording) == tmp_path / "ident" / "ident-layer-p250-s2.partial.mcap"
    assert Path(result.recording).is_file() and not (tmp_path / "ident" / "ident-layer-p250-s2.mcap").exists()
    # only the partial recording: the job config went to a temporary directory
    assert sorted(p.name for p in (tmp_path / "ident").iterdir()) == ["ident-layer-p250-s2.partial.mcap"]


def test_cli_user_errors_exit_2(tmp_path, capsys):
    assert main(["identify", "--runs", "nope", "--out-dir", str(tmp_path)]) == 2
    assert main(["identify", "--workers", "0", "--out-dir", str(tmp_path)]) == 2
    assert main(["identify", "--timeout", "0", "--out-dir", str(tmp_path)]) == 2
    assert main(["identify", "--retries", "-1", "--out-dir", str(tmp_path)]) == 2
    assert main(["identify", "--scheduler", "http://x:1", "--out-dir", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 5 and "unknown identification run(s) nope" in err[0] and "--workers" in err[1]
    assert "--timeout" in err[2] and "--retries" in err[3] and "--scheduler must be tls://HOST:PORT" in err[4]
    assert not any(tmp_path.iterdir())


def test_identify_records_one_double_track_end_to_end(tmp_path):
    """``python -m gp_trainer identify --runs ident-double-track-p250-s5``: its first 120 FE steps, on a coarse
    mesh and without Dask (the Dask runner: tests/test_campaign_dask.py)."""
    from gp_trainer.dataset import read_states
    from messages.recording import is_complete

    name = "ident-double-track-p250-s5"
    cmd = [sys.executable, "-m", "gp_trainer", "identify", "--runs", name, "--out-dir", str(tmp_path),
           "--no-progress", "--json", "--timeout", "120", "--h-um", "50", "--max-steps", "120", "--sequential"]
    proc = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=180)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    summary = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (summary["ok"], summary["failed"], summary["runs"][0]["name"]) == (1, 0, name)
    recording = tmp_path / f"{name}.mcap"
    assert is_complete(recording) and [p.name for p in tmp_path.iterdir()] == [recording.name]
    states = read_states(recording)
    assert len(states) == 121 and states[-1].step == 120
    power = np.array([s.power_w for s in states[1:]])  # state k carries the power of step k - 1
    expected = scenario("ident-double-track", ident_seed=5, ident_mean_w=250.0, ident_amplitude_w=60.0).profile
    np.testing.assert_allclose(power, [expected.command(s.step - 1)[0] for s in states[1:]])
    assert np.all((power >= 190.0) & (power <= 310.0))
    assert len(np.unique(power)) >= 8 and np.ptp(power) > 40.0 and np.std(power) > 10.0  # it varies
    again = subprocess.run(cmd, cwd=REPO, capture_output=True, text=True, timeout=60)  # complete: skipped
    assert again.returncode == 0 and json.loads(again.stdout.strip().splitlines()[-1])["skipped"] == 1


def test_evaluate_records_the_missing_held_out_runs_first(tmp_path, monkeypatch, capsys):
    """On a fresh clone ``evaluate`` records the held-out runs it lacks (as ``identify --runs`` would,
    here a stand-in that writes synthetic recordings), then evaluates on them."""
    from gp_trainer import cli, synthetic
    from tests.test_gp_pipeline import _record

    held_out = ("ident-layer-p250-s2", "ident-double-track-p250-s5", "ident-mpc-double-track-a0.063")
    _record(tmp_path / f"{held_out[0]}.mcap", synthetic.table2_case(2, seed=1))
    asked = []

    def identify(settings, progress=True):
        asked.append(([r.name for r in settings.runs], settings.out_dir))
        settings.out_dir.mkdir(exist_ok=True)
        for i, run in enumerate(settings.runs):
            _record(settings.out_dir / f"{run.name}.mcap", synthetic.table2_case(2, seed=2 + i))
        return []

    monkeypatch.setattr(cli, "run_identification", identify)
    assert main(["evaluate", "--plant", "plate", "--recordings-dir", str(tmp_path), "--json"]) == 0
    assert asked == [(list(held_out[1:]), tmp_path)]
    out, err = capsys.readouterr()
    assert json.loads(out.strip().splitlines()[-1])["held_out"] == list(held_out)
    assert f"identify --plant plate --runs {' '.join(held_out[1:])} --out-dir {tmp_path}" in err.splitlines()[0]
    # a model of `learn`: the held-out runs of the design its provenance records, whatever --plant says
    design = ProcessDesign(133.0, 0.063, "stage1.json", (("preset", "physical"),))
    doc = json.loads(PLATE_MODEL_PATH.read_text())
    doc["provenance"]["design"] = design_record(design, tmp_path / "learned")
    (tmp_path / "learned.json").write_text(json.dumps(doc))
    asked.clear()
    assert main(["evaluate", "--plant", "plate", "--model", str(tmp_path / "learned.json"), "--json"]) == 0
    assert asked == [(list(design.held_out()), tmp_path / "learned")]
    assert json.loads(capsys.readouterr().out.strip().splitlines()[-1])["held_out"] == list(design.held_out())


@pytest.mark.slow
def test_evaluate_on_a_fresh_clone_records_what_it_needs(tmp_path):
    """``python -m gp_trainer evaluate --json`` with no identification recordings: it records the 3
    held-out runs (a layer and two double tracks on the FE plant, 2 Dask workers), then evaluates the
    shipped physical-plant model on them (documented: 40-step rollout 4.7 %, R² 0.93)."""
    proc = subprocess.run([sys.executable, "-m", "gp_trainer", "evaluate", "--recordings-dir", str(tmp_path),
                           "--json"], cwd=REPO, capture_output=True, text=True, timeout=900)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    result = json.loads(proc.stdout.strip().splitlines()[-1])
    assert result["rollout_h40_mape_pct"] < 6.0 and result["r2"] > 0.9, result
