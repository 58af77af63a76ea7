"""Where the shipped models live, and which one a plant gets by default.

Only paths: naming a shipped model loads none of the models' numerics (scipy, numba), so a
process that runs no model (a PID controller node, ``launch.py`` checking a PID run) starts light.
"""

from __future__ import annotations

from pathlib import Path

MODELS_DIR = Path(__file__).resolve().parent / "models"
ONE_STEP_MODEL_PATH = MODELS_DIR / "in625_gp.json"
"""The shipped one-step model of eq. (1) (``python -m gp_trainer train`` writes it; the MPC and the
feed-forward controller load it)."""
DEFAULT_MODEL_PATH = MODELS_DIR / "in625_narx_gp.json"
"""The shipped delay-aware model of the physical plant (``[plant] preset = "physical"``, a 25 µm powder layer;
``python -m gp_trainer learn`` writes it, docs/gp.md; the preview MPC loads it)."""
PLATE_MODEL_PATH = MODELS_DIR / "in625_plate_narx_gp.json"
"""The delay-aware model of the bare plate (no powder; ``python -m gp_trainer narx --plant plate``)."""
PART_MODEL_PATH = MODELS_DIR / "in625_part_narx_gp.json"
"""The delay-aware model of the ``part`` scenario (``python -m gp_trainer narx --plant part``)."""


def default_model_path(powder_layer_m: float) -> Path:
    """The shipped delay-aware model of a plate plant with a powder layer of ``powder_layer_m`` [m]: the
    bare plate's (:data:`PLATE_MODEL_PATH`) without powder, else :data:`DEFAULT_MODEL_PATH` (which refuses
    a plant whose layer is not the one it was identified on)."""
    return PLATE_MODEL_PATH if powder_layer_m == 0 else DEFAULT_MODEL_PATH
