"""The preview MPC's learned turnaround state as a document: what
:meth:`controller_node.preview.PreviewMPC.learning_state` writes and ``launch.py --learning-state``
checks before any node starts (numpy only, so the check loads no controller)."""

from __future__ import annotations

import numpy as np

__all__ = ["LEARNING_FORMAT", "PATH_TOLERANCE_M", "parse_learning_state", "plan_mismatch"]

LEARNING_FORMAT = "meltloop-preview-learning-3"
"""The format name of a learning-state document (``-3``: it records the plan it was learned on)."""
PATH_TOLERANCE_M = 1e-6
"""Two path lengths [m] closer than this are the same path."""


def parse_learning_state(doc: object, sample_period_s: float, n_correction: int, n_profile: int
                         ) -> tuple[np.ndarray, list[np.ndarray], np.ndarray]:
    """The learned turnaround correction (n_correction,), the corrections by turn and the T-rise
    profile (n_profile,) of a :meth:`~controller_node.preview.PreviewMPC.learning_state` document, checked against the
    model's sample period [s] and the controller's lengths (``ValueError`` with one line if it
    does not fit: ``launch.py`` checks a file before any node starts, the controller when it loads it)."""
    if not isinstance(doc, dict) or doc.get("format") != LEARNING_FORMAT:
        found = doc.get("format") if isinstance(doc, dict) else None
        hint = " (written by an older meltloop: delete it to start learning afresh)" if isinstance(found, str) \
            and found.startswith("meltloop-preview-learning-") else ""
        raise ValueError(f"not a {LEARNING_FORMAT} document{hint}")
    try:
        correction = np.asarray(doc.get("turn_correction_m2"), dtype=float)
        by_turn = [np.asarray(c, dtype=float) for c in doc.get("turn_corrections_by_turn_m2") or []]
        profile = np.asarray(doc.get("turn_profile_k"), dtype=float)
    except (TypeError, ValueError):
        raise ValueError("turn_correction_m2, turn_corrections_by_turn_m2 and turn_profile_k must be lists of "
                         "numbers") from None
    if any(c.shape != correction.shape or not np.all(np.isfinite(c)) for c in by_turn):
        raise ValueError("turn_corrections_by_turn_m2 does not fit turn_correction_m2")
    if doc.get("sample_period_s") != sample_period_s:
        raise ValueError(f"learned at a sample period of {doc.get('sample_period_s')} s, the model's is "
                         f"{sample_period_s} s")
    if correction.shape != (n_correction,) or profile.shape != (n_profile,):
        raise ValueError("learned with another turn_learning_steps or turnaround profile length")
    if not (np.all(np.isfinite(correction)) and np.all(np.isfinite(profile))):
        raise ValueError("non-finite values")
    return correction, [c.copy() for c in by_turn], profile


def plan_mismatch(doc: dict, path_lengths_m) -> str | None:
    """Why a learning-state document (checked by :func:`parse_learning_state`) was learned on another
    scan plan than one whose paths have the lengths ``path_lengths_m`` [m] (its turns would be another
    plan's turns; one line), or None."""
    learned = doc.get("path_lengths_m")
    try:
        learned = [float(v) for v in learned]
    except (TypeError, ValueError):
        return "path_lengths_m must be a list of numbers"
    planned = [float(v) for v in path_lengths_m]
    if len(learned) == len(planned) and all(abs(a - b) <= PATH_TOLERANCE_M for a, b in zip(learned, planned)):
        return None
    return (f"learned on a plan of {_describe(learned)}; this run's plan has {_describe(planned)} "
            "(delete it to start learning afresh)")


def _describe(lengths: list[float]) -> str:
    """``4 paths, 10 mm each`` or ``3 paths of 2, 4, 6 mm``."""
    if not lengths:
        return "no paths"
    mm = [round(v * 1e3, 4) for v in lengths]
    if len(set(mm)) == 1:
        return f"{len(mm)} path{'s' * (len(mm) > 1)} of {mm[0]:g} mm"
    shown = ", ".join(f"{v:g}" for v in mm[:6]) + (", ..." if len(mm) > 6 else "")
    return f"{len(mm)} paths of {shown} mm"
