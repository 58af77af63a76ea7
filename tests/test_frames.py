"""A camera's frame period: the FE run as a camera sees it (fe_node.frames), models learned at it, and the
preview MPC refusing a plant at another period."""

from __future__ import annotations

import dataclasses
import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from controller_node.preview import PreviewMPC
from controller_node.process import preview_steps, process_table
from controller_node.settings import ControllerSettings
from controller_node.types import ConfigurationError, Measurement
from fe_node.frames import camera_frames, frame_ratio
from fe_node.settings import Settings
from gp_model.build_up import build_up_steps
from gp_model.narx import NarxGPModel
from gp_trainer.narx_fit import features, rollout_key, structures
from tests.test_preview import synthetic_run

FRAME_S = 1e-3
REPO = Path(__file__).resolve().parents[1]


@dataclasses.dataclass(frozen=True)
class FEState:
    step: int
    time_s: float
    power_w: float
    area_m2: float


def _fe_run(powers_w: list[float], dt_s: float = 50e-6) -> list[FEState]:
    """FE states 0..n: state j carries the power applied during step j−1 → j and an area that tells it apart."""
    return [FEState(j, j * dt_s, p, 1e-8 * j) for j, p in enumerate([0.0, *powers_w])]


def test_a_camera_sees_every_kth_state_with_the_power_held_over_its_frame():
    powers = [200.0] * 4 + [150.0] * 4 + [180.0] * 4 + [99.0] * 3      # 3 whole frames of 4 steps, 1 partial
    frames = camera_frames(_fe_run(powers), 4, 2e-4)
    assert [f.step for f in frames] == [0, 1, 2, 3]
    assert [f.time_s for f in frames] == pytest.approx([0.0, 2e-4, 4e-4, 6e-4])
    assert [f.area_m2 for f in frames] == pytest.approx([0.0, 4e-8, 8e-8, 12e-8])    # FE states 0, 4, 8, 12
    assert [f.power_w for f in frames] == [0.0, 200.0, 150.0, 180.0]


def test_a_power_not_held_over_a_frame_is_refused():
    with pytest.raises(ValueError, match=r"frame 2: the power is not held over the frame \(150-160 W\)"):
        camera_frames(_fe_run([200.0] * 4 + [150.0] * 3 + [160.0]), 4, 2e-4)


def test_a_frame_period_that_is_no_whole_number_of_fe_steps_is_refused():
    assert frame_ratio(1e-3, 50e-6) == 20 and frame_ratio(5e-4, 50e-6) == 10
    with pytest.raises(ValueError, match=r"^--frame-period-s must be a whole number of FE steps of 50 µs, got "
                                         r"0.00103 s \(20.6 steps\)$"):
        frame_ratio(1.03e-3, 50e-6)
    with pytest.raises(ValueError, match="settings: frame_period_s must be a whole number"):
        Settings(frame_period_s=2.5e-5)
    settings = Settings(frame_period_s=FRAME_S)
    assert (settings.steps_per_frame, settings.sample_period_s) == (20, FRAME_S)
    assert (Settings().steps_per_frame, Settings().sample_period_s) == (1, 50e-6)


def test_sample_counts_scale_with_the_period_and_stay_at_the_fe_step():
    assert (build_up_steps(50e-6), build_up_steps(FRAME_S), build_up_steps(5e-4)) == (20, 1, 2)
    assert structures(50e-6) == ((24, 30), (32, 40)) and structures(FRAME_S) == ((2, 2), (4, 4))
    assert features(50e-6)[-1] == (True, 24) and features(FRAME_S)[-1] == (True, 2)
    assert (rollout_key(50e-6), rollout_key(FRAME_S)) == ("rollout_h40_mape_pct", "rollout_h8_mape_pct")
    assert preview_steps(FRAME_S) == {"horizon": 8, "observer_start_steps": 1, "turn_learning_steps": 3}


@pytest.fixture(scope="module")
def frame_model() -> NarxGPModel:
    """A model fitted on runs whose samples are 1 ms apart (the synthetic FIR plant, relabelled)."""
    runs = [dataclasses.replace(synthetic_run(s, n=200), sample_period_s=FRAME_S) for s in range(2)]
    return NarxGPModel.fit(runs, n_power_lags=4, n_temperature_lags=4, quadratic=False, output="identity",
                           n_train=40, n_restarts=1, profile_length=20, speed_m_s=0.8)


def test_a_frame_model_leaves_out_the_build_up_as_time(frame_model):
    """The build-up is the first 1 ms (20 FE steps, 1 frame): at 1 ms every frame from frame 1 is fitted (20
    build-up samples would leave out frames 1-19 of each run)."""
    assert frame_model.sample_period_s == FRAME_S
    assert frame_model.provenance["n_samples"] == 2 * (200 - 1)


