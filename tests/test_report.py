"""The closed-loop report: one fixed evaluation window, turnaround/along-track split, completeness.

Synthetic traces with known numbers (no zenoh); the recording-level checks write small MCAP
files with the recorder's own writer.
"""

from __future__ import annotations

import json
import time

import numpy as np
import pytest

from controller_node import report as rep
from controller_node.report import (
    TURNAROUND_STEPS,
    WINDOW_START_S,
    Trace,
    completeness,
    metrics,
    recording_completeness,
    turnaround_mask,
    window_mask,
)
from messages import ControllerDiagnostics, MeltPoolState, RunEvent
from messages.codec import encode
from messages.recorder import McapRecorder
from messages.topics import CONTROLLER_DIAGNOSTICS, PLANT_STATE, RUN_EVENTS

DT_S = 50e-6
SETPOINT_MM2 = 0.1


def _trace(area_mm2, track=None, t0_s: float = 0.0) -> Trace:
    area = np.asarray(area_mm2, dtype=float)
    n = area.size
    return Trace(time_s=t0_s + DT_S * np.arange(n), area_mm2=area, power_w=np.full(n, 250.0),
                 t_ahead_k=np.full(n, 500.0), track=np.zeros(n, dtype=int) if track is None else np.asarray(track))


def test_window_constants():
    assert WINDOW_START_S == 1.0e-3 and TURNAROUND_STEPS == 50
    assert round(WINDOW_START_S / DT_S) == 20


@pytest.mark.parametrize("t0_s", [0.0, 12.3])
def test_window_opens_at_the_same_fixed_time_whatever_the_area(t0_s):
    n = 100
    ramps = {
        "fast build-up": np.r_[np.linspace(0, 0.12, 5), np.full(n - 5, 0.1)],
        "late build-up": np.r_[np.zeros(60), np.full(n - 60, 0.1)],
        "never reaches 90 %": np.full(n, 0.05),
    }
    for label, area in ramps.items():
        trace = _trace(area, t0_s=t0_s)
        window = window_mask(trace)
        assert np.flatnonzero(window)[0] == 20 and window[20:].all(), label  # 1 ms = 20 steps after laser-on
        m = metrics(trace, SETPOINT_MM2)
        assert m.window_start_s == WINDOW_START_S and m.n_turnaround + m.n_along == n - 20, label
        assert m.steps == n


def test_a_spike_before_the_window_does_not_count_even_after_the_pool_built_up():
    # The area passes 0.9 A_set at step 1 (the old build-up rule would open the window there)
    # and spikes to 2 A_set at step 10, before the fixed window opens.
    area = np.full(100, 0.1)
    area[0] = 0.0
    area[10] = 0.2
    area[50], area[60] = 0.11, 0.095
    m = metrics(_trace(area), SETPOINT_MM2)
    assert m.overshoot_pct == pytest.approx(10.0)
    assert m.undershoot_pct == pytest.approx(5.0)
    assert m.steady_rmse_pct == pytest.approx(100 * np.sqrt((0.1**2 + 0.05**2) / 80))


def test_a_slow_build_up_inside_the_window_counts_against_the_controller():
    # The area reaches the set point only at step 40; the old rule would have started there.
    area = np.r_[np.zeros(40), np.full(60, 0.1)]
    m = metrics(_trace(area), SETPOINT_MM2)
    assert m.undershoot_pct == pytest.approx(100.0)
    assert m.overshoot_pct == pytest.approx(0.0)
    assert m.steady_rmse_pct == pytest.approx(100 * np.sqrt(20 / 80))  # 20 empty-pool states of 80


def test_run_shorter_than_the_window_is_an_error():
    with pytest.raises(ValueError, match="before the evaluation window"):
        metrics(_trace(np.full(20, 0.1)), SETPOINT_MM2)


def test_turnaround_mask_first_50_states_of_every_track_but_the_first():
    track = np.r_[np.full(30, 2), np.full(80, 3), np.full(80, 4)]  # first track index 2, not 0
    mask = turnaround_mask(track)
    expected = np.zeros(190, dtype=bool)
    expected[30:80] = expected[110:160] = True
    assert (mask == expected).all()


