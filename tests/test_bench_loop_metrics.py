"""The figures ``benchmarks/bench_loop.py`` derives from its samples (no zenoh, no timing)."""

import importlib.util
from pathlib import Path

import numpy as np
import pytest

_SPEC = importlib.util.spec_from_file_location(
    "bench_loop", Path(__file__).resolve().parent.parent / "benchmarks" / "bench_loop.py")
bench_loop = importlib.util.module_from_spec(_SPEC)
_SPEC.loader.exec_module(bench_loop)


def test_transport_miss_pct_is_the_share_of_pairs_over_the_period():
    bare = np.full(50, 200.0)
    assert bench_loop.transport_miss_pct(bare, [100.0] * 10, 500.0) == 0.0
    assert bench_loop.transport_miss_pct(bare, [400.0] * 10, 500.0) == 100.0
    # half the updates push the pair over 500 µs
    share = bench_loop.transport_miss_pct(bare, [100.0, 350.0] * 20, 500.0)
    assert share == pytest.approx(50.0, abs=1.0)
    assert bench_loop.transport_miss_pct(np.array([]), [100.0], 500.0) is None
    assert bench_loop.transport_miss_pct(bare, [], 500.0) is None


def test_overhead_ratio():
    assert bench_loop.ratio(300.0, 150.0, 100.0) == 1.2
    assert bench_loop.ratio(None, 150.0, 100.0) is None
