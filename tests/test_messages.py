"""The message contract: codec round trip, JSON Schemas, and rejection of bad payloads."""

from __future__ import annotations

import json
import math

import jsonschema
import msgspec
import pytest

from messages import MeltPoolState, MessageError, decode, encode, json_schema
from messages.topics import LASER_COMMAND, PLANT_STATE, PLANT_TEMPERATURE, TOPICS, key_expr, topic_for_key
from tests.samples import sample_messages


def test_samples_cover_every_topic():
    assert {t.suffix for t, _ in sample_messages("r")} == set(TOPICS)


@pytest.mark.parametrize("topic,msg", sample_messages("run-1"), ids=lambda x: getattr(x, "suffix", ""))
def test_round_trip_and_schema(topic, msg):
    payload = encode(msg)
    assert decode(topic, payload) == msg
    schema = json_schema(topic)
    assert schema["title"] == topic.schema_name
    assert "$ref" not in json.dumps(schema)
    jsonschema.Draft202012Validator.check_schema(schema)
    jsonschema.validate(json.loads(payload), schema)


def test_foxglove_raw_image_bytes_are_base64():
    _, img = [s for s in sample_messages("r") if s[0] is PLANT_TEMPERATURE][0]
    data = json.loads(encode(img))["data"]
    assert isinstance(data, str)
    assert json_schema(PLANT_TEMPERATURE)["properties"]["data"]["contentEncoding"] == "base64"


def _state_dict():
    _, msg = sample_messages("r")[0]
    return json.loads(encode(msg))


@pytest.mark.parametrize(
    "mutate,reason",
    [
        (lambda d: d.update(area_mm2="big"), "Expected `float`"),
        (lambda d: d.pop("t_ahead_k"), "missing required field"),
        (lambda d: d.update(power_w=-5.0), ">= 0"),
        (lambda d: d.update(extra=1), "unknown field"),
        (lambda d: d.update(run_id="bad/run"), "matching regex"),
        (lambda d: d.update(step=1.5), "Expected `int`"),
        (lambda d: d.update(scan_dir_x=2.0), "<= 1"),
    ],
)
def test_decode_rejects_invalid_fields(mutate, reason):
    d = _state_dict()
    mutate(d)
    with pytest.raises(MessageError, match=reason) as err:
        decode(PLANT_STATE, json.dumps(d).encode())
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("payload", [b"", b"garbage", b"{", b"[1,2]", b"null", b'{"area_mm2": NaN}', "é".encode()])
def test_decode_rejects_garbage(payload):
    with pytest.raises(MessageError):
        decode(PLANT_STATE, payload)


@pytest.mark.parametrize("literal", ["NaN", "Infinity", "-Infinity", "1e999"])
def test_decode_rejects_non_finite(literal):
    text = json.dumps(_state_dict()).replace('"area_mm2": 0.0712', f'"area_mm2": {literal}')
    with pytest.raises(MessageError):
        decode(PLANT_STATE, text.encode())


def test_optional_float_nan_cannot_become_null():
    d = _state_dict()
    with pytest.raises(ValueError, match="not finite"):
        MeltPoolState(**{**d, "width_um": math.nan})


def test_oversized_payload_rejected_before_parsing():
    with pytest.raises(MessageError, match="exceeds"):
        decode(LASER_COMMAND, b" " * (LASER_COMMAND.max_bytes + 1))


def test_encode_refuses_out_of_range():
    d = _state_dict()
    msg = msgspec.convert({**d, "power_w": 250.0}, MeltPoolState)
    bad = msgspec.structs.replace(msg, power_w=-1.0)
    with pytest.raises(MessageError, match="power_w"):
        encode(bad)


def test_keys_are_namespaced_by_run():
    assert key_expr("r1", PLANT_STATE) == "meltloop/r1/plant/state"
    assert topic_for_key("r1", "meltloop/r1/plant/state") is PLANT_STATE
    assert topic_for_key("r2", "meltloop/r1/plant/state") is None
    assert topic_for_key("r1", "meltloop/r1/plant/unknown") is None