def test_every_layer_of_a_build_opens_its_window_and_its_turnarounds_anew():
    # Two layers, tracks 0,1 each (track indices repeat): layer 0 states 0-99, layer 1 states 100-199.
    track = np.tile(np.r_[np.zeros(40, int), np.ones(60, int)], 2)
    layer = np.r_[np.zeros(100, int), np.ones(100, int)]
    area = np.full(200, 0.1)
    area[100:120] = 0.0                                 # layer 1's pool build-up: outside the window
    area[150] = 0.13                                    # a turnaround excursion of layer 1
    trace = Trace(time_s=DT_S * np.arange(200), area_mm2=area, power_w=np.full(200, 250.0),
                  t_ahead_k=np.full(200, 500.0), track=track, layer=layer)
    window = window_mask(trace)
    assert (np.flatnonzero(~window) == np.r_[0:20, 100:120]).all()
    expected = np.zeros(200, dtype=bool)
    expected[40:90] = expected[140:190] = True          # track 1 of each layer, not track 0 of layer 1
    assert (turnaround_mask(track, layer) == expected).all()
    m = metrics(trace, SETPOINT_MM2)
    assert m.undershoot_pct == pytest.approx(0.0) and m.overshoot_pct == pytest.approx(30.0)
    assert m.n_turnaround == 100 and m.n_along == 60 and m.turnaround_share_pct == pytest.approx(100.0)
    assert (window_mask(_trace(area, track)) == (np.arange(200) >= 20)).all()   # without layers: one window


def test_turnaround_and_along_track_split_exact():
    # Tracks 0: states 0-29, 1: 30-109, 2: 110-189. Window: 20-189 (170 states).
    # Turnaround: 30-79 and 110-159 (100 states, error +10 %); along-track: 20-29 (first track,
    # inside the window), 80-109, 160-189 (70 states, error -5 %). Before the window: empty pool.
    track = np.r_[np.zeros(30, dtype=int), np.ones(80, dtype=int), np.full(80, 2)]
    turn = np.zeros(190, dtype=bool)
    turn[30:80] = turn[110:160] = True
    area = np.where(turn, 0.11, 0.095)
    area[:20] = 0.0
    m = metrics(_trace(area, track), SETPOINT_MM2)
    assert (m.n_turnaround, m.n_along) == (100, 70)
    assert m.rmse_turnaround_pct == pytest.approx(10.0)
    assert m.rmse_along_pct == pytest.approx(5.0)
    sq_turn, sq_along = 100 * 0.1**2, 70 * 0.05**2
    assert m.turnaround_share_pct == pytest.approx(100 * sq_turn / (sq_turn + sq_along))  # 85.1 %
    assert m.steady_rmse_pct == pytest.approx(100 * np.sqrt((sq_turn + sq_along) / 170))
    assert m.steady_rmse_pct**2 == pytest.approx(
        (m.n_turnaround * m.rmse_turnaround_pct**2 + m.n_along * m.rmse_along_pct**2) / (m.n_turnaround + m.n_along))
    assert (m.overshoot_pct, m.undershoot_pct) == (pytest.approx(10.0), pytest.approx(5.0))


def test_turnaround_cut_by_the_window_counts_only_inside_it():
    # Track 1 starts at state 10: its turnaround 10-59 is cut to 20-59 by the window.
    track = np.r_[np.zeros(10, dtype=int), np.ones(80, dtype=int)]
    area = np.full(90, 0.1)
    area[10:20] = 0.5  # turnaround, but before the window
    area[20:60] = 0.12
    area[60:] = 0.099
    m = metrics(_trace(area, track), SETPOINT_MM2)
    assert (m.n_turnaround, m.n_along) == (40, 30)
    assert m.rmse_turnaround_pct == pytest.approx(20.0)
    assert m.rmse_along_pct == pytest.approx(1.0)
    assert m.overshoot_pct == pytest.approx(20.0)


