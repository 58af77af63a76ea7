"""The recorder process writes every published message into a valid, finished MCAP."""

from __future__ import annotations

import json
from collections import Counter

import jsonschema
import msgspec
from mcap.reader import make_reader

from messages.bus import BusSettings, NodeBus, StopFlag
from messages.recording import is_complete, metadata, read_messages, run_config
from tests import forked_cli
from tests.conftest import finish, spawn
from tests.samples import sample_messages


def validate_recording(path) -> Counter:
    """Every message valid against its channel's JSON Schema (each schema checked once); returns
    counts per channel."""
    counts: Counter = Counter()
    validators = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            if schema.id not in validators:
                document = json.loads(schema.data)
                kind = jsonschema.validators.validator_for(document)
                kind.check_schema(document)
                validators[schema.id] = kind(document)
            validators[schema.id].validate(json.loads(message.data))
            counts[channel.topic] += 1
    return counts


def test_recorder_records_everything_published(tmp_path, hub, run_id):
    out = tmp_path / "run.mcap"
    rec = spawn("messages.recorder", "--run-id", run_id, "--connect", hub, "--out", str(out), "--expect", "tester",
                "--role", "tester=plant,controller")  # it publishes every topic
    stop = StopFlag()
    with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        bus.wait_for_nodes(["recorder"], stop, timeout_s=20)
        bus.ready(config={"purpose": "test"})
        for step in range(200):
            for topic, msg in sample_messages(run_id, step=step):
                if topic.suffix == "log":
                    msg = msgspec.structs.replace(msg, name="tester")  # a node logs under its own name
                if topic.suffix != "run/events":
                    bus.publisher(topic).put(msg)
        published = dict(bus.published)
    status, output = finish(rec, timeout=30)
    assert status == 0, output
    assert is_complete(out)
    counts = validate_recording(out)
    for suffix, n in published.items():
        assert counts["/" + suffix] >= n, suffix
    assert counts["/plant/state"] == 200
    events = [(e.node, e.event) for e in read_messages(out, "/run/events")]
    assert events == [("recorder", "start"), ("tester", "start"), ("tester", "end")]
    states = list(read_messages(out, "/plant/state"))
    assert [s.step for s in states] == list(range(200))
    meta = metadata(out)
    assert meta["meltloop"]["run_id"] == run_id
    assert json.loads(meta["meltloop.counts"]["recorded"])["plant/state"] == 200
    assert run_config(out)["tester"] == {"purpose": "test"}


def test_recorder_finishes_file_on_sigint(tmp_path, hub, run_id):
    out = tmp_path / "int.mcap"
    rec = spawn("messages.recorder", "--run-id", run_id, "--connect", hub, "--out", str(out))
    stop = StopFlag()
    with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        bus.wait_for_nodes(["recorder"], stop, timeout_s=20)
        (topic, msg), = [s for s in sample_messages(run_id) if s[0].suffix == "plant/state"]
        bus.publisher(topic).put(msg)
        import time
        time.sleep(0.5)
        rec.send_signal(2)
        status, output = finish(rec, timeout=15)
    assert status == 0, output
    assert validate_recording(out)["/plant/state"] == 1
    assert metadata(out)["meltloop.counts"]["stopped_by"] == "SIGINT"


def test_recorder_bad_arguments_exit_2(tmp_path):
    run = forked_cli.run("-m", "messages.recorder", "--out", str(tmp_path / "x.txt"))
    assert run.returncode == 2
    assert run.stdout == "" and run.stderr.strip().count("\n") == 0 and "error" in run.stderr


def test_recorder_reports_a_lost_event_even_with_its_own_in_the_file(tmp_path, hub, run_id):
    """A node's lost ``start`` event must not hide behind the recorder's own start event."""
    out = tmp_path / "lost.mcap"
    rec = spawn("messages.recorder", "--run-id", run_id, "--connect", hub, "--out", str(out), "--expect", "tester",
                "--drain-s", "0.5")
    with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,), require=("recorder",))) as bus:
        bus.ready(stop=StopFlag())
        bus.published["run/events"] += 1  # as if a second event had been sent and lost on the way
    status, output = finish(rec, timeout=30)
    assert status == 1, output
    assert "messages published but not recorded: {'run/events/tester': 1}" in output
    assert json.loads(metadata(out)["meltloop.counts"]["published"])["run/events"] == 3
    assert metadata(out)["meltloop.counts"]["complete"] == "false"


def test_ready_waits_for_required_nodes_and_reports_a_missing_one(hub, run_id):
    import threading

    import pytest

    with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,), require=("nobody",))) as bus:
        stop = threading.Event()
        threading.Timer(0.3, stop.set).start()
        with pytest.raises(TimeoutError, match="stopped while waiting for nodes: nobody"):
            bus.ready(stop=stop)


def test_recorder_takes_everything_arrived_in_order_per_wake_up():
    """The recorder's loop writes in batches (``messages.recorder.Arrivals``): all that is queued, in
    order, after waiting for the first item; nothing when nothing comes within the timeout."""
    import threading
    import time

    from messages.recorder import Arrivals

    box = Arrivals("run1")
    assert box.take(0.01) == []
    for k in range(1000):
        box.put("key", bytes([k % 256]), k)
    assert [item[2] for item in box.take(0.01)] == list(range(1000))
    assert box.take(0.0) == []
    threading.Timer(0.05, lambda: box.put("late", b"", 0)).start()
    started = time.monotonic()
    assert box.take(5.0) == [("late", b"", 0)] and time.monotonic() - started < 4.0
