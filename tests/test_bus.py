"""Two real processes exchange every message type over zenoh on loopback."""

from __future__ import annotations

import time

import msgspec

from messages import encode
from messages.bus import BusSettings, NodeBus, StopFlag
from messages.topics import TOPICS, key_expr, message_node
from tests.conftest import finish, spawn
from tests.samples import sample_messages


def test_every_message_type_round_trips_through_another_process(hub, run_id):
    echo = spawn("tests.nodes.echo", "--run-id", run_id, "--connect", hub)
    try:
        stop = StopFlag()
        with NodeBus("tester", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus, NodeBus(
            "tester-in", BusSettings(run_id=run_id + "-echo", connect=(hub,))
        ) as back:
            inboxes = {t.suffix: back.inbox(t) for t in TOPICS.values()}
            bus.wait_for_nodes(["echo"], stop, timeout_s=20)
            back.wait_for_nodes(["echo-out"], stop, timeout_s=20)
            sent = sample_messages(run_id)
            for topic, msg in sent:
                if topic.per_node:  # published as the node the message names
                    bus.session.put(key_expr(run_id, topic, message_node(msg)), encode(msg))
                else:
                    bus.publisher(topic).put(msg)
            received = {}
            deadline = time.monotonic() + 10
            while len(received) < len(sent) and time.monotonic() < deadline:
                for suffix, box in inboxes.items():
                    msg = box.get()
                    if msg is not None and (suffix != "run/events" or msg.node == "fe_node"):
                        if hasattr(msg, "run_id"):
                            assert msg.run_id == run_id + "-echo"
                            msg = msgspec.structs.replace(msg, run_id=run_id)
                        received.setdefault(suffix, msg)
                time.sleep(0.005)
            for topic, msg in sent:
                assert received.get(topic.suffix) == msg, topic.suffix
            assert all(box.n_invalid == 0 for box in inboxes.values())
            echo.terminate()  # while the hub (this test's session) still runs, as launch.py stops nodes
            status, out = finish(echo, timeout=15)
    finally:
        if echo.poll() is None:
            echo.kill()
            echo.communicate()
    assert status == 0, out


def test_inbox_drops_and_counts_invalid_payloads(hub, run_id):
    from messages.topics import PLANT_STATE, key_expr

    with NodeBus("a", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as a:
        box = a.inbox(PLANT_STATE)
        raw = a.session.declare_publisher(key_expr(run_id, PLANT_STATE))
        (_, good), = [s for s in sample_messages(run_id) if s[0] is PLANT_STATE]
        (_, foreign), = [s for s in sample_messages("another-run") if s[0] is PLANT_STATE]
        for payload in (b"garbage", b'{"step": 1}', b"x" * 100_000, encode(foreign)):
            raw.put(payload)
        a.publisher(PLANT_STATE).put(good)
        got = box.get(timeout=5)
        assert got == good
        assert box.n_invalid == 4 and "does not match" in box.last_error
        raw.undeclare()


def test_a_session_is_routed_as_a_client_of_a_router(tmp_path):
    """launch.py's nodes (run credentials) and a file's ``mode: "client"`` are clients, every message
    crossing the router; a node started by hand is a peer (``NodeBus.routed``; a fast free-running
    plant then never polls, fe_node.freerun)."""
    from messages.bus import client_mode, zenoh_config

    assert client_mode(zenoh_config(BusSettings(), ("plant", "secret")))
    assert not client_mode(zenoh_config(BusSettings()))
    path = tmp_path / "zenoh.json5"
    path.write_text('{ mode: "client" }')
    assert client_mode(zenoh_config(BusSettings(zenoh_config=path)))
    path.write_text("{ }")
    assert not client_mode(zenoh_config(BusSettings(zenoh_config=path)))


def test_a_peer_nodebus_is_not_routed(hub, run_id):
    with NodeBus("plant", BusSettings(run_id=run_id, connect=(hub,))) as bus:
        assert bus.routed is False
