"""Command admission and fallback of the plant, without zenoh: the gate, the policy and the lockstep waiter."""

from __future__ import annotations

import threading
import time
from collections import deque

import pytest

from fe_node.commands import CommandGate, CommandPolicy, Verdict
from fe_node.node import CommandWaiter, PlantSettings
from messages import LaserCommand
from messages.cli import UsageError
from messages.types import MAX_STEP


def cmd(step: int, power_w: float = 200.0, speed_mm_s: float = 800.0) -> LaserCommand:
    return LaserCommand(run_id="r", step=step, time_s=0.0, power_w=power_w, speed_mm_s=speed_mm_s, controller="t")


def gate(**policy) -> CommandGate:
    return CommandGate(CommandPolicy(**{"power_min_w": 10.0, "power_max_w": 300.0, "safe_power_w": 10.0, **policy}))


@pytest.mark.parametrize("step", [0, 5, 9])
def test_a_step_before_the_window_is_stale(step):
    g = gate()
    assert g.admit(cmd(step), 10, 10) is Verdict.STALE
    assert g.n_stale == 1 and g.n_dropped == 1


@pytest.mark.parametrize("step", [11, 12, 10_000, MAX_STEP])
def test_a_step_after_the_window_is_ahead(step):
    g = gate()
    assert g.admit(cmd(step), 10, 10) is Verdict.AHEAD
    assert g.counts[Verdict.AHEAD] == 1 and g.n_stale == 0 and g.n_dropped == 1


@pytest.mark.parametrize("step", [10, 11, 12])
def test_every_step_of_the_window_applies(step):
    g = gate()
    assert g.admit(cmd(step), 10, 12) is Verdict.APPLY
    assert g.n_dropped == 0 and g.counts[Verdict.APPLY] == 1


@pytest.mark.parametrize(("power_w", "speed_mm_s", "verdict"), [
    (10.0, 800.0, Verdict.APPLY), (300.0, 800.0, Verdict.APPLY),  # the bounds themselves are allowed
    (9.99, 800.0, Verdict.OUT_OF_BOUNDS), (300.01, 800.0, Verdict.OUT_OF_BOUNDS), (0.0, 800.0, Verdict.OUT_OF_BOUNDS),
    (200.0, 49.0, Verdict.OUT_OF_BOUNDS), (200.0, 5001.0, Verdict.OUT_OF_BOUNDS),
    (200.0, 50.0, Verdict.APPLY), (200.0, 5000.0, Verdict.APPLY),
])
def test_power_and_speed_must_lie_within_the_plants_own_bounds(power_w, speed_mm_s, verdict):
    g = gate()
    assert g.admit(cmd(3, power_w, speed_mm_s), 3, 3) is verdict
    assert g.n_dropped == (verdict is not Verdict.APPLY)


def test_drops_are_counted_by_reason():
    g = gate()
    verdicts = [g.admit(c, 5, 5) for c in (cmd(4), cmd(4), cmd(6), cmd(5, 400.0), cmd(5))]
    assert verdicts == [Verdict.STALE, Verdict.STALE, Verdict.AHEAD, Verdict.OUT_OF_BOUNDS, Verdict.APPLY]
    assert g.counts == {Verdict.APPLY: 1, Verdict.STALE: 2, Verdict.AHEAD: 1, Verdict.OUT_OF_BOUNDS: 1}
    assert g.n_dropped == 4 and g.n_stale == 2


def test_the_default_fallback_is_the_safe_power_of_zero_watts():
    policy = PlantSettings().policy
    assert (policy.fallback, policy.safe_power_w, policy.fallback_source) == ("safe", 0.0, "fallback-safe")
    assert policy.fallback_power(held_w=250.0) == 0.0
    assert CommandPolicy(fallback="hold").fallback_power(held_w=250.0) == 250.0
    assert CommandPolicy(safe_power_w=40.0).fallback_power(held_w=250.0) == 40.0


