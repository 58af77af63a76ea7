"""Typed errors of the GP models and their data; a command line turns each into exit status 2 and a one-line reason."""

from __future__ import annotations


class GPError(Exception):
    """Base class: a user or input error with a one-line, human-readable message."""


class DatasetError(GPError):
    """Samples cannot be built: missing, empty, truncated or non-finite data, or too few samples."""


class ModelFormatError(GPError):
    """A model file is unreadable, corrupt or inconsistent."""


class ModelVersionError(ModelFormatError):
    """A model file was written in another format version than this code reads."""
