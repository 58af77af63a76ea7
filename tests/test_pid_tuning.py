"""The PID baseline's tuning on training staircases (gp_trainer.pid_tuning, `tune-pid`) and the
process record that gives every controller its operating power and gains (controller_node.process)."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from controller_node.node import build_parser, settings_from_args
from controller_node.process import process_table
from gp_model.errors import DatasetError
from gp_model.narx import RunSeries
from gp_model.shipped import DEFAULT_MODEL_PATH
from gp_trainer.pid_tuning import Fopdt, fit_fopdt, pid_record, simc_gains
from messages.cli import UsageError

DT = 50e-6
A, B, C, DELAY = 0.95, 3e-11, 1e-9, 3  # K = 6e-10 m²/W, τ = −Δt/ln a ≈ 0.975 ms


def staircase(seed: int, n_tracks: int = 4, track_steps: int = 250, turn_bump_m2: float = 4e-8) -> RunSeries:
    """A FOPDT plant (A, B, C, DELAY) under a random power staircase, with a decaying bump at each
    track's start (the turnaround, which the fit must leave out)."""
    rng = np.random.default_rng(seed)
    n = n_tracks * track_steps
    power = np.repeat(rng.uniform(100.0, 160.0, n // 25 + 1), 25)[:n]
    track = np.repeat(np.arange(n_tracks), track_steps)
    since = np.arange(n) % track_steps
    x = np.empty(n)
    x[0] = 6e-8
    for k in range(n - 1):
        x[k + 1] = A * x[k] + B * power[max(k + 1 - DELAY, 0)] + C
    x = x + turn_bump_m2 * np.exp(-since / 8.0) * (track > 0)
    return RunSeries(f"stair-s{seed}", x, np.full(n, 600.0), power, track, DT)


def test_the_fit_recovers_gain_time_constant_and_delay_past_the_turnarounds():
    model = fit_fopdt([staircase(1), staircase(2)])
    assert model.delay_steps == DELAY
    assert model.gain_m2_per_w == pytest.approx(B / (1 - A), rel=1e-3)
    assert model.time_constant_s == pytest.approx(-DT / math.log(A), rel=1e-3)
    assert model.dead_time_s == pytest.approx((DELAY + 0.5) * DT)


def test_on_a_part_the_fit_runs_over_each_layer_across_its_short_tracks():
    """Tracks of 30 states (a part's hatches, shorter than the turnaround window): along the tracks there is
    nothing to fit; over each layer (``by_layer``) the same plant is recovered."""
    runs = [staircase(1, n_tracks=40, track_steps=30, turn_bump_m2=0.0),
            staircase(2, n_tracks=40, track_steps=30, turn_bump_m2=0.0)]
    with pytest.raises(DatasetError, match="0 samples along the tracks"):
        fit_fopdt(runs)
    model = fit_fopdt(runs, by_layer=True)
    assert model.delay_steps == DELAY and model.gain_m2_per_w == pytest.approx(B / (1 - A), rel=1e-3)
    record = pid_record(runs, 0.063e-6, part=True)      # a part's record falls back to it, a plate's does not
    assert record["fopdt"]["n_samples"] == model.n_samples and record["method"].endswith("over each layer")
    with pytest.raises(DatasetError):
        pid_record(runs, 0.063e-6)
    long_tracks = [staircase(1), staircase(2)]
    assert pid_record(long_tracks, 0.063e-6, part=True) == pid_record(long_tracks, 0.063e-6)


def test_simc_gains_follow_the_rules():
    model = Fopdt(gain_m2_per_w=6e-10, time_constant_s=1e-3, dead_time_s=1e-4, delay_steps=1, sample_period_s=DT,
                  residual_rms_m2=0.0, n_samples=100)
    gains = simc_gains(model, 0.063e-6)
    kc = 1e-3 / (6e-10 * 1.1e-3)  # τ / (K (τc + θ)), τc = τ
    assert gains["kp_w"] == pytest.approx(kc * 0.063e-6)
    assert gains["ki_w"] == pytest.approx(gains["kp_w"] * DT / 1e-3)  # τI = min(τ, 4 (τc + θ)) = τ
    assert gains["kd_w"] == 0.0


def test_a_power_that_lowers_the_area_is_refused():
    run = staircase(3)
    flipped = RunSeries(run.name, 2e-7 - run.area_m2, run.t_ahead_k, run.power_w, run.track, DT)
    with pytest.raises(DatasetError, match="not a stable positive gain"):
        fit_fopdt([flipped])


def test_the_shipped_model_records_its_operating_power_and_tuned_pid():
    table = process_table(DEFAULT_MODEL_PATH)
    record = json.loads(DEFAULT_MODEL_PATH.read_text())["provenance"]
    assert table["nominal_power_w"] == record["design"]["operating_power_w"]
    assert table["pid"] == {k: record["controller"]["pid"][k] for k in ("kp_w", "ki_w", "kd_w")}
    assert not set(record["controller"]["pid"]["runs"]) & set(record["design"]["held_out"])  # training runs only


def test_the_run_config_wins_over_the_process_record(tmp_path):
    config = tmp_path / "run.toml"
    config.write_text("[controller.pid]\nkp_w = 55.0\n")
    args = build_parser().parse_args(["--process", str(DEFAULT_MODEL_PATH), "--config", str(config)])
    settings = settings_from_args(args)
    table = process_table(DEFAULT_MODEL_PATH)
    assert settings.pid.kp_w == 55.0 and settings.pid.ki_w == table["pid"]["ki_w"]
    assert settings.nominal_power_w == table["nominal_power_w"]
    assert settings_from_args(build_parser().parse_args([])).nominal_power_w == 250.0  # no process: the default


@pytest.mark.parametrize("record, message", [
    ({"nominal_power_w": 130.0}, "must be an object with a pid object"),
    ({"nominal_power_w": "hot", "pid": {"kp_w": 1.0, "ki_w": 1.0, "kd_w": 0.0}}, "nominal_power_w must be a number"),
    ({"nominal_power_w": 130.0, "pid": {"kp_w": 1.0, "kd_w": 0.0}}, "ki_w must be a number"),
])
def test_a_malformed_record_is_a_usage_error_naming_the_key(tmp_path, record, message):
    path = tmp_path / "model.json"
    path.write_text(json.dumps({"provenance": {"controller": record}}))
    with pytest.raises(UsageError, match=message):
        process_table(path)
    assert process_table(_write(tmp_path / "none.json", {"provenance": {}})) == {}


def _write(path: Path, doc: dict) -> Path:
    path.write_text(json.dumps(doc))
    return path


@pytest.mark.parametrize("controller", ["pid", "feedforward", "preview-mpc"])
def test_launch_gives_every_controller_the_process_of_the_plants_model(tmp_path, controller):
    from gp_model.shipped import PLATE_MODEL_PATH
    from launch import RunOptions, default_nodes

    def process_of(config: Path | None) -> str | None:
        opts = RunOptions(controller=controller, config=config)
        args = list({n.name: n for n in default_nodes(opts, tmp_path / "r.mcap")}["controller"].args)
        return args[args.index("--process") + 1] if "--process" in args else None

    bare = tmp_path / "bare.toml"
    bare.write_text('[plant]\npreset = "bare-plate"\n')
    assert process_of(None) == str(DEFAULT_MODEL_PATH)
    assert process_of(bare) == str(PLATE_MODEL_PATH)
    opts = RunOptions(controller=controller, config=bare, process=DEFAULT_MODEL_PATH)  # a learned process, chosen
    args = list({n.name: n for n in default_nodes(opts, tmp_path / "r.mcap")}["controller"].args)
    assert args[args.index("--process") + 1] == str(DEFAULT_MODEL_PATH)
