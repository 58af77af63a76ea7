"""The loop's hot path keeps its behaviour: newest state answered and the rest counted, wake-ups,
arrival stamps, the command before its diagnostics and every diagnostics published (no timing
assertions: timings live in benchmarks/bench_loop.py)."""

from __future__ import annotations

import os
import sys
import threading
import time

import pytest

from controller_node.node import POLL_AT, POLL_SPAN, PREPARE_WINDOW, AnswerLoop
from controller_node.registry import make_controller
from controller_node.settings import ControllerSettings
from fe_node.commands import CommandPolicy
from fe_node.freerun import CommandLatch, FreeRunSettings, PlantSample, run_free
from messages import LaserCommand, MeltPoolState, encode
from messages.bus import BusSettings, NodeBus
from messages.topics import LASER_COMMAND, PLANT_STATE, key_expr


def state(run_id: str, step: int) -> MeltPoolState:
    return MeltPoolState(run_id=run_id, step=step, time_s=step * 50e-6, laser_x_mm=0.0, laser_y_mm=0.0,
                         scan_dir_x=1.0, scan_dir_y=0.0, track=0, area_mm2=0.06, t_ahead_k=300.0, power_w=250.0,
                         speed_mm_s=800.0)


def wait_for(predicate, timeout_s: float = 5.0) -> None:
    deadline = time.monotonic() + timeout_s
    while not predicate():
        assert time.monotonic() < deadline, "condition not met in time"
        time.sleep(0.01)


def test_newest_inbox_returns_the_newest_valid_state_and_counts_the_others(hub, run_id):
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.newest_inbox(PLANT_STATE)
        raw = bus.session.declare_publisher(key_expr(run_id, PLANT_STATE))
        pub = bus.publisher(PLANT_STATE)
        for step in (1, 2):
            pub.put(state(run_id, step))
        raw.put(b"garbage")
        raw.put(encode(state("another-run", 7)))
        pub.put(state(run_id, 3))
        time.sleep(0.3)  # everything queued before the read
        newest, skipped = box.newest()
        assert newest == state(run_id, 3) and skipped == 2
        assert box.n_invalid == 2 and "does not match" in box.last_error
        assert box.newest(block=False) == (None, 0)  # nothing left; returns at once
        raw.undeclare()


