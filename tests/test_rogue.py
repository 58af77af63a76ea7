"""A rogue process in a run under launch.py's default access control (issue 13 acceptance).

A lockstep run compared with the clean one (the runs of ``attack_runs``, shared with
tests/test_fuzz.py) where a node that may read everything but publish no topic (role
``recorder``) forges 10 000 schema-valid messages of the plant and the controller (states,
commands, end events, logs, liveliness tokens) and first tries the hub without credentials.
Nothing forged may be applied or recorded: both runs exit 0 with identical plant traces,
commands and Table-4 figures.
"""

from __future__ import annotations

import json
import re

from messages.recording import metadata, read_messages
from tests.conftest import ATTACK_COUNT, ATTACK_STEPS
from tests.nodes.rogue import FORGED_POWER_W


def test_the_hub_refuses_a_session_without_credentials(attack_runs):
    output, _ = attack_runs["attacked"]
    assert "[rogue] unauthenticated session refused" in output, output


def test_no_forgery_is_applied_or_recorded(attack_runs):
    (output, attacked), clean = attack_runs["attacked"], attack_runs["clean"][1]
    m = re.search(r"rogue done: sent (\{.*\})", output)
    assert m and sum(json.loads(m.group(1)).values()) == ATTACK_COUNT, output
    assert "Traceback" not in output

    def trace(path):
        return [(s.step, s.area_mm2, s.t_ahead_k, s.power_w) for s in read_messages(path, "/plant/state")]

    def commands(path):
        return [(c.step, c.power_w, c.controller) for c in read_messages(path, "/controller/command")]

    assert len(trace(clean)) == ATTACK_STEPS + 1
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


def test_the_table4_figures_are_those_of_the_clean_run(attack_runs):
    from controller_node.summary import summarise

    paths = (attack_runs["clean"][1], attack_runs["attacked"][1])
    figures = [{k: v for k, v in summarise(path, "layer", "mpc", 0, 0.0).items()
                if k.endswith("_pct") or k in ("steps", "complete")} for path in paths]
    assert figures[0] == figures[1] and figures[0]["complete"] is True
