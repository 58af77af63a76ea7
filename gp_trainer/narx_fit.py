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
from gp_model.build_up import ROLLOUT_STRIDE, build_up_steps, rollout_horizon, steps_at
from gp_model.errors import DatasetError
from gp_model.kernel import HyperBounds
from gp_model.narx import DEFAULT_POWER_MAP, NarxGPModel, RunSeries
from gp_model.plan_feature import TurnFeature

STRUCTURES = ((24, 30), (32, 40))
"""Candidate (power lags, temperature lags) of the model selection, at the FE step (the reference period of
:mod:`gp_model.build_up`; at another period as the same time, at least :data:`FRAME_LAG_MINIMA`)."""
FRAME_LAG_MINIMA = ((2, 2), (4, 4))
"""The fewest lags of each candidate of :data:`STRUCTURES` at a longer sample period: at a 1 ms frame the
power→area ramp (~0.75 ms) and T ahead's lags (0.25–0.65 ms) lie within the last frame, so 2 ms and 4 ms."""
FRAME_FEATURE_LAGS_MIN = 2
"""The fewest turnaround-feature lags of a candidate with them at a longer sample period."""
FORMS = (("log", True, True), ("log", True, False), ("log", False, False), ("identity", True, True),
         ("identity", True, False), ("identity", False, False))
"""Candidate (output map, squared lags, lag-matched power × temperature interactions) of the model selection."""
FEATURES = ((False, 0), (True, 0), (True, 24))
"""Candidate uses of the turnaround feature (:mod:`gp_model.plan_feature`): (in the T-ahead forecast,
lags in the regressor)."""
LENGTH_SCALE_FLOORS = (0.5, 2.0)
"""Candidate lower bounds of the GP length-scales (in standard deviations of each input)."""
POWER_FORM_NAMES = {"square": ("square", True), "log1p": ("log1p", True), "log1p-no-gp-power": ("log1p", False)}
"""The named (power map, GP's mean-power input) forms (``refit --power-form``)."""
POWER_FORM = (DEFAULT_POWER_MAP, True)
"""The (power map, GP's mean-power input) of every candidate of the selection (:meth:`NarxGPModel.fit`'s
``power_map`` and ``gp_power_input``). Not selected: the held-out runs' powers do not tell the forms
apart, the response beyond them does (``benchmarks/power_sensitivity.py``, docs/gp.md)."""
SMOOTHINGS = (0.0, 0.1)
"""Candidate weights λ of the smoothness prior on the lag kernels (:func:`gp_model.narx.smoothing_rows`):
without it the lags of one signal, nearly collinear, are fitted with alternating signs that cancel along a
track and give a wrong response to power before a turn (``benchmarks/turn_sensitivity.py``)."""
AFTER_TURN_BIN_STEPS = 5
"""Width of the bins of :func:`evaluate_model`'s ``bias_after_turn_pct``, in states at the FE step (0.25 ms)."""


def rollout_key(sample_period_s: float) -> str:
    """The key of the selecting rollout error in :func:`evaluate_model`'s row at ``sample_period_s`` [s],
    ``rollout_h<H>_mape_pct`` (H = :func:`gp_model.build_up.rollout_horizon`; 40 at the FE step)."""
    return f"rollout_h{rollout_horizon(sample_period_s)}_mape_pct"


def structures(sample_period_s: float) -> tuple[tuple[int, int], ...]:
    """The candidate (power lags, temperature lags) at ``sample_period_s`` [s]: :data:`STRUCTURES` as time
    (:func:`gp_model.build_up.steps_at`), at least :data:`FRAME_LAG_MINIMA` at another period."""
    minima = [FRAME_LAG_MINIMA[min(i, len(FRAME_LAG_MINIMA) - 1)] for i in range(len(STRUCTURES))]
    return tuple((steps_at(n_p, sample_period_s, m_p), steps_at(n_t, sample_period_s, m_t))
                 for (n_p, n_t), (m_p, m_t) in zip(STRUCTURES, minima, strict=True))