def test_the_preview_mpc_refuses_a_50_us_plant_with_a_1_ms_model(frame_model):
    ctrl = PreviewMPC(ControllerSettings(set_point_m2=1.5e-8), frame_model)
    state = dict(area_m2=1e-8, t_ahead_k=300.0, power_w=250.0, speed_m_s=0.8, track=0)
    ctrl.update(Measurement(step=0, time_s=0.0, **{**state, "area_m2": 0.0, "power_w": 0.0}))
    with pytest.raises(ConfigurationError, match="^the plant's sample period is 50 µs but the model was identified "
                                                 "at 1000 µs; retrain at the plant's period$"):
        ctrl.update(Measurement(step=1, time_s=50e-6, **state))


def test_a_frame_model_gives_the_preview_mpc_its_sample_counts(tmp_path):
    record = {"nominal_power_w": 174.0, "pid": {"kp_w": 1.0, "ki_w": 0.1, "kd_w": 0.0},
              "preview": preview_steps(FRAME_S)}
    path = tmp_path / "model.json"
    path.write_text(json.dumps({"provenance": {"controller": record}}))
    assert process_table(path)["preview"] == {"horizon": 8, "observer_start_steps": 1, "turn_learning_steps": 3}


@pytest.mark.slow
def test_the_fe_node_at_a_frame_period_publishes_what_a_camera_sees_of_the_fe_run(tmp_path):
    """The FE plant at 1 ms (lockstep, open loop at 200 W, coarse mesh) publishes every 20th state of the same
    run at 50 µs, as frames 0, 1, 2, 3; both recordings conform."""
    from gp_trainer.dataset import read_states

    recordings = {}
    for name, frame, steps in (("fe", 0.0, 60), ("camera", FRAME_S, 3)):
        config = tmp_path / f"{name}.toml"
        config.write_text(f"[plant]\npower_w = 200.0\nh_fine_m = 5e-5\nframe_period_s = {frame!r}\n")
        out = recordings[name] = tmp_path / f"{name}.mcap"
        subprocess.run([sys.executable, "launch.py", "--scenario", "single-track", "--controller", "none",
                        "--config", str(config), "--max-steps", str(steps), "--out", str(out), "--no-progress"],
                       cwd=REPO, check=True, capture_output=True, timeout=300)
        subprocess.run([sys.executable, "-m", "messages.conformance", str(out)], cwd=REPO, check=True,
                       capture_output=True, timeout=120)
    seen = camera_frames(sorted(read_states(recordings["fe"]), key=lambda s: s.step), 20, FRAME_S)
    published = sorted(read_states(recordings["camera"]), key=lambda s: s.step)
    assert [s.step for s in published] == [0, 1, 2, 3]
    for mine, theirs in zip(published, seen, strict=True):
        assert (mine.step, mine.power_w, mine.area_mm2, mine.t_ahead_k) == (theirs.step, theirs.power_w,
                                                                           theirs.area_mm2, theirs.t_ahead_k)
        assert mine.time_s == pytest.approx(theirs.time_s, rel=1e-9)
    assert np.all(np.array([s.power_w for s in published[1:]]) == 200.0)


def test_the_turnaround_windows_of_the_report_are_2_5_ms_at_any_frame_period():
    from controller_node.report import Trace, metrics

    track = np.repeat([0, 1], 10)
    trace = Trace(time_s=np.arange(20) * FRAME_S, area_mm2=np.full(20, 0.063), power_w=np.full(20, 200.0),
                  t_ahead_k=np.full(20, 500.0), track=track)
    assert metrics(trace, 0.063).n_turnaround == 3


def test_the_pid_baseline_is_tuned_on_frames_with_the_turnarounds_left_out_as_time():
    """Tracks of 12 frames: 2.5 ms (3 frames) after each track's start are left out, not 50 samples."""
    from gp_model.narx import RunSeries
    from gp_trainer.pid_tuning import fit_fopdt

    rng, a, b = np.random.default_rng(3), 0.1, 4.5e-10
    runs = []
    for seed in range(3):
        p = np.r_[0.0, rng.uniform(120.0, 220.0, 47)]
        x = np.zeros(48)
        for j in range(47):
            x[j + 1] = a * x[j] + b * p[j + 1]
        runs.append(RunSeries(f"frames-{seed}", x, np.full(48, 500.0), p, np.arange(48) // 12, FRAME_S))
    model = fit_fopdt(runs)
    assert model.delay_steps == 0 and model.time_constant_s == pytest.approx(-FRAME_S / np.log(a), rel=1e-3)


def test_the_shipped_1_ms_model_is_the_one_the_camera_example_runs():
    from gp_model.shipped import MODELS_DIR

    path = MODELS_DIR / "in625_narx_gp_1ms.json"
    assert str(path.relative_to(REPO)) in (REPO / "docs" / "camera-1khz.toml").read_text()
    model = NarxGPModel.load(path)
    assert model.sample_period_s == pytest.approx(FRAME_S, rel=1e-9)
    assert process_table(path)["preview"] == preview_steps(FRAME_S)
