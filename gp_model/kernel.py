"""SE-ARD covariance (paper eq. 3) and hyper-parameter fitting by maximum marginal likelihood.

Everything here works in *normalised* coordinates: inputs ``U`` (n, d) standardised per
dimension and a target vector ``t`` (n,) of unit scale (see :mod:`gp_model.model`).

Hyper-parameters are handled as ``theta = (log σ_f, log σ_n, log ℓ_1, ..., log ℓ_d)`` so that
the optimiser works on an unconstrained-looking, well-scaled space with box bounds. The kernel
is

    k(u, u') = σ_f² exp(-½ Σ_j (u_j - u'_j)² / ℓ_j²),

i.e. the paper's eq. (3) with ``L = diag(ℓ_1², ..., ℓ_d²)`` (the paper leaves open whether its
``l_i`` are length-scales or their squares; we use length-scales, as in Rasmussen & Williams).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import scipy.linalg

_LOG_2PI = math.log(2.0 * math.pi)
# Returned to the optimiser when K_y is numerically not positive definite: L-BFGS-B backtracks.
_FAILED_OBJECTIVE = 1.0e25


@dataclass(frozen=True)
class HyperBounds:
    """Box bounds of the hyper-parameters, in normalised units (inputs and target of unit scale).

    Attributes
    ----------
    signal_std : tuple[float, float]
        Bounds of σ_f [-], relative to the standard deviation of the residual target.
    noise_std : tuple[float, float]
        Bounds of σ_n [-]. The lower bound keeps ``K_y`` well conditioned (cond ≲ n σ_f²/σ_n²)
        for nearly noise-free FE data.
    length_scale : tuple[float, float]
        Bounds of every ℓ_j [-], in standard deviations of input j. The upper bound is large
        enough to switch an irrelevant input off (ARD); the lower bound forbids spikes narrower
        than 1/20 of the data spread.
    """

    signal_std: tuple[float, float] = (1.0e-2, 1.0e1)
    noise_std: tuple[float, float] = (1.0e-3, 1.0)
    length_scale: tuple[float, float] = (5.0e-2, 1.0e2)

    def log_bounds(self, n_dims: int) -> list[tuple[float, float]]:
        """Bounds of ``theta`` (natural logs), length ``2 + n_dims``."""
        pairs = [self.signal_std, self.noise_std] + [self.length_scale] * n_dims
        return [(math.log(lo), math.log(hi)) for lo, hi in pairs]


def squared_differences(U: np.ndarray) -> np.ndarray:
    """Per-dimension squared differences of the rows of ``U``.

    Parameters
    ----------
    U : np.ndarray, shape (n, d)
        Normalised inputs.

    Returns
    -------
    np.ndarray, shape (d, n, n)
        ``D2[j, a, b] = (U[a, j] - U[b, j])²``.
    """
    diff = U.T[:, :, None] - U.T[:, None, :]
    return diff * diff


def gram(theta: np.ndarray, D2: np.ndarray) -> np.ndarray:
    """Noise-free SE-ARD Gram matrix ``K(X, X)`` (eq. 3), shape (n, n)."""
    sf2 = math.exp(2.0 * theta[0])
    inv_l2 = np.exp(-2.0 * theta[2:])
    return sf2 * np.exp(-0.5 * np.tensordot(inv_l2, D2, axes=1))


def log_marginal_likelihood(theta: np.ndarray, D2: np.ndarray, t: np.ndarray) -> tuple[float, np.ndarray]:
    """Log marginal likelihood (paper eq. after 5) and its analytic gradient in ``theta``.

    ``log p(t | U, θ) = -½ tᵀ K_y⁻¹ t - ½ log|K_y| - n/2 log 2π`` with ``K_y = K + σ_n² I``;
    ``∂/∂θ_i = ½ tr((α αᵀ - K_y⁻¹) ∂K_y/∂θ_i)``, ``α = K_y⁻¹ t`` (Rasmussen & Williams eq. 5.9).

    Parameters
    ----------
    theta : np.ndarray, shape (2 + d,)
        ``(log σ_f, log σ_n, log ℓ_1..d)``.
    D2 : np.ndarray, shape (d, n, n)
        From :func:`squared_differences`.
    t : np.ndarray, shape (n,)
        Normalised targets.

    Returns
    -------
    tuple[float, np.ndarray]
        The log marginal likelihood and its gradient, shape (2 + d,).

    Raises
    ------
    numpy.linalg.LinAlgError
        If ``K_y`` is not numerically positive definite.
    """
    n = t.shape[0]
    sn2 = math.exp(2.0 * theta[1])
    inv_l2 = np.exp(-2.0 * theta[2:])
    Kf = gram(theta, D2)
    Ky = Kf + sn2 * np.eye(n)
    chol = scipy.linalg.cholesky(Ky, lower=True, check_finite=False)
    alpha = scipy.linalg.cho_solve((chol, True), t, check_finite=False)
    lml = -0.5 * float(t @ alpha) - float(np.log(np.diag(chol)).sum()) - 0.5 * n * _LOG_2PI
    W = np.outer(alpha, alpha) - scipy.linalg.cho_solve((chol, True), np.eye(n), check_finite=False)
    WK = W * Kf
    grad = np.empty_like(theta, dtype=float)
    grad[0] = WK.sum()  # ∂K_y/∂log σ_f = 2 K
    grad[1] = sn2 * np.trace(W)  # ∂K_y/∂log σ_n = 2 σ_n² I
    grad[2:] = 0.5 * inv_l2 * np.tensordot(D2, WK, axes=([1, 2], [0, 1]))  # K ∘ D2_j / ℓ_j²
    return lml, grad


def _negative_lml(theta: np.ndarray, D2: np.ndarray, t: np.ndarray) -> tuple[float, np.ndarray]:
    try:
        lml, grad = log_marginal_likelihood(theta, D2, t)
    except np.linalg.LinAlgError:
        return _FAILED_OBJECTIVE, np.zeros_like(theta)
    return -lml, -grad


def fit_hyperparameters(
    U: np.ndarray, t: np.ndarray, *, bounds: HyperBounds, n_restarts: int, seed: int
) -> tuple[np.ndarray, float]:
    """Maximise the log marginal likelihood with L-BFGS-B from several seeded starts.

    The first start is the neutral point (σ_f = 1, σ_n = 0.1, ℓ_j = 1, clipped to the bounds);
    the other ``n_restarts - 1`` are drawn log-uniformly inside the bounds from
    ``numpy.random.default_rng(seed)``, so the result is deterministic given ``seed``.

    Parameters
    ----------
    U : np.ndarray, shape (n, d)
        Normalised inputs.
    t : np.ndarray, shape (n,)
        Normalised targets.
    bounds : HyperBounds
        Box bounds of the hyper-parameters.
    n_restarts : int
        Number of optimiser starts, at least 1.
    seed : int
        Seed of the random starts.

    Returns
    -------
    tuple[np.ndarray, float]
        The best ``theta`` (shape (2 + d,)) and its log marginal likelihood.
    """
    import scipy.optimize  # here, not at the top: a node that only evaluates a model never fits one

    if n_restarts < 1:
        raise ValueError(f"n_restarts must be at least 1, got {n_restarts}")
    D2 = squared_differences(U)
    log_bounds = np.array(bounds.log_bounds(U.shape[1]))
    rng = np.random.default_rng(seed)
    neutral = np.clip(np.r_[0.0, math.log(0.1), np.zeros(U.shape[1])], log_bounds[:, 0], log_bounds[:, 1])
    starts = [neutral] + [rng.uniform(log_bounds[:, 0], log_bounds[:, 1]) for _ in range(n_restarts - 1)]
    best_theta, best_value = neutral, math.inf
    for start in starts:
        result = scipy.optimize.minimize(
            _negative_lml, start, args=(D2, t), jac=True, method="L-BFGS-B", bounds=log_bounds
        )
        if np.isfinite(result.fun) and result.fun < best_value:
            best_theta, best_value = np.asarray(result.x, dtype=float), float(result.fun)
    if not best_value < _FAILED_OBJECTIVE:
        raise np.linalg.LinAlgError("no hyper-parameter start gave a positive-definite covariance")
    return best_theta, -best_value
