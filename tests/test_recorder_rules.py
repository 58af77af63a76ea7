"""Recorder rules in-process, no zenoh: forged messages of other runs or impossible steps, forged
end events, two-way reconciliation, completeness only by the run's own end."""

from __future__ import annotations

import json
import threading
import time
from collections import Counter
from types import SimpleNamespace

import msgspec
import pytest

from messages.cli import UsageError
from messages.codec import encode
from messages.recorder import (
    Admission,
    Intake,
    McapRecorder,
    RunTracker,
    parse_roles,
    reconcile,
    record,
)
from messages.recording import is_complete, metadata, read_messages
from messages.topics import LASER_COMMAND, LOG, PLANT_STATE, RUN_EVENTS, key_expr, message_node
from messages.types import MAX_STEPS_AHEAD, RunEvent
from tests.samples import sample_messages

RUN = "run1"
STATE = dict(sample_messages(RUN))[PLANT_STATE]
COMMAND = dict(sample_messages(RUN))[LASER_COMMAND]


def state(step: int, run_id: str = RUN):
    return msgspec.structs.replace(STATE, step=step, run_id=run_id)


def command(step: int, run_id: str = RUN):
    return msgspec.structs.replace(COMMAND, step=step, run_id=run_id)


def event(node: str, kind: str, published: dict | None = None, run_id: str = RUN) -> RunEvent:
    return RunEvent(run_id=run_id, node=node, event=kind, time_s=0.0, published=published or {})


def key(topic, msg, run_id: str = RUN) -> str:
    """The key ``msg`` is published under (per-node topics: under the node it names)."""
    return key_expr(run_id, topic, message_node(msg) or "*")


def sample(topic, msg, key_run: str = RUN) -> tuple[str, bytes, int]:
    return key(topic, msg, key_run), encode(msg), time.time_ns()


# --- admission -----------------------------------------------------------------------------------

def test_admission_drops_other_runs_and_impossible_steps_per_topic():
    gate = Admission(RUN)
    assert gate.reason_to_drop(PLANT_STATE, state(0, run_id="other")) == "other_run"
    assert gate.reason_to_drop(PLANT_STATE, state(MAX_STEPS_AHEAD)) == "step_too_far_ahead"  # reference -1
    assert gate.reason_to_drop(PLANT_STATE, state(2**31 - 1)) == "step_too_far_ahead"
    assert gate.reason_to_drop(PLANT_STATE, state(0)) is None
    assert gate.reason_to_drop(PLANT_STATE, state(0)) == "step_not_newer"
    assert gate.reason_to_drop(PLANT_STATE, state(MAX_STEPS_AHEAD)) is None  # exactly the window
    assert gate.reason_to_drop(PLANT_STATE, state(MAX_STEPS_AHEAD - 1)) == "step_not_newer"
    assert gate.reason_to_drop(LASER_COMMAND, command(1)) is None  # each topic has its own last step
    assert gate.reason_to_drop(LASER_COMMAND, command(1 + MAX_STEPS_AHEAD + 1)) == "step_too_far_ahead"
    assert gate.reason_to_drop(RUN_EVENTS, event("plant", "start", run_id="other")) == "other_run"
    log = dict(sample_messages(RUN))[LOG]
    assert gate.reason_to_drop(LOG, log) is None  # no run id, no step


def test_intake_records_only_admissible_messages_and_counts_each_reason():
    intake = Intake(RUN, RunTracker(("plant",), drain_s=0.5))
    written = []
    for item in [
        sample(PLANT_STATE, state(0)),
        sample(PLANT_STATE, state(1, run_id="other")),  # another run's message under this run's key
        sample(PLANT_STATE, state(1), key_run="other"),  # another run's key entirely
        sample(PLANT_STATE, state(1)),
        sample(PLANT_STATE, state(1)),  # duplicate
        sample(PLANT_STATE, state(2**31 - 1)),  # the value that once crashed the controller
        sample(PLANT_STATE, state(1 + MAX_STEPS_AHEAD + 1)),
        sample(PLANT_STATE, state(2)),
        (key_expr(RUN, PLANT_STATE), b'{"step": 1}', time.time_ns()),  # schema-invalid
        sample(LOG, msgspec.structs.replace(dict(sample_messages(RUN))[LOG], name="recorder")),
        (key_expr(RUN, RUN_EVENTS, "plant"), encode(event("controller", "start")), time.time_ns()),
    ]:
        written += intake.receive(*item)
    assert [m.msg.step for m in written] == [0, 1, 2]
    assert intake.dropped == Counter(other_run=1, unknown_key=1, step_not_newer=1, step_too_far_ahead=2, invalid=1,
                                     claims_recorder=1, node_mismatch=1)
    assert intake.from_nodes == Counter({"plant/state": 3})
    assert len(intake.warnings) == 8


