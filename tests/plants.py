"""The plants tests pin instead of the default (``physical``) plant.

A test whose subject is not the physics (contract, nodes, recorder, controller logic, zenoh) runs on
the bare plate, which steps faster; a test of closed-loop figures runs on the plant the shipped GP
models were identified on.
"""

from __future__ import annotations

from pathlib import Path

BARE = "bare-plate"
"""The bare plate's preset (``scenario(..., preset=BARE)``)."""
BARE_CONFIG = Path(__file__).resolve().parent.parent / "docs" / "bare-plate.toml"
"""``--config`` of the bare plate (its ``[plant]`` table: ``preset = "bare-plate"``)."""
MODEL_PRESET = BARE
"""The preset the shipped GP models (``gp_model/models/``) were identified on: the closed-loop
thresholds hold on it. Becomes ``"physical"`` with models identified on the physical plant."""
BARE_ARGS = ("--config", str(BARE_CONFIG))
"""The command-line options of ``launch.py`` and ``python -m fe_node`` that select the bare plate."""
