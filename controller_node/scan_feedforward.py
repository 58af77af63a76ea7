"""Scan-plan feed-forward (``scan-feedforward``): the preview MPC's schedule with no feedback.

The baseline the literature calls scan-plan (or vector-level) power scheduling: powers planned
ahead along the scan plan from a thermal model of the plan, never corrected by a measurement. It
is :class:`~controller_node.preview.PreviewMPC` on the same delay-aware model, the same scan-plan
preview and the same turnaround feature ``F`` (:mod:`gp_model.plan_feature`, the heat of the
previous track's powers at the laser after a turn), with the two feedback paths cut:

* the area is never measured: the output-disturbance observer does not run (``d̂ = 0``), so the
  turnaround learning has nothing to learn from, and the T-rise profile is not learned either;
* T ahead is the model's own: each state takes the T ahead that the previous plan forecast for it
  (``T̂[k|k−1]``, :func:`gp_model.narx.forecast_t_ahead`), except at laser-on of a layer, where it
  takes the measured bed temperature (known before a layer starts).

What remains is the open-loop optimal schedule of the learned model along the plan: the
difference from ``preview-mpc`` is what feedback adds to the same model.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from .base import Proposal
from .preview import PreviewMPC
from .settings import ControllerSettings
from .types import Measurement

__all__ = ["ScanFeedForward"]


class ScanFeedForward(PreviewMPC):
    """The preview MPC's schedule without feedback (module docstring).

    Parameters
    ----------
    settings : ControllerSettings
        As for :class:`~controller_node.preview.PreviewMPC`; ``preview.learn_turn_profile`` and
        ``preview.turn_learning_gain`` are set off (both learn from measurements).
    model : gp_model.narx.NarxGPModel
        The delay-aware model.
    """

    name = "scan-feedforward"
    feedback = False

    def __init__(self, settings: ControllerSettings, model) -> None:
        preview = replace(settings.preview, learn_turn_profile=False, turn_learning_gain=0.0)
        super().__init__(replace(settings, preview=preview), model)

    def reset(self) -> None:
        """Forget the run, and the T ahead forecast for the next states."""
        super().reset()
        self._t_forecast: np.ndarray | None = None   # T̂[k+1 ..] [K] of the last plan

    def _propose(self, m: Measurement) -> Proposal:
        prev = self._prev
        if self._t_forecast is not None and prev is not None and m.layer == prev.layer and m.step > prev.step:
            ahead = min(m.step - prev.step, self._t_forecast.size) - 1
            m = replace(m, t_ahead_k=float(self._t_forecast[ahead]))
        proposal = super()._propose(m)
        self._t_forecast = self._kernel.forecast.copy()   # before the node prepares the next state
        return proposal