# --- life cycle ----------------------------------------------------------------------------------

def test_end_counts_only_with_the_node_token_gone_within_the_drain_time():
    tracker = RunTracker(("plant", "controller"), drain_s=1.0)
    assert tracker.on_event(event("evil", "end"), 10.0) == "end_without_start"
    assert tracker.on_event(event("plant", "end"), 10.0) == "end_without_start"  # no start yet
    assert tracker.on_event(event("plant", "start"), 10.0) is None
    assert tracker.on_event(event("plant", "start"), 10.1) == "duplicate_start"
    assert tracker.on_event(event("plant", "end"), 10.8, "forged") == "held"
    assert tracker.on_event(event("plant", "end", {"plant/state": 3}), 11.0, "plant-end") == "held"
    assert tracker.poll(11.4) == ([], [])  # token still there, drain time not over
    assert not tracker.ended
    tracker.gone("plant", 11.6)
    assert tracker.poll(11.6) == (["plant-end"], ["duplicate_end"])  # the end closest to the token going
    assert tracker.published() == Counter({"plant/state": 3})
    assert tracker.on_event(event("plant", "end"), 11.7) == "duplicate_end"
    assert not tracker.all_ended() and tracker.waiting_for() == {"controller"}
    # a forged end of a live node is dropped after the drain time; its real end still counts
    assert tracker.on_event(event("controller", "start"), 10.0) is None
    assert tracker.on_event(event("controller", "end"), 12.0, "forged") == "held"
    assert tracker.poll(13.01) == ([], ["unconfirmed_end"])
    assert tracker.on_event(event("controller", "end"), 20.0, "real") == "held"
    tracker.gone("controller", 19.5)  # the token may go before the end event is taken
    assert tracker.poll(20.0) == (["real"], [])
    assert tracker.all_ended()


def test_end_of_a_node_gone_long_before_is_dropped():
    tracker = RunTracker(("plant",), drain_s=1.0)
    tracker.on_event(event("plant", "start"), 0.0)
    tracker.gone("plant", 1.0)  # crashed
    assert tracker.on_event(event("plant", "end"), 5.0, "late forgery") == "held"
    assert tracker.poll(5.0) == ([], ["unconfirmed_end"])
    assert not tracker.all_ended()


def test_reconcile_finds_missing_and_extra_per_key():
    published = Counter({"plant/state": 10, "run/events/plant": 2})
    recorded = Counter({"plant/state": 12, "run/events/plant": 1, "run/events/helper": 1, "controller/command": 3})
    assert reconcile(published, recorded, lambda key: True) == (
        {"run/events/plant": 1}, {"controller/command": 3, "plant/state": 2, "run/events/helper": 1})
    assert reconcile(published, recorded, lambda key: key != "plant/state") == (
        {"run/events/plant": 1}, {"controller/command": 3, "run/events/helper": 1})


