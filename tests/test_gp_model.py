"""GPModel: gradients, agreement with scikit-learn, accuracy, extrapolation, persistence."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from gp_model.errors import ModelFormatError, ModelVersionError
from gp_model.kernel import log_marginal_likelihood, squared_differences
from gp_model.model import FORMAT_VERSION, GPModel
from gp_trainer import synthetic
from gp_trainer.dataset import build_samples, concatenate
from gp_trainer.selection import farthest_point_indices


@pytest.fixture(scope="module")
def samples():
    parts = [build_samples(synthetic.table2_case(c, noise_rel=0.002, seed=c), f"case{c}")[0] for c in range(1, 10)]
    return concatenate(parts)


@pytest.fixture(scope="module")
def split(samples):
    train = farthest_point_indices(samples.Z, 100, seed=0)
    valid = np.setdiff1d(np.arange(len(samples)), train)
    return train, valid


@pytest.fixture(scope="module")
def model(samples, split):
    train, _ = split
    return GPModel.fit(samples.Z[train], samples.y[train], seed=0, n_restarts=4)


def _probe_points(samples, n=6):
    rng = np.random.default_rng(3)
    rows = samples.Z[rng.choice(len(samples), n, replace=False)]
    return rows * (1.0 + 0.01 * rng.standard_normal(rows.shape))  # off the training points


def _central_difference(fun, z, h):
    grad = np.empty(len(z))
    for j in range(len(z)):
        e = np.zeros(len(z))
        e[j] = h[j]
        grad[j] = (fun(z + e) - fun(z - e)) / (2.0 * h[j])
    return grad


def test_mean_jacobian_matches_finite_differences(model, samples):
    h = 1e-5 * samples.Z.std(axis=0)
    for z in _probe_points(samples):
        mean, jac = model.mean_and_jacobian(z)
        assert mean == pytest.approx(model.predict(z)[0], rel=1e-12)
        fd = _central_difference(lambda q: model.predict(q)[0], z, h)
        np.testing.assert_allclose(jac, fd, rtol=1e-5, atol=1e-8 * np.abs(fd).max())


def test_variance_jacobian_matches_finite_differences(model, samples):
    h = 1e-3 * samples.Z.std(axis=0)
    for z in _probe_points(samples):
        var, jac = model.variance_and_jacobian(z)
        assert var == pytest.approx(model.predict(z)[1], rel=1e-12)
        fd = _central_difference(lambda q: model.predict(q)[1], z, h)
        np.testing.assert_allclose(jac, fd, rtol=1e-4, atol=1e-6 * np.abs(fd).max())


def test_one_evaluation_gives_mean_jacobian_and_variance(model, samples):
    for z in _probe_points(samples):
        mean, jac, var = model.mean_jacobian_and_variance(z)
        mean_only, jac_only = model.mean_and_jacobian(z)
        assert mean == pytest.approx(mean_only, rel=1e-13)
        np.testing.assert_allclose(jac, jac_only, rtol=1e-13)
        assert var == pytest.approx(model.predict(z)[1], rel=1e-13)


def test_the_compiled_evaluation_is_ready_when_the_model_is():
    """Loading the model compiles (or loads) the signature of every later call: none on a hot path.
    In a fresh process, where no earlier call compiled it."""
    code = (
        "import numpy as np\n"
        "from gp_model.gp_eval import evaluate_into\n"
        "from gp_model.model import GPModel\n"
        "from gp_model.shipped import ONE_STEP_MODEL_PATH\n"
        "model = GPModel.load(ONE_STEP_MODEL_PATH)\n"
        "known = len(evaluate_into.signatures)\n"
        "z = np.array([0.07e-6, 600.0, 200.0, 0.8, 1e-9])\n"
        "model.mean_jacobian_and_variance(z)\n"
        "model.predict(list(z))\n"
        "print(known, len(evaluate_into.signatures))\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.split()
    assert out[0] == out[1]


@pytest.mark.parametrize("method", ["predict", "mean_and_jacobian", "mean_jacobian_and_variance"])
def test_an_input_of_the_wrong_length_is_refused(model, method):
    with pytest.raises(ValueError, match="z must have shape"):
        getattr(model, method)(np.array([0.1e-6, 800.0, 200.0]))


def test_lml_gradient_matches_finite_differences():
    rng = np.random.default_rng(0)
    U = rng.standard_normal((30, 4))
    t = np.sin(U @ np.array([1.0, 0.5, -0.3, 0.2])) + 0.05 * rng.standard_normal(30)
    D2 = squared_differences(U)
    for theta in (np.array([0.1, np.log(0.1), 0.0, 0.3, -0.2, 1.0]), rng.uniform(-1.5, 1.5, 6)):
        _, grad = log_marginal_likelihood(theta, D2, t)
        fd = np.empty(6)
        for i in range(6):
            e = np.zeros(6)
            e[i] = 1e-6
            fd[i] = (log_marginal_likelihood(theta + e, D2, t)[0] - log_marginal_likelihood(theta - e, D2, t)[0]) / 2e-6
        np.testing.assert_allclose(grad, fd, rtol=1e-5, atol=1e-6)


def test_agrees_with_scikit_learn(model, samples):
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel, WhiteKernel

    U = (model.train_inputs - model.input_mean) / model.input_scale
    linear = model.mean_coefficients[0] + U @ model.mean_coefficients[1:]
    t = (model.train_targets - linear) / model.residual_scale
    kernel = (ConstantKernel(model.signal_std**2, "fixed") * RBF(model.length_scales, "fixed")
              + WhiteKernel(model.noise_std**2, "fixed"))
    gpr = GaussianProcessRegressor(kernel, alpha=0.0, optimizer=None, normalize_y=False).fit(U, t)

    theta = np.log(np.r_[model.signal_std, model.noise_std, model.length_scales])
    ours_lml = log_marginal_likelihood(theta, squared_differences(U), t)[0]
    assert ours_lml == pytest.approx(gpr.log_marginal_likelihood_value_, rel=1e-9)
    assert model.log_marginal_likelihood == pytest.approx(ours_lml, rel=1e-6)

    Zq = _probe_points(samples, 20)
    Uq = (Zq - model.input_mean) / model.input_scale
    sk_mean, sk_std = gpr.predict(Uq, return_std=True)
    for z, u, m_sk, s_sk in zip(Zq, Uq, sk_mean, sk_std):
        mean, var = model.predict(z)
        expected_mean = model.mean_coefficients[0] + u @ model.mean_coefficients[1:] + model.residual_scale * m_sk
        # sklearn's std includes the WhiteKernel noise; ours is the latent variance.
        expected_var = model.residual_scale**2 * (s_sk**2 - model.noise_std**2)
        assert mean == pytest.approx(expected_mean, rel=1e-9)
        assert var == pytest.approx(expected_var, rel=1e-5, abs=1e-12 * model.residual_scale**2)


def test_fit_recovers_synthetic_dynamics(model, samples, split):
    _, valid = split
    pred = np.array([model.predict(z)[0] for z in samples.Z[valid]])
    y = samples.y[valid]
    r2 = 1.0 - np.sum((pred - y) ** 2) / np.sum((y - y.mean()) ** 2)
    mape = 100.0 * np.mean(np.abs(pred - y) / y)
    assert r2 >= 0.995
    assert mape <= 2.0


def test_far_from_data_reverts_to_explicit_mean(model):
    far = np.array([1.0e-6, 4000.0, 3000.0, 5.0, 0.5e-6])  # many length-scales away in every input
    mean, var = model.predict(far)
    assert mean == pytest.approx(model.explicit_mean(far), rel=1e-9)
    assert abs(mean) > 1e-8  # the explicit mean, not the zero of a zero-mean GP
    assert var == pytest.approx(model.residual_scale**2 * model.signal_std**2, rel=1e-9)
    _, jac = model.mean_and_jacobian(far)
    assert jac[2] > 0.0 and jac[3] < 0.0  # more power -> bigger pool, faster -> smaller


def test_save_load_round_trip_is_bit_exact(model, samples, tmp_path):
    path = model.save(tmp_path / "m.json")
    loaded = GPModel.load(path)
    assert loaded.to_dict() == model.to_dict()
    for z in _probe_points(samples):
        assert loaded.predict(z) == model.predict(z)
        np.testing.assert_array_equal(loaded.mean_and_jacobian(z)[1], model.mean_and_jacobian(z)[1])
    assert loaded.save(tmp_path / "again.json").read_bytes() == path.read_bytes()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["again.json", "m.json"]  # no temp files left


def test_wrong_version_and_corrupt_files_are_rejected(model, tmp_path):
    doc = model.to_dict()
    doc["format_version"] = FORMAT_VERSION + 1
    (tmp_path / "v.json").write_text(json.dumps(doc))
    with pytest.raises(ModelVersionError, match="format version"):
        GPModel.load(tmp_path / "v.json")
    good = model.save(tmp_path / "good.json").read_bytes()
    (tmp_path / "trunc.json").write_bytes(good[: len(good) // 2])
    with pytest.raises(ModelFormatError, match="not valid JSON"):
        GPModel.load(tmp_path / "trunc.json")
    doc = model.to_dict()
    doc["training"]["targets"] = doc["training"]["targets"][:-1]
    (tmp_path / "shape.json").write_text(json.dumps(doc))
    with pytest.raises(ModelFormatError, match="corrupt"):
        GPModel.load(tmp_path / "shape.json")
    with pytest.raises(ModelFormatError, match="cannot read"):
        GPModel.load(tmp_path / "missing.json")
    (tmp_path / "other.json").write_text("[1, 2]")
    with pytest.raises(ModelFormatError, match="not a meltloop-gp-model"):
        GPModel.load(tmp_path / "other.json")


def test_fit_is_deterministic_given_seed(samples, split):
    train, _ = split
    a = GPModel.fit(samples.Z[train], samples.y[train], seed=7, n_restarts=3)
    b = GPModel.fit(samples.Z[train], samples.y[train], seed=7, n_restarts=3)
    assert a.to_dict() == b.to_dict()
    assert a.provenance["seed"] == 7


def test_farthest_point_selection_is_deterministic_and_spread(samples):
    a = farthest_point_indices(samples.Z, 100, seed=1)
    assert np.array_equal(a, farthest_point_indices(samples.Z, 100, seed=1))
    assert len(set(a.tolist())) == 100
    U = (samples.Z - samples.Z.mean(0)) / samples.Z.std(0)

    def min_gap(idx):
        d = np.sqrt(squared_differences(U[idx]).sum(0))
        return d[np.triu_indices(len(idx), 1)].min()

    random_gap = max(min_gap(np.random.default_rng(s).choice(len(U), 100, replace=False)) for s in range(5))
    assert min_gap(a) > 3.0 * random_gap


def test_variance_stays_accurate_for_noise_free_data():
    """Noise-free data drive σ_n to its lower bound (cond K_y ~ 1e10): the variance must still be right."""
    from sklearn.gaussian_process import GaussianProcessRegressor
    from sklearn.gaussian_process.kernels import RBF, ConstantKernel

    clean = concatenate([build_samples(synthetic.table2_case(c), f"case{c}")[0] for c in range(1, 10)])
    idx = farthest_point_indices(clean.Z, 100, seed=0)
    model = GPModel.fit(clean.Z[idx], clean.y[idx], seed=0, n_restarts=2)
    assert model.noise_std == pytest.approx(1e-3)  # at the bound: the ill-conditioned case
    U = (model.train_inputs - model.input_mean) / model.input_scale
    t = (model.train_targets - model.mean_coefficients[0] - U @ model.mean_coefficients[1:]) / model.residual_scale
    gpr = GaussianProcessRegressor(ConstantKernel(model.signal_std**2, "fixed") * RBF(model.length_scales, "fixed"),
                                   alpha=model.noise_std**2, optimizer=None).fit(U, t)
    Zq = _probe_points(clean, 30)
    _, sk_std = gpr.predict((Zq - model.input_mean) / model.input_scale, return_std=True)
    ours = np.sqrt([model.predict(z)[1] for z in Zq])
    np.testing.assert_allclose(ours, model.residual_scale * sk_std, rtol=1e-5)