def test_polled_inbox_takes_what_arrived_in_order_and_counts_the_invalid(hub, run_id):
    def command(step):
        return LaserCommand(run_id=run_id, step=step, time_s=0.0, power_w=200.0, speed_mm_s=800.0, controller="t")

    with NodeBus("plant", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.polled_inbox(LASER_COMMAND)
        assert box.get() is None  # nothing yet, and no wait
        raw = bus.session.declare_publisher(key_expr(run_id, LASER_COMMAND))
        pub = bus.publisher(LASER_COMMAND)
        pub.put(command(1))
        raw.put(b"garbage")
        pub.put(command(2))
        time.sleep(0.3)
        before = time.monotonic()
        assert list(box.drain()) == [command(1), command(2)]
        assert box.n_invalid == 1 and box.received_t >= before  # stamped when taken
        with pytest.raises(TypeError):
            box.get(timeout=0.1)


def test_a_closed_inbox_keeps_what_arrived_and_receives_nothing_more(hub, run_id):
    """NodeBus.close_inbox undeclares the subscriber: a callback inbox still holds what came before
    (a plant switching inboxes reads it after), the session no longer lists it, nothing new arrives."""
    def command(step):
        return LaserCommand(run_id=run_id, step=step, time_s=0.0, power_w=200.0, speed_mm_s=800.0, controller="t")

    with NodeBus("plant", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box, channel = bus.inbox(LASER_COMMAND), bus.polled_inbox(LASER_COMMAND)
        pub = bus.publisher(LASER_COMMAND)
        pub.put(command(1))
        time.sleep(0.3)
        bus.close_inbox(box)
        bus.close_inbox(channel)
        assert box.subscriber not in bus._declared and channel.subscriber not in bus._declared
        pub.put(command(2))
        time.sleep(0.3)
        assert list(box.drain()) == [command(1)]


def test_newest_inbox_wakes_a_blocked_reader_without_counting_anything(hub, run_id):
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.newest_inbox(PLANT_STATE)
        got = []
        reader = threading.Thread(target=lambda: got.append(box.newest()), daemon=True)
        reader.start()
        time.sleep(0.2)
        assert reader.is_alive()  # blocked: nothing arrived
        box.wake()
        reader.join(5)
        assert not reader.is_alive() and got == [(None, 0)] and box.n_invalid == 0
        bus.publisher(PLANT_STATE).put(state(run_id, 5))  # still receives afterwards
        wait_for(lambda: box.newest(block=False)[0] is not None)


def test_newest_inbox_busy_waiting_answers_and_wakes_like_the_blocking_read(hub, run_id):
    """--busy-wait: the reader polls zenoh's channel; a state and a wake end the wait as in recv."""
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.newest_inbox(PLANT_STATE)

        class Polled:  # the channel, without the sleeping recv
            def __init__(self, channel):
                self.try_recv = channel.try_recv

            def recv(self):
                raise AssertionError("a busy wait must not sleep in recv")

        box.subscriber = Polled(box.subscriber)
        got = []
        reader = threading.Thread(target=lambda: [got.append(box.newest(busy=True)) for _ in range(2)], daemon=True)
        reader.start()
        time.sleep(0.2)
        assert reader.is_alive() and not got  # polling: nothing arrived
        bus.publisher(PLANT_STATE).put(state(run_id, 4))
        wait_for(lambda: len(got) == 1)
        assert got[0] == (state(run_id, 4), 0)
        box.wake()
        reader.join(5)
        assert not reader.is_alive() and got[1] == (None, 0) and box.n_invalid == 0


def test_newest_inbox_polls_in_its_window_then_sleeps_in_zenoh(hub, run_id):
    """poll=(start, end): nothing is read before start; a state in the window is taken by polling
    (no recv); after end the reader sleeps in zenoh's recv."""
    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.newest_inbox(PLANT_STATE)
        channel = box.subscriber
        recvs = []

        class Counted:  # the channel, counting the sleeping reads
            try_recv = channel.try_recv

            def recv(self):
                recvs.append(time.monotonic())
                return channel.recv()

        box.subscriber = Counted()
        pub = bus.publisher(PLANT_STATE)
        pub.put(state(run_id, 1))
        time.sleep(0.3)  # arrived, queued
        start = time.monotonic() + 0.3
        assert box.newest(poll=(start, start + 1.0)) == (state(run_id, 1), 0)
        assert time.monotonic() >= start and not recvs  # held until the window opened, then polled
        assert box.queued  # it was waiting when the window opened

        got = []
        now = time.monotonic()
        reader = threading.Thread(target=lambda: got.append(box.newest(poll=(now, now + 0.5))), daemon=True)
        reader.start()
        time.sleep(0.2)
        pub.put(state(run_id, 2))  # inside the window
        wait_for(lambda: got)
        assert got == [(state(run_id, 2), 0)] and not recvs and not box.queued

        got.clear()
        now = time.monotonic()
        reader = threading.Thread(target=lambda: got.append(box.newest(poll=(now, now + 0.2))), daemon=True)
        reader.start()
        wait_for(lambda: recvs)  # the window closed with nothing: asleep in zenoh
        assert recvs[0] >= now + 0.2 and not got
        pub.put(state(run_id, 3))
        wait_for(lambda: got)
        assert got == [(state(run_id, 3), 0)] and not box.queued


@pytest.mark.parametrize("wait", ["busy", "window"])
def test_newest_inbox_gives_up_its_core_after_each_look(hub, run_id, monkeypatch, wait):
    """Polling (``--busy-wait`` or in the window) yields the core between looks at the channel:
    another thread on that core, e.g. the plant's, is not kept waiting for the poller's time slice."""
    import messages.bus as bus_module

    with NodeBus("controller", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.newest_inbox(PLANT_STATE)
        looks, yields = [], []
        channel = box.subscriber

        class Looked:
            def try_recv(self):
                looks.append(None)
                return channel.try_recv()

            def recv(self):
                return channel.recv()

        box.subscriber = Looked()
        monkeypatch.setattr(bus_module.os, "sched_yield", lambda: yields.append(None))
        now = time.monotonic()
        poll = (now, now + 0.3) if wait == "window" else None
        reader = threading.Thread(target=lambda: box.newest(busy=wait == "busy", poll=poll), daemon=True)
        reader.start()
        time.sleep(0.2)
        bus.publisher(PLANT_STATE).put(state(run_id, 1))
        reader.join(5)
        assert not reader.is_alive()
        assert len(looks) > 10 and len(yields) >= len(looks) - 2  # a yield between any two looks


class _Spare:
    """A :class:`~messages.spare_core.SpareCore` stand-in with a fixed answer."""

    def __init__(self, spare: bool):
        self.answer = spare

    def spare(self, t: float) -> bool:
        return self.answer


@pytest.mark.parametrize(("interval_s", "n", "busy", "spare", "polls"), [
    (0.5e-3, 8, False, False, "ahead"),   # a 2 kHz sensor, a busy machine: poll ahead of the next state
    (0.5e-3, 8, False, True, "at once"),  # ... a core to spare: poll from the answer on (keep the core)
    (0.5e-3, 7, False, True, None),       # not yet known to be steady (fewer than PREPARE_WINDOW intervals)
    (2.5e-3, 8, False, True, None),       # slower than PREPARE_LATE_MIN_S (e.g. lockstep FE): sleep in zenoh
    (0.5e-3, 8, True, True, None),        # --busy-wait polls all the time anyway
])
def test_answer_loop_polls_only_for_a_steady_fast_sensor(interval_s, n, busy, spare, polls):
    settings = ControllerSettings(set_point_m2=0.063e-6)
    loop = AnswerLoop(_Bus(), None, settings, None, None, None, done=lambda: True, busy_wait=busy,
                      spare=_Spare(spare))
    times = [10.0 + k * interval_s + (0.1 * interval_s if k % 2 else 0.0) for k in range(n + 1)]
    for t in times:
        loop._arrived(t)
    window = loop.poll_window()
    shortest = min(b - a for a, b in zip(times, times[1:]))
    if polls == "ahead":
        assert window == pytest.approx((times[-1] + POLL_AT * shortest, times[-1] + POLL_SPAN * shortest))
    elif polls == "at once":
        assert window == pytest.approx((times[-1], times[-1] + POLL_SPAN * shortest))
    else:
        assert window is None
    assert loop.n_kept_core == (polls == "at once")


@pytest.mark.parametrize("late", [0.3, 0.5, 0.9])
def test_poll_windows_keep_to_a_steady_sensor_when_the_reader_wakes_late(late):
    """A reader that wakes ``late`` periods after the window opened finds the state waiting; the
    state counts as arriving on schedule, so the windows do not fall further and further behind."""
    period = 0.5e-3
    loop = AnswerLoop(_Bus(), None, ControllerSettings(set_point_m2=0.063e-6), None, None, None, done=lambda: True,
                      spare=_Spare(False))
    for k in range(PREPARE_WINDOW + 1):
        loop._arrived(10.0 + k * period)
    lags = []
    for k in range(PREPARE_WINDOW + 1, PREPARE_WINDOW + 200):
        arrival = 10.0 + k * period
        start, end = loop.poll_window()
        assert start < end
        woken = start + late * period
        queued = woken >= arrival
        taken = woken if queued else arrival  # waiting at the window's opening, else caught polling
        lags.append(taken - arrival)
        loop._arrived(taken, queued)
    assert max(lags) <= max(0.0, late - (1.0 - POLL_AT)) * period + 1e-12  # a steady lag, no drift


def test_inbox_stamps_arrival_not_reading(hub, run_id):
    with NodeBus("plant", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        box = bus.inbox(LASER_COMMAND)
        before = time.monotonic()
        handed = bus.publisher(LASER_COMMAND).put(
            LaserCommand(run_id=run_id, step=1, time_s=0.0, power_w=200.0, speed_mm_s=800.0, controller="t"))
        assert before <= handed <= time.monotonic()  # put returns when it handed the message to zenoh
        time.sleep(0.5)
        read_at = time.monotonic()
        assert box.get(timeout=5) is not None
        assert handed <= box.received_t < read_at - 0.3  # when it arrived, not when it was read


class _States:
    """A NewestInbox stand-in: hands out scripted states, then sets ``stop``."""

    queued = False

    def __init__(self, states, stop, stop_with_last=False):
        self.states, self.stop, self.n_invalid, self.stop_with_last = list(states), stop, 0, stop_with_last
        self.polls = []

    def newest(self, block=True, busy=False, poll=None):
        self.polls.append(poll)
        if not self.states:
            if block:
                self.stop.set()
            return None, 0
        if self.stop_with_last and len(self.states) == 1:
            self.stop.set()  # the run stops while the last state is being answered
        return self.states.pop(0), 0


class _Publisher:
    def __init__(self, log):
        self.log = log

    def put(self, msg):
        self.log.append(msg)
        return time.monotonic()


class _Bus:
    run_id = "t"

    def log(self, level, text, time_s=0.0):
        pass


@pytest.mark.parametrize("stop_with_last", [False, True])
def test_answer_loop_publishes_each_command_then_its_diagnostics_before_the_next_state(stop_with_last):
    stop = threading.Event()
    sent: list = []
    settings = ControllerSettings(set_point_m2=0.063e-6)
    states = _States([state("t", k) for k in range(5)], stop, stop_with_last)
    loop = AnswerLoop(_Bus(), make_controller("pid", settings), settings, states, _Publisher(sent), _Publisher(sent),
                      done=stop.is_set)
    loop.serve()
    assert loop.error is None
    kinds = [(type(m).__name__, m.step) for m in sent]
    commands = [s for k, s in kinds if k == "LaserCommand"]
    diagnostics = [s for k, s in kinds if k == "ControllerDiagnostics"]
    assert commands == diagnostics == [1, 2, 3, 4, 5]
    assert kinds == [(kind, step) for step in commands for kind in ("LaserCommand", "ControllerDiagnostics")]


def test_answer_loop_reads_fast_states_in_its_poll_window():
    """States that come fast (here: at once) are read with a poll window once the window of
    intervals is full; before that the loop sleeps in zenoh."""
    stop = threading.Event()
    settings = ControllerSettings(set_point_m2=0.063e-6)
    states = _States([state("t", k) for k in range(12)], stop)
    loop = AnswerLoop(_Bus(), make_controller("pid", settings), settings, states, _Publisher([]), _Publisher([]),
                      done=stop.is_set)
    loop.serve()
    assert loop.error is None
    assert states.polls[:PREPARE_WINDOW + 1] == [None] * (PREPARE_WINDOW + 1)
    assert all(p is not None and p[0] < p[1] for p in states.polls[PREPARE_WINDOW + 1:])


class _Preparing:
    """A controller that logs its updates and preparations into the publishers' log."""

    name = "logging"

    def __init__(self, inner, log):
        self.inner, self.log = inner, log

    def update(self, measurement):
        self.log.append(("update", measurement.step))
        return self.inner.update(measurement)

    def prepare(self):
        self.log.append(("prepare", None))


def test_answer_loop_prepares_the_next_update_after_each_command():
    """The preparation phase runs after a state's command is published, before the next state."""
    stop = threading.Event()
    sent: list = []
    settings = ControllerSettings(set_point_m2=0.063e-6)
    states = _States([state("t", k) for k in range(4)], stop, True)
    loop = AnswerLoop(_Bus(), _Preparing(make_controller("pid", settings), sent), settings, states, _Publisher(sent),
                      _Publisher(sent), done=stop.is_set)
    loop.serve()
    order = [m if isinstance(m, tuple) else (type(m).__name__, m.step) for m in sent]
    order = [o for o in order if o[0] != "ControllerDiagnostics"]
    assert order == [entry for k in range(4) for entry in (("update", k), ("LaserCommand", k + 1), ("prepare", None))]


class _PacedStates:
    """A NewestInbox stand-in that releases one scripted state every ``period_s`` and can be woken;
    ``taken`` holds the monotonic time [s] at which the loop took each state."""

    queued = False

    def __init__(self, states, period_s, stop, release_s=None):
        self.states, self.period_s, self.stop, self.n_invalid = list(states), period_s, stop, 0
        self.release_s = release_s or [s.step * period_s for s in self.states]
        self.start, self.woken, self.taken = time.monotonic(), threading.Event(), []

    def newest(self, block=True, busy=False, poll=None):
        while self.states:
            due = self.start + self.release_s[len(self.release_s) - len(self.states)]
            if (now := time.monotonic()) >= due:
                self.taken.append(now)
                return self.states.pop(0), 0
            if not block or self.woken.wait(due - time.monotonic()):
                self.woken.clear()
                return None, 0
        self.stop.set()
        return None, 0

    def wake(self):
        self.woken.set()


def test_answer_loop_prepares_late_when_states_come_far_apart():
    """States 50 ms apart: once the last PREPARE_WINDOW intervals are known, the preparation runs
    about PREPARE_AT of the shortest of those intervals after each state arrived (a timer wakes the
    answering thread), still before the next state; before that, right after the command. Both are
    measured from when the loop took the state, against the intervals it saw: a loaded host
    delays some states and shortens the interval after them. (At 20 ms apart, a 14 ms stall of
    the shared host once made an immediate preparation look late.)"""
    from controller_node.node import PREPARE_AT, PREPARE_WINDOW

    stop, log = threading.Event(), []
    settings = ControllerSettings(set_point_m2=0.063e-6)
    period, n = 0.05, PREPARE_WINDOW + 5
    states = _PacedStates([state("t", k) for k in range(n)], period, stop)

    class Timed(_Preparing):
        def update(self, measurement):
            self.log.append(("update", measurement.step, time.monotonic()))
            return self.inner.update(measurement)

        def prepare(self):
            self.log.append(("prepare", None, time.monotonic()))

    loop = AnswerLoop(_Bus(), Timed(make_controller("pid", settings), log), settings, states, _Publisher([]),
                      _Publisher([]), done=stop.is_set)
    loop.serve()
    assert loop.error is None
    kinds = [entry[0] for entry in log]
    assert kinds == ["update", "prepare"] * (n - 1) + ["update"] or kinds == ["update", "prepare"] * n
    taken = states.taken
    for k in range(n - 1):
        (_, step, answered), (_, _, prepared), (_, _, next_update) = log[2 * k], log[2 * k + 1], log[2 * k + 2]
        assert step == k and prepared < next_update
        if k <= PREPARE_WINDOW - 1:   # fewer intervals known than the window: at once, before the next state
            assert prepared - answered < 0.3 * period
        else:                         # late, but before the next state
            shortest = min(b - a for a, b in zip(taken[k - PREPARE_WINDOW:k], taken[k - PREPARE_WINDOW + 1:k + 1]))
            assert prepared - taken[k] > 0.5 * PREPARE_AT * shortest, (k, shortest)


LOOK_S = 20e-6
"""Virtual time one look at an inbox and the yield of the core after it take [s]."""


class VirtualClock:
    """``time`` of :mod:`fe_node.freerun` and of the stand-ins below, and ``os.sched_yield``: a sleep
    advances ``monotonic`` at once (no wall time passes), a yield by :data:`LOOK_S`; so a free-running
    plant keeps its schedule exactly and its misses and round trips do not depend on the machine's load."""

    def __init__(self) -> None:
        self.now, self.yields = 100.0, 0

    def monotonic(self) -> float:
        return self.now

    def time(self) -> float:
        return self.now

    def sleep(self, seconds: float) -> None:
        self.now += max(seconds, 0.0)

    def sched_yield(self) -> None:
        self.yields += 1
        self.now += LOOK_S


@pytest.fixture
def clock(monkeypatch) -> VirtualClock:
    import fe_node.freerun as freerun

    virtual = VirtualClock()
    monkeypatch.setattr(freerun, "time", virtual)
    monkeypatch.setattr(sys.modules[__name__], "time", virtual)  # the stand-ins' stamps
    monkeypatch.setattr(os, "sched_yield", virtual.sched_yield)
    return virtual


class _Plant:
    def initial(self) -> PlantSample:
        return PlantSample(0.06e-6, 300.0, 0.0, 0.0, (1.0, 0.0), 0)

    def step(self, power_w, speed_m_s, dt_s) -> PlantSample:
        return self.initial()


class _Commands:
    """An Inbox stand-in: the command answering each published state arrived 100 µs after it."""

    def __init__(self, published):
        self.published, self.n_invalid, self.received_t, self._given = published, 0, 0.0, 0

    def drain(self):
        while self._given < len(self.published):
            step, t = self.published[self._given]
            self._given += 1
            self.received_t = t + 100e-6
            yield LaserCommand(run_id="t", step=step + 1, time_s=0.0, power_w=200.0, speed_mm_s=800.0,
                               controller="t")


class _PlantBus:
    run_id = "t"
    routed = False

    def __init__(self):
        self.published: list[tuple[int, float]] = []
        self.commands = _Commands(self.published)
        self.logs: list[str] = []

    def publisher(self, topic):
        bus = self

        class _Pub:
            def put(self, msg):
                t = time.monotonic()
                if topic is PLANT_STATE:
                    bus.published.append((msg.step, t))
                return t

        return _Pub()

    def inbox(self, topic):
        return self.commands

    def log(self, level, text, time_s=0.0):
        self.logs.append(text)


def test_free_running_plant_times_commands_from_their_arrival_not_from_its_tick(clock):
    bus = _PlantBus()
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    stats = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=200.0, max_steps=20), threading.Event(),
                     "surrogate", threading.Event())
    assert stats.steps == 20 and stats.misses == 0 and len(stats.rtt_s) == len(bus.published) == 21
    assert all(r == pytest.approx(100e-6, abs=1e-9) for r in stats.rtt_s)  # not up to the 5 ms tick period


class _ArrivingCommands:
    """zenoh's channel or a callback inbox, stand-in: the command answering each published state
    arrives ``delay_s`` after the state's publish, in the inboxes declared then. The channel stamps
    a command when taken, and cannot be read once closed; a callback inbox stamps on arrival."""

    def __init__(self, published, delay_s, callback=False):
        self.published, self.delay_s, self.callback = published, delay_s, callback
        self.n_invalid, self.received_t, self._given = 0, 0.0, 0
        self.looks, self.look_times = 0, []
        self.declared_t, self.closed_t = time.monotonic(), float("inf")

    def drain(self):
        assert self.callback or self.closed_t == float("inf"), "a closed channel cannot be read"
        self.looks += 1
        self.look_times.append(time.monotonic())
        now = time.monotonic()
        while self._given < len(self.published):
            step, t = self.published[self._given]
            arrival = t + self.delay_s
            if arrival > min(now, self.closed_t):
                return
            self._given += 1
            if arrival >= self.declared_t:
                self.received_t = arrival if self.callback else time.monotonic()
                yield LaserCommand(run_id="t", step=step + 1, time_s=0.0, power_w=200.0, speed_mm_s=800.0,
                                   controller="t")


class _FastPlantBus(_PlantBus):
    """A fast plant's bus: the channels and callback inboxes it declared and closed."""

    def __init__(self, delay_s):
        super().__init__()
        self.delay_s, self.channels, self.callbacks = delay_s, [], []

    def polled_inbox(self, topic):
        assert topic is LASER_COMMAND
        self.channels.append(_ArrivingCommands(self.published, self.delay_s))
        return self.channels[-1]

    def inbox(self, topic):
        assert topic is LASER_COMMAND
        self.callbacks.append(_ArrivingCommands(self.published, self.delay_s, callback=True))
        return self.callbacks[-1]

    def close_inbox(self, box):
        assert box.closed_t == float("inf")
        box.closed_t = time.monotonic()


class _NoSpareCore:
    """A machine whose cores are all busy."""

    def spare(self, t):
        return False


class _SpareCore:
    """A machine with a core to spare."""

    def spare(self, t):
        return True


@pytest.mark.parametrize("case", ["on time", "controller gone", "late", "no spare core"])
def test_a_fast_plant_polls_for_its_command_while_its_controller_keeps_up(case, monkeypatch, clock):
    """Faster than POLL_MAX_PERIOD_S, the plant takes each command as it comes (round trip ~ the
    command's delay, not the period) by polling zenoh's channel from POLL_AT of the period. With its
    controller gone, or no core to spare, it switches at once to a callback inbox (stamped on
    arrival) read at its ticks only; with commands coming after the tick, within ~20 steps."""
    import fe_node.freerun as freerun
    from fe_node.freerun import POLL_AT, POLL_MAX_PERIOD_S

    rate_hz = 600.0
    delay_s = 1.3 / rate_hz if case == "late" else 0.5e-3
    assert 1.0 / rate_hz < POLL_MAX_PERIOD_S and POLL_AT / rate_hz < delay_s
    bus = _FastPlantBus(delay_s)
    gone = threading.Event()
    if case == "controller gone":
        gone.set()
    monkeypatch.setattr(freerun, "SpareCore", _NoSpareCore if case == "no spare core" else _SpareCore)
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    stats = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=rate_hz, max_steps=60), threading.Event(),
                     "surrogate", gone)
    rtt = sorted(stats.rtt_s)[len(stats.rtt_s) // 2]
    [channel] = bus.channels
    if case in ("controller gone", "no spare core"):
        assert len(bus.callbacks) == 1 and bus.callbacks[0].looks <= stats.steps + 2 and not clock.yields  # ticks only
        assert channel.looks == 1 and channel.closed_t < bus.published[1][1]  # read once, closed at the start
        assert rtt == pytest.approx(delay_s, abs=1e-9) and stats.misses <= 2  # stamped on arrival
    elif case == "late":
        assert stats.misses >= stats.steps - 3  # (a tick late by 0.3 period would take one in time)
        assert len(bus.callbacks) == 1 and channel.closed_t < bus.published[30][1]
        assert bus.callbacks[0].looks <= stats.steps + 2
    else:
        assert not bus.callbacks and delay_s <= rtt < delay_s + 0.3 / rate_hz and channel.looks > stats.steps
        assert clock.yields >= channel.looks - 2 * stats.steps - 2  # a yield after each look in vain
    assert len(stats.rtt_s) >= stats.steps - 2 and latch.gate.n_stale == 0  # each command taken once


def test_a_fast_plant_behind_a_router_never_polls(monkeypatch, clock):
    """A client of a router (launch.py's nodes): every command crosses the router, whose threads
    need the core a poller would keep; the plant takes its commands at its ticks from a callback
    inbox, a core to spare or not."""
    import fe_node.freerun as freerun

    monkeypatch.setattr(freerun, "SpareCore", _SpareCore)
    bus = _FastPlantBus(0.5e-3)
    bus.routed = True
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    stats = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=600.0, max_steps=30), threading.Event(),
                     "surrogate", threading.Event())
    assert not bus.channels and len(bus.callbacks) == 1 and not clock.yields and stats.polled == 0
    assert bus.callbacks[0].looks <= stats.steps + 2 and len(stats.rtt_s) >= stats.steps - 2
    assert any("client of a router" in text for text in bus.logs)  # said, not silently ignored


