"""gp_model.compiled.BoundOnFirstCall: the dispatcher once, then the machine code of those types."""

from __future__ import annotations

import numpy as np
from numba import njit, typeof

from gp_model.compiled import BoundOnFirstCall


@njit(cache=False)
def _scaled_sum(values, factor):  # pragma: no cover (compiled)
    return factor * values.sum()


def test_first_call_compiles_then_binds_the_entry_point_of_its_types():
    bound = BoundOnFirstCall(_scaled_sum)
    values = np.arange(4.0)
    assert bound.call(values, 2.0) == 12.0
    assert bound.call is _scaled_sum.overloads[(typeof(values), typeof(2.0))].entry_point
    assert bound.call(values + 1.0, 0.5) == 5.0
    assert len(_scaled_sum.signatures) == 1
