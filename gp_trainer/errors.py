"""Typed errors of the GP trainer; the CLI turns each into exit status 2 and a one-line reason."""

from __future__ import annotations


class GPTrainerError(Exception):
    """Base class: a user or input error with a one-line, human-readable message."""


class DatasetError(GPTrainerError):
    """Samples cannot be built: missing, empty, truncated or non-finite data, or too few samples."""


class RecordingError(DatasetError):
    """A recording cannot be read (missing, empty, truncated or of an unknown layout)."""


class ModelFormatError(GPTrainerError):
    """A model file is unreadable, corrupt or inconsistent."""


class ModelVersionError(ModelFormatError):
    """A model file was written in another format version than this code reads."""


class CampaignError(GPTrainerError):
    """The data campaign cannot run (e.g. the launcher is missing) or a case failed."""