def test_a_fast_plant_switching_inboxes_takes_every_command_once(monkeypatch, clock):
    """A core to spare, then none, then one again (every 15 steps): the plant declares a callback
    inbox or a channel, then closes the other, at each switch, and every command is applied
    exactly once (none lost at a switch, no copy counted as stale)."""
    import fe_node.freerun as freerun

    class Alternating:
        calls = 0

        def spare(self, t):
            Alternating.calls += 1
            return (Alternating.calls - 1) // 15 % 2 == 0

    monkeypatch.setattr(freerun, "SpareCore", Alternating)
    bus = _FastPlantBus(0.5e-3)
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    stats = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=600.0, max_steps=75), threading.Event(),
                     "surrogate", threading.Event())
    assert len(bus.callbacks) == 2 and len(bus.channels) == 3
    assert [box.closed_t < float("inf") for box in bus.channels + bus.callbacks] == [True, True, False, True, True]
    assert latch.gate.n_stale == 0 and latch.gate.n_dropped == 0
    assert latch.newest_step >= stats.steps - 1 and len(stats.rtt_s) == latch.newest_step  # none lost, none twice
    assert stats.misses <= 4


def test_a_plant_without_poll_commands_takes_its_commands_at_its_ticks(clock):
    """``--no-poll-commands``: the callback inbox (commands stamped on arrival), looked at once per tick."""
    bus = _PlantBus()
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    stats = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=1000.0, max_steps=20, poll_commands=False),
                     threading.Event(), "surrogate", threading.Event())
    assert stats.steps == 20 and stats.misses == 0
    assert all(r == pytest.approx(100e-6, abs=1e-9) for r in stats.rtt_s)


