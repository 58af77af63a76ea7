"""The GP's prediction at one point, compiled: mean, its gradient and the latent variance in one call.

The hot path of the one-step GP-MPC (one call per update, :func:`controller_node.model.linearise`)
and of the GP surrogate plant (one per frame). The formulas are eq. (4)-(5) over the linear mean,
with the constants :class:`gp_model.model.GPModel` precomputes: with ``w = (z − μ) ∘ g``
(``g = 1/(s ∘ ℓ)``), the scaled training points ``W_i`` and ``k̃_i = exp(W_i·w − ½|W_i|² − ½|w|²)``::

    mean     = b + a·z + c·k̃
    ∂mean/∂z = a + ((c ∘ k̃) @ W − Σ(c ∘ k̃) w) ∘ g
    var      = v₀ − |M k̃|²,   M = s_r σ_f² L⁻¹  (L the Cholesky factor of K_y; M lower triangular)

Why compiled: the numpy formulation is ten small calls, and between plant frames a controller's
caches are cold, so each call costs microseconds of dispatch (``docs/controller.md``, "Speed of the
one-step update"). Checked
against scikit-learn's GP and finite differences in ``tests/test_gp_model.py``.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

__all__ = ["evaluate_into"]


@njit(cache=True, nogil=True, fastmath={"reassoc", "contract"})
def evaluate_into(z, offset, scale, points, half_sq_norms, mean_weights, intercept, slope, variance_factor,
                  prior_variance, want_jacobian, want_variance, out):  # pragma: no cover (compiled)
    """The GP's mean, gradient and variance at ``z`` into ``out``.

    Parameters
    ----------
    z : numpy.ndarray
        Input, shape (d,), SI (:data:`gp_model.model.INPUT_NAMES` order).
    offset, scale : numpy.ndarray
        ``μ`` and ``g``, shape (d,): ``w = (z − μ) ∘ g``.
    points : numpy.ndarray
        Scaled training points ``W``, shape (n, d + 1) (a last column of ones, unused here).
    half_sq_norms : numpy.ndarray
        ``−½|W_i|²``, shape (n,).
    mean_weights : numpy.ndarray
        ``c``, shape (n,) [m²].
    intercept : float
        ``b`` [m²].
    slope : numpy.ndarray
        ``a``, shape (d,) (SI per input).
    variance_factor : numpy.ndarray
        ``M``, shape (n, n) [m²], lower triangular (its upper triangle is not read).
    prior_variance : float
        ``v₀`` [m⁴].
    want_jacobian, want_variance : bool
        Which of the gradient and the variance to compute (the mean always is).
    out : numpy.ndarray
        Shape (d + 2,): ``[mean [m²], ∂mean/∂z (d,), variance [m⁴] (≥ 0)]``; the parts not asked
        for are left as they were.
    """
    d, n = z.size, half_sq_norms.size
    w = (z - offset) * scale
    half_w = 0.0
    mean = intercept
    for j in range(d):
        half_w += w[j] * w[j]
        mean += slope[j] * z[j]
    half_w *= 0.5
    k = half_sq_norms.copy()
    for i in range(n):
        e = k[i] - half_w
        for j in range(d):
            e += points[i, j] * w[j]
        k[i] = math.exp(e)
    weighted_sum = 0.0
    if want_jacobian:
        grad = np.zeros(d)
        for i in range(n):
            c = mean_weights[i] * k[i]
            weighted_sum += c
            for j in range(d):
                grad[j] += c * points[i, j]
        for j in range(d):
            out[1 + j] = slope[j] + (grad[j] - weighted_sum * w[j]) * scale[j]
    else:
        for i in range(n):
            weighted_sum += mean_weights[i] * k[i]
    out[0] = mean + weighted_sum
    if want_variance:
        sq = 0.0
        for r in range(n):
            v = 0.0
            for i in range(r + 1):
                v += variance_factor[r, i] * k[i]
            sq += v * v
        out[d + 1] = max(prior_variance - sq, 0.0)
