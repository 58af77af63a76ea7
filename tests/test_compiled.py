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


def test_the_compile_lock_lets_one_holder_in_at_a_time_and_does_nothing_where_it_cannot_write(tmp_path):
    """Two holders of a package's compile lock (two opens of the lock file, as two processes) take turns:
    the second enters only after the first left. Where ``__pycache__`` cannot be made, it does nothing."""
    import threading
    import time

    from gp_model.compiled import compile_lock

    module = tmp_path / "kernels.py"
    order, inside = [], threading.Event()

    def first() -> None:
        with compile_lock(str(module)):
            order.append("first in")
            inside.set()
            time.sleep(0.3)
            order.append("first out")

    thread = threading.Thread(target=first)
    thread.start()
    inside.wait(5)
    with compile_lock(str(module)):
        order.append("second in")
    thread.join()
    assert order == ["first in", "first out", "second in"]
    with compile_lock(str(module)), compile_lock(str(module)):   # taken again inside itself: no wait on itself
        order.append("nested")
    assert order[-1] == "nested"
    assert (tmp_path / "__pycache__" / "numba-compile.lock").is_file()

    not_a_folder = tmp_path / "file"          # (a read-only folder: root may write it anyway)
    not_a_folder.write_text("")
    with compile_lock(str(not_a_folder / "kernels.py")):
        order.append("unlocked")
    assert order[-1] == "unlocked"



def test_a_long_compile_lock_says_what_it_prepares_and_how_long_it_took(tmp_path, monkeypatch, capsys):
    """A block under the compile lock that outlasts ``COMPILE_NOTICE_S`` (a compilation, or the wait for
    another process's) prints one line naming the package when the delay passes and one with its
    duration at the end; a short one (a load from numba's cache) prints nothing."""
    import re
    import time

    from gp_model import compiled

    monkeypatch.setattr(compiled, "COMPILE_NOTICE_S", 0.05)
    module = tmp_path / "kernels" / "stages.py"
    module.parent.mkdir()
    with compiled.compile_lock(str(module)):
        pass
    assert capsys.readouterr().err == ""
    with compiled.compile_lock(str(module)):
        time.sleep(0.5)
        during = capsys.readouterr().err
    after = capsys.readouterr().err
    assert during.startswith("info: preparing the compiled functions of kernels: numba compiles them once"), during
    assert re.fullmatch(r"info: the compiled functions of kernels ready after 0\.\d s\n", after), after

def test_building_the_preview_mpc_and_a_plant_take_their_package_s_compile_lock(monkeypatch):
    """The preview MPC's kernel and the plant's kernels compile under their package's lock."""
    import contextlib

    import gp_model.compiled as compiled
    from controller_node import ControllerSettings, make_controller
    from gp_model.narx import NarxGPModel
    from gp_model.shipped import DEFAULT_MODEL_PATH

    taken = []

    @contextlib.contextmanager
    def recording_lock(module_file):
        taken.append(module_file.replace("\\", "/").rsplit("/", 2)[-2:])
        yield

    monkeypatch.setattr(compiled, "compile_lock", recording_lock)
    import controller_node.preview as preview
    import fe_node.kernels as kernels

    monkeypatch.setattr(preview, "compile_lock", recording_lock)
    make_controller("preview-mpc", ControllerSettings(), NarxGPModel.load(DEFAULT_MODEL_PATH))
    kernels.warm()
    assert taken == [["controller_node", "preview_kernel.py"], ["fe_node", "kernels.py"]]
