"""Fuzzing during a run: 10,000 malformed payloads from another process change nothing.

Every payload is rejected and counted (controller and plant diagnostics ``n_dropped``,
recorder ``invalid_dropped``), no process crashes, and the deterministic lockstep run gives the
same trace as the clean run with the same configuration (the runs of ``attack_runs``, shared
with tests/test_rogue.py).
"""

from __future__ import annotations

import json
import re

from messages.recording import metadata, read_messages
from tests.conftest import ATTACK_COUNT, ATTACK_STEPS


def test_every_malformed_payload_is_rejected_and_counted(attack_runs):
    output, out = attack_runs["fuzzed"]
    m = re.search(r"fuzz done: sent (\{.*\}) in [\d.]+ s at plant step (\d+)", output)
    assert m, output
    sent, settled_at = json.loads(m.group(1)), int(m.group(2))
    assert sum(sent.values()) == ATTACK_COUNT and settled_at < ATTACK_STEPS, output
    assert "Traceback" not in output
    controller_last = list(read_messages(out, "/controller/diagnostics"))[-1]
    plant_last = list(read_messages(out, "/plant/diagnostics"))[-1]
    assert controller_last.n_dropped == sent["plant/state"]
    assert plant_last.n_dropped == sent["controller/command"] and plant_last.n_fallbacks == 0
    counts = metadata(out)["meltloop.counts"]
    assert json.loads(counts["invalid_dropped"]) == sent
    assert counts["complete"] == "true"


def test_fuzzed_run_gives_the_clean_result(attack_runs):
    clean, fuzzed = attack_runs["clean"][1], attack_runs["fuzzed"][1]

    def trace(path):
        return [(s.step, s.area_mm2, s.t_ahead_k, s.power_w) for s in read_messages(path, "/plant/state")]

    def commands(path):
        return [(c.step, c.power_w) for c in read_messages(path, "/controller/command")]

    assert len(trace(clean)) == ATTACK_STEPS + 1
    assert trace(fuzzed) == trace(clean)
    assert commands(fuzzed) == commands(clean)
