"""GP dynamics model of the melt pool, ``x[k+1] = f(x_k, T_k, p_k, v_k[, x_k − x_{k-1}])`` (paper eq. 1-5, 8).

Input ``z = (area_m2 [m²], t_ahead_k [K], power_w [W], speed_m_s [m/s])`` as in the paper, or
with the last area change ``area_change_m2 = x_k − x_{k-1}`` [m²] as a fifth input
(:data:`HISTORY_INPUT_NAMES`, the shipped model: the pool's shape carries memory its area alone
does not, see docs/gp.md);
output the melt-pool top-surface area one step later [m²]. All public quantities are SI;
normalisation is internal.

Structure
---------
``x[k+1] = m(z) + r(z)`` where

* ``m(z) = β_0 + Σ_j β_j u_j`` is an explicit *linear least-squares mean* in the standardised
  inputs ``u = (z - μ_z) / s_z``, fitted to the training points before the GP. Why linear and
  not zero (the paper's eq. 2) or persistence ``x[k+1] = x_k``: the MPC linearises the model
  and sometimes leaves the trained region. A zero-mean GP then predicts ``x[k+1] → 0`` with zero
  input gains; persistence keeps the area but still has zero gain on power and speed, so the
  controller would lose its authority exactly where it is lost. The linear model contains
  persistence as a special case (β for ``x_k``), keeps the physically right signs of the gains
  (∂x/∂p > 0, ∂x/∂v < 0, ∂x/∂T > 0) everywhere and is what a one-step melt-pool model is to
  first order; the GP only has to learn the (smaller, local) nonlinearity.
* ``r(z) ~ GP(0, k)`` with the SE-ARD kernel of eq. (3) on ``u`` and the residual scaled to
  unit standard deviation; hyper-parameters ``(σ_f, σ_n, ℓ_1..d)`` maximise the log marginal
  likelihood (:mod:`gp_model.kernel`).

Far from the data ``k(z, X) → 0`` so the mean reverts to ``m(z)`` and the variance to
``σ_f² s_r²`` (the prior), which is the honest "I don't know" the MPC can read.

``predict`` returns the variance of the *latent* function ``f*`` (the paper's ``cov(f*)``,
eq. 5) without the observation noise; add :attr:`GPModel.noise_variance` for the variance of a
new noisy observation.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import scipy.linalg

from gp_model.compiled import BoundOnFirstCall, compile_lock
from gp_model.errors import ModelFormatError, ModelVersionError
from gp_model.files import is_format, read_document, write_document
from gp_model.gp_eval import evaluate_into
from gp_model.kernel import HyperBounds, fit_hyperparameters, gram, squared_differences

FORMAT_NAME = "meltloop-gp-model"
FORMAT_VERSION = 2
READABLE_VERSIONS = (1, 2)  # version 1: the paper's four inputs only
INPUT_NAMES = ("area_m2", "t_ahead_k", "power_w", "speed_m_s")
"""The paper's inputs (eq. 1)."""
HISTORY_INPUT_NAMES = (*INPUT_NAMES, "area_change_m2")
"""The paper's inputs plus the last area change ``x_k − x_{k-1}`` (the shipped model)."""
INPUT_SETS = (INPUT_NAMES, HISTORY_INPUT_NAMES)
DEFAULT_RESTARTS = 8


def _safe_scale(values: np.ndarray, axis: int | None = None) -> np.ndarray:
    """Standard deviation, replaced where (near) zero so that division is safe.

    A constant column (e.g. constant scan speed in every training case) gets the scale
    ``max(|mean|, 1)``: its normalised value is then ≈ 0 in training and the GP extrapolates
    smoothly if the MPC varies it.
    """
    std = np.std(values, axis=axis)
    fallback = np.maximum(np.abs(np.mean(values, axis=axis)), 1.0)
    return np.where(std > 1.0e-12 * fallback, std, fallback)


