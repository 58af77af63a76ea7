"""The fast loop's nodes run BLAS on one thread (``messages.bus.single_threaded_blas``), before any
numerical work (``docs/realtime.md``, "The loop's first 200 steps")."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

import controller_node.node as controller_main
import fe_node.example_sensor as sensor_main
import fe_node.node as plant_main
import fe_node.surrogate as surrogate_main

BLAS_THREADS = (
    "import json, numpy, scipy.linalg, threadpoolctl\n"
    "from messages.bus import single_threaded_blas\n"
    "before = [i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']\n"
    "single_threaded_blas()\n"
    "after = [i['num_threads'] for i in threadpoolctl.threadpool_info() if i['user_api'] == 'blas']\n"
    "print(json.dumps([before, after]))\n"
)


@pytest.mark.skipif(len(os.sched_getaffinity(0)) < 2, reason="BLAS runs on one thread anyway on one CPU")
def test_single_threaded_blas_limits_every_blas_to_one_thread():
    env = {k: v for k, v in os.environ.items() if not k.endswith("_NUM_THREADS")}
    out = subprocess.run([sys.executable, "-c", BLAS_THREADS], capture_output=True, text=True, check=True, env=env)
    before, after = json.loads(out.stdout)
    assert max(before) > 1 and after and max(after) == 1


@pytest.mark.parametrize(("module", "loader", "argv"), [
    (surrogate_main, "load_model", ["--model", "/nonexistent/model.json"]),
    (controller_main, "load_model", ["--controller", "mpc", "--model", "/nonexistent/model.json"]),
])
def test_loop_nodes_limit_blas_before_loading_their_model(monkeypatch, module, loader, argv):
    calls: list[str] = []
    real_loader = getattr(module, loader)
    monkeypatch.setattr(module, "single_threaded_blas", lambda: calls.append("blas"))

    def load(*args):
        calls.append("model")
        return real_loader(*args)

    monkeypatch.setattr(module, loader, load)
    assert module.main(argv) == 2  # the model cannot be loaded: a usage error, after the limit
    assert calls == ["blas", "model"]


def test_example_sensor_limits_blas(monkeypatch):
    calls: list[str] = []
    monkeypatch.setattr(sensor_main, "single_threaded_blas", lambda: calls.append("blas"))
    assert sensor_main.main(["--power-w", "-1"]) == 2  # out of the command bounds: refused after the limit
    assert calls == ["blas"]


def test_fe_plant_limits_blas_before_building_its_plant(monkeypatch):
    """The FE plant node too: with two BLAS threads its workers spin beside the controller and the
    bus threads on a two-core machine."""
    calls: list[str] = []

    def build_plant(*args):
        calls.append("plant")
        raise SystemExit(3)     # (stop before the bus)

    monkeypatch.setattr(plant_main, "single_threaded_blas", lambda: calls.append("blas"))
    monkeypatch.setattr(plant_main, "plant_model", build_plant)
    with pytest.raises(SystemExit):
        plant_main.main(["--scenario", "single-track"])
    assert calls == ["blas", "plant"]