def features(sample_period_s: float) -> tuple[tuple[bool, int], ...]:
    """The candidate uses of the turnaround feature at ``sample_period_s`` [s]: :data:`FEATURES`, lags as
    time, at least :data:`FRAME_FEATURE_LAGS_MIN` at another period."""
    return tuple((with_f, steps_at(n_f, sample_period_s, FRAME_FEATURE_LAGS_MIN) if n_f else 0)
                 for with_f, n_f in FEATURES)


def evaluate_model(model: NarxGPModel, runs: Sequence[RunSeries], horizon: int | None = None,
                   stride: int | None = None) -> dict[str, Any]:
    """Held-out metrics: one-step R² and MAPE, 95 % coverage, and the mean ``horizon``-step rollout error.

    ``horizon``, ``stride``, the build-up and the turnaround windows are counted in samples of the model's
    period (default horizon and stride 40 and 5 at the FE step, the same time at
    another period: :mod:`gp_model.build_up`).

    The rollout starts every ``stride`` states after the build-up and predicts ``x[k+1..k+H]`` from
    what is known at k (:meth:`NarxGPModel.rollout`: applied powers as the plan, T forecast from the
    scan plan); its error is the mean relative error over the horizon, averaged over the starts.
    Coverage counts held-out one-step targets inside ``mean ± 1.96 sqrt(var + σ_n²)``, over all of
    them and separately in the turnaround windows (the first
    :data:`controller_node.report.TURNAROUND_STEPS` states of every track but a layer's first) and
    along the tracks, with the one-step MAPE of each: where the model is overconfident. The one-step
    bias (mean signed relative error, model minus plant) of each tells what a disturbance estimate
    would have to absorb there; ``bias_after_turn_pct`` splits the turnaround windows' bias into bins of
    ``after_turn_bin_states`` states since the turn (:data:`AFTER_TURN_BIN_STEPS` at the FE step): where
    after a turn the model misses the pool (None for a bin without a sample).
    """
    period = model.sample_period_s
    horizon = rollout_horizon(period) if horizon is None else horizon
    stride = steps_at(ROLLOUT_STRIDE, period) if stride is None else stride
    build_up, turnaround = build_up_steps(period), steps_at(TURNAROUND_STEPS, period)
    after_turn_bin = max(1, steps_at(AFTER_TURN_BIN_STEPS, period))
    ys, means, sds, rollouts, turns, sinces = [], [], [], [], [], []
    for run in runs:
        mean, var = model.predict_run(run)
        since_laser_on = run.steps_since_layer_start()
        keep = (since_laser_on[1:] >= build_up) & (run.area_m2[1:] > 0)
        since_track = run.steps_since_track_start()[1:]
        turn = ~run.first_track_of_layer()[1:] & (since_track < turnaround)
        turns.append(turn[keep])
        sinces.append(since_track[keep])
        ys.append(run.area_m2[1:][keep]), means.append(mean[keep])
        sds.append(np.sqrt(var[keep] + model.residual.noise_variance))
        for k in range(build_up, len(run) - horizon - 1, stride):
            truth = run.area_m2[k + 1:k + horizon + 1]
            if since_laser_on[k] >= build_up and np.all(truth > 0):
                rollouts.append(float(np.mean(np.abs(model.rollout(run, k, horizon) - truth) / truth)))
    y, mean, sd, turn = np.concatenate(ys), np.concatenate(means), np.concatenate(sds), np.concatenate(turns)
    since = np.concatenate(sinces)
    inside, signed = np.abs(mean - y) <= 1.96 * sd, (mean - y) / y
    error = np.abs(signed)

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
        "bias_turnaround_pct": share(signed, turn),
        "bias_along_pct": share(signed, ~turn),
        "bias_after_turn_pct": [share(signed, turn & (since >= start) & (since < start + after_turn_bin))
                                for start in range(0, turnaround, after_turn_bin)],
        "after_turn_bin_states": after_turn_bin,
        "n_turnaround": int(np.sum(turn)),
        "held_out": [r.name for r in runs],
    }