def test_steady_misses_leave_out_the_first_warmup_steps(clock):
    """``steady_miss_pct`` counts the misses after the first WARMUP_STEPS; ``deadline_miss_pct`` all."""
    from fe_node.freerun import WARMUP_STEPS, FreeRunStats

    stats = FreeRunStats(WARMUP_STEPS + 800, 1.0, 30, 0, 0, 0, 0, 0, (1e-4,), warmup_misses=20)
    summary = stats.summary()
    assert summary["deadline_miss_pct"] == pytest.approx(100.0 * 30 / (WARMUP_STEPS + 800))
    assert summary["steady_miss_pct"] == pytest.approx(100.0 * 10 / 800)
    assert FreeRunStats(WARMUP_STEPS, 1.0, 3, 0, 0, 0, 0, 0, (), 3).summary()["steady_miss_pct"] is None

    bus = _PlantBus()  # every command two periods late: every step misses, warm-up or not
    bus.commands = _ArrivingCommands(bus.published, 2.0 / 2000.0)
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    run = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=2000.0, max_steps=WARMUP_STEPS + 100,
                                                         poll_commands=False),
                   threading.Event(), "surrogate", threading.Event())
    assert WARMUP_STEPS - 5 <= run.warmup_misses <= WARMUP_STEPS and run.misses >= WARMUP_STEPS + 95
    assert run.summary()["steady_miss_pct"] >= 95.0


