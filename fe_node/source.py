"""Moving Gaussian laser source (paper eq. 6) integrated exactly onto the top face.

Eq. 6 is a volumetric Gaussian with penetration depth c = 3 µm, far below any affordable
element size.  Its c -> 0 limit is the surface flux

    q(x, y) = 3 a P / (pi r_s²) * exp(-3 ((x - x_L)² + (y - y_L)²) / r_s²)     [W/m²],

a Gaussian with standard deviation ``s = r_s / sqrt(6)``; it carries exactly ``a P``.
The flux is separable, so the consistent nodal load of the bilinear top face is an outer
product of 1-D integrals ``g_i = int N_i(x) exp(-(x - x_L)²/(2 s²)) dx``, evaluated in
closed form with erf (no quadrature error).  Motion during a time step is integrated by
averaging over evenly spaced sub-positions along the path (spacing <= r_s / 20); the
load is finally renormalised so that the deposited energy is exactly ``a P dt``.

With a penetration depth ``c`` resolved by the mesh (``Settings.penetration_depth_m`` > 0) the
depth factor ``exp(-3 z² / c²)`` of eq. 6 is kept: :func:`depth_weights` splits each column's
load over the nodes below it in proportion to the integral of the factor over each node's share
of the column (lumped), so the column still receives exactly its load.
"""
from __future__ import annotations

import numpy as np
from scipy.special import erf

DEPTH_TAIL = 1e-12
"""Share of the depth factor's integral below which deeper nodes get no load."""


def depth_weights(zs: np.ndarray, penetration_depth_m: float) -> np.ndarray:
    """Share [-] of a column's laser load at each node from the top down (eq. 6's depth factor).

    Node ``k`` from the top (depth ``d_k = zs[-1] - zs[-1 - k]``) takes the integral of
    ``exp(-3 z² / c²)`` over its lumped share of the column, from the midpoint to the node above
    to the midpoint to the node below, normalised: ``erf(sqrt(3) z / c)`` between those depths.

    Parameters
    ----------
    zs : ndarray, shape (nz,)
        Node heights [m], increasing; ``zs[-1]`` is the top surface.
    penetration_depth_m : float
        c [m]; 0 puts the whole load on the top node (the surface flux).

    Returns
    -------
    ndarray, shape (n,)
        Weights of the top ``n`` nodes, summing to 1 (``n = 1`` for ``c = 0``).
    """
    if penetration_depth_m <= 0:
        return np.ones(1)
    depth = zs[-1] - zs[::-1]
    bounds = np.concatenate([[0.0], 0.5 * (depth[1:] + depth[:-1]), [np.inf]])
    cdf = erf(np.sqrt(3.0) * bounds / penetration_depth_m)
    w = np.diff(cdf)
    n = max(1, int(np.searchsorted(-(1.0 - cdf[1:]), -DEPTH_TAIL)) + 1)
    w = w[:n]
    return w / w.sum()


def hat_gaussian_integrals(x: np.ndarray, centre: float | np.ndarray, sigma: float) -> np.ndarray:
    """Exact ``int N_i(x) exp(-(x - centre)² / (2 sigma²)) dx`` for the hat functions on ``x``.

    Parameters
    ----------
    x : ndarray, shape (n,)
        Increasing node coordinates [m].
    centre : float or ndarray, shape (m, 1)
        Gaussian centre(s) [m].
    sigma : float
        Gaussian standard deviation [m].

    Returns
    -------
    ndarray, shape (n,), or (m, n) for m centres
        Nodal integrals [m]; their sum is the integral of the Gaussian over [x0, x_{n-1}].
    """
    p, q = x[:-1], x[1:]
    h = q - p
    r2s = np.sqrt(2.0) * sigma
    i0 = sigma * np.sqrt(np.pi / 2) * (erf((q - centre) / r2s) - erf((p - centre) / r2s))
    gp = np.exp(-((p - centre) ** 2) / (2 * sigma**2))
    gq = np.exp(-((q - centre) ** 2) / (2 * sigma**2))
    i1 = sigma**2 * (gp - gq) + centre * i0          # int x g dx over [p, q]
    right = (i1 - p * i0) / h                        # int (x - p)/h g
    left = i0 - right                                # int (q - x)/h g
    out = np.zeros(np.broadcast_shapes(np.shape(centre), x.shape))
    out[..., :-1] += left
    out[..., 1:] += right
    return np.maximum(out, 0.0)          # round-off in the far tails


def surface_load(xs: np.ndarray, ys: np.ndarray, positions: np.ndarray, power_w: float,
                 absorptivity: float, beam_radius_m: float) -> np.ndarray:
    """Time-averaged consistent nodal load [W] of the moving surface Gaussian.

    Parameters
    ----------
    xs, ys : ndarray
        Top-face node coordinates [m], shapes (nx,), (ny,).
    positions : ndarray, shape (n_sub, 2)
        Laser centre positions [m] sampled evenly in time over the interval; the
        load is their average.
    power_w : float
        Laser power P [W].
    absorptivity : float
        a [-].
    beam_radius_m : float
        r_s [m].

    Returns
    -------
    ndarray, shape (nx, ny)
        Nodal powers [W], summing exactly to ``a * P``.
    """
    sigma = beam_radius_m / np.sqrt(6.0)
    load = np.zeros((len(xs), len(ys)))
    if power_w == 0.0 or len(positions) == 0:
        return load
    reach = LOAD_REACH_SIGMAS * sigma
    x, y = positions[:, 0], positions[:, 1]
    i = _nodes_within(xs, x.min() - reach, x.max() + reach)
    k = _nodes_within(ys, y.min() - reach, y.max() + reach)
    gx = hat_gaussian_integrals(xs[i], x[:, None], sigma)
    if np.all(y == y[0]):          # a track along x: the y factor is common
        load[i, k] = np.outer(gx.sum(axis=0), hat_gaussian_integrals(ys[k], y[0], sigma))
    else:                          # sum over the positions of their separable loads
        load[i, k] = gx.T @ hat_gaussian_integrals(ys[k], y[:, None], sigma)
    return load * (absorptivity * power_w / load.sum())


LOAD_REACH_SIGMAS = 10.0
"""Half-width of the node window a beam's load is integrated on, in beam standard deviations:
the Gaussian beyond it is below ``exp(-50)`` of its peak, under the rounding of the load."""


def _nodes_within(coords: np.ndarray, lo: float, hi: float) -> slice:
    """The nodes of ``coords`` (increasing) from the last at or below ``lo`` to the first at or above ``hi``."""
    i0 = max(int(np.searchsorted(coords, lo, side="right")) - 1, 0)
    return slice(i0, min(int(np.searchsorted(coords, hi)) + 1, len(coords)))
