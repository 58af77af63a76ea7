"""Command-line conventions shared by every meltloop entry point."""

from __future__ import annotations

import argparse
import os
import select
import sys
from collections.abc import Callable
from typing import NoReturn

SIGPIPE_STATUS = 141
"""Exit status of a program whose reader closed its standard output early: 128 + SIGPIPE, as a
shell reports a program killed by SIGPIPE (``yes | head -1``)."""


class UsageError(Exception):
    """A bad command line or configuration value: reported in one line, exit status 2."""


class ArgumentParser(argparse.ArgumentParser):
    """``argparse`` parser whose errors are one line (``prog: error: ...``) and exit status 2."""

    def error(self, message: str) -> NoReturn:  # noqa: D102 - argparse hook
        self.exit(2, f"{self.prog}: error: {message}\n")


def exit_error(prog: str, err: Exception) -> int:
    """Print ``err`` as a one-line run-time error of ``prog`` and return exit status 1."""
    text = " ".join(str(err).split())
    print(f"{prog}: error: {text}", file=sys.stderr)
    return 1


def exit_usage(prog: str, err: Exception) -> int:
    """Print ``err`` as a one-line usage error of ``prog`` and return exit status 2."""
    text = " ".join(str(err).split())
    print(f"{prog}: error: {text}", file=sys.stderr)
    return 2


def run_main(main: Callable[..., int | None], *args: object) -> NoReturn:
    """Run the entry point ``main(*args)`` and exit with its status.

    When the reader of standard output goes away first (``python -m controller_node.report REC
    --json | head -1``), the program ends quietly with :data:`SIGPIPE_STATUS`, not with a
    ``BrokenPipeError`` traceback or an "Exception ignored" message at exit. A broken pipe that is
    not standard output's propagates as before.
    """
    try:
        try:
            status = main(*args)
        finally:
            sys.stdout.flush()
    except BrokenPipeError:
        if not _reader_gone(sys.stdout):
            raise
        os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())  # nothing left to flush at exit
        sys.exit(SIGPIPE_STATUS)
    sys.exit(status)


def _reader_gone(stream) -> bool:
    """True when ``stream`` is a pipe whose read end is closed (its file descriptor polls POLLERR)."""
    try:
        poller = select.poll()
        poller.register(stream.fileno(), select.POLLOUT)
        return any(event & select.POLLERR for _, event in poller.poll(0))
    except (OSError, ValueError):
        return False
