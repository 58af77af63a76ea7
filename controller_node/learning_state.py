"""The preview MPC's learned turnaround state as a document: what
:meth:`controller_node.preview.PreviewMPC.learning_state` writes and ``launch.py --learning-state``
checks before any node starts (numpy only, so the check loads no controller)."""

from __future__ import annotations

import numpy as np

__all__ = ["LEARNING_FORMAT", "parse_learning_state"]

LEARNING_FORMAT = "meltloop-preview-learning-2"
"""The format name of a learning-state document."""


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
