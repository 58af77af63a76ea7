"""Training samples of eq. (8) from recorded plant states.

A sample is ``z_k = (x_k, T_k, p_k, v_k, x_k − x_{k-1}) → x_{k+1}`` with ``x_k = state[k].area``,
``T_k = state[k].t_ahead_k``, ``p_k, v_k`` the inputs applied during the step k → k+1,
which the plant echoes in ``state[k+1].power_w / speed_mm_s`` (see ``messages.types``), and
the last area change with ``x_{k-1} = state[k-1].area`` (used by history models; the paper's
model takes the first four columns). Units are converted to SI here, at the edge: mm² → m²,
mm/s → m/s.

Dropped pairs, counted in :class:`DropReport`:

* ``gap``: states k and k+1 are not consecutive steps of the same track (track change, lost
  message), or, after start-up, state k-1 is not the step before k on the same track (the
  first state of a recording, the state after a lost message). The turn to a new track is
  not a one-step dynamics sample.
* ``startup``: the pool of a track has not formed yet. A track's start-up is the prefix of its
  states before the first one whose area reaches ``startup_fraction`` × the median of the
  track's positive areas (a fixed fraction of the track's own level, so it works at any power);
  every pair whose state k lies in it is dropped.
* ``no_pool``: an area ≤ 0 at k or k+1 after start-up (the pool vanished, e.g. at very low
  power); a relative error is undefined there and the one-step model is not meant for it.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import zipfile
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from gp_model.atomic import atomic_write
from gp_model.errors import DatasetError
from gp_trainer.errors import RecordingError
from messages.recording import RecordingError as ReaderError
from messages.recording import metadata, read_all, run_config
from messages.topics import PLANT_STATE

FIELDS = ("step", "time_s", "track", "area_mm2", "t_ahead_k", "power_w", "speed_mm_s")


@dataclass(frozen=True)
class DatasetSettings:
    """How samples are built.

    Attributes
    ----------
    startup_fraction : float
        A track's start-up ends at its first state whose area reaches this fraction of the
        median positive area of the track (0 < fraction ≤ 1).
    min_samples : int
        Fewer samples than this in the whole dataset is an error (100 train + some validation).
    """

    startup_fraction: float = 0.5
    min_samples: int = 120


@dataclass(frozen=True)
class DropReport:
    """Bookkeeping of one source: states read, samples kept and pairs dropped, by reason."""

    source: str
    n_states: int
    n_samples: int
    dropped_startup: int
    dropped_no_pool: int
    dropped_gap: int

    def summary(self) -> str:
        """One line for humans."""
        return (f"{self.source}: {self.n_states} states -> {self.n_samples} samples "
                f"(dropped: {self.dropped_startup} start-up, {self.dropped_no_pool} no pool, "
                f"{self.dropped_gap} track change/gap)")


@dataclass(frozen=True)
class Samples:
    """Samples of eq. (8), SI units.

    Attributes
    ----------
    Z : np.ndarray, shape (n, 5)
        ``(area_m2, t_ahead_k, power_w, speed_m_s, area_change_m2)`` at step k (the order of
        ``gp_model.model.HISTORY_INPUT_NAMES``).
    y : np.ndarray, shape (n,)
        ``area_m2`` at step k+1.
    source : np.ndarray of str, shape (n,)
        Name of the recording each sample comes from (e.g. ``table2-case2``).
    step : np.ndarray of int, shape (n,)
        Step index k of the input state.
    track : np.ndarray of int, shape (n,)
        Track index.
    """

    Z: np.ndarray
    y: np.ndarray
    source: np.ndarray
    step: np.ndarray
    track: np.ndarray

    def __len__(self) -> int:
        return int(self.y.shape[0])

    def subset(self, index: np.ndarray) -> Samples:
        """Rows ``index`` (integer or boolean array) as new samples."""
        return Samples(self.Z[index], self.y[index], self.source[index], self.step[index], self.track[index])

    def of_source(self, source: str) -> Samples:
        """All samples of one source, in step order."""
        return self.subset(np.flatnonzero(self.source == source))


def _field_array(records: Sequence[Any], name: str, source: str) -> np.ndarray:
    try:
        values = [getattr(r, name) for r in records]
    except AttributeError:
        raise DatasetError(f"{source}: a state record has no field `{name}`") from None
    try:
        array = np.array(values, dtype=float)
    except (TypeError, ValueError):
        raise DatasetError(f"{source}: field `{name}` is not numeric") from None
    if not np.all(np.isfinite(array)):
        bad = int(np.flatnonzero(~np.isfinite(array))[0])
        raise DatasetError(f"{source}: non-finite `{name}` in state record {bad}")
    return array


def _startup_mask(area: np.ndarray, track: np.ndarray, fraction: float) -> np.ndarray:
    """True for states in the start-up prefix of their track (see module docstring)."""
    startup = np.zeros(area.shape, dtype=bool)
    for t in np.unique(track):
        idx = np.flatnonzero(track == t)
        positive = area[idx][area[idx] > 0.0]
        if positive.size == 0:
            startup[idx] = True
            continue
        formed = np.flatnonzero(area[idx] >= fraction * np.median(positive))
        startup[idx[: formed[0]]] = True
    return startup


def build_samples(states: Iterable[Any], source: str,
                  settings: DatasetSettings = DatasetSettings()) -> tuple[Samples, DropReport]:
    """Samples of eq. (8) from one recording's plant states.

    Parameters
    ----------
    states : iterable
        Plant states in step order, objects with the attributes :data:`FIELDS` (e.g.
        ``messages.MeltPoolState``): ``area_mm2`` [mm²], ``t_ahead_k`` [K], ``power_w`` [W],
        ``speed_mm_s`` [mm/s], ``step``, ``time_s`` [s], ``track``.
    source : str
        Name stored with each sample and used in messages.
    settings : DatasetSettings
        Start-up rule.

    Returns
    -------
    tuple[Samples, DropReport]

    Raises
    ------
    DatasetError
        No states, a missing or non-finite field, or steps that do not increase.
    """
    records = list(states)
    if not records:
        raise DatasetError(f"{source}: no plant states")
    data = {name: _field_array(records, name, source) for name in FIELDS}
    step, track = data["step"].astype(np.int64), data["track"].astype(np.int64)
    if np.any(np.diff(step) <= 0):
        raise DatasetError(f"{source}: plant-state steps do not increase "
                           f"(record {int(np.argmax(np.diff(step) <= 0)) + 1})")
    area_m2 = data["area_mm2"] * 1e-6
    startup = _startup_mask(area_m2, track, settings.startup_fraction)

    k = np.arange(len(records) - 1)
    contiguous = (step[k + 1] == step[k] + 1) & (track[k + 1] == track[k])
    has_history = np.zeros(k.size, dtype=bool)  # state k-1 is the previous step of the same track
    has_history[1:] = (step[k[1:] - 1] == step[k[1:]] - 1) & (track[k[1:] - 1] == track[k[1:]])
    formed = contiguous & ~startup[k]
    usable = formed & has_history
    keep = usable & (area_m2[k] > 0.0) & (area_m2[k + 1] > 0.0)
    kept = k[keep]
    Z = np.column_stack([area_m2[kept], data["t_ahead_k"][kept], data["power_w"][kept + 1],
                         data["speed_mm_s"][kept + 1] * 1e-3, area_m2[kept] - area_m2[kept - 1]])
    samples = Samples(Z=Z, y=area_m2[kept + 1], source=np.full(kept.size, source), step=step[kept],
                      track=track[kept])
    report = DropReport(source=source, n_states=len(records), n_samples=int(kept.size),
                        dropped_startup=int(np.sum(contiguous & startup[k])),
                        dropped_no_pool=int(np.sum(usable & ~keep)),
                        dropped_gap=int(np.sum(~contiguous) + np.sum(formed & ~has_history)))
    return samples, report


def concatenate(parts: Sequence[Samples], settings: DatasetSettings = DatasetSettings()) -> Samples:
    """Join the samples of several sources; raise :class:`DatasetError` if too few in total."""
    total = sum(len(p) for p in parts)
    if total < settings.min_samples:
        raise DatasetError(f"only {total} usable samples, need at least {settings.min_samples}")
    return Samples(*(np.concatenate([getattr(p, f) for p in parts]) for f in ("Z", "y", "source", "step", "track")))


def read_states(path: str | os.PathLike[str]) -> list[Any]:
    """All ``/plant/state`` messages of one MCAP recording (``messages.MeltPoolState``).

    The only place that touches the recording format; everything else works on records.

    Raises
    ------
    RecordingError
        Missing, empty, truncated or invalid recording, or no plant states in it.
    """
    try:
        return read_all(path, PLANT_STATE, finished=True)
    except ReaderError as exc:
        raise RecordingError(str(exc)) from None


def recording_info(path: str | os.PathLike[str]) -> dict[str, Any]:
    """Provenance of one recording: name, size, SHA-256, recorder metadata and node configs."""

    try:
        data = Path(path).read_bytes()
        info = {"meltloop": metadata(path).get("meltloop", {}), "config": run_config(path)}
    except (OSError, ReaderError, ValueError) as exc:  # run_config parses JSON attachments
        raise RecordingError(f"{path}: unreadable metadata ({exc})") from None
    return {"name": Path(path).name, "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest(), **info}


def save_samples(path: str | os.PathLike[str], samples: Samples, meta: dict[str, Any]) -> Path:
    """Write samples and a JSON-serialisable ``meta`` (sources, drop reports, settings) atomically.

    The ``.npz`` holds only plain arrays (no pickles); ``meta`` is stored as a JSON string.
    """
    buffer = io.BytesIO()
    np.savez(buffer, Z=samples.Z, y=samples.y, source=samples.source.astype(str), step=samples.step,
             track=samples.track, meta=np.array(json.dumps(meta, sort_keys=True)))
    return atomic_write(path, lambda handle: handle.write(buffer.getvalue()))


def load_samples(path: str | os.PathLike[str]) -> tuple[Samples, dict[str, Any]]:
    """Read samples and meta written by :func:`save_samples`.

    Raises
    ------
    DatasetError
        Missing, unreadable or inconsistent file.
    """
    try:
        with np.load(path, allow_pickle=False) as npz:
            samples = Samples(Z=npz["Z"], y=npz["y"], source=npz["source"], step=npz["step"], track=npz["track"])
            meta = json.loads(str(npz["meta"]))
    except FileNotFoundError:
        raise DatasetError(f"dataset not found: {path} (run `python -m gp_trainer dataset` first)") from None
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        raise DatasetError(f"dataset {path} is unreadable ({type(exc).__name__}: {exc})") from None
    n = len(samples)
    if samples.Z.shape == (n, 4):
        raise DatasetError(f"dataset {path} has no area-change column (an older format); rebuild it "
                           "with `python -m gp_trainer dataset`")
    if samples.Z.shape != (n, 5) or any(getattr(samples, f).shape != (n,) for f in ("source", "step", "track")):
        raise DatasetError(f"dataset {path} is inconsistent (array shapes)")
    if not (np.all(np.isfinite(samples.Z)) and np.all(np.isfinite(samples.y))):
        raise DatasetError(f"dataset {path} contains non-finite values")
    return samples, meta
