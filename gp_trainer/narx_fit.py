"""Selecting and evaluating the delay-aware model (:class:`gp_model.narx.NarxGPModel`) on held-out runs.

:func:`select_and_fit` fits every candidate structure on the training runs and keeps the one with the
smallest rollout error on the held-out ones (:func:`evaluate_model`); ``python -m gp_trainer narx``
runs it on the identification recordings and writes the shipped model.
"""

from __future__ import annotations

import functools
import itertools
import multiprocessing
from collections.abc import Mapping, Sequence
from concurrent.futures import ProcessPoolExecutor
from typing import Any

import numpy as np

from controller_node.report import TURNAROUND_STEPS
from gp_model.kernel import HyperBounds
from gp_model.narx import BUILD_UP_STEPS, NarxGPModel, RunSeries
from gp_model.plan_feature import TurnFeature

ROLLOUT_HORIZON = 40
STRUCTURES = ((24, 30), (32, 40))
"""Candidate (power lags, temperature lags) of the model selection."""
FORMS = (("log", True, True), ("log", True, False), ("log", False, False), ("identity", True, True),
         ("identity", True, False), ("identity", False, False))
"""Candidate (output map, squared lags, lag-matched power × temperature interactions) of the model selection."""
FEATURES = ((False, 0), (True, 0), (True, 24))
"""Candidate uses of the turnaround feature (:mod:`gp_model.plan_feature`): (in the T-ahead forecast,
lags in the regressor)."""
LENGTH_SCALE_FLOORS = (0.5, 2.0)
"""Candidate lower bounds of the GP length-scales (in standard deviations of each input)."""
SMOOTHINGS = (0.0, 0.1)
"""Candidate weights λ of the smoothness prior on the lag kernels (:func:`gp_model.narx.smoothing_rows`):
without it the lags of one signal, nearly collinear, are fitted with alternating signs that cancel along a
track and give a wrong response to power before a turn (``benchmarks/turn_sensitivity.py``)."""


def evaluate_model(model: NarxGPModel, runs: Sequence[RunSeries], horizon: int = ROLLOUT_HORIZON,
                   stride: int = 5) -> dict[str, Any]:
    """Held-out metrics: one-step R² and MAPE, 95 % coverage, and the mean ``horizon``-step rollout error.

    The rollout starts every ``stride`` states after the build-up and predicts ``x[k+1..k+H]`` from
    what is known at k (:meth:`NarxGPModel.rollout`: applied powers as the plan, T forecast from the
    scan plan); its error is the mean relative error over the horizon, averaged over the starts.
    Coverage counts held-out one-step targets inside ``mean ± 1.96 sqrt(var + σ_n²)``, over all of
    them and separately in the turnaround windows (the first
    :data:`controller_node.report.TURNAROUND_STEPS` states of every track but a layer's first) and
    along the tracks, with the one-step MAPE of each: where the model is overconfident.
    """
    ys, means, sds, rollouts, turns = [], [], [], [], []
    for run in runs:
        mean, var = model.predict_run(run)
        since_laser_on = run.steps_since_layer_start()
        keep = (since_laser_on[1:] >= BUILD_UP_STEPS) & (run.area_m2[1:] > 0)
        turn = ~run.first_track_of_layer()[1:] & (run.steps_since_track_start()[1:] < TURNAROUND_STEPS)
        turns.append(turn[keep])
        ys.append(run.area_m2[1:][keep]), means.append(mean[keep])
        sds.append(np.sqrt(var[keep] + model.residual.noise_variance))
        for k in range(BUILD_UP_STEPS, len(run) - horizon - 1, stride):
            truth = run.area_m2[k + 1:k + horizon + 1]
            if since_laser_on[k] >= BUILD_UP_STEPS and np.all(truth > 0):
                rollouts.append(float(np.mean(np.abs(model.rollout(run, k, horizon) - truth) / truth)))
    y, mean, sd, turn = np.concatenate(ys), np.concatenate(means), np.concatenate(sds), np.concatenate(turns)
    inside, error = np.abs(mean - y) <= 1.96 * sd, np.abs(mean - y) / y

    def share(values: np.ndarray, where: np.ndarray) -> float | None:
        return float(100.0 * np.mean(values[where])) if np.any(where) else None

    return {
        "r2": float(1.0 - np.sum((y - mean) ** 2) / np.sum((y - y.mean()) ** 2)),
        "mape_pct": float(100.0 * np.mean(error)),
        "n_valid": int(y.size),
        f"rollout_h{horizon}_mape_pct": float(100.0 * np.mean(rollouts)) if rollouts else None,
        "coverage_95_pct": float(100.0 * np.mean(inside)),
        "coverage_95_turnaround_pct": share(inside, turn),
        "coverage_95_along_pct": share(inside, ~turn),
        "mape_turnaround_pct": share(error, turn),
        "mape_along_pct": share(error, ~turn),
        "n_turnaround": int(np.sum(turn)),
        "held_out": [r.name for r in runs],
    }


def _fit_candidate(train: Sequence[RunSeries], held_out: Sequence[RunSeries], candidate: tuple, seed: int,
                   n_train: int, provenance: Mapping[str, Any] | None) -> tuple[NarxGPModel, dict[str, Any]]:
    """Fit one candidate of :func:`select_and_fit` and score it on ``held_out``: the model and its row."""
    (n_p, n_t), (output, quadratic, with_x), (with_f, n_f), floor, smoothing = candidate
    model = NarxGPModel.fit(train, n_power_lags=n_p, n_temperature_lags=n_t, n_train=n_train, seed=seed,
                            output=output, quadratic=quadratic, interaction=with_x, feature_lags=n_f,
                            turn_feature=TurnFeature() if with_f else None, smoothing=smoothing,
                            bounds=HyperBounds(length_scale=(floor, 100.0)), provenance=provenance)
    row = {"n_power_lags": n_p, "n_temperature_lags": n_t, "output": output, "quadratic": quadratic,
           "interaction": with_x, "turn_feature": with_f, "feature_lags": n_f, "length_scale_floor": floor,
           "smoothing": smoothing, **evaluate_model(model, held_out)}
    return model, row


def select_and_fit(
    train: Sequence[RunSeries],
    held_out: Sequence[RunSeries],
    *,
    seed: int = 0,
    n_train: int = 150,
    provenance: Mapping[str, Any] | None = None,
    workers: int = 1,
) -> tuple[NarxGPModel, dict[str, Any], list[dict[str, Any]]]:
    """Fit every candidate (lags, output map, squared lags, interactions, feature lags, length-scale floor,
    smoothness prior) on
    ``train``; keep the one with the smallest 40-step rollout error on ``held_out`` (not the one-step fit).
    Returns it, its row and the whole table; ``provenance`` goes into every candidate's. ``workers`` > 1 fits
    the candidates in that many forked processes (each fit is deterministic: the same model either way)."""
    candidates = list(itertools.product(STRUCTURES, FORMS, FEATURES, LENGTH_SCALE_FLOORS, SMOOTHINGS))
    fit = functools.partial(_fit_candidate, train, held_out, seed=seed, n_train=n_train, provenance=provenance)
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            fitted = list(pool.map(fit, candidates))
    else:
        fitted = [fit(c) for c in candidates]
    table = [row for _, row in fitted]
    key = f"rollout_h{ROLLOUT_HORIZON}_mape_pct"
    best = min(range(len(fitted)), key=lambda i: table[i][key])  # the first of equal ones, as in table order
    return fitted[best][0], table[best], table
