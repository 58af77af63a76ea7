"""Validation of a trained model on the held-out samples (paper IV.A, Fig. 4a/4b).

* One-step accuracy on every sample that is not a training point: R² and MAPE (paper: R² =
  99.5 %, mean error 2.06 %), scatter of predicted vs recorded area (Fig. 4a).
* Multi-step forward simulation of one case (paper: Table 2 case 2, Fig. 4b): start from the
  recorded first state, then feed the model its own prediction with the recorded T, p and v,
  ``x̂[k+1] = mean(x̂_k, T_k, p_k, v_k[, x̂_k − x̂_{k-1}])`` (a history model gets its own
  previous prediction too, the recorded ``x_{k-1}`` only at the start). If the case's samples are not
  contiguous (a track change in a double-track case), the rollout restarts from the recorded
  state after the gap.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gp_model.atomic import atomic_write
from gp_model.errors import DatasetError
from gp_model.model import GPModel
from gp_trainer.dataset import Samples

ROLLOUT_SOURCE = "table2-case2"
TARGET_R2 = 0.995
TARGET_MAPE_PCT = 2.0


@dataclass(frozen=True)
class Rollout:
    """Forward simulation of one source.

    Attributes
    ----------
    step : np.ndarray of int, shape (n,)
        Step index k of each input state; predictions are for k+1.
    recorded : np.ndarray, shape (n,)
        Recorded ``x[k+1]`` [m²].
    simulated : np.ndarray, shape (n,)
        Model rollout ``x̂[k+1]`` [m²].
    power_w : np.ndarray, shape (n,)
        Recorded power applied during k → k+1 [W].
    """

    step: np.ndarray
    recorded: np.ndarray
    simulated: np.ndarray
    power_w: np.ndarray


def r2_score(y: np.ndarray, pred: np.ndarray) -> float:
    """Coefficient of determination ``1 - SS_res / SS_tot`` [-]."""
    return float(1.0 - np.sum((pred - y) ** 2) / np.sum((y - np.mean(y)) ** 2))


def mape_pct(y: np.ndarray, pred: np.ndarray) -> float:
    """Mean absolute percentage error ``100 · mean(|pred - y| / |y|)`` [%] (y ≠ 0)."""
    return float(100.0 * np.mean(np.abs(pred - y) / np.abs(y)))


def held_out_mask(samples: Samples, model: GPModel) -> np.ndarray:
    """True for samples that are not training points of ``model`` (exact match of its z and y)."""
    train = {tuple(z) + (y,) for z, y in zip(model.train_inputs.tolist(), model.train_targets.tolist())}
    inputs = samples.Z[:, : model.n_inputs]
    return np.array([tuple(z) + (y,) not in train for z, y in zip(inputs.tolist(), samples.y.tolist())],
                    dtype=bool)


def predict_means(model: GPModel, Z: np.ndarray) -> np.ndarray:
    """Posterior means [m²] at the rows of ``Z`` (n, 5) (the model uses its first ``n_inputs`` columns)."""
    return np.array([model.predict(z)[0] for z in Z[:, : model.n_inputs]])


def rollout(model: GPModel, samples: Samples) -> Rollout:
    """Multi-step forward simulation over one source's samples (see module docstring).

    Parameters
    ----------
    model : GPModel
    samples : Samples
        One source, in step order (``Samples.of_source``), at least one sample.
    """
    simulated = np.empty(len(samples))
    x, x_prev = samples.Z[0, 0], samples.Z[0, 0] - samples.Z[0, 4]
    for i, z in enumerate(samples.Z):
        if i > 0 and samples.step[i] != samples.step[i - 1] + 1:
            x, x_prev = z[0], z[0] - z[4]  # gap: restart from the recorded states
        x, x_prev = model.predict(np.array([x, z[1], z[2], z[3], x - x_prev][: model.n_inputs]))[0], x
        simulated[i] = x
    return Rollout(step=samples.step, recorded=samples.y, simulated=simulated, power_w=samples.Z[:, 2])


def _pyplot() -> Any:
    """``matplotlib.pyplot`` on the non-interactive Agg backend (works without a display)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save_figure(fig: Any, path: Path) -> str:
    atomic_write(path, lambda handle: fig.savefig(handle, format="png", dpi=120))
    return str(path)


