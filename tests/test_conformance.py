"""``python -m messages.conformance``: a conforming recording passes, each broken rule is named.

The recordings are written with the mcap writer (no zenoh): a small closed-loop run whose
``meltloop.counts`` is computed like the recorder's, then one mutation per rule. A real
``launch.py`` run and the same run with a broken state sequence are checked too.
"""

from __future__ import annotations

import json
from collections import Counter
from pathlib import Path

import pytest
from mcap.writer import CompressionType, Writer

from messages import conformance
from messages.codec import json_schema
from messages.recording import read_recording
from messages.topics import TOPICS
from tests import forked_cli

RUN = "r1"
DT_S = 50e-6
N = 60
PLANT_CONFIG = {"policy": {"power_min_w": 0.0, "power_max_w": 350.0}, "sample_period_s": DT_S}
CONTROLLER_CONFIG = {"power_min_w": 0.0, "power_max_w": 350.0}


def _event(node, event, time_s=0.0, config=None, published=None):
    return ("run/events", {"run_id": RUN, "node": node, "event": event, "time_s": time_s,
                           "config_json": json.dumps(config) if config else "", "published": published or {}})


def _log(node, text, time_s):
    return ("log", {"timestamp": {"sec": 0, "nsec": int(time_s * 1e9)}, "level": 2, "message": text, "name": node})


def clean_run():
    """``[(suffix, payload dict), ...]`` of a conforming closed-loop run, in recording order."""
    msgs = [_event("recorder", "start", config={"out": "x.mcap"}),
            _event("controller", "start", config=CONTROLLER_CONFIG),
            _event("plant", "start", config=PLANT_CONFIG)]
    for k in range(N + 1):
        t = k * DT_S
        msgs.append(("plant/state", {
            "run_id": RUN, "step": k, "time_s": t, "laser_x_mm": 0.04 * k, "laser_y_mm": 0.0, "scan_dir_x": 1.0,
            "scan_dir_y": 0.0, "track": 0, "area_mm2": 0.06, "t_ahead_k": 500.0, "power_w": 250.0,
            "speed_mm_s": 800.0, "source": "sensor"}))
        if k % 10 == 0:
            msgs.append(("plant/diagnostics", {"run_id": RUN, "step": k, "time_s": t, "step_wall_ms": 0.1}))
        msgs.append(("controller/command", {"run_id": RUN, "step": k + 1, "time_s": t, "power_w": 250.0,
                                            "speed_mm_s": 800.0, "controller": "pid"}))
        msgs.append(("controller/diagnostics", {"run_id": RUN, "step": k + 1, "time_s": t, "controller": "pid",
                                                "status": "ok", "solve_time_us": 3.0}))
    for node, t in (("plant", N * DT_S), ("controller", N * DT_S)):
        msgs.append(_log(node, "finished", t))
        own = Counter(s for s, p in msgs if s.split("/")[0] == node or p.get("node", p.get("name")) == node)
        msgs.append(_event(node, "end", t, published={**own, "run/events": own["run/events"] + 1}))
    return msgs


def write(path: Path, msgs, counts: dict | None = None) -> Path:
    """Write ``msgs`` as the recorder would, with its ``meltloop.counts`` (or ``counts`` instead)."""
    published = Counter()
    for suffix, payload in msgs:
        if suffix == "run/events" and payload.get("event") == "end":
            published.update(payload["published"])
    recorded = Counter(suffix for suffix, _ in msgs)
    with path.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="test")
        channels = {}
        for topic in TOPICS.values():
            schema = writer.register_schema(name=topic.schema_name, encoding="jsonschema",
                                            data=json.dumps(json_schema(topic)).encode())
            channels[topic.suffix] = writer.register_channel(topic=topic.channel, message_encoding="json",
                                                             schema_id=schema)
        writer.add_metadata("meltloop", {"run_id": RUN})
        for seq, (suffix, payload) in enumerate(msgs):
            data = payload if isinstance(payload, bytes) else json.dumps(payload).encode()
            writer.add_message(channel_id=channels[suffix], log_time=seq, publish_time=seq, data=data, sequence=seq)
        writer.add_metadata("meltloop.counts", counts or {
            "complete": "true", "published": json.dumps(dict(published)), "recorded": json.dumps(dict(recorded)),
            "missing": "{}", "extra": "{}"})
        writer.finish()
    return path


def _find(msgs, suffix, step=None, node=None):
    for i, (s, p) in enumerate(msgs):
        if s == suffix and (step is None or p.get("step") == step) and (node is None or p.get("node") == node):
            return i
    raise LookupError(suffix)


def _set(suffix, at, **changes):
    def edit(msgs):
        i = _find(msgs, suffix, at)
        msgs[i] = (suffix, {**msgs[i][1], **changes})
    return edit


def _drop(suffix, step):
    return lambda msgs: msgs.pop(_find(msgs, suffix, step))


def _start_late(msgs):
    start = msgs.pop(_find(msgs, "run/events", node="plant"))
    msgs.insert(_find(msgs, "plant/state", 0) + 1, start)


def _corrupt(msgs):
    i = _find(msgs, "plant/diagnostics", 20)
    msgs[i] = ("plant/diagnostics", json.dumps({**msgs[i][1], "extra": 1}).encode())


def _log_after_end(msgs):
    msgs.append(msgs.pop(_find(msgs, "log")))


def _ghost_log(msgs):
    i = _find(msgs, "log")
    msgs[i] = ("log", {**msgs[i][1], "name": "ghost"})


