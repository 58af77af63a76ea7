"""launch.py supervises real node processes: readiness, failure, and orderly shutdown."""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from messages.recording import is_complete, is_finished, metadata, read_messages
from tests import forked_cli
from tests.conftest import REPO, finish
from tests.test_recorder import validate_recording

NODES = """
[[node]]
name = "recorder"
module = "messages.recorder"

[[node]]
name = "ticker"
module = "tests.nodes.ticker"
roles = ["plant"]
args = {ticker_args}
main = true
"""


def start_launch(tmp_path, ticker_args, *extra):
    nodes = tmp_path / "nodes.toml"
    nodes.write_text(NODES.format(ticker_args=ticker_args))
    out = tmp_path / "run.mcap"
    proc = subprocess.Popen(
        [sys.executable, "launch.py", "--nodes", str(nodes), "--out", str(out), *extra],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )
    return proc, out


def child_pids(output: str) -> list[int]:
    return [int(p) for p in re.findall(r"started \S+ \(pid (\d+)\)", output)]


def alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    return True


def test_launch_help():
    out = forked_cli.run("launch.py", "--help")
    assert out.returncode == 0 and "usage" in out.stdout.lower()


def test_run_to_completion_records_everything(tmp_path):
    proc, out = start_launch(tmp_path, '["--steps", "300", "--rate-hz", "1000", "--require", "recorder"]', "--json")
    status, output = finish(proc, timeout=60)
    assert status == 0, output
    assert "[ticker] published 300 states" in output
    assert is_complete(out)
    assert validate_recording(out)["/plant/state"] == 300
    assert [s.step for s in read_messages(out, "/plant/state")] == list(range(300))


def test_sigint_stops_every_node_within_10_s_and_finishes_the_mcap(tmp_path):
    proc, out = start_launch(tmp_path, '["--steps", "0", "--require", "recorder"]')
    deadline = time.monotonic() + 30
    lines = []
    while time.monotonic() < deadline:
        line = proc.stdout.readline()
        lines.append(line)
        if "[ticker] info: step 100" in line:
            break
    pids = child_pids("".join(lines))
    assert len(pids) == 2, "".join(lines)
    proc.send_signal(signal.SIGINT)
    t0 = time.monotonic()
    status, output = finish(proc, timeout=15)
    assert status == 130, output
    while any(alive(p) for p in pids) and time.monotonic() - t0 < 10:
        time.sleep(0.1)
    assert not any(alive(p) for p in pids)
    assert time.monotonic() - t0 < 10
    counts = validate_recording(out)
    assert counts["/plant/state"] > 100
    assert is_finished(out)  # a footer and closing metadata; complete or not depends on who stopped first
    assert metadata(out)["meltloop.counts"]["complete"] in ("true", "false")


def test_failing_node_ends_the_run_with_a_clear_message(tmp_path):
    proc, out = start_launch(tmp_path, '["--steps", "0", "--require", "recorder", "--fail-at", "20"]')
    status, output = finish(proc, timeout=60)
    assert status == 1
    assert "node ticker exited with status 3" in output
    assert out.is_file(), output[-4000:]   # (one CI run on a loaded host: no recording, cause not seen)
    validate_recording(out)  # readable up to the fault


