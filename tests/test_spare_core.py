"""The machine's busy share, and whether a core is to spare (messages.spare_core)."""

import pytest

from messages.spare_core import SPARE_BUSY_MAX, SPARE_BUSY_RESUME, SpareCore, cpu_times


def stat(user, system, idle, iowait, steal=0):
    return (f"cpu  {user} 0 {system} {idle} {iowait} 0 0 {steal} 0 0\n"
            f"cpu0 {user} 0 {system} {idle} {iowait} 0 0 {steal} 0 0\nintr 1 2 3\n")


def test_cpu_times_counts_iowait_as_idle_and_steal_as_busy():
    assert cpu_times(stat(100, 50, 800, 20, steal=30)) == (180, 1000)


def test_a_core_is_spare_until_the_machine_was_busy_most_of_the_last_interval():
    texts = iter([stat(0, 0, 0, 0), stat(60, 10, 130, 0), stat(250, 50, 130, 0), stat(260, 50, 300, 10)])
    reads = []
    core = SpareCore(read=lambda: reads.append(None) or next(texts), sample_s=0.1, smoothing=1.0,
                     spare_until_measured=False)
    assert not core.spare(0.0)                       # nothing measured yet
    assert not core.spare(0.05) and len(reads) == 1  # not re-read within the interval
    assert core.spare(0.1) and core.busy_share == pytest.approx(70 / 200)
    assert not core.spare(0.2) and core.busy_share == pytest.approx(1.0) and core.busy_share > SPARE_BUSY_MAX
    assert core.spare(0.31) and core.busy_share == pytest.approx(10 / 190)


def test_without_proc_stat_a_core_counts_as_spare(monkeypatch):
    import messages.spare_core as spare_core

    monkeypatch.setattr(spare_core, "PROC_STAT", spare_core.Path("/nonexistent/stat"))
    assert SpareCore().spare(0.0) and SpareCore().read is None


def test_a_core_becomes_spare_under_the_resume_share_and_stays_so_up_to_the_max():
    """Hysteresis: 85 % busy is not enough to start polling, nor to stop it."""
    assert SPARE_BUSY_RESUME < 0.85 < SPARE_BUSY_MAX
    totals = [(0, 0), (85, 100), (170, 200), (220, 300), (305, 400), (400, 500), (485, 600)]
    texts = iter(stat(busy, 0, total - busy, 0) for busy, total in totals)
    core = SpareCore(read=lambda: next(texts), sample_s=0.1, smoothing=1.0, spare_until_measured=False)
    assert [core.spare(0.1 * k) for k in range(len(totals))] == [False, False, False, True, True, False, False]


@pytest.mark.parametrize(("first_busy_pct", "spare_after"), [(85, True), (95, False)])
def test_a_core_counts_as_spare_until_the_first_interval_is_measured(first_busy_pct, spare_after):
    """By default a core is spare from the start (the loop's first 0.1 s runs as a quiet run does);
    the first measured interval keeps it so up to the max share, and ends it above."""
    texts = iter([stat(0, 0, 0, 0), stat(first_busy_pct, 0, 100 - first_busy_pct, 0)])
    core = SpareCore(read=lambda: next(texts), sample_s=0.1)
    assert core.spare(0.0) and core.busy_share is None
    assert core.spare(0.05)
    assert core.spare(0.1) is spare_after and core.busy_share == pytest.approx(first_busy_pct / 100)


def test_one_busy_interval_of_another_job_does_not_stop_the_polling():
    """The busy share is averaged: quiet at 60 %, one interval at 100 % (a burst of another job)
    leaves a core spare, a sustained 100 % (a busy loop) does not."""
    busy = [60, 60, 100, 60, 60, 100, 100, 100, 100]
    totals = [(sum(busy[:k]), 100 * k) for k in range(len(busy) + 1)]
    texts = iter(stat(b, 0, t - b, 0) for b, t in totals)
    core = SpareCore(read=lambda: next(texts), sample_s=0.1)
    spare = [core.spare(0.1 * k) for k in range(len(totals))]
    assert spare[1:3] == [True, True] and spare[3] and spare[4]  # through the burst
    assert spare[-1] is False and core.busy_share > SPARE_BUSY_MAX


@pytest.mark.parametrize("kwargs", [{"busy_resume": 0.95}, {"busy_max": 1.5}, {"smoothing": 0.0}, {"sample_s": 0.0}])
def test_inconsistent_thresholds_are_refused(kwargs):
    with pytest.raises(ValueError):
        SpareCore(read=lambda: stat(0, 0, 0, 0), **kwargs)