MUTATIONS = {  # name: (edit, violated rule, first offending step)
    "state step missing": (_drop("plant/state", 30), "state_steps", 31),
    "state step repeated": (_set("plant/state", 30, step=29), "state_steps", 29),
    "state time jumps": (_set("plant/state", 40, time_s=40.5 * DT_S), "state_time", 40),
    "command answers no state": (_set("controller/command", N + 1, step=N + 5), "command_answers", N + 5),
    "command step repeated": (_set("controller/command", 21, step=20), "command_answers", 20),
    "command time is not its state's": (_set("controller/command", 12, time_s=0.5), "command_answers", 12),
    "command power above the controller's bound": (_set("controller/command", 7, power_w=351.0), "power_bounds", 7),
    "applied power above the plant's bound": (_set("plant/state", 8, power_w=400.0), "power_bounds", 8),
    "payload not valid against its schema": (_corrupt, "schema", None),
    "foreign run id": (_set("controller/diagnostics", 5, run_id="other"), "run_id", 5),
    "state before the plant's start": (_start_late, "lifecycle", 0),
    "message after the end event": (_log_after_end, "lifecycle", None),
    "log names no node": (_ghost_log, "node_names", None),
}


def run_checker(path, *extra):
    run = forked_cli.run("-m", "messages.conformance", str(path), *extra)
    return run.returncode, run.stdout, run.stderr


def test_clean_recording_conforms(tmp_path, capsys):
    path = write(tmp_path / "clean.mcap", clean_run())
    assert conformance.main([str(path)]) == 0
    assert capsys.readouterr().out == f"{path}: conforming; {len(clean_run())} messages, nodes controller, plant, " \
                                      "recorder\n"


@pytest.mark.parametrize("name", MUTATIONS)
def test_each_mutation_violates_its_rule(tmp_path, capsys, name):
    edit, rule, step = MUTATIONS[name]
    msgs = clean_run()
    edit(msgs)
    path = write(tmp_path / "mutated.mcap", msgs)
    assert conformance.main([str(path), "--json"]) == 1
    result = json.loads(capsys.readouterr().out)
    assert result["conforming"] is False
    assert result["rules"][rule]["ok"] is False and result["rules"][rule]["first_step"] == step, result["rules"][rule]
    assert conformance.main([str(path)]) == 1
    lines = capsys.readouterr().out.splitlines()
    assert any(line.startswith(f"{rule} [") for line in lines) and "NOT conforming" in lines[-1]


def test_counts_that_do_not_reconcile(tmp_path):
    msgs = clean_run()
    path = write(tmp_path / "counts.mcap", msgs, counts={"complete": "true", "published": "{}", "recorded": "{}"})
    report = conformance.check(path)
    assert set(report.found) == {"counts"} and report.found["counts"].count == 2
    write(path, msgs, counts={"complete": "false", "incomplete_reason": "no confirmed end of plant"})
    assert "complete = 'false': no confirmed end of plant" in conformance.check(path).found["counts"].first


def test_unfinished_file_fails_finished(tmp_path):
    full = write(tmp_path / "full.mcap", clean_run()).read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(full[: len(full) // 2])
    assert "finished" in conformance.check(cut).found


def test_node_filter_reports_only_that_node(tmp_path, capsys):
    msgs = clean_run()
    _set("controller/command", 7, power_w=351.0)(msgs)
    _set("plant/state", 9, power_w=400.0)(msgs)
    _set("plant/state", 10, power_w=400.0)(msgs)
    path = write(tmp_path / "m.mcap", msgs)
    assert conformance.main([str(path)]) == 1
    assert "power_bounds [controller, plant]: 3 violations; first at step 7" in capsys.readouterr().out
    assert conformance.main([str(path), "--node", "plant"]) == 1
    assert "power_bounds [plant]: 2 violations; first at step 9" in capsys.readouterr().out
    assert conformance.main([str(path), "--node", "controller"]) == 1
    assert "power_bounds [controller]: 1 violation; first at step 7" in capsys.readouterr().out
    assert conformance.main([str(path), "--node", "recorder"]) == 0


@pytest.mark.parametrize("make, message", [
    (lambda tmp: tmp / "missing.mcap", "recording not found"),
    (lambda tmp: (tmp / "x.mcap").write_text("hello") and tmp / "x.mcap", "not an MCAP file"),
])
def test_usage_errors_exit_2_in_one_line(tmp_path, make, message):
    status, out, err = run_checker(make(tmp_path))
    assert status == 2 and out == "" and err.count("\n") == 1 and message in err


def test_real_run_conforms_and_a_broken_step_sequence_does_not(tmp_path, mpc_run):
    status, output, out = mpc_run
    assert status == 0, output
    status, stdout, _ = run_checker(out)
    assert status == 0 and stdout.strip().endswith("nodes controller, plant, recorder"), stdout

    source = read_recording(out)
    broken = tmp_path / "broken.mcap"
    with broken.open("wb") as stream:
        writer = Writer(stream, compression=CompressionType.ZSTD)
        writer.start(profile="", library="test")
        schemas = {i: writer.register_schema(name=s.name, encoding=s.encoding, data=s.data)
                   for i, s in source.schemas.items()}
        channels = {i: writer.register_channel(topic=c.topic, message_encoding=c.message_encoding,
                                               schema_id=schemas[c.schema_id]) for i, c in source.channels.items()}
        for name, data in source.metadata.items():
            writer.add_metadata(name, data)
        for m in source.messages:
            state = source.channels[m.channel_id].topic == "/plant/state" and json.loads(m.data)["step"] == 17
            if not state:  # drop state 17
                writer.add_message(channel_id=channels[m.channel_id], log_time=m.log_time, data=m.data,
                                   publish_time=m.publish_time, sequence=m.sequence)
        writer.finish()
    status, stdout, _ = run_checker(broken)
    assert status == 1
    assert "state_steps [plant]: 1 violation; first at step 18: step 18 where 17 was due (gap)" in stdout
