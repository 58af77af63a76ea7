"""Calling a compiled (numba) function on a hot path without the dispatcher's type resolution."""

from __future__ import annotations

from numba import typeof

__all__ = ["BoundOnFirstCall"]


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