def _fit_candidate(train: Sequence[RunSeries], held_out: Sequence[RunSeries], candidate: tuple, seed: int,
                   n_train: int, provenance: Mapping[str, Any] | None) -> tuple[NarxGPModel, dict[str, Any]]:
    """Fit one candidate of :func:`select_and_fit` and score it on ``held_out``: the model and its row."""
    (n_p, n_t), (output, quadratic, with_x), (with_f, n_f), floor, smoothing, (power_map, gp_power), remnant = \
        candidate
    period = train[0].sample_period_s
    feature = TurnFeature(n_targets=steps_at(TurnFeature.n_targets, period),
                          n_sources=steps_at(TurnFeature.n_sources, period))
    model = NarxGPModel.fit(train, n_power_lags=n_p, n_temperature_lags=n_t, n_train=n_train, seed=seed,
                            output=output, quadratic=quadratic, interaction=with_x, feature_lags=n_f,
                            turn_feature=feature if with_f else None, remnant=remnant, smoothing=smoothing,
                            bounds=HyperBounds(length_scale=(floor, 100.0)), power_map=power_map,
                            gp_power_input=gp_power, provenance=provenance)
    row = {"n_power_lags": n_p, "n_temperature_lags": n_t, "output": output, "quadratic": quadratic,
           "interaction": with_x, "turn_feature": with_f, "feature_lags": n_f, "length_scale_floor": floor,
           "smoothing": smoothing, "power_map": power_map, "gp_power_input": gp_power,
           "remnant": None if remnant is None else remnant.to_dict(),
           **evaluate_model(model, held_out)}
    return model, row


def candidate_of(model: NarxGPModel) -> tuple:
    """The candidate of :func:`select_and_fit` that ``model`` was fitted as: its (power lags, temperature
    lags), (output map, squared lags, p × T terms), (turnaround feature, its lags), length-scale floor,
    smoothness prior λ (from ``provenance.bounds`` and ``provenance.smoothing``), (power map, GP's
    mean-power input) and remnant terms."""
    try:
        floor = float(model.provenance["bounds"]["length_scale"][0])
        smoothing = float(model.provenance["smoothing"])
    except (KeyError, IndexError, TypeError, ValueError):
        raise DatasetError("the model records no length-scale bounds or smoothing in its provenance") from None
    return ((model.n_power_lags, model.n_temperature_lags),
            (model.output, model.temperature_square_coefficients.size > 0,
             model.power_temperature_coefficients.size > 0),
            (model.turn_feature is not None, model.n_feature_lags), floor, smoothing,
            (model.power_map, "mean_power_w" in model.gp_inputs), model.remnant_feature)


def select_and_fit(
    train: Sequence[RunSeries],
    held_out: Sequence[RunSeries],
    *,
    seed: int = 0,
    n_train: int = 150,
    provenance: Mapping[str, Any] | None = None,
    workers: int = 1,
    candidates: Sequence[tuple] | None = None,
) -> tuple[NarxGPModel, dict[str, Any], list[dict[str, Any]]]:
    """Fit every candidate (lags, output map, squared lags, interactions, feature lags, length-scale floor,
    smoothness prior; the power form :data:`POWER_FORM`; no remnant terms: :func:`gp_trainer.learn.refit`
    adds them to a selected one) on ``train``; keep the one with the smallest 40-step rollout error on
    ``held_out`` (not the one-step fit). Returns it, its row and the whole table; ``provenance`` goes into every
    candidate's. ``workers`` > 1 fits the candidates in that many forked processes (each fit is deterministic: the
    same model either way). ``candidates`` (default: every combination of the module's candidate lists) restricts the
    choice, e.g. to :func:`candidate_of` a selected model (refitting it on other data or with another feature)."""
    period = train[0].sample_period_s if train else held_out[0].sample_period_s
    if candidates is None:
        candidates = list(itertools.product(structures(period), FORMS, features(period), LENGTH_SCALE_FLOORS,
                                            SMOOTHINGS, [POWER_FORM], [None]))
    fit = functools.partial(_fit_candidate, train, held_out, seed=seed, n_train=n_train, provenance=provenance)
    if workers > 1:
        with ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork")) as pool:
            fitted = list(pool.map(fit, candidates))
    else:
        fitted = [fit(c) for c in candidates]
    table = [row for _, row in fitted]
    key = rollout_key(period)
    best = min(range(len(fitted)), key=lambda i: table[i][key])  # the first of equal ones, as in table order
    return fitted[best][0], table[best], table
