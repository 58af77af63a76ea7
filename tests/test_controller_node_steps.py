"""The controller node drops schema-valid states it cannot answer, instead of crashing (issue 13)."""

from __future__ import annotations

import threading

from msgspec.structs import replace

from controller_node.node import inadmissible, run
from controller_node.registry import make_controller
from controller_node.settings import ControllerSettings
from messages import MeltPoolState
from messages.types import MAX_STEP, MAX_STEPS_AHEAD


def test_inadmissible_steps():
    assert inadmissible(0, None) is None
    assert inadmissible(MAX_STEP - 1, None) is None
    assert "no next step" in inadmissible(MAX_STEP, None)
    assert inadmissible(10 + MAX_STEPS_AHEAD, 10) is None
    assert "more than" in inadmissible(11 + MAX_STEPS_AHEAD, 10)
    assert "not newer" in inadmissible(10, 10) and "not newer" in inadmissible(9, 10)


class _Inbox:
    queued = False

    def __init__(self, states, stop):
        self.states, self.stop, self.n_invalid = list(states), stop, 0

    def newest(self, block=True, busy=False, poll=None):
        if not self.states:
            self.stop.set()
            return None, 0
        return self.states.pop(0), 0

    def wake(self):
        pass


class _Publisher:
    def __init__(self):
        self.sent = []

    def put(self, message):
        self.sent.append(message)


class _Empty:
    def get(self, timeout=None):
        return None


class _Bus:
    run_id = "t"

    def __init__(self, states, stop):
        self._inbox, self.pubs, self.logs = _Inbox(states, stop), {}, []

    def newest_inbox(self, topic):
        return self._inbox

    def inbox(self, topic):  # the run events (the plant's end): none here, the run is stopped
        return _Empty()

    def publisher(self, topic):
        return self.pubs.setdefault(topic.suffix if hasattr(topic, "suffix") else str(topic), _Publisher())

    def watch_presence(self, name):
        return threading.Event()

    def ready(self, **_):
        pass

    def log(self, level, text, time_s=0.0):
        self.logs.append(text)

    def end_detail(self, text):
        self.logs.append(text)


def _state(step):
    return MeltPoolState(run_id="t", step=step, time_s=step * 50e-6, laser_x_mm=0.0, laser_y_mm=0.0, scan_dir_x=1.0,
                         scan_dir_y=0.0, track=0, area_mm2=0.06, t_ahead_k=300.0, power_w=250.0, speed_mm_s=800.0)


def test_node_drops_impossible_and_duplicate_states_and_keeps_answering():
    stop = threading.Event()
    states = [_state(0), _state(1), _state(MAX_STEP), _state(2), _state(2), _state(2 + MAX_STEPS_AHEAD + 1), _state(3)]
    bus = _Bus(states, stop)
    settings = ControllerSettings(set_point_m2=0.063e-6)
    assert run(bus, make_controller("pid", settings), settings, stop, "plant", {}) == 0
    commands = [m for p in bus.pubs.values() for m in p.sent if type(m).__name__ == "LaserCommand"]
    assert [c.step for c in commands] == [1, 2, 3, 4]
    assert any("no next step" in line for line in bus.logs)
    assert "3 impossible states dropped" in bus.logs[-1]  # the duplicate of state 2 gets no second command


def test_node_ends_with_a_logged_fault_on_a_state_at_another_speed_than_its_models(capsys):
    """The preview MPC's model was identified at 800 mm/s: a state at 1000 mm/s gets no command; the node
    logs the one-line reason, ends its run with it and returns exit status 2."""
    from gp_model.narx import NarxGPModel
    from gp_model.shipped import PLATE_MODEL_PATH

    stop = threading.Event()
    states = [_state(0), _state(1), replace(_state(2), speed_mm_s=1000.0), _state(3)]
    bus = _Bus(states, stop)
    settings = ControllerSettings(set_point_m2=0.063e-6)
    controller = make_controller("preview-mpc", settings, NarxGPModel.load(PLATE_MODEL_PATH))
    assert run(bus, controller, settings, stop, "plant", {}) == 2
    commands = [m for p in bus.pubs.values() for m in p.sent if type(m).__name__ == "LaserCommand"]
    assert [c.step for c in commands] == [1, 2]
    reason = "the plant scans at 1000 mm/s but the model was identified at 800 mm/s; retrain at the plant's speed"
    assert bus.logs == [reason, f"refused: {reason}"]
    assert capsys.readouterr().err.strip() == f"python -m controller_node: error: {reason}"
