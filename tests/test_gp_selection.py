"""Training-point designs (maximin, integrated-variance reduction), pipeline bounds, data-source provenance."""

from __future__ import annotations

import numpy as np
import pytest

from gp_model.errors import DatasetError
from gp_model.model import GPModel
from gp_trainer import synthetic
from gp_trainer.cli import FE_SOURCE, RECORDED_SOURCE, SYNTHETIC_SOURCE, _recorded_source, main
from gp_trainer.dataset import build_samples, concatenate
from gp_trainer.selection import farthest_point_indices, variance_reduction_indices
from gp_trainer.train import TRAIN_BOUNDS, TrainSettings, check_design_spans_inputs, select_training_points, train


@pytest.fixture(scope="module")
def samples():
    return concatenate([build_samples(synthetic.table2_case(c, noise_rel=0.002, seed=c), f"case{c}")[0]
                        for c in range(1, 10)])


def _brute_force_scores(W, chosen, ratio):
    """Summed posterior-variance reduction of every candidate, from the explicit GP posterior."""
    K = np.exp(-0.5 * ((W[:, None, :] - W[None, :, :]) ** 2).sum(-1))
    if chosen:
        S = np.array(chosen)
        C = K - K[:, S] @ np.linalg.solve(K[np.ix_(S, S)] + ratio * np.eye(len(S)), K[S, :])
    else:
        C = K
    return (C**2).sum(0) / (np.diag(C) + ratio)


def test_variance_design_matches_brute_force_greedy():
    W = np.random.default_rng(0).normal(size=(60, 3))
    ratio = 0.05
    chosen = variance_reduction_indices(W, 8, noise_ratio=ratio)
    for i in range(8):
        scores = _brute_force_scores(W, list(chosen[:i]), ratio)
        scores[chosen[:i]] = -np.inf
        assert chosen[i] == int(np.argmax(scores))


def test_variance_design_is_deterministic_distinct_and_follows_density():
    rng = np.random.default_rng(1)
    dense = 0.05 * rng.normal(size=(400, 2))           # a steady state the time series dwell on
    sparse = rng.uniform(-4.0, 4.0, size=(100, 2))      # transients
    W = np.vstack([dense, sparse])
    a = variance_reduction_indices(W, 30, noise_ratio=0.1)
    assert np.array_equal(a, variance_reduction_indices(W, 30, noise_ratio=0.1))
    assert len(set(a.tolist())) == 30
    maximin = farthest_point_indices(W, 30, seed=0)
    assert np.sum(a < 400) > np.sum(maximin < 400)  # more points where the data are
    assert np.sum(a >= 400) >= 15                    # and still covers the sparse region


@pytest.mark.parametrize("kwargs, message", [
    ({"n_select": 0, "noise_ratio": 0.1}, "cannot select"),
    ({"n_select": 11, "noise_ratio": 0.1}, "cannot select"),
    ({"n_select": 3, "noise_ratio": 0.0}, "noise_ratio"),
])
def test_variance_design_rejects_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        variance_reduction_indices(np.zeros((10, 2)) + np.arange(10)[:, None], **kwargs)


def test_maximin_selection_is_the_sorted_farthest_point_design(samples):
    index, record = select_training_points(samples, TrainSettings(selection="maximin", seed=2))
    assert np.array_equal(index, np.sort(farthest_point_indices(samples.Z, 100, seed=2)))
    assert "maximin" in record["method"]


def test_variance_selection_is_deterministic_and_recorded(samples):
    settings = TrainSettings(n_restarts=2)
    a, record = select_training_points(samples, settings)
    b, _ = select_training_points(samples, settings)
    assert np.array_equal(a, b) and a.size == 100 and np.all(np.diff(a) > 0)
    assert "integrated-variance" in record["method"]
    assert record["pilot_noise_ratio"] >= 1.0e-3 and len(record["pilot_hyperparameters"]["length_scales"]) == 5


def test_train_uses_pipeline_bounds_and_copies_data_source(samples):
    model = train(samples, {"data_source": "unit test"}, TrainSettings(n_restarts=2))
    assert model.provenance["data_source"] == "unit test"
    assert model.provenance["bounds"]["length_scale"] == list(TRAIN_BOUNDS.length_scale)
    assert np.all(model.length_scales >= TRAIN_BOUNDS.length_scale[0] * (1 - 1e-12))
    assert model.noise_std >= TRAIN_BOUNDS.noise_std[0] * (1 - 1e-12)


def test_unknown_selection_is_a_dataset_error(samples):
    with pytest.raises(DatasetError, match="unknown selection"):
        select_training_points(samples, TrainSettings(selection="random"))


def test_data_source_of_recordings():
    fe = {"config": {"plant": {"nodes": 112897, "settings": {}, "scenario": "table2-case1"}}}
    other = {"config": {}}
    assert _recorded_source([fe, fe]) == FE_SOURCE
    assert _recorded_source([fe, other]) == RECORDED_SOURCE
    assert _recorded_source([]) == RECORDED_SOURCE


def test_cli_synthetic_model_says_synthetic(tmp_path, capsys):
    data, model = tmp_path / "d.npz", tmp_path / "m.json"
    assert main(["dataset", "--synthetic", "--out", str(data)]) == 0
    assert main(["train", "--dataset", str(data), "--out", str(model), "--restarts", "1",
                 "--selection", "maximin"]) == 0
    prov = GPModel.load(model).provenance
    assert prov["data_source"] == SYNTHETIC_SOURCE and "maximin" in prov["selection"]["method"]


def test_shipped_model_is_trained_on_the_fe_campaign():
    from gp_model.shipped import ONE_STEP_MODEL_PATH

    model = GPModel.load(ONE_STEP_MODEL_PATH)
    prov = model.provenance
    assert prov["data_source"] == FE_SOURCE and model.n_train == 100
    assert "integrated-variance" in prov["selection"]["method"]
    names = [r["name"] for r in prov["dataset"]["recordings"]]
    assert names == [f"table2-case{c}.mcap" for c in range(1, 10)]
    assert all("synthetic" not in name for name in names)


def test_a_design_that_does_not_vary_an_input_is_refused():
    rng = np.random.default_rng(0)
    Z = rng.uniform(size=(200, 5))
    check_design_spans_inputs(Z, np.arange(100))  # a spread design passes
    Z[:100, 2] = 0.5  # the first 100 samples all at one power
    with pytest.raises(DatasetError, match="do not vary input power_w"):
        check_design_spans_inputs(Z, np.arange(100))
