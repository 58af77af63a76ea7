"""Choice of the GP training points (paper IV.A: 100 training points, all others validate).

Two designs. :func:`variance_reduction_indices` (the default of ``python -m gp_trainer train``) is
described there; :func:`farthest_point_indices` is the pilot design and the alternative:

Greedy maximin (farthest-point) design on the standardised inputs: start from one point drawn
with the seed, then repeatedly add the sample farthest from everything chosen so far. Why not
random: the FE samples are time series, very dense along slowly varying trajectories (constant
power and speed for most of a track) and sparse in the transients (track starts, sinusoid
extremes, second-track heating). A random 100 mostly repeats the dense steady state; maximin
covers the transients and the corners of the (x, T, p, v) box, which is where a 100-point GP
otherwise extrapolates, and it spreads the points so ``K`` stays well conditioned. The result
depends only on the data and the seed (ties broken by the lowest index).
"""

from __future__ import annotations

import numpy as np


def _candidates(points: np.ndarray, n_select: int) -> np.ndarray:
    """``points`` as a float array of candidate rows; :class:`ValueError` unless ``1 <= n_select <= n``."""
    points = np.asarray(points, dtype=float)
    if not 1 <= n_select <= points.shape[0]:
        raise ValueError(f"cannot select {n_select} points out of {points.shape[0]}")
    return points


def farthest_point_indices(Z: np.ndarray, n_select: int, *, seed: int = 0) -> np.ndarray:
    """Indices of ``n_select`` rows of ``Z`` chosen by greedy maximin on standardised columns.

    Parameters
    ----------
    Z : np.ndarray, shape (n, d)
        Candidate inputs (any units; each column is standardised here).
    n_select : int
        Number of points to choose, ``1 <= n_select <= n``.
    seed : int
        Seeds the choice of the first point.

    Returns
    -------
    np.ndarray of int, shape (n_select,)
        Distinct row indices in the order they were chosen.
    """
    Z = _candidates(Z, n_select)
    std = Z.std(axis=0)
    U = (Z - Z.mean(axis=0)) / np.where(std > 0.0, std, 1.0)
    chosen = np.empty(n_select, dtype=np.intp)
    chosen[0] = np.random.default_rng(seed).integers(Z.shape[0])
    nearest = np.sum((U - U[chosen[0]]) ** 2, axis=1)
    for i in range(1, n_select):
        chosen[i] = int(np.argmax(nearest))
        np.minimum(nearest, np.sum((U - U[chosen[i]]) ** 2, axis=1), out=nearest)
    return chosen


MAX_VARIANCE_CANDIDATES = 6000
"""Candidate limit of :func:`variance_reduction_indices` (it holds an n × n matrix: 288 MB at 6000)."""


def variance_reduction_indices(W: np.ndarray, n_select: int, *, noise_ratio: float) -> np.ndarray:
    """Indices of ``n_select`` rows of ``W`` chosen by greedy integrated-variance reduction.

    ``W`` are the candidate inputs in *kernel units* (each column divided by its ARD
    length-scale, e.g. from a pilot fit), so the unit-signal SE kernel is
    ``k(w, w') = exp(-½ |w - w'|²)``. Each step adds the candidate ``c`` that removes the most
    GP posterior variance summed over *all* candidates,

        score(c) = Σ_j C_jc² / (C_cc + noise_ratio),

    where ``C`` is the posterior covariance given the points chosen so far and ``noise_ratio``
    is ``σ_n²/σ_f²``; then ``C`` gets the rank-one update of observing ``c``. Summed posterior
    variance over the candidates is what an average held-out error measures, so unlike maximin
    the design follows the density of the data (many points where the time series dwell, e.g.
    the nominal steady state) and still reaches into sparse regions where one point removes a
    lot of variance. Inputs only, no targets; deterministic (ties to the lowest index).

    Parameters
    ----------
    W : np.ndarray, shape (n, d)
        Candidate inputs in length-scale units, ``n <= MAX_VARIANCE_CANDIDATES``.
    n_select : int
        Number of points, ``1 <= n_select <= n``.
    noise_ratio : float
        ``σ_n²/σ_f²`` (> 0); floored at 1e-6 for numerical safety.

    Returns
    -------
    np.ndarray of int, shape (n_select,)
        Distinct row indices in the order they were chosen.
    """
    W = _candidates(W, n_select)
    n = W.shape[0]
    if n > MAX_VARIANCE_CANDIDATES:
        raise ValueError(f"{n} candidates exceed the limit of {MAX_VARIANCE_CANDIDATES} for variance-reduction "
                         "selection; use farthest-point selection")
    if not noise_ratio > 0.0:
        raise ValueError(f"noise_ratio must be positive, got {noise_ratio}")
    jitter = max(float(noise_ratio), 1.0e-6)
    sq = np.einsum("ij,ij->i", W, W)
    C = W @ W.T
    C *= 2.0
    C -= sq[:, None]
    C -= sq[None, :]
    np.minimum(C, 0.0, out=C)
    C *= 0.5
    np.exp(C, out=C)  # prior covariance of the unit-signal SE kernel
    taken = np.zeros(n, dtype=bool)
    chosen = np.empty(n_select, dtype=np.intp)
    for i in range(n_select):
        score = np.einsum("ij,ij->j", C, C) / (np.maximum(np.diagonal(C), 0.0) + jitter)
        score[taken] = -np.inf
        c = int(np.argmax(score))
        chosen[i], taken[c] = c, True
        v = C[:, c].copy()
        C -= np.outer(v / (max(v[c], 0.0) + jitter), v)
    return chosen