def test_a_node_that_finishes_before_it_is_seen_ready_ends_the_run_with_0(tmp_path):
    """A short run can end with status 0 faster than the launch's readiness query sees its token:
    the launch then judges the run by the exit status, not as a failure to become ready."""
    nodes = tmp_path / "nodes.toml"
    nodes.write_text('[[node]]\nname = "quick"\nmodule = "tests.nodes.finished"\nmain = true\n')
    run = subprocess.run([sys.executable, "launch.py", "--nodes", str(nodes), "--out", str(tmp_path / "run.mcap")],
                         cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 0, run.stdout + run.stderr
    assert "before it was ready" not in run.stdout + run.stderr


def test_a_node_started_without_a_readiness_wait_that_fails_ends_the_wait_for_the_next(tmp_path):
    """``launch.py`` starts the controller beside the plant (``wait_ready = false``), and the plant waits for
    it: a node started so that fails must end the launch's wait for the next node's readiness at once,
    naming it (the waiting node would otherwise give up only at its own timeout, 60 s)."""
    nodes = tmp_path / "nodes.toml"
    nodes.write_text('[[node]]\nname = "broken"\nmodule = "tests.nodes.no_such_node"\nwait_ready = false\n\n'
                     '[[node]]\nname = "waiter"\nmodule = "tests.nodes.ticker"\n'
                     'args = ["--steps", "0", "--require", "broken"]\nmain = true\n')
    run = subprocess.run([sys.executable, "launch.py", "--nodes", str(nodes), "--out", str(tmp_path / "run.mcap")],
                         cwd=REPO, capture_output=True, text=True, timeout=40)
    assert run.returncode == 1, run.stdout + run.stderr
    assert "node broken exited with status 1 while the launch waited for waiter to be ready" in run.stdout


def test_the_default_run_starts_the_controller_beside_the_plant():
    """The plant waits for the controller itself (``--require controller``), so the launch does not wait for
    the controller's readiness before starting the plant: their start-ups overlap."""
    from launch import RunOptions, default_nodes

    specs = {s.name: s for s in default_nodes(RunOptions(), Path("run.mcap"))}
    assert specs["controller"].wait_ready is False and specs["recorder"].wait_ready is True
    plant = list(specs["plant"].args)
    assert [plant[i + 1] for i, a in enumerate(plant) if a == "--require"] == ["recorder", "controller"]


def test_bad_node_list_exit_2(tmp_path):
    bad = tmp_path / "bad.toml"
    bad.write_text("[[node]]\nname='x'\n")
    out = forked_cli.run("launch.py", "--nodes", str(bad))
    assert out.returncode == 2
    assert out.stderr.count("\n") == 1 and "without 'module'" in out.stderr


def test_verdict_of_a_run():
    from messages.launch.service import verdict

    assert verdict([("rec", None, False), ("plant", None, True)], None, 1.0, 15.0) == (None, None, "")
    assert verdict([("rec", None, False), ("plant", 0, True)], None, 1.0, 15.0) == (None, 1.0, "")
    assert verdict([("rec", 0, False), ("plant", 0, True)], 1.0, 2.0, 15.0) == (0, 1.0, "")
    assert verdict([("rec", None, False), ("plant", 0, True)], 1.0, 17.0, 15.0) == (
        1, 1.0, "rec still running 15 s after the run finished")
    assert verdict([("rec", 2, False), ("plant", None, True)], None, 1.0, 15.0) == (
        1, None, "node rec exited with status 2")
    assert verdict([("rec", None, False), ("aux", 0, False)], None, 1.0, 15.0) == (None, None, "")


def running(pid: int) -> bool:
    """Whether ``pid`` is a process that has not ended (an unreaped zombie has ended)."""
    try:
        return Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()[0] != "Z"
    except FileNotFoundError:
        return False


@pytest.mark.skipif(not Path("/proc").is_dir(), reason="needs Linux /proc")
def test_stop_ends_the_children_of_a_wrapper_script_node(tmp_path):
    """A node that is a shell script starting the real program: stopping the node stops both
    (the background child ignores SIGINT, as a non-interactive shell's background jobs do)."""
    from messages.launch.node import NodeProcess, NodeSpec

    script = tmp_path / "wrapper.sh"
    script.write_text('#!/bin/sh\nsleep 300 &\necho "child $!"\nwait\n')
    script.chmod(0o755)
    lines: list[str] = []
    node = NodeProcess.spawn(NodeSpec("wrapped", command=(str(script),)), "r", "tcp/127.0.0.1:9", {},
                             lines.append, lines.append)
    node.sigint_timeout_s = node.sigterm_timeout_s = 1.0
    deadline = time.monotonic() + 10
    while not (found := [line for line in lines if line.startswith("[wrapped] child ")]):
        assert time.monotonic() < deadline, lines
        time.sleep(0.02)
    child = int(found[0].split()[-1])
    assert running(child)
    node.stop()
    assert node.poll() is not None
    assert not running(child), lines


def test_every_controller_commands_the_plants_scan_speed(tmp_path):
    """Power-only control: a controller commands its nominal speed, so launch.py gives it the plant's
    (``[plant] speed_m_s``) and refuses a ``[controller] nominal_speed_m_s`` that differs from it."""
    from controller_node.node import build_parser, settings_from_args
    from launch import RunOptions, check_config, default_nodes
    from messages.cli import UsageError

    config = tmp_path / "slow.toml"
    config.write_text("[plant]\nspeed_m_s = 0.6\n")
    for controller in ("pid", "preview-mpc"):
        opts = RunOptions(controller=controller, config=config)
        args = list({n.name: n for n in default_nodes(opts, tmp_path / "r.mcap")}["controller"].args)
        assert float(args[args.index("--nominal-speed-m-s") + 1]) == 0.6
    assert settings_from_args(build_parser().parse_args(args)).nominal_speed_m_s == 0.6
    check_config(RunOptions(controller="pid", config=config))
    config.write_text("[plant]\nspeed_m_s = 0.6\n[controller]\nnominal_speed_m_s = 0.8\n")
    with pytest.raises(UsageError, match=r"\[controller\] nominal_speed_m_s: 0.8 m/s, but the plant scans at 0.6"):
        check_config(RunOptions(controller="pid", config=config))
    config.write_text("[plant]\nspeed_m_s = 0.6\n[controller]\nnominal_speed_m_s = 0.6\n")
    check_config(RunOptions(controller="pid", config=config))
    nodes = {n.name: n for n in default_nodes(RunOptions(controller="pid", config=config), tmp_path / "r.mcap")}
    assert "--nominal-speed-m-s" not in nodes["controller"].args  # the user's own, read by the node
