"""No schema-valid value crashes a decoder or a node's logic (property tests).

Schema-valid payloads of every topic are drawn from the shipped JSON Schemas (any step, any
number in range). The codec returns a message or raises its ``MessageError``; every controller
answers any admissible sequence of such states with a command for the next step inside its
power bounds (or refuses the plant's configuration); the plant's command gate returns a verdict
for any command and applies only commands inside its bounds and window. Each draws fewer examples
in the default run than with ``-m slow`` (:func:`examples`).
"""

from __future__ import annotations

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller_node.node import inadmissible, load_model, measurement_from_state
from controller_node.registry import CONTROLLERS, make_controller
from controller_node.settings import ControllerSettings
from controller_node.types import ConfigurationError
from fe_node.commands import CommandGate, CommandPolicy, Verdict
from messages.codec import MessageError, decode
from messages.topics import LASER_COMMAND, PLANT_STATE, TOPICS
from tests.strategies import payloads

RUN = "r"



def examples(default: int, slow: int) -> pytest.MarkDecorator:
    """Parametrize ``max_examples``: ``default`` in the default run, ``slow`` with ``-m slow``."""
    return pytest.mark.parametrize("max_examples", [default, pytest.param(slow, marks=pytest.mark.slow)])


@examples(30, 75)
@pytest.mark.parametrize("topic", TOPICS.values(), ids=lambda t: t.suffix)
def test_a_schema_valid_payload_decodes_or_is_rejected_by_the_codec(topic, max_examples):
    @settings(max_examples=max_examples, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(data=st.data())
    def check(data):
        payload = data.draw(payloads(topic))
        try:
            decode(topic, payload)
        except MessageError:
            pass  # a cross-field rule the schema cannot state (e.g. image size); never another error

    check()


_MODELS: dict[str, object] = {}


def _controller(name: str):
    if name not in _MODELS:
        _MODELS[name] = load_model(name, None)
    return make_controller(name, ControllerSettings(), _MODELS[name])


@examples(15, 40)
@pytest.mark.parametrize("name", CONTROLLERS)
def test_any_admissible_schema_valid_states_get_a_bounded_command(name, max_examples):
    @settings(max_examples=max_examples, deadline=None, suppress_health_check=[HealthCheck.too_slow])
    @given(batch=st.lists(payloads(PLANT_STATE, run_id=RUN), min_size=1, max_size=12))
    def check(batch):
        controller, bounds = _controller(name), ControllerSettings()
        last_step = None
        for payload in batch:
            state = decode(PLANT_STATE, payload)
            if inadmissible(state.step, last_step) is not None:
                continue
            try:
                command, _ = controller.update(measurement_from_state(state))
            except ConfigurationError:
                return  # a plant of another sample period: the node refuses it in one line
            last_step = state.step
            assert command.step == state.step + 1
            assert bounds.power_min_w <= command.power_w <= bounds.power_max_w

    check()


@examples(100, 300)
def test_the_plant_applies_only_commands_in_its_window_and_bounds(max_examples):
    @settings(max_examples=max_examples, deadline=None)
    @given(payload=payloads(LASER_COMMAND, run_id=RUN), first=st.integers(0, 2**31 - 1), width=st.integers(0, 3))
    def check(payload, first, width):
        cmd = decode(LASER_COMMAND, payload)
        policy = CommandPolicy()
        gate = CommandGate(policy)
        verdict = gate.admit(cmd, first, first + width)
        if verdict is Verdict.APPLY:
            assert first <= cmd.step <= first + width
            assert policy.within_bounds(cmd.power_w, cmd.speed_mm_s * 1e-3)
        assert sum(gate.counts.values()) == 1

    check()