def test_a_state_before_the_preparations_timer_is_prepared_for_on_its_path():
    """A state that comes before the timer gets the preparation first (so every state is answered
    as if prepared right after the command: the run does not depend on timing), and the time
    spent preparing is in its diagnostics' solve_time_us."""
    from controller_node.node import PREPARE_WINDOW

    stop, log, diagnostics = threading.Event(), [], []
    settings = ControllerSettings(set_point_m2=0.063e-6)
    n, period = PREPARE_WINDOW + 3, 0.02
    release = [k * period for k in range(n - 1)] + [(n - 2) * period + 0.004]   # the last one early

    on_path_s = 0.05  # far above an update's time, however loaded the machine

    class Slow(_Preparing):
        def prepare(self):
            self.log.append(("prepare", None))
            time.sleep(on_path_s if self.log[-2] == ("update", n - 2) else 0.003)  # the one on the last path

    states = _PacedStates([state("t", k) for k in range(n)], period, stop, release)
    loop = AnswerLoop(_Bus(), Slow(make_controller("pid", settings), log), settings, states, _Publisher([]),
                      _Publisher(diagnostics), done=stop.is_set)
    loop.serve()
    assert loop.error is None
    last = log.index(("update", n - 1))
    assert log[last - 2:last + 1] == [("update", n - 2), ("prepare", None), ("update", n - 1)]
    times = {d.step: d.solve_time_us for d in diagnostics}
    assert times[n] >= on_path_s * 1e6 and times[n - 1] < on_path_s * 1e6


