"""The ``[controller]`` values a learned process records: ``provenance.controller`` of a model written
by ``python -m gp_trainer learn`` (or ``tune-pid``), namely the operating power, from which every
controller starts (``nominal_power_w``), and the PID baseline's gains tuned on the process's training
staircases (``pid``: ``kp_w``, ``ki_w``, ``kd_w``; :mod:`gp_trainer.pid_tuning`), and for a process
observed at a camera's frame period the preview MPC's sample counts at that period (``preview``:
:func:`preview_steps`).

``python -m controller_node --process MODEL.json`` puts them under the run's own ``[controller]``
table, which wins; ``launch.py`` passes the model of the run's plant, so that the baselines and the
preview MPC on a learned process start from what was learned of it, not from the bare plate's values.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

from gp_model.build_up import build_up_steps, rollout_horizon, steps_at
from gp_model.errors import ModelFormatError
from gp_model.files import read_document
from messages.cli import UsageError

__all__ = ["PID_KEYS", "PREVIEW_KEYS", "preview_steps", "process_mismatch", "process_table"]

PERIOD_TOLERANCE = 0.01
"""Relative difference between the plant's and the model's sample period that is refused."""
SPEED_TOLERANCE = 0.01
"""Relative difference between the plant's and the model's scan speed that is refused."""


def process_mismatch(model, speed_m_s: float | None = None, sample_period_s: float | None = None,
                     material: str | None = None, powder_layer_m: float | None = None) -> str | None:
    """Why a plant scanning at ``speed_m_s`` [m/s] with the sample period ``sample_period_s`` [s],
    ``material`` and a powder layer of ``powder_layer_m`` [m] is not the process ``model`` was identified
    on (one line), or None. A value not given, or a material or layer the model does not record, is not
    compared."""
    if speed_m_s is not None and not abs(speed_m_s / model.speed_m_s - 1.0) <= SPEED_TOLERANCE:
        return (f"the plant scans at {speed_m_s * 1e3:.4g} mm/s but the model was identified at "
                f"{model.speed_m_s * 1e3:.4g} mm/s; retrain at the plant's speed")
    if sample_period_s is not None and not abs(sample_period_s / model.sample_period_s - 1.0) <= PERIOD_TOLERANCE:
        return (f"the plant's sample period is {sample_period_s * 1e6:.4g} µs but the model was identified at "
                f"{model.sample_period_s * 1e6:.4g} µs; retrain at the plant's period")
    if material is not None and model.material is not None and material != model.material:
        return f"the plant's material is {material} but the model was identified on {model.material}"
    recorded = model.powder_layer_m
    if powder_layer_m is not None and recorded is not None and not math.isclose(powder_layer_m, recorded,
                                                                                rel_tol=1e-6, abs_tol=1e-9):
        return (f"the plant's powder layer is {powder_layer_m * 1e6:.4g} µm but the model was identified on "
                f"{recorded * 1e6:.4g} µm; retrain on the plant's layer")
    return None

PID_KEYS = ("kp_w", "ki_w", "kd_w")
"""The gains of ``provenance.controller.pid`` that become ``[controller.pid]`` values."""
PREVIEW_KEYS = ("horizon", "observer_start_steps", "turn_learning_steps")
"""The sample counts of ``provenance.controller.preview`` that become ``[controller.preview]`` values."""


def preview_steps(sample_period_s: float) -> dict[str, int]:
    """The preview MPC's sample counts (:data:`PREVIEW_KEYS`) for a model at ``sample_period_s`` [s]: the
    defaults of :class:`~controller_node.settings.PreviewSettings`, chosen at the FE step, as the same time
    (:func:`gp_model.build_up.steps_at`); the horizon at least :func:`gp_model.build_up.rollout_horizon`'s
    floor, the observer after the model's build-up. At 1 ms: horizon 8, observer_start_steps 1,
    turn_learning_steps 3."""
    from controller_node.settings import PreviewSettings

    defaults = PreviewSettings()
    return {"horizon": max(steps_at(defaults.horizon, sample_period_s), rollout_horizon(sample_period_s)),
            "observer_start_steps": build_up_steps(sample_period_s),
            "turn_learning_steps": steps_at(defaults.turn_learning_steps, sample_period_s)}


def process_table(path: Path) -> dict[str, Any]:
    """The ``[controller]`` values the model at ``path`` records (``{}`` for a model that records none).

    Raises
    ------
    UsageError
        ``--process``: the file cannot be read, or its record is malformed (naming the key).
    """
    try:
        doc = read_document(path)
    except ModelFormatError as err:
        raise UsageError(f"--process: {err}") from None
    provenance = doc.get("provenance") if isinstance(doc, dict) else None
    record = provenance.get("controller") if isinstance(provenance, dict) else None
    if record is None:
        return {}
    where = f"--process {path}: provenance.controller"
    if not isinstance(record, dict) or not isinstance(record.get("pid"), dict):
        raise UsageError(f"{where} must be an object with a pid object")
    table = {"nominal_power_w": record.get("nominal_power_w"), "pid": {k: record["pid"].get(k) for k in PID_KEYS}}
    for key, value in (("nominal_power_w", table["nominal_power_w"]), *table["pid"].items()):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise UsageError(f"{where}: {key} must be a number, got {value!r}")
    if "preview" in record:
        preview = record["preview"]
        if not isinstance(preview, dict) or set(preview) != set(PREVIEW_KEYS):
            raise UsageError(f"{where}.preview must be an object with {', '.join(PREVIEW_KEYS)}")
        for key, value in preview.items():
            if isinstance(value, bool) or not isinstance(value, int):
                raise UsageError(f"{where}.preview: {key} must be an integer, got {value!r}")
        table["preview"] = dict(preview)
    return table
