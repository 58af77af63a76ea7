"""Shared fixtures: a loopback zenoh hub and helpers to run nodes as real processes."""

from __future__ import annotations

import compileall
import os
import subprocess
import sys
import tempfile
import time
import uuid
from pathlib import Path

import pytest

from tests.plants import BARE_ARGS, BARE_CONFIG

REPO = Path(__file__).resolve().parent.parent


BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")
WARM_NUMBA = """
import pathlib, sys
try:
    from controller_node.node import load_model
    from controller_node.registry import CONTROLLERS, make_controller
    from controller_node.settings import ControllerSettings
    for name in CONTROLLERS:
        make_controller(name, ControllerSettings(), load_model(name, None))
finally:
    pathlib.Path(sys.argv[1]).touch()
"""
WARM_DONE_VARIABLE = "MELTLOOP_TEST_NUMBA_WARM"
"""Environment variable naming the file that :data:`WARM_NUMBA` creates when it ends."""
NUMBA_FREE_MODULES = frozenset({
    "test_bench_loop_metrics.py", "test_fe_cases.py", "test_fe_core.py", "test_fe_layers.py", "test_fe_operators.py",
    "test_fe_physics.py", "test_fe_powder_evaporation.py", "test_fe_window.py", "test_messages.py",
    "test_recorder_property.py", "test_recorder_rules.py", "test_resources.py", "test_spare_core.py",
    "test_fe_physical.py", "test_fe_node_lockstep.py", "test_bus.py", "test_recorder.py", "test_constraints.py",
    "test_contract_schemas.py", "test_plant_commands.py", "test_stop_flag.py",  # no controller at all
    "test_hub.py", "test_security.py", "test_plant_flood.py", "test_plant_fallback.py", "test_example_sensor.py",
    "test_live.py", "test_light_imports.py",  # the PID controller node only
    "test_fe_scan.py", "test_fe_config.py", "test_contract_nodes.py", "test_launch.py", "test_recorder_crash.py",
    "test_report.py", "test_layering.py", "test_plan_feature.py", "test_low_latency.py", "test_hostile_input.py",
    "test_controller_types.py", "test_controller_node.py", "test_blas_threads.py", "test_turn_sensitivity.py",
    "test_bench_suite.py", "test_fe_multilevel.py", "test_freerun.py", "test_replay.py", "test_contract_plain_node.py",
    "test_campaign_dask.py", "test_mesh_convergence.py",  # the open-loop plant (under launch.py), no controller
})
"""Test modules that build no controller but the PID and no GP model (no numba function): they run
first, while the warm-up compiles; every other test waits for it."""
WARM_TIMEOUT_S = 600.0
WARM_PROCESS = pytest.StashKey[subprocess.Popen]()
"""The warm-up process of :func:`pytest_configure`, in the run's stash."""


