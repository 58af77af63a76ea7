"""Free-running plants: the command latch (pure) and the GP surrogate node against the controller."""

from __future__ import annotations

import json

import pytest

from fe_node.commands import CommandPolicy, Verdict
from fe_node.freerun import RING, CommandLatch, FreeRunSettings
from fe_node.surrogate import TrackProfile
from messages import LaserCommand
from messages.cli import UsageError
from tests.conftest import finish, spawn


def cmd(step: int, power_w: float = 200.0) -> LaserCommand:
    return LaserCommand(run_id="r", step=step, time_s=0.0, power_w=power_w, speed_mm_s=800.0, controller="t")


def latch(**policy) -> CommandLatch:
    return CommandLatch(CommandPolicy(**{"power_max_w": 300.0, "timeout_s": 1.0, "fallback": "safe", **policy}),
                        power_w=250.0, speed_m_s=0.8)


def test_on_time_command_applies_and_counts_round_trip():
    lt = latch()
    lt.published(0, 10.0)
    lt.offer(cmd(1), 10.0002)
    assert not lt.missed(1)
    assert lt.command_for(10.0005, started_t=10.0, controller_gone=False) == (200.0, 0.8, "controller")
    assert lt.rtt_s == [pytest.approx(2e-4)]


def test_late_command_is_a_miss_but_still_the_newest_applied():
    lt = latch()
    lt.published(0, 0.0)
    assert lt.missed(1)  # nothing arrived before state 1
    lt.published(1, 0.001)
    lt.offer(cmd(1, 220.0), 0.0012)  # answers state 0, arrives after state 1 was published
    assert lt.n_late == 1 and lt.command_for(0.0013, 0.0, False)[0] == 220.0
    lt.offer(cmd(2, 230.0), 0.0014)
    lt.offer(cmd(1, 100.0), 0.0015)  # an older step never overrides a newer command
    assert not lt.missed(2) and lt.command_for(0.0016, 0.0, False)[0] == 230.0
    assert lt.gate.n_stale == 1


def test_out_of_bounds_command_is_rejected_never_applied():
    lt = latch()
    lt.published(0, 0.0)
    lt.offer(cmd(1, 340.0), 0.0001)
    assert lt.gate.counts[Verdict.OUT_OF_BOUNDS] == 1 and lt.missed(1)
    assert lt.command_for(0.0002, 0.0, False) == (250.0, 0.8, "open-loop")  # the initial command, not a controller's


def test_fallback_after_timeout_without_commands():
    lt = latch(safe_power_w=20.0)
    lt.published(0, 0.0)
    assert lt.command_for(0.5, 0.0, False)[2] == "open-loop"
    lt.offer(cmd(1), 0.1)
    assert lt.command_for(1.0, 0.0, False)[2] == "controller"
    assert lt.command_for(1.2, 0.0, False) == (20.0, 0.8, "fallback-safe") and lt.n_fallbacks == 1
    hold = latch(fallback="hold")
    assert hold.command_for(1.5, 0.0, False) == (250.0, 0.8, "fallback-hold")


def test_fallback_as_soon_as_the_controller_is_gone():
    lt = latch(safe_power_w=20.0)
    lt.published(0, 0.0)
    lt.offer(cmd(1), 0.0001)
    assert lt.command_for(0.0002, 0.0, controller_gone=True) == (20.0, 0.8, "fallback-safe")  # long before the timeout


def test_steps_the_plant_cannot_have_asked_for_are_dropped():
    lt = latch()
    lt.published(0, 0.0)
    for step in (2, 1000, 2**31 - 1):  # ahead of the newest published state + 1
        lt.offer(cmd(step, 123.0), 0.0001)
    assert lt.gate.counts[Verdict.AHEAD] == 3 and lt.command_for(0.0002, 0.0, False)[0] == 250.0
    lt.offer(cmd(0, 123.0), 0.0003)  # step 0 is the initial command, answers no state
    assert lt.gate.n_stale == 1 and lt.command_for(0.0004, 0.0, False)[0] == 250.0
    lt.offer(cmd(1), 0.0005)
    lt.offer(cmd(1, 123.0), 0.0006)  # a duplicate
    assert lt.gate.n_stale == 2 and lt.command_for(0.0007, 0.0, False)[0] == 200.0


def test_a_command_older_than_the_window_is_stale():
    lt = latch()
    for step in range(RING + 1):
        lt.published(step, step * 1e-3)
    lt.offer(cmd(1, 123.0), RING * 1e-3)  # answers state 0, RING steps ago
    lt.offer(cmd(2, 124.0), RING * 1e-3)  # answers state 1, RING - 1 steps ago: late but applied
    assert lt.gate.n_stale == 1 and lt.n_late == 1 and lt.command_for(RING * 1e-3, 0.0, False)[0] == 124.0


@pytest.mark.parametrize("kwargs", [{"rate_hz": 0}, {"rate_hz": 2e5}, {"max_steps": 0}, {"duration_s": -1},
                                    {"diagnostics_every": 0}, {"dt_s": 0.0}])
def test_free_run_settings_validate(kwargs):
    with pytest.raises(UsageError):
        FreeRunSettings(**kwargs)


def test_track_profile_heats_along_and_across_tracks():
    p = TrackProfile()
    assert p.at(0.0).t_ahead_k == p.t0_k
    assert p.at(3e-3).t_ahead_k > p.at(1e-3).t_ahead_k
    assert p.at(5 * p.track_length_m).t_ahead_k > p.at(p.track_length_m).t_ahead_k
    assert p.at(p.track_length_m + 1e-3).direction == (-1.0, 0.0) and p.at(p.track_length_m + 1e-3).track == 1


def test_surrogate_node_runs_free_against_the_controller_node(hub, run_id):
    from messages.bus import BusSettings, NodeBus, StopFlag

    common = ("--run-id", run_id, "--connect", hub)
    with NodeBus("hub", BusSettings(run_id=run_id, connect=(), listen=(hub,))) as bus:
        controller = spawn("controller_node", "--controller", "pid", "--setpoint-mm2", "0.063", *common)
        bus.wait_for_nodes(["controller"], StopFlag(), timeout_s=30)
        plant = spawn("fe_node.surrogate", "--rate-hz", "500", "--duration-s", "1.5", "--require", "controller",
                      "--json", *common)
        status, out = finish(plant, timeout=60)
        assert status == 0, out
        c_status, c_out = finish(controller, timeout=20)
    stats = json.loads(out.strip().splitlines()[-1])
    assert set(stats) >= {"rtt_median_us", "rtt_p99_us", "rate_hz", "deadline_miss_pct"}
    # never faster than asked; how close to it, and how many commands in time, depends on the machine
    # (bench_loop.py measures both)
    assert 0 < stats["rate_hz"] <= 520 and 0 < stats["commands"] <= stats["steps"] + 1
    assert 0 < stats["rtt_median_us"] < 2e5 and stats["rejected_commands"] == stats["invalid_commands"] == 0
    assert c_status == 0 and "plant 'plant' ended" in c_out, c_out