class _Queued:
    """An inbox stand-in holding what was put in it (arrival times given); a closed channel cannot be read."""

    def __init__(self, channel):
        self.queue, self.n_invalid, self.received_t, self.channel, self.open = [], 0, 0.0, channel, True

    def drain(self):
        assert self.open or not self.channel, "a closed channel cannot be read"
        while self.queue:
            cmd, self.received_t = self.queue.pop(0)
            yield cmd


def test_a_command_in_both_inboxes_at_a_switch_is_taken_once():
    """A command that came while the plant switched its inbox is in the old one and the new one:
    it is applied once (from the old one, with its arrival time), its copy ignored, not counted as
    stale; a channel is read before it is closed."""
    from fe_node.freerun import CommandInboxes

    class Bus:
        def __init__(self):
            self.boxes = []

        def polled_inbox(self, topic):
            self.boxes.append(_Queued(channel=True))
            return self.boxes[-1]

        def inbox(self, topic):
            self.boxes.append(_Queued(channel=False))
            return self.boxes[-1]

        def close_inbox(self, box):
            box.open = False

    bus = Bus()
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    for step in range(4):
        latch.published(step, 0.01 * step)
    inboxes = CommandInboxes(bus, fast=True)
    commands = [LaserCommand(run_id="t", step=k, time_s=0.0, power_w=200.0 + k, speed_mm_s=800.0, controller="t")
                for k in (1, 2, 3)]
    [channel] = bus.boxes
    channel.queue.append((commands[0], 0.001))
    callback = inboxes.read(False, latch)   # to the callback inbox: the channel read, then closed
    assert latch.newest_step == 1 and not channel.open and callback is bus.boxes[1]
    for box, t in ((channel, 0.0115), (callback, 0.011)):
        box.queue.append((commands[1], t))
    for cmd in callback.drain():
        latch.offer(cmd, callback.received_t)
    assert latch.newest_step == 2
    callback.queue.append((commands[2], 0.021))
    channel2 = inboxes.read(True, latch)    # back to a channel: the callback inbox read, then closed
    channel2.queue.append((commands[2], 0.0215))
    assert not callback.open and latch.newest_step == 3 and latch.rtt_s[-1] == pytest.approx(0.001)
    for cmd in channel2.drain():            # the copy
        latch.offer(cmd, channel2.received_t)
    assert latch.newest_step == 3 and len(latch.rtt_s) == 3 and latch.gate.n_stale == 0


