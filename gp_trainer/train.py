"""Training pipeline: select the training points of a dataset and fit the GP (paper IV.A)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from gp_trainer.dataset import Samples
from gp_trainer.errors import DatasetError
from gp_trainer.model import DEFAULT_RESTARTS, GPModel
from gp_trainer.provenance import code_version
from gp_trainer.selection import farthest_point_indices


@dataclass(frozen=True)
class TrainSettings:
    """How the GP is trained.

    Attributes
    ----------
    n_train : int
        Training points (paper: 100); all other samples are for validation.
    seed : int
        Seeds the first selected point and the optimiser restarts.
    n_restarts : int
        L-BFGS-B starts of the hyper-parameter fit.
    """

    n_train: int = 100
    seed: int = 0
    n_restarts: int = DEFAULT_RESTARTS


def train(samples: Samples, dataset_meta: dict[str, Any], settings: TrainSettings = TrainSettings()) -> GPModel:
    """Select ``n_train`` points by farthest-point sampling and fit :class:`GPModel` on them.

    Parameters
    ----------
    samples : Samples
        The whole dataset (SI units).
    dataset_meta : dict
        Provenance of the dataset (recordings, drop reports, settings), stored in the model.
    settings : TrainSettings

    Returns
    -------
    GPModel
        With provenance: dataset meta, selection, code version, seed.

    Raises
    ------
    DatasetError
        Fewer samples than ``n_train`` + 1 (nothing left to validate on).
    """
    if len(samples) <= settings.n_train:
        raise DatasetError(f"dataset has {len(samples)} samples, need more than n_train={settings.n_train}")
    index = np.sort(farthest_point_indices(samples.Z, settings.n_train, seed=settings.seed))
    provenance = {
        "dataset": dataset_meta,
        "selection": {"method": "greedy farthest-point (maximin) on standardised inputs",
                      "n_train": settings.n_train, "n_samples": len(samples)},
        "code": code_version(),
    }
    return GPModel.fit(samples.Z[index], samples.y[index], seed=settings.seed,
                       n_restarts=settings.n_restarts, provenance=provenance)
