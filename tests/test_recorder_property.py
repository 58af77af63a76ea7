"""No schema-valid value crashes the recorder's logic or its MCAP writing (property test)."""

from __future__ import annotations

import io
import time

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from mcap.reader import make_reader

from messages.recorder import Intake, McapRecorder, RunTracker
from messages.topics import TOPICS, key_expr
from tests.strategies import payloads

RUN = "r"
NODES = ("plant", "controller", "recorder", "x")


def samples():
    """(key, payload) of any topic, this run's id or another's, under any node's key."""
    return st.sampled_from(list(TOPICS.values())).flatmap(lambda topic: st.tuples(
        st.sampled_from(NODES).map(lambda node: key_expr(RUN, topic, node)),
        st.sampled_from([RUN, "other"]).flatmap(lambda run_id: payloads(topic, run_id=run_id)),
    ))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(received=st.lists(samples(), max_size=25), gone=st.lists(st.sampled_from(NODES), max_size=3))
def test_any_schema_valid_sequence_is_recorded_or_dropped_and_the_file_finishes(tmp_path_factory, received, gone):
    stream = io.BytesIO()
    stream.close = lambda: None  # keep the bytes readable after finish()
    recorder = McapRecorder(tmp_path_factory.mktemp("p") / "p.mcap", RUN, stream)
    intake = Intake(RUN, RunTracker(("plant",), drain_s=0.1))
    now = time.time()
    for i, (key, payload) in enumerate(received):
        for item in intake.receive(key, payload, int((now + i * 0.01) * 1e9)):
            recorder.write(item.topic, item.payload, item.msg, item.received_ns)
        for node in gone[:i]:
            intake.tracker.gone(node, now + i * 0.01)
        for item in intake.poll(now + i * 0.01):
            recorder.write(item.topic, item.payload, item.msg, item.received_ns)
    for item in intake.poll(now + 100.0):  # every held end decided
        recorder.write(item.topic, item.payload, item.msg, item.received_ns)
    counts, _problem = intake.summary(None)
    recorder.finish({**counts, "recorded": "{}"})
    stream.seek(0)
    read = sum(1 for _ in make_reader(stream).iter_messages())
    assert read == sum(recorder.recorded.values())
    assert read + sum(intake.dropped.values()) == len(received)  # each sample recorded or dropped, once
