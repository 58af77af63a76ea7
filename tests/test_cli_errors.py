"""Bad command-line values for every entry point: exit status 2 and one line on stderr."""

from __future__ import annotations

import ast
import os
import subprocess
import sys

import pytest

from messages.cli import SIGPIPE_STATUS
from tests import forked_cli
from tests.conftest import REPO

CASES = [
    # launch.py
    (["launch.py", "--controller", "bogus"], "--controller: choose one of"),
    (["launch.py", "--setpoint-mm2", "-1"], "--setpoint-mm2 must be in"),
    (["launch.py", "--max-steps", "0"], "--max-steps must be >= 1"),
    (["launch.py", "--scenario", "nope"], "--scenario: unknown 'nope'"),
    (["launch.py", "--config", "missing.toml"], "--config: file not found"),
    (["launch.py", "--h-um", "0"], "--h-um must be in (0, 1000]"),
    (["launch.py", "--h-um", "-5"], "--h-um must be in (0, 1000]"),
    (["launch.py", "--fallback", "off"], "--fallback must be 'safe' or 'hold'"),
    (["launch.py", "--command-timeout-s", "0"], "--command-timeout-s must be in (0, 60]"),
    (["launch.py", "--out", "/proc/meltloop/run.mcap"], "--out /proc/meltloop/run.mcap: cannot create its folder"),
    (["launch.py", "--run-id", "bad id"], "invalid run id"),
    (["launch.py", "--hub", "nonsense"], "invalid zenoh endpoint"),
    (["launch.py", "--max-steps", "x"], "invalid int value"),
    (["launch.py", "--part", "fe_node/parts/cylinder_d1.5_h0.5_mm.stl"], "--part needs --scenario part"),
    (["launch.py", "--scenario", "part", "--part", "missing.stl"], "--part: file not found: missing.stl"),
    (["launch.py", "--layers", "0"], "--layers must be >= 1"),
    (["launch.py", "--controller", "none", "--fallback", "hold"], "with --controller none there are none"),
    (["launch.py", "--out", "run.txt"], "--out run.txt: must name a .mcap file (a folder only with --compare)"),
    (["launch.py", "--out", "recordings"], "--out recordings: must name a .mcap file"),
    (["launch.py", "--h-um", "1000"], "mesh too coarse for the beam: h_fine_m 0.001 m"),
    (["launch.py", "--controller", "pid", "--model", "gp_model/models/in625_gp.json"],
     "--model: the pid controller uses no model"),
    (["launch.py", "--model", "README.md"], "cannot load GP model README.md"),
    (["launch.py", "--process", "missing.json"], "--process: file not found: missing.json"),
    (["launch.py", "--controller", "pid", "--process", "README.md"], "--process: model file README.md is not valid"),
    (["launch.py", "--controller", "mpc", "--model", "gp_model/models/in625_narx_gp.json"],
     "is not a meltloop-gp-model file"),
    (["launch.py", "--compare", "--controller", "pid"], "--controller cannot be combined with --compare"),
    (["launch.py", "--compare", "--learning-state", "x.json"], "--learning-state cannot be combined with --compare"),
    (["-m", "fe_node", "--part", "fe_node/parts/cylinder_d1.5_h0.5_mm.stl"], "--part needs --scenario part"),
    # the FE plant node
    (["-m", "fe_node", "--max-steps", "0"], "--max-steps must be >= 1"),
    (["-m", "fe_node", "--command-timeout-s", "0"], "--command-timeout-s must be finite and > 0"),
    (["-m", "fe_node", "--power-min-w", "300", "--power-max-w", "200"], "power bounds"),
    (["-m", "fe_node", "--safe-power-w", "999"], "--safe-power-w must lie within"),
    (["-m", "fe_node", "--fallback", "panic"], "invalid choice"),
    (["-m", "fe_node", "--connect", "tcp"], "invalid zenoh endpoint"),
    (["-m", "fe_node", "--zenoh-config", "missing.json5"], "zenoh config file not found"),
    # controller node
    (["-m", "controller_node", "--controller", "bogus"], "invalid choice"),
    (["-m", "controller_node", "--run-id=_x"], "invalid run id"),
    (["-m", "controller_node", "--config", "missing.toml"], "config file not found"),
    (["-m", "controller_node", "--setpoint-mm2", "nan"], "must be a finite number"),
    (["-m", "controller_node", "--require", "a/b"], "invalid node name"),
    (["-m", "controller_node", "--controller", "pid", "--model", "gp_model/models/in625_gp.json"],
     "--model: the pid controller uses no model"),
    # recorder
    (["-m", "messages.recorder", "--out", "x.txt"], "--out must name a .mcap file"),
    (["-m", "messages.recorder", "--drain-s", "-1"], "--drain-s must be >= 0"),
    (["-m", "messages.recorder", "--drain-s", "nan"], "--drain-s must be >= 0 and at most 60 s, got nan"),
    # example sensor, surrogate (free-running plants)
    (["-m", "fe_node.example_sensor", "--rate-hz", "0"], "--rate-hz must be in"),
    (["-m", "fe_node.example_sensor", "--rate-hz", "1e9"], "--rate-hz must be in"),
    (["-m", "fe_node.example_sensor", "--max-steps", "0"], "--max-steps must be >= 1"),
    (["-m", "fe_node.example_sensor", "--duration-s", "0"], "--duration-s must be > 0"),
    (["-m", "fe_node.example_sensor", "--power-w", "500"], "must lie within the command bounds"),
    (["-m", "fe_node.example_sensor", "--command-timeout-s", "-1"], "--command-timeout-s must be finite and > 0"),
    (["-m", "fe_node.surrogate", "--rate-hz", "-5"], "--rate-hz must be in"),
    (["-m", "fe_node.surrogate", "--model", "missing.json"], "cannot load GP model"),
    (["-m", "fe_node.surrogate", "--speed-mm-s", "0"], "must lie within the command bounds"),
    # replay
    (["-m", "fe_node.replay", "missing.mcap"], "recording not found"),
    (["-m", "fe_node.replay", "README.md", "--rate-scale", "-1"], "--rate-scale must be finite and > 0"),
    (["-m", "fe_node.replay"], "the following arguments are required"),
    # offline tools
    (["-m", "fe_node", "run", "--scenario", "nope"], ""),
    (["-m", "gp_trainer", "train", "--restarts", "-1"], ""),
    (["-m", "gp_trainer", "bogus"], "invalid choice"),
]