def test_single_track_has_no_turnaround():
    area = 0.1 * (1 + 0.03 * np.sin(np.arange(120)))
    m = metrics(_trace(area), SETPOINT_MM2)
    assert m.rmse_turnaround_pct is None and m.turnaround_share_pct is None and m.n_turnaround == 0
    assert m.n_along == 100 and m.rmse_along_pct == pytest.approx(m.steady_rmse_pct)


def test_completeness_rules():
    assert completeness(251, 250) == rep.Completeness(True, None)
    assert completeness(300, None) == rep.Completeness(True, None)  # nothing announced: the recorder's mark only
    short = completeness(83, 250)
    assert not short.complete and short.reason == "83 of 251 plant states recorded"
    assert completeness(250, 250).complete is False  # the last state is missing
    unmarked = completeness(251, 250, recorded_complete=False)
    assert not unmarked.complete and "recorder" in unmarked.reason
    # The FE plant announces its steps at the lowest profile speed; "finished at step 122"
    # with all 123 states is the end of its scan plan, with fewer it is not.
    assert completeness(123, 167, finished_at_step=122).complete
    assert not completeness(100, 167, finished_at_step=122).complete
    # The replay node announces the number of states it sends.
    assert completeness(13, 13, total_counts_states=True).complete
    assert not completeness(12, 13, total_counts_states=True).complete


def _write_recording(path, n_states: int, total_steps: int | None, *, complete: bool = True,
                     end_detail: str = "", setpoint_mm2: float = SETPOINT_MM2):
    """A small closed-loop recording written with the recorder's own writer (no zenoh)."""
    rec = McapRecorder(path, "r", path.open("wb"))

    def put(topic, msg):
        rec.write(topic, encode(msg), msg, time.time_ns())

    put(RUN_EVENTS, RunEvent(run_id="r", node="plant", event="start", time_s=0.0, total_steps=total_steps))
    put(RUN_EVENTS, RunEvent(run_id="r", node="controller", event="start", time_s=0.0))
    for k in range(n_states):
        put(PLANT_STATE, MeltPoolState(
            run_id="r", step=k, time_s=k * DT_S, laser_x_mm=0.04 * k, laser_y_mm=0.0, scan_dir_x=1.0, scan_dir_y=0.0,
            track=0, area_mm2=0.1 if k >= 5 else 0.0, t_ahead_k=500.0, power_w=250.0, speed_mm_s=800.0))
        put(CONTROLLER_DIAGNOSTICS, ControllerDiagnostics(
            run_id="r", step=k, time_s=k * DT_S, controller="pid", status="ok", solve_time_us=10.0 + k,
            setpoint_mm2=setpoint_mm2))
    put(RUN_EVENTS, RunEvent(run_id="r", node="plant", event="end", time_s=(n_states - 1) * DT_S, detail=end_detail))
    rec.finish({"complete": "true" if complete else "false"})
    return path


def test_recording_short_of_the_announced_steps_is_incomplete(tmp_path, capsys):
    path = _write_recording(tmp_path / "short.mcap", 40, 60, end_detail="stopped at step 39; 0 fallbacks")
    done = recording_completeness(path, 40)
    assert not done.complete and done.reason == "40 of 61 plant states recorded"
    status = rep.main([str(path), "--json", "--figure", str(tmp_path / "short.png")])
    lines = capsys.readouterr().out.strip().splitlines()
    assert status == 1
    assert lines[0].startswith("INCOMPLETE (40 of 61 plant states recorded)") and "overshoot" not in lines[0]
    result = json.loads(lines[-1])
    assert result["complete"] is False and result["incomplete_reason"] == "40 of 61 plant states recorded"


def test_recording_not_marked_complete_is_incomplete(tmp_path):
    path = _write_recording(tmp_path / "unmarked.mcap", 61, 60, complete=False)
    done = recording_completeness(path, 61)
    assert not done.complete and "recorder did not mark" in done.reason


