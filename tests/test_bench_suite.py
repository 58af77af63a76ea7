"""The off-design suite (``benchmarks/bench_suite.py``): which cases are in-sample, and one short run
through ``launch.py`` giving the records it prints and writes."""

from __future__ import annotations

import json
import math
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))

import bench_suite  # noqa: E402
import learning_bound  # noqa: E402

from gp_trainer.pid_tuning import Fopdt  # noqa: E402

RUNS = ["ident-layer-p139-s1", "ident-pid-double-track-a0.055", "ident-preview-mpc-layer-a0.061-h110um-450K",
        "ident-layer-8x5mm-p174-s7", "ident-part-p100-s1"]


def test_training_plans_are_read_from_the_run_names():
    assert bench_suite.training_plans(RUNS) == {(4, 0.01, 0.0001), (2, 0.005, 0.0001), (4, 0.01, 0.00011),
                                                (8, 0.005, 0.0001), bench_suite.EXAMPLE_PART}


def test_a_case_is_in_sample_only_on_a_trained_plan_and_process():
    plans = bench_suite.training_plans(RUNS)
    cases = {c.name: c for c in bench_suite.CASES}
    assert bench_suite.in_sample(cases["default-layer"], plans)
    assert bench_suite.in_sample(cases["setpoint-0.09"], plans)  # another reference on a trained plan
    assert not bench_suite.in_sample(cases["default-layer"], bench_suite.training_plans(RUNS[1:2]))
    for name in ("tight-6x4mm-h80", "speed-1.0", "preheat-500K", "absorptivity-10pct"):
        assert not bench_suite.in_sample(cases[name], plans), name
    assert bench_suite.in_sample(cases["part-2-layers"], plans)        # ident-part-p100-s1 built the example part
    assert not bench_suite.in_sample(cases["part-2-layers"], bench_suite.training_plans(RUNS[:4]))
    for runs, example, bracket in ((["ident-part-block_5mm-p60-s21"], False, False),   # another part: the STL's stem
                                   (["ident-pid-part-l_bracket_3mm-a0.063"], False, True),
                                   (["ident-pid-part-a0.063"], True, False)):
        plans_of = bench_suite.training_plans(runs)
        assert bench_suite.in_sample(cases["part-2-layers"], plans_of) is example
        assert bench_suite.in_sample(cases["l-bracket-3-layers"], plans_of) is bracket
    at_1mps = {"preset": "physical", "speed_m_s": 1.0}                # the [plant] of a model learned at 1 m/s
    assert bench_suite.in_sample(cases["speed-1.0"], plans, at_1mps)
    assert not bench_suite.in_sample(cases["speed-0.6"], plans, at_1mps)
    assert not bench_suite.in_sample(cases["preheat-500K"], plans, at_1mps)


def test_the_model_a_case_is_judged_on_is_the_one_launch_gives_its_plant(tmp_path):
    from gp_model.shipped import DEFAULT_MODEL_PATH, PART_MODEL_PATH, PLATE_MODEL_PATH

    cases = {c.name: c for c in bench_suite.CASES}
    assert bench_suite.shipped_model(cases["default-layer"], tmp_path) == DEFAULT_MODEL_PATH
    assert bench_suite.shipped_model(cases["part-2-layers"], tmp_path) == PART_MODEL_PATH
    bare = bench_suite.Case("bare-plate", {"powder_layer_m": 0.0})
    assert bench_suite.shipped_model(bare, tmp_path) == PLATE_MODEL_PATH
    with pytest.raises(ValueError, match="bad-key"):
        bench_suite.shipped_model(bench_suite.Case("bad-key", {"no_such_key": 1.0}), tmp_path)


