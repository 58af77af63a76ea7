"""Whether the machine has a core to spare: the busy share of all its CPUs, from ``/proc/stat``.

Polling for a message trades an otherwise idle core for latency (no wake-up on the message's
path): a fast free-running plant polls for its commands (``fe_node.freerun``) and the controller
node keeps its core between states (``controller_node.node.AnswerLoop.poll_window``) while one is
to spare. When every core is busy (another job, a ``--load`` busy loop), the poller takes that time
from the threads the loop itself needs, and sleeping until woken is faster. ``busy share`` =
1 − (idle + iowait) / total, summed over all CPUs, measured every :data:`SAMPLE_S` and averaged
(:data:`SMOOTHING`); a core is spare from a share under :data:`SPARE_BUSY_RESUME` until one over
:data:`SPARE_BUSY_MAX`. Before the first interval is measured a core counts as spare: the loop's
first :data:`SAMPLE_S` (200 steps at 2 kHz) then runs as the rest of a quiet run does, and on a
busy machine the first measurement ends it (``docs/realtime.md``, "A core to spare").
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

SPARE_BUSY_MAX = 0.9
"""A spare core is no longer spare once the machine's busy share (averaged) exceeds this."""
SPARE_BUSY_RESUME = 0.8
"""A core becomes spare again once the busy share is under this (a loaded machine hovers around
:data:`SPARE_BUSY_MAX` without the poller)."""
SAMPLE_S = 0.1
"""Sampling interval [s] of the busy share."""
SMOOTHING = 0.3
"""Weight of the newest interval in the busy share (an exponential average over ~0.3 s: one busy
interval of another job does not stop the polling)."""
PROC_STAT = Path("/proc/stat")


def proc_stat_line() -> str:
    """The first line of ``/proc/stat``: the jiffies of all CPUs together."""
    with PROC_STAT.open() as f:
        return f.readline()


def cpu_times(text: str) -> tuple[int, int]:
    """(busy, total) jiffies of all CPUs from the text of ``/proc/stat`` (its first, ``cpu`` line)."""
    fields = [int(v) for v in text.split("\n", 1)[0].split()[1:]]
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)  # idle + iowait
    total = sum(fields[:8])  # user nice system idle iowait irq softirq steal (guest is in user)
    return total - idle, total


@dataclass
class SpareCore:
    """Samples the machine's busy share every :data:`SAMPLE_S` and says whether a core is to spare.

    Parameters
    ----------
    read : callable or None
        Returns the text of ``/proc/stat`` (default: :func:`proc_stat_line`, or ``None`` where
        there is no ``/proc/stat``: a core then always counts as spare).
    busy_max : float
        Busy share above which a spare core is no longer spare (:data:`SPARE_BUSY_MAX`).
    busy_resume : float
        Busy share under which a core becomes spare (:data:`SPARE_BUSY_RESUME`).
    sample_s : float
        Sampling interval [s] (:data:`SAMPLE_S`).
    spare_until_measured : bool
        Whether a core counts as spare before the first interval is measured (default); the first
        measured share then keeps it spare up to ``busy_max``.
    smoothing : float
        Weight of the newest interval in :attr:`busy_share` (:data:`SMOOTHING`; 1: the last
        interval alone).

    Attributes
    ----------
    busy_share : float or None
        Busy share of the machine's CPUs, the first measured interval's, then an exponential
        average of the intervals (``None`` before the first interval is measured).
    """

    read: Callable[[], str] | None = None
    busy_max: float = SPARE_BUSY_MAX
    busy_resume: float = SPARE_BUSY_RESUME
    smoothing: float = SMOOTHING
    sample_s: float = SAMPLE_S
    spare_until_measured: bool = True
    busy_share: float | None = None
    _last: tuple[int, int] | None = None
    _spare: bool = False
    _next_t: float = field(default=float("-inf"))

    def __post_init__(self) -> None:
        if not 0.0 < self.busy_resume <= self.busy_max <= 1.0:
            raise ValueError(f"need 0 < busy_resume <= busy_max <= 1, got {self.busy_resume}, {self.busy_max}")
        if not 0.0 < self.smoothing <= 1.0 or not self.sample_s > 0.0:
            raise ValueError(f"need smoothing in (0, 1] and sample_s > 0, got {self.smoothing}, {self.sample_s}")
        if self.read is None and PROC_STAT.exists():
            self.read = proc_stat_line
        self._spare = self.spare_until_measured

    def spare(self, t: float) -> bool:
        """Whether a core is to spare at monotonic time ``t`` [s] (re-sampled every ``sample_s``;
        before the first interval is measured: ``spare_until_measured``)."""
        if self.read is None:
            return True
        if t >= self._next_t:
            self._next_t = t + self.sample_s
            now = cpu_times(self.read())
            if self._last is not None and now[1] > self._last[1]:
                share = (now[0] - self._last[0]) / (now[1] - self._last[1])
                if self.busy_share is not None:
                    share = self.busy_share + self.smoothing * (share - self.busy_share)
                self.busy_share = share
                self._spare = share < (self.busy_max if self._spare else self.busy_resume)
            self._last = now
        return self._spare
