"""Open-loop baseline (constant power).  The other baselines live in
:mod:`controller_node.pid` and :mod:`controller_node.feedforward`."""

from __future__ import annotations

from .base import Controller, Proposal
from .types import Measurement

__all__ = ["OpenLoopController"]


class OpenLoopController(Controller):
    """Constant ``settings.nominal_power_w`` (the paper's open-loop comparison)."""

    name = "open-loop"

    def _propose(self, m: Measurement) -> Proposal:
        return Proposal(self.settings.nominal_power_w)