def test_a_short_case_runs_through_launch_and_is_recorded(tmp_path):
    """Each controller's record (launch's figures, the plan, the bound); the preview MPC's also how its model
    predicts that very run (the figures ``python -m gp_trainer evaluate --runs`` gives on the recording)."""
    from gp_model.narx import NarxGPModel, series_from_states
    from gp_model.shipped import DEFAULT_MODEL_PATH
    from gp_trainer.dataset import read_states
    from gp_trainer.narx_fit import evaluate_model

    out = subprocess.run([sys.executable, "benchmarks/bench_suite.py", "--cases", "short-8x2mm", "--controllers",
                          "pid", "preview-mpc", "--max-steps", "60", "--out-dir", str(tmp_path), "--json", "--bound",
                          "--bound-iterations", "1"],
                         cwd=REPO, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    record, mpc = json.loads(out.stdout.strip().splitlines()[-1])["cases"]
    assert not any(k.startswith("model_") for k in record)
    recording = tmp_path / "short-8x2mm-preview-mpc.mcap"
    fit = evaluate_model(NarxGPModel.load(DEFAULT_MODEL_PATH), [series_from_states(read_states(recording), "r")])
    assert fit["n_turnaround"] > 0
    assert {k: mpc[f"model_{k}"] for k in bench_suite.MODEL_FIT_KEYS} == {k: fit[k] for k in bench_suite.MODEL_FIT_KEYS}
    assert record["case"] == "short-8x2mm" and record["controller"] == "pid" and record["status"] == 0
    assert record["track_length_m"] == 2e-3 and record["hatch_m"] == 1e-4 and record["in_sample"] is False
    assert all(record[k] is not None and record[k] >= 0 for k in ("overshoot_pct", "undershoot_pct", "rmse_pct"))
    assert json.loads((tmp_path / "short-8x2mm-pid.json").read_text()) == record
    assert record["bound_iteration"] in (0, 1) and 0 < record["bound_rmse_pct"] < 100
    assert "short-8x2mm" in out.stdout.splitlines()[1]


def test_the_model_goes_to_launch_for_the_controllers_that_use_it(monkeypatch, tmp_path):
    """``--model`` reaches ``launch.py`` for preview-mpc and scan-feedforward (else the suite would score the
    shipped model whatever was given), and to PID as its process record (``--process``: its operating power
    and gains learned on that process); without it launch picks the plant's model."""
    commands = []

    def run(cmd, **kwargs):
        commands.append(cmd)
        return subprocess.CompletedProcess(cmd, 0, stdout="{}\n", stderr="")

    monkeypatch.setattr(bench_suite.subprocess, "run", run)
    case = next(c for c in bench_suite.CASES if c.name == "short-8x2mm")
    for controller in bench_suite.CONTROLLERS:
        bench_suite.run_case(case, controller, tmp_path, None, tmp_path / "m.json")
    bench_suite.run_case(case, "preview-mpc", tmp_path, None)
    given = [cmd[cmd.index("--model") + 1] if "--model" in cmd else None for cmd in commands]
    assert given == [str(tmp_path / "m.json"), None, str(tmp_path / "m.json"), None]
    process = [cmd[cmd.index("--process") + 1] if "--process" in cmd else None for cmd in commands]
    assert process == [None, str(tmp_path / "m.json"), None, None]


@pytest.mark.parametrize("name, speed", [("speed-0.6", 0.6), ("speed-1.0", 1.0)])
def test_the_speed_cases_name_a_model_learned_at_their_speed(name, speed):
    """Each speed case runs on the shipped model learned at its speed (its provenance records that process
    and the default layer's plan among its training runs), so its record is in-sample on that process."""
    from gp_model.narx import NarxGPModel

    case = next(c for c in bench_suite.CASES if c.name == name)
    model = NarxGPModel.load(REPO / case.model)
    assert model.speed_m_s == case.plant["speed_m_s"] == speed
    provenance = model.provenance
    assert provenance["process"]["plant"] == {"preset": "physical", "speed_m_s": speed}
    assert bench_suite.in_sample(case, bench_suite.training_plans(provenance["runs"]), provenance["process"]["plant"])


PROCESS = Fopdt(gain_m2_per_w=5e-10, time_constant_s=0.715e-3, dead_time_s=0.125e-3, delay_steps=2,
                sample_period_s=50e-6, residual_rms_m2=0.0, n_samples=1)
BOUND = learning_bound.BoundSettings(iterations=3, gain=0.5, process=PROCESS, start_power_w=174.0)


def test_the_norm_optimal_step_solves_the_lifted_problem():
    """The banded solve equals ``(GᵀG + λI)⁻¹ Gᵀ e`` with the dense lifted impulse response."""
    n, rng = 200, np.random.default_rng(0)
    error = rng.normal(size=n) * 1e-9
    a = math.exp(-PROCESS.sample_period_s / PROCESS.time_constant_s)
    one_step = PROCESS.gain_m2_per_w * (1 - a)
    lifted = np.zeros((n, n))
    for k in range(n):
        j = np.arange(n - k)
        lifted[k:, k] = np.where(j >= PROCESS.delay_steps, one_step * a ** (j - PROCESS.delay_steps), 0.0)
    expected = np.linalg.solve(lifted.T @ lifted + one_step ** 2 * np.eye(n), lifted.T @ error)
    np.testing.assert_allclose(learning_bound.norm_optimal_step(error, BOUND), expected, rtol=1e-6,
                               atol=1e-9 * np.abs(expected).max())


def test_the_learning_iterations_lower_the_error_on_the_fe_plant():
    from fe_node.scenarios import scenario

    result = learning_bound.learning_bound(scenario("layer", n_tracks=8, track_length_m=2e-3), 0.063e-6, BOUND,
                                           max_steps=60)
    first, *later = result["rmse_by_iteration_pct"]
    assert later[-1] < later[0] < first and result["bound_rmse_pct"] == min(later)
