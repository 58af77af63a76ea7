"""``--nodes`` lists: ``command = [...]`` for any executable, one-line usage errors naming the key."""

from __future__ import annotations

import sys

import pytest

from messages.cli import UsageError
from messages.launch.node import NodeSpec, load_node_list
from tests import forked_cli
from tests.conftest import REPO


def _load(tmp_path, text):
    path = tmp_path / "nodes.toml"
    path.write_text(text)
    return load_node_list(path)


def test_command_node_gets_the_appended_arguments(tmp_path):
    (spec,) = _load(tmp_path, f'[[node]]\nname = "cam"\ncommand = ["{sys.executable}", "cam.py", "--x"]\n'
                              'args = ["--rate-hz", "10"]\nroles = ["plant"]\nmain = true\n')
    assert spec.command == (sys.executable, "cam.py", "--x") and spec.module == "" and spec.main
    assert spec.argv("R", "tcp/127.0.0.1:1") == [sys.executable, "cam.py", "--x", "--rate-hz", "10",
                                                 "--run-id", "R", "--connect", "tcp/127.0.0.1:1"]


def test_module_node_runs_unbuffered_python():
    spec = NodeSpec("plant", "fe_node", ("--max-steps", "3"))
    assert spec.argv("R", "E") == [sys.executable, "-u", "-m", "fe_node", "--max-steps", "3",
                                   "--run-id", "R", "--connect", "E"]
    assert spec.roles == ("plant",)


@pytest.mark.parametrize("body, expected", [
    ('name = "a"\nmodule = "m"\ncommand = ["python"]', "node 'a' has both 'module' and 'command'"),
    ('name = "a"', "node 'a' without 'module' or 'command'"),
    ('name = "a"\ncommand = []', "node 'a': 'command' must name an executable"),
    ('name = "a"\ncommand = [""]', "node 'a': 'command' must name an executable"),
    ('name = "a"\ncommand = "python x.py"', "node 'a': 'command' must be a list of strings"),
    ('name = "a"\ncommand = ["python", 3]', "node 'a': 'command' must be a list of strings"),
    ('name = "a"\ncommand = ["no-such-exe-4711"]', "'command' executable 'no-such-exe-4711' not found"),
    ('name = "a"\ncommand = ["./README.md"]', "'command' executable './README.md' not found or not executable"),
    ('name = "a"\nmodule = "m"\nargs = "--x"', "node 'a': 'args' must be a list of strings"),
    ('name = "a"\nmodule = "m"\nmain = "yes"', "node 'a': 'main' must be true or false"),
    ('name = "a"\nmodule = "m"\nroles = ["camera"]', "invalid roles ['camera'] for node 'a'"),
    ('name = "a"\nmodule = "m"\nexe = "x"', "unknown node keys ['exe']"),
])
def test_bad_entries_are_one_line_usage_errors(tmp_path, body, expected):
    with pytest.raises(UsageError, match="^--nodes .*nodes.toml: ") as err:
        _load(tmp_path, f"[[node]]\n{body}\n")
    assert expected in str(err.value)


def test_launch_exits_2_naming_the_command_key(tmp_path):
    nodes = tmp_path / "nodes.toml"
    nodes.write_text('[[node]]\nname = "cam"\ncommand = ["no-such-exe-4711", "--x"]\n')
    run = forked_cli.run("launch.py", "--nodes", str(nodes), "--out", str(tmp_path / "r.mcap"))
    assert run.returncode == 2 and run.stdout == ""
    assert run.stderr.count("\n") == 1 and "'command' executable 'no-such-exe-4711' not found" in run.stderr


def test_contract_states_what_the_launch_service_appends_and_sets():
    from messages.auth import PASSWORD_ENV, USER_ENV
    from messages.bus import SUPERVISOR_ENV

    doc = (REPO / "docs" / "launch.md").read_text(encoding="utf-8")
    tail = NodeSpec("n", command=(sys.executable,)).argv("RUN", "ENDPOINT")[1:]
    assert f"COMMAND... ARGS... {' '.join(tail)}" in doc
    for variable in (USER_ENV, PASSWORD_ENV, SUPERVISOR_ENV, "PYTHONUNBUFFERED"):
        assert f"| `{variable}` |" in doc
