"""A rogue process in a run under launch.py's default access control (issue 13 acceptance).

Two lockstep runs with the same nodes, side by side: a clean one, and one where a node that
may read everything but publish no topic (role ``recorder``) forges 10 000 schema-valid messages
of the plant and the controller (states, commands, end events, logs, liveliness tokens) and first
tries the hub without credentials.
Nothing forged may be applied or recorded: both runs exit 0 with identical plant traces,
commands and Table-4 figures.
"""

from __future__ import annotations

import json
import re
import subprocess

import pytest

from messages.recording import metadata, read_messages
from tests.conftest import RECORDER_NODE, controller_node, finish, start_node_list
from tests.nodes.rogue import FORGED_POWER_W
from tests.plants import BARE_CONFIG

STEPS = 150
COUNT = 10_000


def start_run(tmp_path, name: str, count: int) -> tuple[subprocess.Popen[str], object]:
    rogue_and_plant = f"""
[[node]]
name = "rogue"
module = "tests.nodes.rogue"
roles = ["recorder"]  # it times its forgeries by the plant states
args = ["--count", "{count}", "--require", "recorder"]

[[node]]
name = "plant"
module = "fe_node"
args = ["--h-um", "40", "--max-steps", "{STEPS}", "--command-timeout-s", "30", "--config", "{BARE_CONFIG}",
        "--require", "recorder", "--require", "controller", "--require", "rogue"]
main = true
"""
    return start_node_list(tmp_path, name, RECORDER_NODE + controller_node("pid") + rogue_and_plant)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("rogue")
    started = [start_run(tmp, "clean", 0), start_run(tmp, "attacked", COUNT)]
    results = []
    for proc, out in started:
        status, output = finish(proc, timeout=300)
        assert status == 0, output
        results.append((output, out))
    return results


def test_the_hub_refuses_a_session_without_credentials(runs):
    _, (output, _) = runs
    assert "[rogue] unauthenticated session refused" in output, output


def test_no_forgery_is_applied_or_recorded(runs):
    (_, clean), (output, attacked) = runs
    m = re.search(r"rogue done: sent (\{.*\})", output)
    assert m and sum(json.loads(m.group(1)).values()) == COUNT, output
    assert "Traceback" not in output

    def trace(path):
        return [(s.step, s.area_mm2, s.t_ahead_k, s.power_w) for s in read_messages(path, "/plant/state")]

    def commands(path):
        return [(c.step, c.power_w, c.controller) for c in read_messages(path, "/controller/command")]

    assert len(trace(clean)) == STEPS + 1
    assert trace(attacked) == trace(clean)
    assert commands(attacked) == commands(clean)
    assert all(power != FORGED_POWER_W for _, power, _ in commands(attacked))
    assert not [e for e in read_messages(attacked, "/run/events") if e.node != "rogue" and e.event == "end"
                and e.published == {"plant/state": 1}]
    assert not [line for line in read_messages(attacked, "/log") if line.message == "forged"]
    counts = metadata(attacked)["meltloop.counts"]
    assert counts["complete"] == "true", counts
    plant_diag = list(read_messages(attacked, "/plant/diagnostics"))[-1]
    assert plant_diag.n_fallbacks == 0


def test_the_table4_figures_are_those_of_the_clean_run(runs):
    from controller_node.summary import summarise

    (_, clean), (_, attacked) = runs
    figures = [{k: v for k, v in summarise(path, "layer", "pid", 0, 0.0).items()
                if k.endswith("_pct") or k in ("steps", "complete")} for path in (clean, attacked)]
    assert figures[0] == figures[1] and figures[0]["complete"] is True
