"""gp_trainer pipeline: samples from states and MCAP recordings, CLI, evaluation, campaign."""

from __future__ import annotations

import dataclasses
import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from gp_model.errors import DatasetError
from gp_model.model import GPModel
from gp_trainer import synthetic
from gp_trainer.campaign import CampaignSettings, recording_path, run_campaign
from gp_trainer.cli import main
from gp_trainer.dataset import DatasetSettings, build_samples, concatenate, read_states
from gp_trainer.errors import CampaignError, RecordingError

State = synthetic.SyntheticState


def _track(areas, track=0, first_step=0, power=250.0, speed=800.0):
    return [State(first_step + i, (first_step + i) * 50e-6, track, a, 400.0 + i, power + i, speed)
            for i, a in enumerate(areas)]


def test_samples_pair_state_k_with_inputs_of_step_k_plus_1_in_si():
    states = _track([0.0, 0.05, 0.06, 0.07, 0.071, 0.072])
    samples, report = build_samples(states, "t", DatasetSettings(startup_fraction=0.5))
    # median of positive areas 0.07 -> formed from the first area >= 0.035, i.e. state 1
    assert report.dropped_startup == 1 and report.n_samples == 4 and report.dropped_gap == 0
    np.testing.assert_allclose(samples.Z[0], [0.05e-6, 401.0, 252.0, 0.8, 0.05e-6])  # x_1 − x_0 (start-up history kept)
    np.testing.assert_allclose(samples.Z[1:, 4], np.array([0.01, 0.01, 0.001]) * 1e-6)
    np.testing.assert_allclose(samples.y, np.array([0.06, 0.07, 0.071, 0.072]) * 1e-6)
    assert samples.step.tolist() == [1, 2, 3, 4]


def test_track_changes_gaps_and_vanished_pools_are_dropped_and_counted():
    states = (_track([0.0, 0.06, 0.07, 0.07]) + _track([0.0, 0.05, 0.07, 0.0, 0.07, 0.07], track=1, first_step=4)
              + _track([0.07, 0.07], track=1, first_step=20))
    samples, report = build_samples(states, "t")
    # 3 -> 4 (new track), 9 -> 20 (lost messages) and 20 -> 21 (state 19, its history, is lost)
    assert report.dropped_gap == 3
    assert report.dropped_no_pool == 2  # 6 -> 7 and 7 -> 8 around the zero area
    assert report.dropped_startup == 2  # the first state of each track
    assert report.n_samples == len(samples) == 4
    assert samples.step.tolist() == [1, 2, 5, 8]  # 8 keeps its history x_7 = 0 (an input, not a target)
    assert report.n_samples + report.dropped_gap + report.dropped_no_pool + report.dropped_startup == len(states) - 1
    assert np.all(samples.Z[:, 0] > 0) and np.all(samples.y > 0)


@pytest.mark.parametrize("states, reason", [
    ([], "no plant states"),
    (_track([0.0, float("nan"), 0.07]), "non-finite `area_mm2`"),
    ([State(1, 0.0, 0, 0.07, 400.0, 250.0, 800.0), State(1, 0.0, 0, 0.07, 400.0, 250.0, 800.0)], "do not increase"),
    ([object()], "no field `step`"),
])
def test_bad_states_raise_a_typed_error(states, reason):
    with pytest.raises(DatasetError, match=reason):
        build_samples(states, "t")


@settings(max_examples=60, deadline=None)
@given(st.lists(st.tuples(st.sampled_from([0.0, 0.0, 0.03, 0.07, 0.08]), st.integers(0, 2), st.integers(1, 3)),
                min_size=2, max_size=60))
def test_every_pair_is_either_a_sample_or_counted_as_dropped(rows):
    step, states = 0, []
    for area, track_step, gap in rows:
        step += gap
        states.append(State(step, step * 50e-6, track_step, area, 400.0, 250.0, 800.0))
    samples, report = build_samples(states, "t")
    assert report.n_samples + report.dropped_gap + report.dropped_no_pool + report.dropped_startup == len(states) - 1
    assert np.all(samples.Z[:, 0] > 0) and np.all(samples.y > 0) and np.all(np.diff(samples.step) > 0)


def test_too_few_samples_is_an_error():
    samples, _ = build_samples(_track([0.07] * 20), "t")  # 19 pairs; the first has no history
    with pytest.raises(DatasetError, match="only 18 usable samples"):
        concatenate([samples], DatasetSettings(min_samples=120))


