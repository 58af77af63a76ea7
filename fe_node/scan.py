"""Scan plans (laser paths) and open-loop power/speed profiles.

A :class:`ScanPlan` is a sequence of straight tracks in any direction in the plane, traversed in
order; between tracks the laser jumps, off and with no delay, to the next track's start (paper
Fig. 5: new tracks at ~13, 26, 39 ms for 10 mm at 800 mm/s).  The laser position is a function
of the travelled arc length ``s`` [m], counted along the tracks only.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from typing import NamedTuple

import numpy as np

from fe_node.settings import check_type


class _Geometry(NamedTuple):
    """Per track of a :class:`ScanPlan`: start point [m] (n, 2), unit direction (n, 2), length [m]
    and arc length at its end [m]; the plan's total length [m]; the first and the last track of
    the path each track belongs to (:meth:`ScanPlan.preview`)."""

    starts: np.ndarray
    directions: np.ndarray
    lengths: np.ndarray
    ends_m: np.ndarray
    total_m: float
    first: np.ndarray
    last: np.ndarray


@dataclass(frozen=True)
class ScanPlan:
    """Straight tracks, each from its start to its end point, in any direction.

    Parameters
    ----------
    tracks : tuple of ((x0, y0), (x1, y1))
        Start and end points [m]; finite, and each track of non-zero length.
    """

    tracks: tuple

    def __post_init__(self):
        if not self.tracks:
            raise ValueError("scan plan: need at least one track")
        for i, ((x0, y0), (x1, y1)) in enumerate(self.tracks):
            if not all(math.isfinite(v) for v in (x0, y0, x1, y1)):
                raise ValueError(f"scan plan: track {i} has a non-finite point")
            if (x0, y0) == (x1, y1):
                raise ValueError(f"scan plan: track {i} is empty (start = end)")

    @classmethod
    def single(cls, length_m: float = 5e-3) -> ScanPlan:
        """One track from (0, 0) to (length, 0)."""
        return cls.layer(1, length_m, 1e-4)

    @classmethod
    def layer(cls, n_tracks: int, length_m: float, hatch_m: float,
              bidirectional: bool = True) -> ScanPlan:
        """``n_tracks`` tracks along x of ``length_m`` spaced ``hatch_m``, centred on y = 0.

        Bidirectional (serpentine) by default: odd tracks run in -x.
        """
        check_type("scan plan: n_tracks", n_tracks, "int")
        check_type("scan plan: track length", length_m, "float")
        check_type("scan plan: hatch", hatch_m, "float")
        check_type("scan plan: bidirectional", bidirectional, "bool")
        if n_tracks < 1:
            raise ValueError(f"scan plan: n_tracks must be a positive integer, got {n_tracks}")
        if not length_m > 0:
            raise ValueError(f"scan plan: track length must be > 0, got {length_m}")
        if not hatch_m > 0:
            raise ValueError(f"scan plan: hatch must be > 0, got {hatch_m}")
        tracks = []
        for j in range(int(n_tracks)):
            y = (j - (n_tracks - 1) / 2) * hatch_m
            ends = ((0.0, y), (length_m, y))
            tracks.append(ends[::-1] if bidirectional and j % 2 else ends)
        return cls(tuple(tracks))

    @cached_property
    def _geometry(self) -> _Geometry:
        ends = np.array(self.tracks, dtype=float)            # (n, 2 points, 2 coordinates)
        delta = ends[:, 1] - ends[:, 0]
        lengths = np.hypot(delta[:, 0], delta[:, 1])
        joined = np.all(ends[1:, 0] == ends[:-1, 1], axis=1)  # track k + 1 starts where track k ends
        first = np.maximum.accumulate(np.where(np.r_[False, joined], 0, np.arange(len(lengths))))
        last = np.minimum.accumulate(np.where(np.r_[joined, False], len(lengths) - 1,
                                              np.arange(len(lengths)))[::-1])[::-1]
        return _Geometry(ends[:, 0], delta / lengths[:, None], lengths, np.cumsum(lengths),
                         float(lengths.sum()), first, last)

    @property
    def lengths(self) -> np.ndarray:
        """Length of each track [m]."""
        return self._geometry.lengths.copy()

    @property
    def path_lengths(self) -> np.ndarray:
        """Length of each path [m], in scan order (a path: tracks each starting where the one before
        ends, :meth:`preview`; a hatch line is a path of one track)."""
        g = self._geometry
        starts = np.flatnonzero(g.first == np.arange(len(g.lengths)))
        return g.ends_m[g.last[starts]] - (g.ends_m[starts] - g.lengths[starts])

    @property
    def angles_deg(self) -> np.ndarray:
        """Direction of each track [deg], counter-clockwise from +x, in (-180, 180]."""
        d = self._geometry.directions
        return np.degrees(np.arctan2(d[:, 1], d[:, 0]))

    @property
    def total_length(self) -> float:
        """Total scanned length [m]."""
        return self._geometry.total_m

    def bounds(self) -> tuple[float, float, float, float]:
        """(x_min, x_max, y_min, y_max) of all tracks [m]."""
        pts = np.array([p for t in self.tracks for p in t])
        return pts[:, 0].min(), pts[:, 0].max(), pts[:, 1].min(), pts[:, 1].max()

    def preview(self, s: float) -> tuple[float, float, bool]:
        """Scan-plan preview at arc length ``s`` [m]: distance travelled on the current path,
        distance left to its end [m], and whether another path follows it.

        A path is a run of tracks each starting where the one before ends (a contour's polygon),
        scanned without a jump; a hatch line is a path of one track.
        """
        track, _, _ = self.locate(s)
        g, k = self._geometry, int(track)
        start = g.ends_m[g.first[k]] - g.lengths[g.first[k]]
        end = g.ends_m[g.last[k]]
        return float(min(s, end) - start), float(max(end - s, 0.0)), bool(g.last[k] + 1 < len(self.tracks))

    def locate(self, s):
        """Track index, position and unit direction at arc length(s) ``s`` [m].

        Returns
        -------
        track : ndarray of int
        xy : ndarray, shape (..., 2) [m]
        direction : ndarray, shape (..., 2)
        """
        g = self._geometry
        s = np.clip(np.asarray(s, dtype=float), 0.0, g.total_m)
        k = np.minimum(np.searchsorted(g.ends_m, s, side="right"), len(self.tracks) - 1)
        local = s - (g.ends_m - g.lengths)[k]
        xy = g.starts[k] + local[..., None] * g.directions[k]
        return k, xy, g.directions[k]


@dataclass(frozen=True)
class Signal:
    """A scalar signal of time: constant, sinusoid, or piecewise-constant profile.

    ``value(t) = mean + amplitude * sin(2 pi t / period_s)`` if ``period_s > 0``;
    if ``times_s`` is given, ``values[i]`` holds on ``[times_s[i], times_s[i+1])``.
    """

    mean: float = 0.0
    amplitude: float = 0.0
    period_s: float = 0.0
    times_s: tuple = ()
    values: tuple = ()

    def __post_init__(self):
        if len(self.times_s) != len(self.values):
            raise ValueError("profile: times_s and values differ in length")
        if self.times_s and (self.times_s[0] != 0 or np.any(np.diff(self.times_s) <= 0)):
            raise ValueError("profile: times_s must start at 0 and increase")

    def __call__(self, t: float) -> float:
        if self.times_s:
            i = int(np.searchsorted(self.times_s, t, side="right")) - 1
            return float(self.values[i])
        if self.period_s > 0:
            return float(self.mean + self.amplitude * np.sin(2 * np.pi * t / self.period_s))
        return float(self.mean)

    def range(self) -> tuple[float, float]:
        """(min, max) the signal can take."""
        if self.times_s:
            return min(self.values), max(self.values)
        a = abs(self.amplitude) if self.period_s > 0 else 0.0
        return self.mean - a, self.mean + a


@dataclass(frozen=True)
class Profile:
    """Open-loop command: power [W] and speed [m/s] as signals of time.

    Parameters
    ----------
    power_w, speed_m_s : Signal
    dt_s : float
        Step length [s]; step ``k`` is commanded with the values at ``t = k * dt_s``.
    """

    power_w: Signal
    speed_m_s: Signal
    dt_s: float = 50e-6

    def __post_init__(self):
        if self.power_w.range()[0] < 0:
            raise ValueError(f"profile: power must be >= 0 W, got min {self.power_w.range()[0]}")
        if self.speed_m_s.range()[0] <= 0:
            raise ValueError(f"profile: speed must be > 0, got min {self.speed_m_s.range()[0]} m/s")

    @classmethod
    def constant(cls, power_w: float, speed_m_s: float, dt_s: float = 50e-6) -> Profile:
        return cls(Signal(power_w), Signal(speed_m_s), dt_s)

    def command(self, step: int) -> tuple[float, float]:
        """(power_w, speed_m_s) for step index ``step`` (0 = first step)."""
        t = step * self.dt_s
        return self.power_w(t), self.speed_m_s(t)