@pytest.mark.parametrize("declare", ["inbox", "publisher"])
def test_declaring_a_publisher_or_an_inbox_builds_its_topics_decoder(declare):
    """The validating decoder (slow to build: msgspec compiles the type) is made when a node declares
    the topic, not by the first message on the loop's hot path (e.g. the plant's first diagnostics)."""
    from messages import codec
    from messages.bus import Inbox, TopicPublisher
    from messages.topics import PLANT_DIAGNOSTICS

    codec._decoder.cache_clear()
    if declare == "inbox":
        Inbox(PLANT_DIAGNOSTICS)
    else:
        TopicPublisher(None, PLANT_DIAGNOSTICS, None)
    assert codec._decoder.cache_info().currsize == 1
    codec._decoder(PLANT_DIAGNOSTICS.type)
    assert codec._decoder.cache_info().hits == 1  # the one built at the declaration


def test_miss_bursts_count_runs_of_consecutive_misses(clock):
    """A run of misses counts once, however long; the longest is kept (a stall of the machine)."""
    from fe_node.freerun import MissBursts

    bursts = MissBursts()
    for missed in [False, True, False, True, True, True, False, False, True, True]:
        bursts.add(missed)
    assert (bursts.count, bursts.longest) == (3, 3)

    bus = _PlantBus()  # every command two periods late: one run of every step after the first
    bus.commands = _ArrivingCommands(bus.published, 2.0 / 2000.0)
    latch = CommandLatch(CommandPolicy(timeout_s=1.0), power_w=250.0, speed_m_s=0.8)
    summary = run_free(bus, _Plant(), latch, FreeRunSettings(rate_hz=2000.0, max_steps=100, poll_commands=False),
                       threading.Event(), "surrogate", threading.Event()).summary()
    assert summary["miss_bursts"] <= 2 and summary["longest_miss_burst_steps"] >= 95