def test_no_extra_is_claimed_while_an_unexpected_node_has_not_reported_and_the_run_is_incomplete():
    tracker = RunTracker(("plant",), drain_s=1.0)
    intake = Intake(RUN, tracker)
    for node in ("plant", "helper"):  # "helper" started but is not expected and never ends
        tracker.on_event(event(node, "start"), 1.0)
        intake.from_nodes[f"run/events/{node}"] += 1
    tracker.on_event(event("plant", "end", {"run/events": 2}), 2.0, "end")
    intake.from_nodes["run/events/plant"] += 1
    tracker.gone("plant", 2.1)
    tracker.poll(2.1)
    assert tracker.all_ended() and tracker.not_ended() == {"helper"}
    intake.from_nodes["log/helper"] += 1
    counts, reason = intake.summary(None)
    assert json.loads(counts["extra"]) == {} and counts["complete"] == "false", (counts, reason)
    assert reason == "no confirmed end of helper"
    tracker.on_event(event("helper", "end", {"run/events": 2, "log": 1}), 3.0, "end")
    tracker.gone("helper", 3.0)
    tracker.poll(3.0)
    intake.from_nodes["run/events/helper"] += 1
    counts, _ = intake.summary(None)
    assert counts["complete"] == "true", counts
    intake.from_nodes["plant/state"] += 1  # now every node reported: a message nobody published is extra
    counts, _ = intake.summary(None)
    assert json.loads(counts["extra"]) == {"plant/state": 1} and counts["complete"] == "false"


def test_roles_decide_whose_counts_a_node_answers_for():
    tracker = RunTracker(("camera",), drain_s=1.0, roles={"camera": ("plant",), "plant": ()})
    assert tracker.owns("camera", PLANT_STATE) and tracker.owns("camera", LOG)
    assert not tracker.owns("plant", PLANT_STATE)  # given no role, whatever its name
    assert tracker.owns("controller", LASER_COMMAND) and not tracker.owns("helper", LASER_COMMAND)  # by name
    claims = event("camera", "end", {"plant/state": 4, "controller/command": 4, "run/events": 2, "nope": 1})
    assert tracker.foreign_claims(claims) == ["controller/command", "nope"]
    for node in ("camera", "plant"):
        tracker.on_event(event(node, "start"), 0.0)
    tracker.on_event(claims, 1.0, "end")
    tracker.gone("camera", 1.0)
    tracker.poll(1.0)
    assert tracker.published() == Counter({"plant/state": 4, "run/events/camera": 2})
    assert tracker.settled("plant/state")  # "plant" has not ended, but it cannot publish plant/state
    assert tracker.settled("run/events/camera") and not tracker.settled("run/events/plant")


@pytest.mark.parametrize("item", ["camera", "camera=laser", "=plant"])
def test_a_bad_role_option_is_a_usage_error(item):
    with pytest.raises(UsageError, match="--role"):
        parse_roles([item])


# --- the whole loop, with a fake bus ------------------------------------------------------------

class FakeStop(threading.Event):
    signal_name: str | None = None

    def stop(self, name: str) -> None:
        self.signal_name = name
        self.set()


class FakeBus:
    """What :func:`record` uses of a NodeBus; ``ready`` plays ``script(bus)`` in a thread.

    If the script fails, or the recording outlives ``WATCHDOG_S``, ``stop`` ends it (a broken
    recorder must fail its test, not hang it).
    """

    WATCHDOG_S = 15.0

    def __init__(self, script, stop: FakeStop) -> None:
        self.run_id = RUN
        self.presence: dict[str, threading.Event] = {}
        self._script = script
        self._stop = stop
        self._callback = None

    def subscribe_raw(self, key: str, callback) -> None:
        self._callback = callback

    def watch_presence(self, node: str) -> threading.Event:
        return self.presence.setdefault(node, threading.Event())

    def ready(self, config) -> None:
        threading.Thread(target=self._play, daemon=True).start()
        watchdog = threading.Timer(self.WATCHDOG_S, self._stop.stop, ("watchdog",))
        watchdog.daemon = True
        watchdog.start()

    def _play(self) -> None:
        try:
            self._script(self)
        except BaseException:
            self._stop.stop("test script failed")
            raise

    def send(self, topic, msg, key_run: str = RUN) -> None:
        self._callback(SimpleNamespace(key_expr=key(topic, msg, key_run), payload=SimpleNamespace(
            to_bytes=lambda data=encode(msg): data)))

    def leave(self, node: str) -> None:
        self.watch_presence(node).set()