def test_complete_recording_prints_the_table4_line(tmp_path, capsys):
    path = _write_recording(tmp_path / "full.mcap", 61, 60, end_detail="finished at step 60; 0 fallbacks")
    status = rep.main([str(path), "--json", "--figure", str(tmp_path / "full.png")])
    lines = capsys.readouterr().out.strip().splitlines()
    assert status == 0
    assert "steady-state RMSE 0.00 %" in lines[0] and "window from 1 ms after laser-on" in lines[0]
    result = json.loads(lines[-1])
    assert result["complete"] is True and result["incomplete_reason"] is None
    assert result["window_start_s"] == WINDOW_START_S and result["n_along"] == 41
    assert result["rmse_turnaround_pct"] is None  # single track
    # the node's update as its diagnostics timed it: 10 + k µs for k = 0..60
    assert result["update_median_us"] == 40.0 and result["update_p99_us"] == pytest.approx(69.4)


def test_plan_finished_before_the_announced_total_is_complete(tmp_path):
    path = _write_recording(tmp_path / "early.mcap", 50, 70, end_detail="finished at step 49; 0 fallbacks")
    assert recording_completeness(path, 50).complete


def test_launch_summary_and_table_of_an_incomplete_run(tmp_path, capsys):
    from controller_node.summary import summarise, table_line

    path = _write_recording(tmp_path / "run.mcap", 40, 60, end_detail="stopped at step 39; 0 fallbacks")
    summary = summarise(path, "single-track", "pid", 0, 1.0)
    assert summary["complete"] is False and summary["incomplete_reason"] == "40 of 61 plant states recorded"
    out = table_line(summary)
    assert "pid on single-track: INCOMPLETE (40 of 61 plant states recorded)" in out and "overshoot" not in out

    full = _write_recording(tmp_path / "full.mcap", 61, 60)
    summary = summarise(full, "single-track", "pid", 0, 1.0)
    assert summary["complete"] is True and summary["window_start_s"] == WINDOW_START_S
    assert summary["rmse_turnaround_pct"] is None and summary["n_along"] == 41
    assert "window from 1 ms after laser-on" in table_line(summary)


def test_launch_summary_takes_the_set_point_the_controller_recorded(tmp_path):
    from controller_node.summary import summarise

    recorded = summarise(_write_recording(tmp_path / "at.mcap", 61, 60, setpoint_mm2=0.08), "single-track", "pid",
                         0, 1.0)
    assert recorded["setpoint_mm2"] == 0.08 and "steady_rmse_pct" in recorded
    plain = summarise(_write_recording(tmp_path / "plain.mcap", 61, 60, setpoint_mm2=0.1), "single-track", "pid",
                      0, 1.0)
    assert plain["steady_rmse_pct"] != recorded["steady_rmse_pct"]


@pytest.mark.parametrize("n_states, expected_status", [(40, 1), (61, 0)])
def test_launch_exits_1_when_a_normally_ended_run_did_not_finish(
    tmp_path, monkeypatch, capsys, n_states, expected_status
):
    import launch

    out = tmp_path / "run.mcap"

    def fake_launch(specs, path, *args, **kwargs):  # the supervisor saw a normal end (status 0)
        _write_recording(path, n_states, 60)
        return 0, 1.0

    monkeypatch.setattr(launch, "launch", fake_launch)
    status = launch.main(["--scenario", "single-track", "--controller", "pid", "--setpoint-mm2", "0.1",
                          "--out", str(out), "--json", "--no-progress"])
    summary = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert status == expected_status and summary["status"] == expected_status
    assert summary["complete"] is (expected_status == 0)


def test_comparison_table_states_each_controllers_update_median():
    from controller_node.summary import comparison_table

    row = {"controller": "preview-mpc", "overshoot_pct": 5.76, "undershoot_pct": 9.6, "steady_rmse_pct": 1.19,
           "rmse_turnaround_pct": 3.0, "rmse_along_pct": 0.25, "wall_s": 28.0}
    table = comparison_table("layer", 0.063, [{**row, "update_median_us": 104.9}, {**row, "controller": "replay"}])
    assert "| update median [µs] |" in table
    assert "| preview-mpc | 5.8 | 9.6 | 1.19 | 3.00 | 0.25 | 105 | 28.0 |" in table
    assert "| replay | 5.8 | 9.6 | 1.19 | 3.00 | 0.25 | n/a | 28.0 |" in table