@pytest.mark.parametrize(("kwargs", "option"), [
    ({"timeout_s": 0.0}, "--command-timeout-s"), ({"timeout_s": float("inf")}, "--command-timeout-s"),
    ({"timeout_s": float("nan")}, "--command-timeout-s"), ({"fallback": "off"}, "--fallback"),
    ({"safe_power_w": 400.0}, "--safe-power-w"), ({"safe_power_w": float("nan")}, "--safe-power-w"),
    ({"power_min_w": 50.0}, "--safe-power-w"),  # the default 0 W safe power lies below the bounds
    ({"power_max_w": float("inf")}, "--power-max-w"), ({"power_min_w": -1.0}, "--power-min-w"),
])
def test_policy_rejects_impossible_values_naming_the_option(kwargs, option):
    with pytest.raises(UsageError, match=option):
        CommandPolicy(**kwargs)


@pytest.mark.parametrize(("kwargs", "option"), [
    ({"max_steps": 0}, "--max-steps"), ({"image_every": 0}, "--image-every"), ({"controller": ""}, "--controller"),
])
def test_plant_settings_reject_impossible_values_naming_the_option(kwargs, option):
    with pytest.raises(UsageError, match=option):
        PlantSettings(**kwargs)


class ScriptedInbox:
    """Stands in for the zenoh inbox: hands out queued commands, then ``forever`` (if any) until ``until`` s."""

    def __init__(self, commands: list[LaserCommand], forever: LaserCommand | None = None, until_s: float = 0.0):
        self.queue = deque(commands)
        self.forever, self.until = forever, time.monotonic() + until_s
        self.n_invalid = 0
        self.n_idle = 0  # calls that found nothing and waited

    def get(self, timeout: float | None = None) -> LaserCommand | None:
        if self.queue:
            return self.queue.popleft()
        if self.forever is not None and time.monotonic() < self.until:
            return self.forever
        self.n_idle += 1
        time.sleep(timeout or 0.0)
        return None


class CountingEvent(threading.Event):
    """An event that counts the waits on it."""

    def __init__(self) -> None:
        super().__init__()
        self.n_waits = 0

    def wait(self, timeout: float | None = None) -> bool:
        self.n_waits += 1
        return super().wait(timeout)


def waiter(inbox: ScriptedInbox, timeout_s: float = 5.0) -> CommandWaiter:
    return CommandWaiter(inbox, CommandPolicy(timeout_s=timeout_s))  # type: ignore[arg-type]


def test_a_flood_of_future_commands_neither_delays_nor_replaces_the_awaited_one():
    inbox = ScriptedInbox([cmd(k) for k in range(8, 10_008)] + [cmd(7, 123.0)])
    stop, gone = CountingEvent(), CountingEvent()
    w = waiter(inbox)
    got = w.wait(7, stop, gone)
    assert got is not None and got.power_w == 123.0
    assert inbox.n_idle == 0 and stop.n_waits == gone.n_waits == 0  # 10 000 drops, no wait
    assert w.gate.counts[Verdict.AHEAD] == 10_000 and w.n_dropped == 10_000


def test_dropped_commands_never_extend_the_wait():
    w = waiter(ScriptedInbox([], forever=cmd(MAX_STEP), until_s=3.0), timeout_s=0.2)
    t0 = time.monotonic()
    assert w.wait(7, threading.Event(), threading.Event()) is None
    assert 0.2 <= time.monotonic() - t0 < 1.0


def test_the_wait_ends_as_soon_as_the_controller_is_gone():
    gone = threading.Event()
    w = waiter(ScriptedInbox([]), timeout_s=5.0)
    threading.Timer(0.05, gone.set).start()
    t0 = time.monotonic()
    assert w.wait(1, threading.Event(), gone) is None
    assert time.monotonic() - t0 < 1.0  # far under the 5 s timeout (a 0.1 s bound failed on a busy CI host)
    w = waiter(ScriptedInbox([cmd(1)]))
    assert w.wait(1, threading.Event(), gone) is None  # gone: not even a queued command applies
