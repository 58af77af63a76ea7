"""``benchmarks/turn_reachability.py``: a power profile optimised on the FE plant through a turnaround."""

from __future__ import annotations

import json
import subprocess
import sys

import numpy as np
import pytest

from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))

from turn_reachability import band_cost, excursions  # noqa: E402


def test_the_band_cost_adds_the_weighted_excess_beyond_the_band_to_the_mean_square():
    e = np.array([0.0, 8.0, -12.0, 3.0])     # 2 % over a 6 % edge, 3 % under a −9 % edge
    assert band_cost(e, 6.0, 9.0, 0.0) == pytest.approx(np.mean(e ** 2))
    assert band_cost(e, 6.0, 9.0, 20.0) == pytest.approx(np.mean(e ** 2) + 20.0 * (4.0 + 9.0) / 4)
    assert band_cost(np.array([5.0, -8.0]), 6.0, 9.0, 20.0) == pytest.approx((25.0 + 64.0) / 2)


def test_excursions_are_the_largest_error_each_way_and_the_rms():
    assert excursions(np.array([1.0, -4.0, 3.0])) == pytest.approx((3.0, 4.0, np.sqrt(26.0 / 3)))
    assert excursions(np.array([-1.0, -2.0]))[0] == 0.0 and excursions(np.array([1.0, 2.0]))[1] == 0.0


def test_the_optimised_profile_lowers_the_cost_within_the_power_bounds():
    """One iteration on the coarse double track's turn: the profile keeps the MPC's later commands, stays in
    0-350 W and scores better than the MPC's own commands on the same plant copy."""
    proc = subprocess.run([sys.executable, "benchmarks/turn_reachability.py", "--scenario", "double-track", "--turn",
                           "0", "--h-um", "50", "--before", "3", "--free", "4", "--window", "10", "--iterations", "1",
                           "--json"], cwd=REPO, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    r = json.loads(proc.stdout.strip().splitlines()[-1])
    assert r["states_after_turn"] == list(range(-2, 8)) and r["iterations"] == 1
    mpc, profile = np.array(r["mpc_power_w"]), np.array(r["profile_power_w"])
    assert np.all((profile >= 0) & (profile <= 350)) and np.array_equal(profile[4:], mpc[4:])
    cost = {k: band_cost(np.array(r[f"{k}_error_pct"]), 6.0, 9.0, 20.0) for k in ("mpc", "profile")}
    assert cost["profile"] < cost["mpc"]
    assert (r["profile_over_pct"], r["profile_under_pct"], r["profile_rms_pct"]) == pytest.approx(
        excursions(np.array(r["profile_error_pct"])), abs=0.01)
