"""Choice of the GP training points (paper IV.A: 100 training points, all others validate).

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
    Z = np.asarray(Z, dtype=float)
    n = Z.shape[0]
    if not 1 <= n_select <= n:
        raise ValueError(f"cannot select {n_select} points out of {n}")
    std = Z.std(axis=0)
    U = (Z - Z.mean(axis=0)) / np.where(std > 0.0, std, 1.0)
    chosen = np.empty(n_select, dtype=np.intp)
    chosen[0] = np.random.default_rng(seed).integers(n)
    nearest = np.sum((U - U[chosen[0]]) ** 2, axis=1)
    for i in range(1, n_select):
        chosen[i] = int(np.argmax(nearest))
        np.minimum(nearest, np.sum((U - U[chosen[i]]) ** 2, axis=1), out=nearest)
    return chosen