def run_recorder(tmp_path, script, stop=None, expect=("plant",), drain_s=2.0, roles=None):
    """Record ``script`` in process; ``drain_s`` 2 s: an end is confirmed when the recorder's loop sees the
    token go within ``drain_s`` of it, which a starved host (a CI run beside a long run) stretched past 0.3 s."""
    out = tmp_path / "rec.mcap"
    recorder = McapRecorder(out, RUN, out.open("wb"))
    stop = stop or FakeStop()
    status = record(recorder, FakeBus(script, stop), stop, RunTracker(expect, drain_s, roles=roles or {}), drain_s, {})
    return status, out


def plant_run(n: int, forge=None):
    """A plant that starts, publishes ``n`` states, ends and leaves; ``forge(bus, step)`` adds forgeries."""

    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        for step in range(n):
            bus.send(PLANT_STATE, state(step))
            if forge:
                forge(bus, step)
        bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": n, "run/events": 2}))
        time.sleep(0.05)
        bus.leave("plant")

    return script


def test_clean_run_is_complete(tmp_path, capsys):
    status, out = run_recorder(tmp_path, plant_run(20))
    assert status == 0
    counts = metadata(out)["meltloop.counts"]
    assert counts["complete"] == "true" and counts["stopped_by"] == "run end", counts
    assert json.loads(counts["dropped"]) == {} and json.loads(counts["extra"]) == {}
    assert [s.step for s in read_messages(out, PLANT_STATE)] == list(range(20))
    assert "(complete: true; dropped: none)" in capsys.readouterr().out


def test_forged_messages_are_dropped_counted_and_the_run_stays_complete(tmp_path, capsys):
    def forge(bus, step):
        bus.send(PLANT_STATE, state(step + 1, run_id="other"))
        bus.send(PLANT_STATE, state(2**31 - 1))
        bus.send(PLANT_STATE, state(step))  # replay of the last state
        if step == 5:
            bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": 6, "run/events": 2}))  # forged end, node alive
            bus.send(RUN_EVENTS, event("controller", "end"))  # a node that never started

    # both ends (the forged one at step 5) within drain_s of the token going, also on a loaded host
    status, out = run_recorder(tmp_path, plant_run(20, forge))
    assert status == 0, capsys.readouterr()
    counts = metadata(out)["meltloop.counts"]
    assert [s.step for s in read_messages(out, PLANT_STATE)] == list(range(20))  # the forged end did not end it
    assert json.loads(counts["dropped"]) == {"other_run": 20, "step_too_far_ahead": 20, "step_not_newer": 20,
                                             "duplicate_end": 1, "end_without_start": 1}
    assert counts["complete"] == "true", counts  # the real end (closest to the token going) was taken
    assert [e.event for e in read_messages(out, RUN_EVENTS)] == ["start", "end"]
    line = capsys.readouterr().out.strip().splitlines()[-1]
    assert "other_run 20" in line and "step_too_far_ahead 20" in line and "end_without_start 1" in line


def test_forged_end_alone_never_finishes_the_recording(tmp_path):
    stop = FakeStop()

    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        bus.send(PLANT_STATE, state(0))
        bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": 1, "run/events": 2}))  # token stays
        time.sleep(0.8)
        stop.stop("SIGTERM")

    status, out = run_recorder(tmp_path, script, stop=stop, drain_s=0.3)  # held 0.8 s > drain_s
    counts = metadata(out)["meltloop.counts"]
    assert status == 0
    assert counts["complete"] == "false" and counts["stopped_by"] == "SIGTERM"
    assert json.loads(counts["dropped"]) == {"unconfirmed_end": 1}
    assert [e.event for e in read_messages(out, RUN_EVENTS)] == ["start"]  # the forged end is not recorded
    assert not is_complete(out)


def test_recorded_but_not_published_makes_the_run_incomplete(tmp_path, capsys):
    def forge(bus, step):
        if step == 3:
            bus.send(LASER_COMMAND, command(4))  # injected command, admissible: only reconciliation sees it

    status, out = run_recorder(tmp_path, plant_run(10, forge))
    counts = metadata(out)["meltloop.counts"]
    assert status == 1
    assert counts["complete"] == "false" and json.loads(counts["extra"]) == {"controller/command": 1}
    assert "messages recorded but not published: {'controller/command': 1}" in counts["incomplete_reason"]
    assert "error: messages recorded but not published" in capsys.readouterr().err


