"""Command-line conventions shared by every meltloop entry point."""

from __future__ import annotations

import argparse
import sys
from typing import NoReturn


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
