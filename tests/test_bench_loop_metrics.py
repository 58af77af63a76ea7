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


def test_worked_summary_counts_the_echoes_later_than_a_period():
    rtt = [200.0] * 90 + [600.0] * 10
    summary = bench_loop.worked_summary(rtt, 500.0)
    assert summary == {"worked_rtt_median_us": 200.0, "worked_rtt_p99_us": 600.0, "worked_miss_pct": 10.0}
    assert bench_loop.worked_summary(rtt, 700.0)["worked_miss_pct"] == 0.0
    assert bench_loop.worked_summary([], 500.0) == {
        "worked_rtt_median_us": None, "worked_rtt_p99_us": None, "worked_miss_pct": None}


def test_pong_computes_for_its_work_before_each_echo(hub, run_id):
    """``zenoh_pingpong.py pong --work-us``: every echo leaves at least the work after its ping."""
    import json
    import subprocess
    import sys

    import zenoh

    from messages.bus import BusSettings, zenoh_config

    script = str(Path(__file__).resolve().parent.parent / "benchmarks" / "zenoh_pingpong.py")
    common = ["--run-id", run_id, "--connect", hub]
    with zenoh.open(zenoh_config(BusSettings(run_id=run_id, connect=(), listen=(hub,)))):
        pong = subprocess.Popen([sys.executable, script, "pong", *common, "--work-us", "3000"],
                                stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        try:
            ping = subprocess.run([sys.executable, script, "ping", *common, "--rate-hz", "100", "--duration-s", "0.5",
                                   "--samples"], capture_output=True, text=True, timeout=120)
        finally:
            pong.terminate()
            pong.wait(timeout=20)
    assert ping.returncode == 0, ping.stdout + ping.stderr
    rtt = json.loads(ping.stdout.strip().splitlines()[-1])["rtt_us"]
    assert len(rtt) >= 40 and min(rtt) >= 3000.0