def test_published_but_not_recorded_makes_the_run_incomplete(tmp_path):
    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        bus.send(PLANT_STATE, state(0))
        bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": 2, "run/events": 2}))
        bus.leave("plant")

    status, out = run_recorder(tmp_path, script)
    counts = metadata(out)["meltloop.counts"]
    assert status == 1 and counts["complete"] == "false"
    assert json.loads(counts["missing"]) == {"plant/state": 1}


@pytest.mark.parametrize("reason", ["SIGINT", "supervisor gone"])
def test_a_stopped_run_is_never_complete(tmp_path, reason):
    stop = FakeStop()

    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        bus.send(PLANT_STATE, state(0))
        time.sleep(0.2)
        stop.stop(reason)

    status, out = run_recorder(tmp_path, script, stop=stop)
    counts = metadata(out)["meltloop.counts"]
    assert counts["complete"] == "false" and counts["stopped_by"] == reason
    assert counts["incomplete_reason"] == f"stopped by {reason}"


# --- completeness by node -------------------------------------------------------------------------

def log(node: str, text: str = "line"):
    return msgspec.structs.replace(dict(sample_messages(RUN))[LOG], name=node, message=text)


def test_a_roleless_node_that_never_ends_hides_no_loss_of_another_node(tmp_path, capsys):
    """Its logs would make up for two the plant lost; per-node counts and its missing end show both."""

    def script(bus):
        bus.send(RUN_EVENTS, event("plant", "start"))
        bus.send(RUN_EVENTS, event("helper", "start"))
        for step in range(10):
            bus.send(PLANT_STATE, state(step))
        for i in range(3):
            bus.send(LOG, log("plant", f"plant {i}"))
        for i in range(2):
            bus.send(LOG, log("helper", f"helper {i}"))
        bus.send(RUN_EVENTS, event("plant", "end", {"plant/state": 10, "log": 5, "run/events": 2}))  # 2 logs lost
        time.sleep(0.05)
        bus.leave("plant")

    status, out = run_recorder(tmp_path, script)
    counts = metadata(out)["meltloop.counts"]
    assert status == 1 and counts["complete"] == "false", counts
    assert json.loads(counts["missing"]) == {"log/plant": 2}
    assert "no confirmed end of helper" in counts["incomplete_reason"]
    assert not is_complete(out)


def test_a_node_cannot_claim_counts_of_keys_it_does_not_own(tmp_path, capsys):
    def forge(bus, step):
        if step == 0:
            bus.send(RUN_EVENTS, event("helper", "start"))
        if step == 5:
            bus.send(RUN_EVENTS, event("helper", "end", {"plant/state": 10**9, "log/plant": 3, "run/events": 2}))
            time.sleep(0.05)
            bus.leave("helper")

    status, out = run_recorder(tmp_path, plant_run(20, forge))
    counts = metadata(out)["meltloop.counts"]
    assert status == 0 and counts["complete"] == "true", counts
    assert json.loads(counts["published"]) == {"plant/state": 20, "run/events": 4}
    assert json.loads(counts["dropped"]) == {"foreign_count": 2}
    assert "foreign_count 2" in capsys.readouterr().out


def test_the_recorder_waits_for_a_node_that_started_and_ends_after_the_expected_ones(tmp_path):
    def script(bus):
        bus.send(RUN_EVENTS, event("helper", "start"))
        plant_run(5)(bus)
        time.sleep(0.2)  # the helper ends after the plant, within the drain time
        bus.send(RUN_EVENTS, event("helper", "end", {"run/events": 2}))
        time.sleep(0.05)
        bus.leave("helper")

    status, out = run_recorder(tmp_path, script, drain_s=1.0)
    counts = metadata(out)["meltloop.counts"]
    assert status == 0 and counts["complete"] == "true", counts
    assert [e.node for e in read_messages(out, RUN_EVENTS)][-1] == "helper"