class GPModel:
    """One-step melt-pool GP model with an explicit linear mean; see the module docstring.

    Construct with :meth:`fit` or :meth:`load`. Prediction methods are pure and allocation-light
    (a few small temporaries), a few microseconds per call for 100 training points; the object
    is immutable after construction and safe to share between threads.

    Parameters
    ----------
    train_inputs : np.ndarray, shape (n, d)
        Training inputs ``z`` in SI units, ``d = 4`` (:data:`INPUT_NAMES`) or ``d = 5``
        (:data:`HISTORY_INPUT_NAMES`).
    train_targets : np.ndarray, shape (n,)
        Training targets ``x[k+1]`` [m²].
    input_mean, input_scale : np.ndarray, shape (d,)
        Normalisation ``u = (z - input_mean) / input_scale`` (SI units).
    mean_coefficients : np.ndarray, shape (d + 1,)
        ``(β_0, β_1..d)`` of the linear mean ``m = β_0 + β·u`` [m²].
    residual_scale : float
        Scale of the GP residual ``s_r`` [m²]; the GP is fitted to ``(y - m) / s_r``.
    signal_std, noise_std : float
        σ_f and σ_n in units of ``s_r`` [-].
    length_scales : np.ndarray, shape (d,)
        ℓ_j in units of ``input_scale`` [-].
    log_marginal_likelihood : float, optional
        Of the normalised residual at these hyper-parameters (for the record).
    provenance : Mapping, optional
        JSON-serialisable description of where the model came from.
    """

    def __init__(
        self,
        *,
        train_inputs: np.ndarray,
        train_targets: np.ndarray,
        input_mean: np.ndarray,
        input_scale: np.ndarray,
        mean_coefficients: np.ndarray,
        residual_scale: float,
        signal_std: float,
        noise_std: float,
        length_scales: np.ndarray,
        log_marginal_likelihood: float | None = None,
        provenance: Mapping[str, Any] | None = None,
    ) -> None:
        Z = np.array(train_inputs, dtype=float)
        y = np.array(train_targets, dtype=float)
        mu = np.array(input_mean, dtype=float)
        s = np.array(input_scale, dtype=float)
        beta = np.array(mean_coefficients, dtype=float)
        ell = np.array(length_scales, dtype=float)
        n = y.shape[0] if y.ndim == 1 else -1
        d = Z.shape[1] if Z.ndim == 2 else -1
        if d not in (len(names) for names in INPUT_SETS):
            raise ValueError(f"train_inputs has shape {Z.shape}, expected (n, 4) or (n, 5)")
        expected = {
            "train_inputs": (Z, (n, d)),
            "train_targets": (y, (n,)),
            "input_mean": (mu, (d,)),
            "input_scale": (s, (d,)),
            "mean_coefficients": (beta, (d + 1,)),
            "length_scales": (ell, (d,)),
        }
        for name, (array, shape) in expected.items():
            if array.shape != shape or n < 1:
                raise ValueError(f"{name} has shape {array.shape}, expected {shape} with n >= 1")
            if not np.all(np.isfinite(array)):
                raise ValueError(f"{name} contains non-finite values")
        positive = {"input_scale": s, "length_scales": ell, "residual_scale": residual_scale,
                    "signal_std": signal_std, "noise_std": noise_std}
        for name, value in positive.items():
            if not np.all(np.isfinite(value)) or not np.all(np.asarray(value) > 0.0):
                raise ValueError(f"{name} must be finite and positive, got {value}")

        self.input_names = INPUT_SETS[d - 4]
        self.n_inputs = d
        self.train_inputs, self.train_targets = Z, y
        self.input_mean, self.input_scale = mu, s
        self.mean_coefficients = beta
        self.residual_scale = float(residual_scale)
        self.signal_std, self.noise_std = float(signal_std), float(noise_std)
        self.length_scales = ell
        self.log_marginal_likelihood = None if log_marginal_likelihood is None else float(log_marginal_likelihood)
        self.provenance: dict[str, Any] = dict(provenance or {})
        for array in (Z, y, mu, s, beta, ell):
            array.setflags(write=False)

        U = (Z - mu) / s
        residual = (y - (beta[0] + U @ beta[1:])) / self.residual_scale
        theta = np.log(np.r_[self.signal_std, self.noise_std, ell])
        Ky = gram(theta, squared_differences(U)) + self.noise_std**2 * np.eye(n)
        try:
            chol = scipy.linalg.cholesky(Ky, lower=True)
        except np.linalg.LinAlgError as exc:
            raise ValueError("covariance matrix is not positive definite") from exc
        alpha = scipy.linalg.cho_solve((chol, True), residual)
        chol_inv = scipy.linalg.solve_triangular(chol, np.eye(n), lower=True)

        # Hot-path constants (SI in, SI out). With w = u/ℓ = (z - μ) ∘ g, g = 1/(s ∘ ℓ), training
        # points W_i = U_i/ℓ and k̃_i = exp(-½ |W_i - w|²) = exp(W_i·w - ½|W_i|² - ½|w|²):
        #   mean = b + a·z + c_m·k̃,      ∂mean/∂z = a + ((c_m ∘ k̃) @ W - Σ(c_m ∘ k̃) w) ∘ g,
        #   var  = v_0 - |M k̃|²,         ∂var/∂z  = -2 ((Mᵀ M k̃ ∘ k̃) @ W - Σ(Mᵀ M k̃ ∘ k̃) w) ∘ g,
        # with M = s_r σ_f² L⁻¹ (L the Cholesky factor of K_y): |M k̃|² is far less sensitive to
        # the conditioning of K_y than k̃ᵀ K_y⁻¹ k̃ with an explicit inverse.
        # The expansion of |W_i - w|² avoids an (n, 4) temporary; its rounding error (≈ 1e-16 of
        # |W_i|² + |w|²) is negligible in the exponent. [W, 1] gives @ W and Σ in one product.
        sf2 = self.signal_std**2
        rs = self.residual_scale
        scaled = U / ell
        self._slope = beta[1:] / s
        self._intercept = float(beta[0] - self._slope @ mu)
        self._grad_scale = 1.0 / (s * ell)
        self._scaled_inputs = np.ascontiguousarray(scaled)
        self._scaled_inputs_1 = np.ascontiguousarray(np.column_stack([scaled, np.ones(n)]))
        self._half_sq_norms = -0.5 * np.einsum("ij,ij->i", scaled, scaled)
        self._mean_weights = rs * sf2 * alpha
        self._prior_variance = rs * rs * sf2
        self._variance_factor = np.ascontiguousarray(rs * sf2 * chol_inv)
        self._variance_factor_t = np.ascontiguousarray(self._variance_factor.T)
        # the compiled evaluation is built (or loaded from numba's cache) and bound now, not on the hot path
        self._evaluate_compiled = BoundOnFirstCall(evaluate_into)
        with compile_lock(__file__):        # one process compiles on a fresh install, the others load
            self._evaluate(self.input_mean.copy(), True, True)

    # ------------------------------------------------------------------ prediction (hot path)
    def _kernel_row(self, z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """``k̃`` (n,) and ``w`` (d,) at ``z`` (see the constants in ``__init__``)."""
        w = (z - self.input_mean) * self._grad_scale
        k = self._scaled_inputs @ w
        k += self._half_sq_norms
        k -= 0.5 * float(w @ w)
        return np.exp(k, out=k), w

    def _gradient(self, weights: np.ndarray, w: np.ndarray) -> np.ndarray:
        """``(weights @ W - Σ weights · w) ∘ g``, shape (d,)."""
        v = weights @ self._scaled_inputs_1
        return (v[:-1] - v[-1] * w) * self._grad_scale

    def predict(self, z: np.ndarray) -> tuple[float, float]:
        """Posterior mean and variance of ``x[k+1]`` at one point (eq. 5 over the linear mean).

        Parameters
        ----------
        z : np.ndarray, shape (d,)
            ``(area_m2 [m²], t_ahead_k [K], power_w [W], speed_m_s [m/s][, area_change_m2 [m²]])``
            in the order of :attr:`input_names`.

        Returns
        -------
        tuple[float, float]
            Mean [m²] and latent variance [m⁴] (≥ 0, observation noise excluded).
        """
        out = self._evaluate(z, False, True)
        return float(out[0]), float(out[-1])

    def mean_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Posterior mean and its gradient with respect to ``z``, both SI.

        For the MPC linearisation ``x[k+1] ≈ mean + J·(z' - z)`` (paper eq. 9: ``A_d = J[0]``,
        ``B_d = J[2:4]``, ``J[1]`` the sensitivity to the measured disturbance T, ``J[4]`` the
        gain on the area change ``x_k − x_{k-1}`` of a history model).

        Parameters
        ----------
        z : np.ndarray, shape (d,)
            As in :meth:`predict`.

        Returns
        -------
        tuple[float, np.ndarray]
            Mean [m²] and ``J``, shape (d,): ``[-, m²/K, m²/W, m²/(m/s)[, -]]``.
        """
        out = self._evaluate(z, True, False)
        return float(out[0]), out[1:-1]

    def mean_jacobian_and_variance(self, z: np.ndarray) -> tuple[float, np.ndarray, float]:
        """:meth:`mean_and_jacobian` and :meth:`predict`'s variance at ``z`` (as in :meth:`predict`) in one
        evaluation of the kernel row: mean [m²], ``J`` shape (d,), latent variance [m⁴] (≥ 0)."""
        out = self._evaluate(z, True, True)
        return float(out[0]), out[1:-1], float(out[-1])

    def _evaluate(self, z: np.ndarray, jacobian: bool, variance: bool) -> np.ndarray:
        """``[mean, J (d,), variance]`` at ``z`` (:func:`gp_model.gp_eval.evaluate_into`; the parts
        not asked for are undefined). Every call passes the same argument types (``z`` made a
        contiguous float64 vector of the model's length), so it skips numba's dispatcher."""
        z = np.ascontiguousarray(z, dtype=float)
        if z.shape != (self.n_inputs,):
            raise ValueError(f"z must have shape ({self.n_inputs},), got {z.shape}")
        out = np.empty(self.n_inputs + 2)
        self._evaluate_compiled.call(z, self.input_mean, self._grad_scale, self._scaled_inputs_1, self._half_sq_norms,
                                     self._mean_weights, self._intercept, self._slope, self._variance_factor,
                                     self._prior_variance, jacobian, variance, out)
        return out

    def variance_and_jacobian(self, z: np.ndarray) -> tuple[float, np.ndarray]:
        """Posterior latent variance [m⁴] at ``z`` (shape (d,), as in :meth:`predict`) and its gradient
        with respect to ``z``, shape (d,): ``[m², m⁴/K, m⁴/W, m⁴/(m/s)[, m²]]``. Where the variance is
        clipped at 0 (numerically, at a training point) the gradient is 0."""
        k, w = self._kernel_row(z)
        v = self._variance_factor @ k
        variance = self._prior_variance - float(v @ v)
        if variance <= 0.0:
            return 0.0, np.zeros(self.n_inputs)
        return variance, -2.0 * self._gradient((self._variance_factor_t @ v) * k, w)

    def explicit_mean(self, z: np.ndarray) -> float:
        """The linear mean ``m(z)`` alone [m²], to which :meth:`predict` reverts far from data."""
        return self._intercept + float(self._slope @ np.asarray(z, dtype=float))

    @property
    def n_train(self) -> int:
        """Number of training points."""
        return int(self.train_targets.shape[0])

    @property
    def noise_variance(self) -> float:
        """Observation-noise variance σ_n² s_r² [m⁴] (not included in :meth:`predict`)."""
        return (self.noise_std * self.residual_scale) ** 2

    def __repr__(self) -> str:
        ell = ", ".join(f"{v:.3g}" for v in self.length_scales)
        return (f"GPModel(n_train={self.n_train}, signal_std={self.signal_std:.3g}, "
                f"noise_std={self.noise_std:.3g}, length_scales=[{ell}])")

    # ------------------------------------------------------------------ fitting
    @classmethod
    def fit(
        cls,
        Z: np.ndarray,
        y: np.ndarray,
        *,
        seed: int = 0,
        n_restarts: int = DEFAULT_RESTARTS,
        bounds: HyperBounds = HyperBounds(),
        provenance: Mapping[str, Any] | None = None,
    ) -> GPModel:
        """Fit the linear mean by least squares, then the GP hyper-parameters by max. LML.

        Parameters
        ----------
        Z : np.ndarray, shape (n, 4) or (n, 5)
            Training inputs, SI (see :data:`INPUT_NAMES`, :data:`HISTORY_INPUT_NAMES`); ``n`` ≈ 100 (cost O(n³) per
            optimiser iteration).
        y : np.ndarray, shape (n,)
            Training targets ``x[k+1]`` [m²].
        seed : int
            Seed of the optimiser's random restarts; the result is deterministic given it.
        n_restarts : int
            Number of L-BFGS-B starts (≥ 1).
        bounds : HyperBounds
            Hyper-parameter bounds in normalised units.
        provenance : Mapping, optional
            Stored with the model; ``seed``, ``n_restarts`` and the bounds are added.

        Returns
        -------
        GPModel
        """
        Z = np.asarray(Z, dtype=float)
        y = np.asarray(y, dtype=float)
        if Z.ndim != 2 or Z.shape[1] not in (4, 5) or y.shape != (Z.shape[0],) or Z.shape[0] < Z.shape[1] + 2:
            raise ValueError(f"need Z of shape (n, 4) or (n, 5) and y of shape (n,), n >= d + 2; "
                             f"got {Z.shape} and {y.shape}")
        if not (np.all(np.isfinite(Z)) and np.all(np.isfinite(y))):
            raise ValueError("training data contain non-finite values")
        mu = Z.mean(axis=0)
        s = _safe_scale(Z, axis=0)
        U = (Z - mu) / s
        design = np.column_stack([np.ones(len(y)), U])
        beta = np.linalg.lstsq(design, y, rcond=None)[0]
        residual = y - design @ beta
        residual_scale = max(float(np.std(residual)), 1.0e-9 * float(np.std(y)), np.finfo(float).tiny)
        theta, lml = fit_hyperparameters(U, residual / residual_scale, bounds=bounds,
                                         n_restarts=n_restarts, seed=seed)
        record = dict(provenance or {})
        record.update(seed=seed, n_restarts=n_restarts, bounds={
            "signal_std": list(bounds.signal_std), "noise_std": list(bounds.noise_std),
            "length_scale": list(bounds.length_scale)})
        params = np.exp(theta)
        return cls(train_inputs=Z, train_targets=y, input_mean=mu, input_scale=s, mean_coefficients=beta,
                   residual_scale=residual_scale, signal_std=float(params[0]), noise_std=float(params[1]),
                   length_scales=params[2:], log_marginal_likelihood=lml, provenance=record)

    # ------------------------------------------------------------------ persistence
    def to_dict(self) -> dict[str, Any]:
        """The JSON document written by :meth:`save` (floats round-trip exactly)."""
        return {
            "format": FORMAT_NAME,
            "format_version": FORMAT_VERSION,
            "inputs": list(self.input_names),
            "output": "area_m2 at step k+1",
            "kernel": "squared-exponential ARD (paper eq. 3), k = sf^2 exp(-0.5 sum((u-u')/l)^2)",
            "mean_model": "linear least squares in u = (z - input_mean) / input_scale",
            "hyperparameters": {"signal_std": self.signal_std, "noise_std": self.noise_std,
                                "length_scales": self.length_scales.tolist()},
            "normalisation": {"input_mean": self.input_mean.tolist(), "input_scale": self.input_scale.tolist(),
                              "residual_scale": self.residual_scale},
            "mean_coefficients": self.mean_coefficients.tolist(),
            "log_marginal_likelihood": self.log_marginal_likelihood,
            "training": {"inputs": self.train_inputs.tolist(), "targets": self.train_targets.tolist()},
            "provenance": self.provenance,
        }

    def save(self, path: str | os.PathLike[str]) -> Path:
        """Write the model as versioned JSON, atomically (temporary file + ``os.replace``).

        Returns
        -------
        Path
            The written path.
        """
        return write_document(path, self.to_dict())

    @classmethod
    def load(cls, path: str | os.PathLike[str]) -> GPModel:
        """Read a model written by :meth:`save`.

        Raises
        ------
        ModelVersionError
            The file is a model of another format version.
        ModelFormatError
            The file is missing, not JSON, not a model file or inconsistent.
        """
        return cls.from_dict(read_document(path), source=str(path))

    @classmethod
    def from_dict(cls, doc: Any, *, source: str = "<dict>") -> GPModel:
        """Build a model from the document of :meth:`to_dict`; errors as in :meth:`load`."""
        if not is_format(doc, FORMAT_NAME):
            raise ModelFormatError(f"{source} is not a {FORMAT_NAME} file")
        if doc.get("format_version") not in READABLE_VERSIONS:
            raise ModelVersionError(f"{source} has format version {doc.get('format_version')!r}, "
                                    f"this code reads versions {', '.join(map(str, READABLE_VERSIONS))}; "
                                    "retrain or convert it")
        if tuple(doc.get("inputs", INPUT_NAMES)) not in INPUT_SETS:
            raise ModelFormatError(f"{source} has unsupported inputs {doc.get('inputs')!r}; expected "
                                   f"{list(INPUT_NAMES)} or {list(HISTORY_INPUT_NAMES)}")
        try:
            hyper, norm, training = doc["hyperparameters"], doc["normalisation"], doc["training"]
            return cls(
                train_inputs=np.array(training["inputs"], dtype=float),
                train_targets=np.array(training["targets"], dtype=float),
                input_mean=np.array(norm["input_mean"], dtype=float),
                input_scale=np.array(norm["input_scale"], dtype=float),
                mean_coefficients=np.array(doc["mean_coefficients"], dtype=float),
                residual_scale=float(norm["residual_scale"]),
                signal_std=float(hyper["signal_std"]),
                noise_std=float(hyper["noise_std"]),
                length_scales=np.array(hyper["length_scales"], dtype=float),
                log_marginal_likelihood=doc.get("log_marginal_likelihood"),
                provenance=doc.get("provenance") or {},
            )
        except (KeyError, TypeError, ValueError) as exc:
            detail = f"missing field {exc}" if isinstance(exc, KeyError) else str(exc)
            raise ModelFormatError(f"{source} is a corrupt model file: {detail}") from exc
