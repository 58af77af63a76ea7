"""Calling a compiled (numba) function on a hot path without the dispatcher's type resolution, and
compiling a package's functions once when several processes start together."""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

from numba import typeof

__all__ = ["BoundOnFirstCall", "compile_lock"]


_HELD = threading.local()
"""``folders``: the package folders whose compile lock this thread holds."""

COMPILE_NOTICE_S = 2.0
"""Seconds inside :func:`compile_lock` (waiting for it, or compiling under it) after which a line on
stderr says what the process is doing: loading from numba's cache takes well under a second, a
compilation tens of seconds."""


@contextlib.contextmanager
def compile_lock(module_file: str) -> Iterator[None]:
    """Hold an exclusive lock on ``__pycache__/numba-compile.lock`` beside ``module_file`` while compiling
    (or loading from numba's cache) that package's functions.

    On a fresh install numba compiles each function in every process that calls it before its cache file
    exists: processes that start together (pytest's workers, a campaign's Dask workers, the nodes of a run)
    would each compile the same code, the preview MPC's about 30 s of CPU. Under the lock the first
    process compiles and writes numba's cache and the others then load it. Without a writable
    ``__pycache__`` (an installed, read-only package) or ``fcntl`` (not POSIX) it does nothing; taken again
    by the thread that holds it, it does nothing.
    """
    folder = Path(module_file).resolve().parent
    held = _HELD.__dict__.setdefault("folders", set())
    if folder in held:        # taken again inside itself: already this thread's (flock would wait on itself)
        yield
        return
    try:
        import fcntl

        lock_path = folder / "__pycache__" / "numba-compile.lock"
        lock_path.parent.mkdir(exist_ok=True)
        lock = lock_path.open("a")
    except (ImportError, OSError):
        yield
        return
    with lock, _notice(folder.name):
        fcntl.flock(lock, fcntl.LOCK_EX)
        held.add(folder)
        try:
            yield
        finally:
            held.discard(folder)


@contextlib.contextmanager
def _notice(package: str) -> Iterator[None]:
    """Print on stderr, from a timer thread, that ``package``'s compiled functions are being prepared if
    the block (the lock's wait and what runs under it) is still running after :data:`COMPILE_NOTICE_S`,
    and then how long it took when it ends: a node's first run after an install is otherwise silent for
    tens of seconds."""
    start, said = time.monotonic(), threading.Event()

    def say() -> None:
        said.set()
        print(f"info: preparing the compiled functions of {package}: numba compiles them once after an install or a "
              "change (up to a minute, one process at a time); later runs load them from its cache",
              file=sys.stderr, flush=True)

    timer = threading.Timer(COMPILE_NOTICE_S, say)
    timer.daemon = True
    timer.start()
    try:
        yield
    finally:
        timer.cancel()
        if said.is_set():
            print(f"info: the compiled functions of {package} ready after {time.monotonic() - start:.1f} s",
                  file=sys.stderr, flush=True)


class BoundOnFirstCall:
    """A compiled function whose ``call`` goes through numba's dispatcher once (compiling or loading),
    then straight to the machine code of that call's argument types, skipping the dispatcher's type
    resolution, a large part of a cold call's cost that grows with the number of arguments
    (``docs/controller.md``, Speed).

    The caller must pass the same argument types every time (dtype, dimensions and layout of each
    array, kind of each scalar): the machine code does not check them.

    Parameters
    ----------
    dispatcher : numba.core.registry.CPUDispatcher
        The ``@njit`` function.
    """

    def __init__(self, dispatcher) -> None:
        self._dispatcher = dispatcher
        self.call = self._first

    def _first(self, *args):  # noqa: ANN002, ANN202
        result = self._dispatcher(*args)
        self.call = self._dispatcher.overloads[tuple(typeof(a) for a in args)].entry_point
        return result
