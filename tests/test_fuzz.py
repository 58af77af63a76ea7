"""Fuzzing during a run: 10,000 malformed payloads from another process change nothing.

Every payload is rejected and counted (controller and plant diagnostics ``n_dropped``,
recorder ``invalid_dropped``), no process crashes, and the deterministic lockstep run gives the
same trace as a clean run with the same configuration.
"""

from __future__ import annotations

import json
import re
import subprocess

import pytest

from messages.recording import metadata, read_messages
from tests.conftest import RECORDER_NODE, controller_node, finish, start_node_list
from tests.plants import BARE_CONFIG

STEPS = 150


def start_run(tmp_path, name: str, count: int) -> tuple[subprocess.Popen[str], object]:
    fuzzer_and_plant = f"""
[[node]]
name = "fuzzer"
module = "tests.nodes.fuzzer"
roles = ["plant", "controller"]  # authenticated, yet sending garbage: the nodes must cope
args = ["--require", "recorder", "--count", "{count}", "--seed", "7",
        "--topic", "plant/state", "--topic", "controller/command", "--topic", "run/events"]

[[node]]
name = "plant"
module = "fe_node"
args = ["--h-um", "40", "--max-steps", "{STEPS}", "--command-timeout-s", "30", "--config", "{BARE_CONFIG}",
        "--require", "recorder", "--require", "controller", "--require", "fuzzer"]
main = true
"""
    return start_node_list(tmp_path, name, RECORDER_NODE + controller_node("mpc") + fuzzer_and_plant)


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    """The clean and the fuzzed run, side by side (lockstep: the result does not depend on timing)."""
    tmp = tmp_path_factory.mktemp("fuzz")
    started = [start_run(tmp, "clean", 0), start_run(tmp, "fuzzed", 10_000)]
    results = []
    for proc, out in started:
        status, output = finish(proc, timeout=300)
        assert status == 0, output
        results.append((output, out))
    return results


def test_every_malformed_payload_is_rejected_and_counted(runs):
    _, (output, out) = runs
    m = re.search(r"fuzz done: sent (\{.*\}) in [\d.]+ s at plant step (\d+)", output)
    assert m, output
    sent, settled_at = json.loads(m.group(1)), int(m.group(2))
    assert sum(sent.values()) == 10_000 and settled_at < STEPS, output
    assert "Traceback" not in output
    controller_last = list(read_messages(out, "/controller/diagnostics"))[-1]
    plant_last = list(read_messages(out, "/plant/diagnostics"))[-1]
    assert controller_last.n_dropped == sent["plant/state"]
    assert plant_last.n_dropped == sent["controller/command"] and plant_last.n_fallbacks == 0
    counts = metadata(out)["meltloop.counts"]
    assert json.loads(counts["invalid_dropped"]) == sent
    assert counts["complete"] == "true"


def test_fuzzed_run_gives_the_clean_result(runs):
    (_, clean), (_, fuzzed) = runs

    def trace(path):
        return [(s.step, s.area_mm2, s.t_ahead_k, s.power_w) for s in read_messages(path, "/plant/state")]

    def commands(path):
        return [(c.step, c.power_w) for c in read_messages(path, "/controller/command")]

    assert len(trace(clean)) == STEPS + 1
    assert trace(fuzzed) == trace(clean)
    assert commands(fuzzed) == commands(clean)