def pytest_configure(config: pytest.Config) -> None:
    """Under pytest-xdist, before the workers start: BLAS on one thread in each process (the workers
    already take both cores; OpenBLAS's spinning threads would fight them for the cores), and, for
    the default run, every controller built once in a fresh interpreter started in the background,
    which compiles numba's cached functions (about 35 s of CPU on a fresh clone, loaded in a few
    seconds after). The workers run the :data:`NUMBA_FREE_MODULES` meanwhile; every other test waits
    for it (:func:`pytest_runtest_setup`), so that no two workers or nodes compile at once."""
    if not getattr(config.option, "numprocesses", None) or hasattr(config, "workerinput"):
        return
    for name in BLAS_THREAD_VARIABLES:  # inherited by the workers and everything they start
        os.environ.setdefault(name, "1")
    share_bytecode()
    if config.args_source is pytest.Config.ArgsSource.TESTPATHS:
        done = Path(tempfile.mkdtemp(prefix="meltloop-warm-")) / "done"
        os.environ[WARM_DONE_VARIABLE] = str(done)
        # (a controller that cannot be built fails its own tests; the run goes on)
        config.stash[WARM_PROCESS] = subprocess.Popen([sys.executable, "-c", WARM_NUMBA, str(done)], cwd=REPO,
                                                      stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


BYTECODE_SOURCES = ("messages", "fe_node", "controller_node", "gp_model", "gp_trainer", "benchmarks", "tests",
                    "launch.py")
"""The project's sources, compiled once per test run (:func:`share_bytecode`)."""


def share_bytecode() -> None:
    """Let the run's processes share the project's compiled bytecode: compile :data:`BYTECODE_SOURCES` into
    their ``__pycache__`` folders (beside numba's cache) once, and let the workers and the processes they
    start read and write bytecode even where ``PYTHONDONTWRITEBYTECODE`` is set. Without it, on a fresh
    clone with that variable set, each of the run's few hundred processes compiled every project module it
    imported again (about 0.2 s of CPU each)."""
    os.environ.pop("PYTHONDONTWRITEBYTECODE", None)
    for name in BYTECODE_SOURCES:
        path = REPO / name
        if path.is_dir():
            compileall.compile_dir(path, quiet=2)
        else:
            compileall.compile_file(path, quiet=2)


def pytest_unconfigure(config: pytest.Config) -> None:
    """End the warm-up process of :func:`pytest_configure`, if any (a run cut short)."""
    process = config.stash.get(WARM_PROCESS, None)
    if process is not None and process.poll() is None:
        process.kill()
        process.wait()


def pytest_runtest_setup(item: pytest.Item) -> None:
    """Outside :data:`NUMBA_FREE_MODULES`, wait for the warm-up of :func:`pytest_configure`, if it runs."""
    done = os.environ.get(WARM_DONE_VARIABLE)
    if done is None or item.path.name in NUMBA_FREE_MODULES:
        return
    deadline = time.monotonic() + WARM_TIMEOUT_S
    while not os.path.exists(done) and time.monotonic() < deadline:
        time.sleep(0.2)


@pytest.hookimpl(tryfirst=True)  # before pytest-xdist reads the groups into the node ids
def pytest_collection_modifyitems(items: list[pytest.Item]) -> None:
    """Under pytest-xdist (``--dist loadgroup``), keep the tests that share one of this suite's
    module- or session-scoped fixtures on one worker, so that the fixture is built once: group
    ``<file>`` for a module fixture, ``<fixture name>`` for a session fixture (e.g. ``mpc_run``).
    The :data:`NUMBA_FREE_MODULES` come first (they run during the numba warm-up), and in each
    part the groups before the single tests, which fill the end of the run. The workers take the
    tests in this order (``--no-loadscope-reorder`` in the project's addopts: pytest-xdist would
    otherwise start with the largest groups, numba's or not, and all three workers would wait for
    the warm-up at once)."""
    tests_dir = Path(__file__).resolve().parent
    for item in items:
        info = getattr(item, "_fixtureinfo", None)
        if info is None or item.get_closest_marker("xdist_group"):
            continue
        group = None
        for name in item.fixturenames:
            definition = info.name2fixturedefs.get(name, ())[-1:]
            code = getattr(definition[0].func, "__code__", None) if definition else None
            if code is None or tests_dir not in Path(code.co_filename).resolve().parents:
                continue  # not this suite's (pytest's own tmp_path_factory, ...)
            if definition[0].scope == "session":
                group = name
            elif definition[0].scope == "module" and group is None:
                group = item.path.name
        if group is not None:
            item.add_marker(pytest.mark.xdist_group(group))
    # (stable: in file order otherwise)
    items.sort(key=lambda item: (item.path.name not in NUMBA_FREE_MODULES, not item.get_closest_marker("xdist_group")))


def free_endpoint() -> str:
    from launch import free_loopback_endpoint

    return free_loopback_endpoint()


@pytest.fixture
def run_id() -> str:
    return "t" + uuid.uuid4().hex[:10]


@pytest.fixture(scope="session")
def mpc_run(tmp_path_factory) -> tuple[int, str, Path]:
    """One short closed-loop run under ``launch.py`` (MPC, 100 steps on a 40 µm mesh), shared by the
    tests that check a real run's recording in different ways: (exit status, output, recording)."""
    out = tmp_path_factory.mktemp("mpc_run") / "e2e.mcap"
    proc = subprocess.run([sys.executable, "launch.py", "--no-progress", "--controller", "mpc", "--max-steps", "100",
                           "--h-um", "40", *BARE_ARGS, "--out", str(out), "--json"], cwd=REPO, capture_output=True,
                          text=True, timeout=240)
    return proc.returncode, proc.stdout + proc.stderr, out


@pytest.fixture
def hub() -> str:
    """A fresh loopback endpoint for this test's hub."""
    return free_endpoint()


def spawn(module: str, *args: str, cwd: Path = REPO) -> subprocess.Popen[str]:
    """Start ``python -m module args`` in its own process (own session), output captured."""
    return subprocess.Popen(
        [sys.executable, "-u", "-m", module, *args],
        cwd=cwd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
        env=dict(os.environ, PYTHONUNBUFFERED="1"), start_new_session=True,
    )


def finish(proc: subprocess.Popen[str], timeout: float = 30) -> tuple[int, str]:
    """Wait for a process; kill it if it outlives ``timeout``. Returns (status, output)."""
    try:
        out, _ = proc.communicate(timeout=timeout)
    except subprocess.TimeoutExpired:
        proc.kill()
        out, _ = proc.communicate()
        raise AssertionError(f"process did not end in {timeout} s; output:\n{out}") from None
    return proc.returncode, out


RECORDER_NODE = """
[[node]]
name = "recorder"
module = "messages.recorder"
args = ["--expect", "plant", "--expect", "controller"]
"""


def controller_node(controller: str = "pid") -> str:
    """The ``[[node]]`` table of a controller node at the default set point, recorded."""
    return f"""
[[node]]
name = "controller"
module = "controller_node"
args = ["--controller", "{controller}", "--setpoint-mm2", "0.063", "--require", "recorder"]
"""


ATTACK_STEPS = 300
"""Plant steps of the lockstep runs that a fuzzer or a rogue node attacks (tests/test_fuzz.py,
tests/test_rogue.py) and of the clean run they are compared with."""
ATTACK_COUNT = 10_000
"""Messages the fuzzer or the rogue node sends in its run."""
ATTACKERS = {
    "fuzzed": ("fuzzer", f"""
[[node]]
name = "fuzzer"
module = "tests.nodes.fuzzer"
roles = ["plant", "controller"]  # authenticated, yet sending garbage: the nodes must cope
args = ["--require", "recorder", "--count", "{ATTACK_COUNT}", "--seed", "7",
        "--topic", "plant/state", "--topic", "controller/command", "--topic", "run/events"]
"""),
    "attacked": ("rogue", f"""
[[node]]
name = "rogue"
module = "tests.nodes.rogue"
roles = ["recorder"]  # it times its forgeries by the plant states
args = ["--count", "{ATTACK_COUNT}", "--require", "recorder"]
"""),
}
"""The attacking node of each attacked run, by run name: (node name, its ``[[node]]`` table)."""


def attacked_plant_node(*require: str) -> str:
    """The ``[[node]]`` table of the FE plant of those runs (bare plate, 40 µm mesh), which waits
    for the recorder, the controller and the nodes ``require``."""
    waits = "".join(f', "--require", "{name}"' for name in ("recorder", "controller", *require))
    return f"""
[[node]]
name = "plant"
module = "fe_node"
args = ["--h-um", "40", "--max-steps", "{ATTACK_STEPS}", "--command-timeout-s", "30",
        "--config", "{BARE_CONFIG}"{waits}]
main = true
"""


@pytest.fixture(scope="session")
def attack_runs(tmp_path_factory) -> dict[str, tuple[str, Path]]:
    """Three lockstep runs of recorder, MPC controller and plant, side by side: ``clean``, and
    ``fuzzed`` and ``attacked`` with the node of :data:`ATTACKERS` added (lockstep: the result does
    not depend on timing). Each exits 0; by run name: (output, recording)."""
    tmp = tmp_path_factory.mktemp("attack")
    started = {}
    for name, (node, table) in {"clean": (None, ""), **ATTACKERS}.items():
        plant = attacked_plant_node(*([node] if node else []))
        started[name] = start_node_list(tmp, name, RECORDER_NODE + controller_node("mpc") + table + plant)
    runs = {}
    for name, (proc, out) in started.items():
        status, output = finish(proc, timeout=300)
        assert status == 0, output
        runs[name] = (output, out)
    return runs


def start_node_list(tmp_path: Path, name: str, nodes_toml: str, *extra: str) -> tuple[subprocess.Popen[str], Path]:
    """Start ``launch.py --nodes`` on ``nodes_toml`` (written to ``<name>.toml``), recording to
    ``<name>.mcap``; returns the process (output captured) and the recording path."""
    nodes = tmp_path / f"{name}.toml"
    nodes.write_text(nodes_toml)
    out = tmp_path / f"{name}.mcap"
    proc = subprocess.Popen(
        [sys.executable, "launch.py", "--nodes", str(nodes), "--out", str(out), "--no-progress", *extra],
        cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, start_new_session=True,
    )
    return proc, out