def plot_scatter(y: np.ndarray, pred: np.ndarray, r2: float, mape: float, path: Path) -> str:
    """Predicted vs recorded ``x[k+1]`` of the validation set (paper Fig. 4a) as PNG."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(5, 5), layout="constrained")
    ax.scatter(y * 1e6, pred * 1e6, s=6, alpha=0.6, label=f"validation (n = {len(y)})")
    lo, hi = 1e6 * min(y.min(), pred.min()), 1e6 * max(y.max(), pred.max())
    ax.plot([lo, hi], [lo, hi], "k--", lw=1, label="ideal")
    ax.set(xlabel="recorded area x[k+1] [mm²]", ylabel="GP predicted area [mm²]",
           title=f"One-step prediction: R² = {r2:.4f}, MAPE = {mape:.2f} %")
    ax.legend(loc="upper left")
    out = _save_figure(fig, path)
    plt.close(fig)
    return out


def plot_rollout(result: Rollout, name: str, mape: float, path: Path) -> str:
    """Recorded vs rolled-out area over the steps of one case (paper Fig. 4b) as PNG."""
    plt = _pyplot()
    fig, (ax, ax_p) = plt.subplots(2, 1, figsize=(8, 5), sharex=True, height_ratios=(3, 1), layout="constrained")
    ax.plot(result.step + 1, result.recorded * 1e6, label="recorded (plant)")
    ax.plot(result.step + 1, result.simulated * 1e6, "--", label="GP forward simulation")
    ax.set(ylabel="melt-pool area [mm²]", title=f"{name}: multi-step prediction, MAPE = {mape:.2f} %")
    ax.legend()
    ax_p.plot(result.step + 1, result.power_w, color="tab:red")
    ax_p.set(xlabel="step k", ylabel="power [W]")
    out = _save_figure(fig, path)
    plt.close(fig)
    return out


def evaluate(model: GPModel, samples: Samples, plots_dir: str | os.PathLike[str] | None,
             rollout_source: str = ROLLOUT_SOURCE) -> dict[str, Any]:
    """Metrics of ``model`` on the held-out part of ``samples`` and the rollout of one source.

    Parameters
    ----------
    model : GPModel
    samples : Samples
        The dataset the model was trained from (training points are recognised and excluded).
    plots_dir : path-like or None
        Where to write ``gp_scatter.png`` and ``gp_rollout.png``; ``None`` for no plots.
    rollout_source : str
        Source name of the forward-simulation case.

    Returns
    -------
    dict
        ``r2``, ``mape_pct``, ``n_train``, ``n_valid``, ``rollout_case2_mape_pct`` (``None`` if
        the source is absent), ``n_train_found`` (training points found in ``samples``),
        ``meets_targets`` and the PNG paths.
    """
    held_out = held_out_mask(samples, model)
    valid = samples.subset(held_out)
    if len(valid) == 0:
        raise DatasetError("no held-out samples to validate on (the dataset holds only training points)")
    pred = predict_means(model, valid.Z)
    r2, mape = r2_score(valid.y, pred), mape_pct(valid.y, pred)
    result: dict[str, Any] = {
        "r2": r2, "mape_pct": mape, "n_train": model.n_train, "n_valid": len(valid),
        "n_train_found": int(np.sum(~held_out)), "rollout_source": rollout_source,
        "rollout_case2_mape_pct": None,
    }
    case = samples.of_source(rollout_source)
    if len(case):
        traj = rollout(model, case)
        result["rollout_case2_mape_pct"] = mape_pct(traj.recorded, traj.simulated)
    result["meets_targets"] = bool(r2 >= TARGET_R2 and mape <= TARGET_MAPE_PCT)
    if plots_dir is not None:
        plots = Path(plots_dir)
        result["scatter_png"] = plot_scatter(valid.y, pred, r2, mape, plots / "gp_scatter.png")
        if len(case):
            result["rollout_png"] = plot_rollout(traj, rollout_source, result["rollout_case2_mape_pct"],
                                                 plots / "gp_rollout.png")
    return result


def plot_narx(model: Any, runs: list[Any], plots_dir: str | os.PathLike[str]) -> dict[str, str]:
    """Figures of a delay-aware model (:class:`gp_model.narx.NarxGPModel`) on held-out runs
    (:class:`gp_model.narx.RunSeries`): the one-step scatter over all of them (``narx_scatter.png``, as
    Fig. 4a) and the forward simulation of the last one from its powers and measured T
    (``narx_rollout.png``, as Fig. 4b); the states of the pool build-up are left out."""
    from gp_model.build_up import build_up_steps

    ys, preds, traj = [], [], None
    for run in runs:
        mean, _ = model.predict_run(run)
        keep = (run.steps_since_layer_start()[1:] >= build_up_steps(run.sample_period_s)) & (run.area_m2[1:] > 0)
        ys.append(run.area_m2[1:][keep]), preds.append(mean[keep])
        step = np.arange(len(run) - 1)[keep]
        traj = Rollout(step=step, recorded=run.area_m2[1:][keep], simulated=mean[keep], power_w=run.power_w[1:][keep])
    y, pred = np.concatenate(ys), np.concatenate(preds)
    plots = Path(plots_dir)
    return {"scatter_png": plot_scatter(y, pred, r2_score(y, pred), mape_pct(y, pred), plots / "narx_scatter.png"),
            "rollout_png": plot_rollout(traj, runs[-1].name, mape_pct(traj.recorded, traj.simulated),
                                        plots / "narx_rollout.png")}