@pytest.mark.parametrize("argv, message", CASES, ids=[" ".join(a) for a, _ in CASES])
def test_bad_value_exits_2_with_one_line(argv, message):
    run = forked_cli.run(*argv)
    assert run.returncode == 2, run.stdout + run.stderr
    lines = run.stderr.splitlines()
    assert len(lines) == 1 and "error" in lines[0] and message in lines[0], run.stderr


def test_launch_refuses_default_node_options_with_a_node_list(tmp_path):
    nodes = tmp_path / "nodes.toml"
    nodes.write_text('[[node]]\nname = "recorder"\nmodule = "messages.recorder"\n')
    run = forked_cli.run("launch.py", "--nodes", str(nodes), "--setpoint-mm2", "0.07", "--h-um", "20")
    assert run.returncode == 2 and run.stderr.count("\n") == 1, run.stderr
    assert "--setpoint-mm2, --h-um cannot be combined with --nodes" in run.stderr


def test_launch_with_its_hub_port_in_use_fails_in_one_line():
    import socket

    with socket.socket() as busy:
        busy.bind(("127.0.0.1", 0))
        busy.listen()
        port = busy.getsockname()[1]
        run = subprocess.run([sys.executable, "launch.py", "--hub", f"tcp/127.0.0.1:{port}", "--max-steps", "5"],
                             cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 1 and run.stdout == "", run.stdout
    assert run.stderr.count("\n") == 1 and "cannot open the run's hub" in run.stderr, run.stderr


def _run_with_reader_gone(argv: list[str], unbuffered: bool) -> subprocess.CompletedProcess:
    """Run ``python argv`` with a standard output whose reader has already closed its end."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    env = {k: v for k, v in os.environ.items() if k != "PYTHONUNBUFFERED"}
    env.update({"PYTHONUNBUFFERED": "1"} if unbuffered else {})
    try:
        return subprocess.run([sys.executable, *argv], cwd=REPO, stdout=write_end, stderr=subprocess.PIPE, text=True,
                              env=env, timeout=60)
    finally:
        os.close(write_end)


PRINTS_AND_RETURNS = "from messages.cli import run_main\nrun_main(lambda: print('x' * 100_000) or 3)"


@pytest.mark.parametrize("unbuffered", [False, True], ids=["buffered", "unbuffered"])
@pytest.mark.parametrize("argv", [["launch.py", "--help"], ["-c", PRINTS_AND_RETURNS]], ids=["launch.py", "run_main"])
def test_a_reader_that_leaves_early_ends_the_program_quietly(argv, unbuffered):
    """``... | head -1``: no traceback, no "Exception ignored" message; status 141 as for SIGPIPE
    (0 where argparse's help already ignored the failed write). Every other entry point ends the
    same way through :func:`messages.cli.run_main` (the next test)."""
    run = _run_with_reader_gone(argv, unbuffered)
    assert run.stderr == "", run.stderr
    expected = {0, SIGPIPE_STATUS} if unbuffered and argv[-1] == "--help" else {SIGPIPE_STATUS}
    assert run.returncode in expected


def _calls_run_main(statements: list[ast.stmt]) -> bool:
    """Whether one of ``statements`` is the expression ``run_main(...)``."""
    return any(isinstance(st, ast.Expr) and isinstance(st.value, ast.Call) and isinstance(st.value.func, ast.Name)
               and st.value.func.id == "run_main" for st in statements)


def _is_main_guard(st: ast.stmt) -> bool:
    return isinstance(st, ast.If) and ast.unparse(st.test) in ("__name__ == '__main__'", '__name__ == "__main__"')


def test_every_entry_point_runs_through_run_main():
    """A program started as ``python -m <package>``, ``python -m <module>`` or ``python launch.py``
    exits through ``run_main`` (the reader-gone handling tested above)."""
    paths = [REPO / "launch.py", *(p for package in ("messages", "gp_model", "fe_node", "controller_node", "gp_trainer")
                                   for p in sorted((REPO / package).rglob("*.py")))]
    entry_points = 0
    for path in paths:
        body = ast.parse(path.read_text(encoding="utf-8")).body
        guards = [st for st in body if _is_main_guard(st)]
        if path.name == "__main__.py":
            entry_points += 1
            assert _calls_run_main(body), path
        for guard in guards:
            entry_points += 1
            assert _calls_run_main(guard.body), path
    assert entry_points >= 16


def test_run_main_passes_on_the_status_and_other_broken_pipes():
    done = subprocess.run([sys.executable, "-c", PRINTS_AND_RETURNS], cwd=REPO, capture_output=True, text=True,
                          timeout=60)
    assert done.returncode == 3 and len(done.stdout) == 100_001
    other_pipe = ("import os\nfrom messages.cli import run_main\nr, w = os.pipe()\nos.close(r)\n"
                  "run_main(lambda: os.write(w, b'x'))")
    run = subprocess.run([sys.executable, "-c", other_pipe], cwd=REPO, capture_output=True, text=True, timeout=60)
    assert run.returncode == 1 and "BrokenPipeError" in run.stderr, run.stderr


@pytest.mark.parametrize("table, message", [
    ("power_max_w = 1e6", "power bounds [0, 1e+06] W must lie within the plant's [0, 350] W"),
    ("nominal_speed_m_s = 9.0", "nominal_speed_m_s 9 m/s must lie within the plant's [0.05, 5] m/s"),
])
def test_launch_refuses_controller_bounds_the_plant_would_drop(tmp_path, table, message):
    config = tmp_path / "run.toml"
    config.write_text(f"[controller]\n{table}\n")
    run = forked_cli.run("launch.py", "--config", str(config))
    assert run.returncode == 2 and run.stderr.count("\n") == 1 and message in run.stderr, run.stderr
