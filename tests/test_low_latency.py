"""``--low-latency``: zenoh's low-latency unicast transport on a node's session, and the size limit
that keeps zenoh from losing a message it cannot carry on it (never a silent loss)."""

from __future__ import annotations

import json
import threading

import pytest

from controller_node.node import build_parser
from messages.bus import (
    LOW_LATENCY_MAX_BYTES,
    BusSettings,
    NodeBus,
    bus_settings_from_args,
    low_latency,
    run_node,
    zenoh_config,
)
from messages.codec import MessageError
from messages.foxglove import LogLevel
from messages.topics import PLANT_STATE
from tests.test_loop_hotpath import state


def test_the_flag_selects_zenohs_low_latency_transport_with_qos_off():
    args = build_parser().parse_args(["--low-latency"])
    settings = bus_settings_from_args(args)
    assert settings.low_latency
    config = zenoh_config(settings)
    assert low_latency(config) and config.get_json("transport/unicast/qos/enabled") == "false"
    # one peer of each pair opens the link (two at once lost the other's token on this transport)
    assert json.loads(config.get_json("scouting/gossip/autoconnect_strategy"))["peer"]["to_peer"] == "greater-zid"
    assert not low_latency(zenoh_config(bus_settings_from_args(build_parser().parse_args([]))))


def test_a_config_file_that_selects_it_counts_too(tmp_path):
    path = tmp_path / "zenoh.json5"
    path.write_text('{ transport: { unicast: { lowlatency: true, qos: { enabled: false } } } }')
    assert low_latency(zenoh_config(BusSettings(zenoh_config=path)))


def test_two_low_latency_nodes_exchange_states(hub, run_id):
    listen = BusSettings(run_id=run_id, connect=(), listen=(hub,), low_latency=True)
    connect = BusSettings(run_id=run_id, connect=(hub,), low_latency=True)
    with NodeBus("controller", listen) as receiver, NodeBus("plant", connect) as sender:
        box = receiver.newest_inbox(PLANT_STATE)
        pub = sender.publisher(PLANT_STATE)
        got: list = []

        def read() -> None:
            while len(got) < 1:
                msg, _ = box.newest()
                if msg is not None:
                    got.append(msg)

        reader = threading.Thread(target=read, daemon=True)
        reader.start()
        for step in range(1, 50):  # until the receiver's subscription has reached the sender
            pub.put(state(run_id, step))
            reader.join(0.05)
            if got:
                break
        assert got and got[0].run_id == run_id


@pytest.mark.parametrize("low", [True, False])
def test_a_message_too_large_for_the_transport_is_refused_not_lost(hub, run_id, low):
    with NodeBus("plant", BusSettings(run_id=run_id, connect=(), listen=(hub,), low_latency=low)) as bus:
        assert bus.max_payload_bytes == (LOW_LATENCY_MAX_BYTES if low else float("inf"))
        bus.log(LogLevel.INFO, "x" * 8000)  # a large message within the limit still goes
        big = {"table": "y" * (LOW_LATENCY_MAX_BYTES + 1)}
        if low:
            with pytest.raises(MessageError, match="low-latency transport"):
                bus.event("start", time_s=0.0, config=big)
        else:
            bus.event("start", time_s=0.0, config=big)
        counts = dict(bus.published)
    assert ("run/events" in counts) is not low  # a refused message is not counted as published


def test_a_node_that_cannot_publish_exits_1_with_one_line(hub, run_id, capsys):
    settings = BusSettings(run_id=run_id, connect=(), listen=(hub,), low_latency=True)

    def body(bus: NodeBus) -> int:
        bus.event("start", time_s=0.0, config={"table": "z" * (LOW_LATENCY_MAX_BYTES + 1)})
        return 0

    assert run_node("python -m fe_node", "plant", settings, body) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exceeds the" in err[0] and "low-latency" in err[0]
