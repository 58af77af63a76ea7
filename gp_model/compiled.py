"""Calling a compiled (numba) function on a hot path without the dispatcher's type resolution, and
compiling a package's functions once when several processes start together."""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Iterator
from pathlib import Path

from numba import typeof

__all__ = ["BoundOnFirstCall", "compile_lock"]


_HELD = threading.local()
"""``folders``: the package folders whose compile lock this thread holds."""


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
    with lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        held.add(folder)
        try:
            yield
        finally:
            held.discard(folder)


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
