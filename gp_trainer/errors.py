"""Typed errors of the training pipeline (below them, :mod:`gp_model.errors`); the CLI turns each into
exit status 2 and a one-line reason."""

from __future__ import annotations

from gp_model.errors import DatasetError, GPError


class RecordingError(DatasetError):
    """A recording cannot be read (missing, empty, truncated or of an unknown layout)."""


class CampaignError(GPError):
    """The data campaign cannot run (e.g. the launcher is missing) or a case failed."""


class LearnError(GPError):
    """A process cannot be learned as asked (e.g. its set point is out of reach of the power limits)."""