def _record(path: Path, states, *, finish: bool = True) -> Path:
    from messages import MeltPoolState, encode
    from messages.recorder import McapRecorder
    from messages.topics import PLANT_STATE

    recorder = McapRecorder(path, "gp-test", path.open("wb"))
    for s in states:
        msg = MeltPoolState(run_id="gp-test", step=s.step, time_s=s.time_s, laser_x_mm=0.0, laser_y_mm=0.0,
                            scan_dir_x=1.0, scan_dir_y=0.0, track=s.track, area_mm2=s.area_mm2,
                            t_ahead_k=s.t_ahead_k, power_w=s.power_w, speed_mm_s=s.speed_mm_s)
        recorder.write(PLANT_STATE, encode(msg), msg, time.time_ns())
    if finish:
        recorder.finish({"complete": "true"})
    else:
        recorder._stream.close()  # simulate a writer killed before finish()
    return path


def test_read_states_from_mcap_and_bad_recordings(tmp_path):
    states = synthetic.table2_case(2)
    got = read_states(_record(tmp_path / "table2-case2.mcap", states))
    assert [(g.step, g.area_mm2, g.power_w) for g in got] == [(s.step, s.area_mm2, s.power_w) for s in states]
    with pytest.raises(RecordingError, match="not found"):
        read_states(tmp_path / "missing.mcap")
    (tmp_path / "empty.mcap").write_bytes(b"")
    with pytest.raises(RecordingError, match="empty"):
        read_states(tmp_path / "empty.mcap")
    full = (tmp_path / "table2-case2.mcap").read_bytes()
    (tmp_path / "cut.mcap").write_bytes(full[: len(full) // 3])
    with pytest.raises(RecordingError):
        read_states(tmp_path / "cut.mcap")


def test_cli_dataset_train_evaluate_end_to_end_on_recordings(tmp_path, capsys):
    rec = tmp_path / "rec"
    rec.mkdir()
    for case in range(1, 10):
        _record(rec / f"table2-case{case}.mcap", synthetic.table2_case(case, noise_rel=0.002, seed=case))
    data, model_a, model_b = tmp_path / "d.npz", tmp_path / "a.json", tmp_path / "b.json"
    assert main(["dataset", "--recordings-dir", str(rec), "--out", str(data)]) == 0
    assert main(["train", "--dataset", str(data), "--out", str(model_a), "--restarts", "3"]) == 0
    assert main(["train", "--dataset", str(data), "--out", str(model_b), "--restarts", "3"]) == 0
    assert model_a.read_bytes() == model_b.read_bytes()  # fixed seed -> identical file
    prov = GPModel.load(model_a).provenance
    assert [r["name"] for r in prov["dataset"]["recordings"]][:2] == ["table2-case1.mcap", "table2-case2.mcap"]
    assert len(prov["dataset"]["recordings"][0]["sha256"]) == 64 and prov["seed"] == 0
    capsys.readouterr()
    assert main(["evaluate", "--model", str(model_a), "--dataset", str(data),
                 "--plots-dir", str(tmp_path), "--json"]) == 0
    result = json.loads(capsys.readouterr().out.strip().splitlines()[-1])
    assert result["n_train"] == 100 and result["n_valid"] > 1400
    assert result["r2"] >= 0.995 and result["mape_pct"] <= 2.0 and result["rollout_case2_mape_pct"] < 2.0
    assert Path(result["scatter_png"]).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert Path(result["rollout_png"]).stat().st_size > 1000


@pytest.mark.parametrize("argv, reason", [
    (["train", "--dataset", "{tmp}/missing.npz"], "dataset not found"),
    (["dataset", "--recordings-dir", "{tmp}"], "no recordings given"),
    (["dataset", "{tmp}/truncated.mcap", "--out", "{tmp}/d.npz"], "truncated"),
    (["dataset", "{tmp}/short.mcap", "--out", "{tmp}/d.npz"], "usable samples"),
    (["evaluate", "--model", "{tmp}/missing.json"], "cannot read model file"),
    (["train", "--dataset", "{tmp}/garbage.npz"], "unreadable"),
    (["dataset", "--synthetic", "{tmp}/short.mcap", "--out", "{tmp}/d.npz"], "not both"),
    (["dataset", "--synthetic", "--startup-fraction", "0", "--out", "{tmp}/d.npz"], "--startup-fraction"),
])
def test_cli_user_errors_exit_2_with_one_line(tmp_path, capsys, argv, reason):
    _record(tmp_path / "short.mcap", synthetic.table2_case(1)[:40])
    full = _record(tmp_path / "full.mcap", synthetic.table2_case(1)).read_bytes()
    (tmp_path / "truncated.mcap").write_bytes(full[: len(full) // 2])
    (tmp_path / "garbage.npz").write_bytes(b"not a zip")
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    err = capsys.readouterr().err.strip()
    assert reason in err and len(err.splitlines()) == 1 and "Traceback" not in err
    assert not (tmp_path / "d.npz").exists()  # nothing half-written


def test_cli_synthetic_dataset(tmp_path, capsys):
    assert main(["dataset", "--synthetic", "--out", str(tmp_path / "d.npz")]) == 0
    out = capsys.readouterr().out.splitlines()
    assert len(out) == 10 and "table2-case9" in out[8] and "start-up" in out[8]
    assert out[-1].startswith("1645 samples from 9 sources")


FAKE_LAUNCHER = '''
import shutil, sys
args = sys.argv[1:]
scenario = args[args.index("--scenario") + 1]
assert args[args.index("--controller") + 1] == "none" and "--json" in args
with open({log!r}, "a") as f:
    f.write(scenario + "\\n")
if scenario == "table2-case4":
    print("plant diverged", file=sys.stderr)
    sys.exit(1)
shutil.copyfile({recordings!r} + "/" + scenario + ".mcap", args[args.index("--out") + 1])
print('{{"status": 0}}')
'''
"""A stand-in for ``launch.py``: copies a recording made beforehand (no FE, no import of the project)."""


def test_campaign_runs_cases_and_skips_complete_ones(tmp_path):
    """In this process, one after the other (on Dask: tests/test_campaign_dask.py)."""
    log = tmp_path / "calls.txt"
    launcher = tmp_path / "fake_launch.py"
    for case in (1, 2):
        _record(tmp_path / f"table2-case{case}.mcap", synthetic.table2_case(case)[:30])
    launcher.write_text(FAKE_LAUNCHER.format(recordings=str(tmp_path), log=str(log)))
    settings = CampaignSettings(cases=(1, 2, 4), out_dir=tmp_path / "campaign", sequential=True, launcher=launcher,
                                python=sys.executable)
    first = run_campaign(settings, progress=False)
    assert [(r.case, r.status) for r in first] == [(1, "ok"), (2, "ok"), (4, "failed")]
    assert "plant diverged" in first[2].detail
    assert recording_path(settings, 1).is_file() and not recording_path(settings, 4).exists()
    second = run_campaign(settings, progress=False)
    assert [(r.case, r.status) for r in second] == [(1, "skipped"), (2, "skipped"), (4, "failed")]
    # case 4 is retried once per campaign
    assert sorted(log.read_text().split()) == sorted(["table2-case1", "table2-case2"] + ["table2-case4"] * 4)
    with pytest.raises(CampaignError, match="cases are 1-9"):
        run_campaign(dataclasses.replace(settings, cases=(0, 10)), progress=False)
    with pytest.raises(CampaignError, match="launcher not found"):
        run_campaign(dataclasses.replace(settings, launcher=tmp_path / "nope.py"), progress=False)


def test_the_delay_aware_model_records_the_process_of_its_recordings(tmp_path):
    """``learn``/``narx`` write the material and powder layer of the FE plant's recorded
    configuration into the model's process, and refuse recordings of different processes."""
    from gp_trainer.learn import process_record

    def recording(name, material, layer_m=40e-6):
        from messages.recorder import McapRecorder

        path = tmp_path / f"{name}.mcap"
        recorder = McapRecorder(path, "gp-test", path.open("wb"))
        if material is not None:
            settings = {"material": {"name": material}, "powder_layer_m": layer_m}
            recorder.attach("config/plant.json", json.dumps({"settings": settings}).encode())
        recorder.finish({"complete": "true"})
        return path

    a, b = recording("a", "IN625"), recording("b", "IN625")
    assert process_record([a, b]) == {"material": "IN625", "powder_layer_m": 40e-6}
    assert process_record([recording("sensor", None)]) == {"material": None, "powder_layer_m": None}
    with pytest.raises(DatasetError, match="different material: IN625, IN718"):
        process_record([a, recording("c", "IN718")])
    with pytest.raises(DatasetError, match="different powder_layer_m"):
        process_record([a, recording("d", "IN625", 0.0)])
