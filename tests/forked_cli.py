"""Short command lines as real processes, forked from one interpreter that imported the project once.

``python tests/forked_cli.py`` imports the project's entry points, then reads one JSON command per
line on its standard input (``["launch.py", ...]`` or ``["-m", "module", ...]``, as after
``python``) and answers each with one JSON line ``{"returncode", "stdout", "stderr"}``. Every command
runs in a child forked for it, with its own standard output and error, exactly as ``python argv``
runs it (``runpy``, the ``-m`` module or the script as ``__main__``), but without paying the
imports again: a test of many refused command lines takes a fraction of a second for each.
:class:`ForkedCli` is the test side.
"""

from __future__ import annotations

import atexit
import functools
import json
import os
import runpy
import subprocess
import sys
import tempfile
import traceback
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent
PRELOADED = ("launch", "fe_node.cli", "fe_node.node", "fe_node.example_sensor", "fe_node.surrogate", "fe_node.replay",
             "controller_node.node", "controller_node.report", "gp_trainer.cli", "messages.recorder")


def run_in_child(argv: list[str]) -> int:
    """What ``python argv`` does, in this process: the exit status."""
    try:
        if argv[0] == "-m":
            sys.argv = [argv[1], *argv[2:]]
            sys.modules.pop(argv[1], None)  # as under ``python -m``: the module runs as __main__ only
            runpy.run_module(argv[1], run_name="__main__", alter_sys=True)
        else:
            sys.argv = list(argv)
            runpy.run_path(argv[0], run_name="__main__")
    except SystemExit as stop:
        if stop.code is None or isinstance(stop.code, int):
            return stop.code or 0
        print(stop.code, file=sys.stderr)
        return 1
    except BaseException:  # what the interpreter would print for an uncaught exception
        traceback.print_exc()
        return 1
    return 0


def fork_and_run(argv: list[str]) -> dict:
    """Run ``argv`` in a forked child with its own output files; its status and output."""
    with tempfile.TemporaryFile() as out, tempfile.TemporaryFile() as err:
        sys.stdout.flush(), sys.stderr.flush()
        pid = os.fork()
        if pid == 0:
            os.dup2(os.open(os.devnull, os.O_RDONLY), 0)
            os.dup2(out.fileno(), 1)
            os.dup2(err.fileno(), 2)
            status = run_in_child(argv)
            sys.stdout.flush(), sys.stderr.flush()
            os._exit(status)
        _, wait_status = os.waitpid(pid, 0)
        out.seek(0), err.seek(0)
        return {"returncode": os.waitstatus_to_exitcode(wait_status),
                "stdout": out.read().decode("utf-8", "replace"), "stderr": err.read().decode("utf-8", "replace")}


def serve() -> None:
    """Answer the commands on standard input, one JSON line each, until it closes."""
    os.chdir(REPO)
    sys.path.insert(0, str(REPO))
    for name in PRELOADED:
        __import__(name)
    answers = os.fdopen(os.dup(1), "w")
    for line in sys.stdin:
        answers.write(json.dumps(fork_and_run(json.loads(line))) + "\n")
        answers.flush()


class ForkedCli:
    """The test side: one server process for many command lines."""

    def __init__(self) -> None:
        self.proc = subprocess.Popen([sys.executable, __file__], cwd=REPO, stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True)

    def run(self, argv: list[str]) -> subprocess.CompletedProcess:
        """Run ``python argv`` in the repository root; its status and output."""
        self.proc.stdin.write(json.dumps(argv) + "\n")
        self.proc.stdin.flush()
        answer = json.loads(self.proc.stdout.readline())
        return subprocess.CompletedProcess(argv, answer["returncode"], answer["stdout"], answer["stderr"])

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait(timeout=30)


@functools.cache
def shared() -> ForkedCli:
    """The one server of this test session, started on first use and closed at exit."""
    runner = ForkedCli()
    atexit.register(runner.close)
    return runner


def run(*argv: str) -> subprocess.CompletedProcess:
    """``python argv`` in the repository root, forked by the session's server: status and output."""
    return shared().run(list(argv))


if __name__ == "__main__":
    serve()
