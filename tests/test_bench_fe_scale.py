"""benchmarks/bench_fe_scale.py's timing windows: each case's window is run again from copies of the plants
taken at its start (the same steps), and the median of the windows' means is reported with the window's mean
melt-pool area."""

from __future__ import annotations

import copy
import sys

import pytest

from tests.conftest import REPO

sys.path.insert(0, str(REPO / "benchmarks"))
import bench_fe_scale  # noqa: E402

from fe_node.multilevel import plant_model  # noqa: E402
from fe_node.scenarios import scenario  # noqa: E402


def test_repeated_windows_run_from_copies_and_leave_the_start_alone():
    scs = [scenario("layer", n_tracks=1, track_length_m=1e-3, mesh=m, h_fine_m=40e-6) for m in bench_fe_scale.MESHES]
    models = [plant_model(sc.settings, sc.plan) for sc in scs]
    bench_fe_scale.timed_window(scs, models, 3)
    start = [copy.deepcopy(m) for m in models]
    first = bench_fe_scale.timed_window(scs, models, 4)
    again = bench_fe_scale.repeated(scs, start, 4, 3)
    assert [m.step_index for m in start] == [3, 3] and [m.step_index for m in models] == [7, 7]
    assert [len(w) for w in first] == [4, 4] and [[len(w) for w in ws] for ws in again] == [[4, 4], [4, 4]]
    assert bench_fe_scale.repeated(scs, start, 4, 1) == [[], []]
    for i in range(2):     # the same steps again: the same melt pools, the plant's own
        assert [t[2] for t in first[i]] == [t[2] for t in again[i][0]] == [t[2] for t in again[i][1]]
        assert all(t[2] > 0 for t in first[i])
    case = {}
    bench_fe_scale.record(case, "uniform", [[(1e-3, 2e-3, 5e-8)] * 4, [(5e-3, 5e-3, 5e-8)] * 4,
                                            [(2e-3, 3e-3, 5e-8)] * 4])
    assert case == {"ms_per_step_uniform": 2.0, "wall_ms_per_step_uniform": 3.0,    # the median window
                    "area_mm2_uniform": 0.05}


def test_repeats_below_one_is_a_usage_error(monkeypatch, capsys):
    monkeypatch.setattr(sys, "argv", ["bench_fe_scale.py", "--repeats", "0"])
    with pytest.raises(SystemExit) as stop:
        bench_fe_scale.main()
    assert stop.value.code == 2 and "--repeats must be >= 1" in capsys.readouterr().err
