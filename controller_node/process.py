"""The ``[controller]`` values a learned process records: ``provenance.controller`` of a model written
by ``python -m gp_trainer learn`` (or ``tune-pid``), namely the operating power, from which every
controller starts (``nominal_power_w``), and the PID baseline's gains tuned on the process's training
staircases (``pid``: ``kp_w``, ``ki_w``, ``kd_w``; :mod:`gp_trainer.pid_tuning`).

``python -m controller_node --process MODEL.json`` puts them under the run's own ``[controller]``
table, which wins; ``launch.py`` passes the model of the run's plant, so that the baselines and the
preview MPC on a learned process start from what was learned of it, not from the bare plate's values.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from gp_model.errors import ModelFormatError
from gp_model.files import read_document
from messages.cli import UsageError

__all__ = ["PID_KEYS", "process_table"]

PID_KEYS = ("kp_w", "ki_w", "kd_w")
"""The gains of ``provenance.controller.pid`` that become ``[controller.pid]`` values."""


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
    return table
