"""Which received laser commands a plant applies, and what it applies without one (pure, no I/O).

A decoded ``LaserCommand`` of the right run (the inbox checks the ``run_id``) is applied only if
its step is one the plant can use now and its power and speed lie within the plant's own bounds.
Anything else — a past or duplicated step, a step the plant cannot have asked for yet (up to
2³¹ − 1), a power outside the bounds — is dropped and counted, never applied and never waited
for. :class:`CommandGate` makes that decision; the lockstep node (:mod:`fe_node.node`) and the
free-running loop (:mod:`fe_node.freerun`) differ only in the window of steps they pass it.
Without an applicable command — the controller's liveliness token is gone, or no command came
within the timeout — the plant applies the fallback of its :class:`CommandPolicy`.
"""

from __future__ import annotations

import enum
import math
from dataclasses import dataclass, field

from messages import LaserCommand
from messages.cli import UsageError
from messages.types import LASER_POWER_MAX_W

FALLBACKS = ("safe", "hold")


@dataclass(frozen=True)
class CommandPolicy:
    """The plant's own command bounds and fallback (powers in W, speeds in m/s, times in s).

    Attributes
    ----------
    power_min_w, power_max_w : float
        Lowest and highest power ever applied [W].
    speed_min_m_s, speed_max_m_s : float
        Lowest and highest scan speed ever applied [m/s].
    timeout_s : float
        Without an applicable command for this long, the fallback applies [s].
    fallback : {"safe", "hold"}
        ``safe``: apply ``safe_power_w`` (the default for a laser); ``hold``: keep the last power.
    safe_power_w : float
        Power of the ``safe`` fallback [W]; must lie within the power bounds.

    Raises
    ------
    UsageError
        On construction, naming the command-line option of the first invalid value.
    """

    power_min_w: float = 0.0
    power_max_w: float = LASER_POWER_MAX_W
    speed_min_m_s: float = 0.05
    speed_max_m_s: float = 5.0
    timeout_s: float = 5.0
    fallback: str = "safe"
    safe_power_w: float = 0.0

    def __post_init__(self) -> None:
        if not (math.isfinite(self.power_max_w) and 0 <= self.power_min_w < self.power_max_w):
            raise UsageError(f"power bounds need 0 <= --power-min-w < --power-max-w (finite), "
                             f"got {self.power_min_w} and {self.power_max_w}")
        if not (math.isfinite(self.speed_max_m_s) and 0 < self.speed_min_m_s < self.speed_max_m_s):
            raise UsageError("speed bounds need 0 < min < max")
        if not (math.isfinite(self.timeout_s) and self.timeout_s > 0):
            raise UsageError(f"--command-timeout-s must be finite and > 0, got {self.timeout_s}")
        if self.fallback not in FALLBACKS:
            raise UsageError(f"--fallback must be one of {', '.join(FALLBACKS)}, got {self.fallback!r}")
        if not self.power_min_w <= self.safe_power_w <= self.power_max_w:
            raise UsageError(f"--safe-power-w must lie within the power bounds "
                             f"[{self.power_min_w}, {self.power_max_w}] W, got {self.safe_power_w}")

    @property
    def fallback_source(self) -> str:
        """``command_source`` of a step under the fallback (``fallback-safe`` or ``fallback-hold``)."""
        return f"fallback-{self.fallback}"

    def within_bounds(self, power_w: float, speed_m_s: float) -> bool:
        """Whether ``power_w`` [W] and ``speed_m_s`` [m/s] lie within the bounds (never apply others)."""
        return (self.power_min_w <= power_w <= self.power_max_w
                and self.speed_min_m_s <= speed_m_s <= self.speed_max_m_s)

    def fallback_power(self, held_w: float) -> float:
        """Power applied under the fallback when ``held_w`` [W] was applied last."""
        return self.safe_power_w if self.fallback == "safe" else held_w


class Verdict(enum.Enum):
    """What becomes of one received command."""

    APPLY = "apply"
    STALE = "stale"  # a step before the window: answered already, duplicated or late
    AHEAD = "ahead"  # a step after the window: the plant cannot have asked for it
    OUT_OF_BOUNDS = "out-of-bounds"  # power or speed outside the plant's own bounds


@dataclass
class CommandGate:
    """Admits the commands a plant may apply and counts the dropped ones by reason.

    Parameters
    ----------
    policy : CommandPolicy
        The plant's own power and speed bounds.
    """

    policy: CommandPolicy
    counts: dict[Verdict, int] = field(default_factory=lambda: dict.fromkeys(Verdict, 0))

    def admit(self, cmd: LaserCommand, first_step: int, last_step: int) -> Verdict:
        """Judge ``cmd`` against the steps ``first_step..last_step`` the plant can apply now.

        A lockstep plant passes the one step it waits for; a free-running plant the steps after
        the newest applied command up to the one answering its newest state. The verdict is
        counted in :attr:`counts`.
        """
        if cmd.step < first_step:
            verdict = Verdict.STALE
        elif cmd.step > last_step:
            verdict = Verdict.AHEAD
        elif not self.policy.within_bounds(cmd.power_w, cmd.speed_mm_s * 1e-3):
            verdict = Verdict.OUT_OF_BOUNDS
        else:
            verdict = Verdict.APPLY
        self.counts[verdict] += 1
        return verdict

    @property
    def n_dropped(self) -> int:
        """Commands dropped so far, for any reason."""
        return sum(n for verdict, n in self.counts.items() if verdict is not Verdict.APPLY)

    @property
    def n_stale(self) -> int:
        """Commands dropped so far for a step before the window."""
        return self.counts[Verdict.STALE]
