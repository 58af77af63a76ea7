"""The closed loop end to end through ``launch.py``: real processes, zenoh, FE plant, MCAP."""

from __future__ import annotations

import json
import subprocess
import sys

from messages.recording import is_complete, metadata, read_messages, run_config
from tests.conftest import REPO
from tests.plants import BARE_ARGS
from tests.test_recorder import validate_recording


def run_launch(*args: str, timeout: float = 240) -> tuple[int, str]:
    proc = subprocess.run([sys.executable, "launch.py", "--no-progress", *args], cwd=REPO,
                          capture_output=True, text=True, timeout=timeout)
    return proc.returncode, proc.stdout + proc.stderr


def test_short_mpc_run_is_complete_valid_and_reported(tmp_path, mpc_run):
    status, output, out = mpc_run
    assert status == 0, output
    summary = json.loads(output.strip().splitlines()[-1])
    assert summary["steps"] == 100 and summary["recording"] == str(out)
    for key in ("overshoot_pct", "undershoot_pct", "steady_rmse_pct", "wall_s"):
        assert isinstance(summary[key], float)

    # Every message valid against its channel's JSON Schema, and nothing published is missing.
    assert is_complete(out)
    counts = validate_recording(out)
    meta = metadata(out)["meltloop.counts"]
    published, recorded = json.loads(meta["published"]), json.loads(meta["recorded"])
    assert all(recorded[topic] >= n for topic, n in published.items()), (published, recorded)
    assert counts["/plant/state"] == 101 and counts["/controller/command"] == 101  # one answer per state
    assert counts["/plant/temperature"] >= 10 and counts["/log"] >= 2
    assert counts["/plant/laser"] == 101 and counts["/plant/scene"] == 1      # one layer: one scene
    states = list(read_messages(out, "/plant/state"))
    poses = list(read_messages(out, "/plant/laser"))
    assert all(abs(p.pose.position.x * 1e3 - s.laser_x_mm) < 1e-9 and p.frame_id == "plate"
               for p, s in zip(poses, states, strict=True))
    scene = next(iter(read_messages(out, "/plant/scene")))
    assert [e.id for e in scene.entities] == ["scan_plan"] and len(scene.entities[0].lines[0].points) == 8
    commands = {c.step: c for c in read_messages(out, "/controller/command")}
    assert all(s.power_w == commands[s.step].power_w for s in states[1:])  # the plant applied what was commanded
    assert all(0.0 <= c.power_w <= 350.0 for c in commands.values())
    assert set(run_config(out)) == {"recorder", "controller", "plant"}

    # The report command reads the recording back.
    figure = tmp_path / "fig5.png"
    proc = subprocess.run([sys.executable, "-m", "controller_node.report", str(out), "--figure", str(figure), "--json"],
                          cwd=REPO, capture_output=True, text=True, timeout=60)
    assert proc.returncode == 0, proc.stderr
    report = json.loads(proc.stdout.strip().splitlines()[-1])
    assert (report["steady_rmse_pct"] == summary["steady_rmse_pct"]
            or abs(report["steady_rmse_pct"] - summary["steady_rmse_pct"]) < 0.01)
    assert figure.stat().st_size > 10_000


def test_open_loop_profile_run(tmp_path):
    out = tmp_path / "case2.mcap"
    status, output = run_launch("--scenario", "table2-case2", "--controller", "none", "--max-steps", "60",
                                "--h-um", "40", "--out", str(out), "--json")
    assert status == 0, output
    powers = [s.power_w for s in read_messages(out, "/plant/state")][1:]
    assert len(powers) == 60 and max(powers) - min(powers) > 10  # the sinusoidal power profile is played


def test_same_config_gives_the_same_recording(tmp_path):
    """Two runs of one configuration, side by side (each on its own hub), record the same states."""
    outs = [tmp_path / f"{name}.mcap" for name in ("a", "b")]
    procs = [subprocess.Popen([sys.executable, "launch.py", "--no-progress", "--controller", "pid", "--max-steps", "40",
                               "--h-um", "40", *BARE_ARGS, "--out", str(out)], cwd=REPO, stdout=subprocess.PIPE,
                              stderr=subprocess.STDOUT, text=True) for out in outs]
    traces = []
    for proc, out in zip(procs, outs):
        output, _ = proc.communicate(timeout=240)
        assert proc.returncode == 0, output
        traces.append([(s.step, s.area_mm2, s.power_w, s.t_ahead_k) for s in read_messages(out, "/plant/state")])
    assert traces[0] == traces[1]

