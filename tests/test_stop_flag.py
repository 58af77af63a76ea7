"""StopFlag: a signal that lands while the main thread waits must stop the node, never hang it."""

from __future__ import annotations

import subprocess
import sys
import textwrap

from tests.conftest import REPO

# SIGALRM every millisecond through the very handler StopFlag installs for SIGINT/SIGTERM, while
# the main thread waits in stop.wait: a handler that took the Event's lock (Event.set) deadlocks
# here within a second, as an echo node once did on SIGTERM.
STRESS = textwrap.dedent("""
    import faulthandler, signal, time
    from messages.bus import StopFlag
    faulthandler.dump_traceback_later(20, exit=True)
    stop = StopFlag()
    signal.signal(signal.SIGALRM, stop._handle)
    signal.setitimer(signal.ITIMER_REAL, 0.001, 0.001)
    end = time.monotonic() + 2
    while time.monotonic() < end:
        stop.wait(0.0001)
    signal.setitimer(signal.ITIMER_REAL, 0)
    print("stopped by", stop.signal_name)
""")

# One SIGTERM while the main thread sleeps in a long wait: it returns at once, set.
WAKE = textwrap.dedent("""
    import os, signal, threading, time
    from messages.bus import StopFlag
    stop = StopFlag()
    threading.Timer(0.2, os.kill, (os.getpid(), signal.SIGTERM)).start()
    t0 = time.monotonic()
    woke = stop.wait(30)
    print(woke, stop.is_set(), stop.signal_name, round(time.monotonic() - t0, 1))
""")


def run(code: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-c", code], cwd=REPO, capture_output=True, text=True, timeout=60)


def test_signals_landing_inside_wait_never_deadlock():
    proc = run(STRESS)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.strip() == "stopped by SIGALRM"


def test_a_signal_wakes_a_waiting_node_at_once():
    proc = run(WAKE)
    assert proc.returncode == 0, proc.stderr[-2000:]
    woke, is_set, name, waited = proc.stdout.split()
    assert (woke, is_set, name) == ("True", "True", "SIGTERM")
    assert float(waited) < 5


# A forked child's SIGTERM stops the child, never the parent that shares its StopFlag's past.
FORK = textwrap.dedent("""
    import os, signal, sys, time
    from messages.bus import StopFlag
    stop = StopFlag()
    pid = os.fork()
    if pid == 0:
        woke = stop.wait(30)
        os._exit(0 if woke and stop.signal_name == "SIGTERM" else 3)
    time.sleep(0.3)
    os.kill(pid, signal.SIGTERM)
    _, status = os.waitpid(pid, 0)
    time.sleep(0.3)
    print(os.waitstatus_to_exitcode(status), stop.is_set())
""")


def test_a_forked_childs_signal_stops_the_child_only():
    proc = run(FORK)
    assert proc.returncode == 0, proc.stderr[-2000:]
    assert proc.stdout.split() == ["0", "False"]
