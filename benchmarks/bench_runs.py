"""Reliability of default runs: ``python launch.py`` N times in a row, under its default
authentication and access control; how many pass (exit 0, complete recording, Table-4 line).

Prints one line per run, then, as the last line, JSON: ``runs``, ``passed``, ``failed`` (run
index, exit status, last output line), ``wall_s_median``, ``loadavg_1min_at_start``.

Usage: ``python benchmarks/bench_runs.py --runs 20 [-- launch.py options ...]``
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=int, default=20, help="number of runs (default: %(default)s)")
    parser.add_argument("launch_args", nargs="*", help="options passed to launch.py (after --)")
    args = parser.parse_args()
    load = os.getloadavg()[0]
    failed, walls = [], []
    with tempfile.TemporaryDirectory() as tmp:
        for i in range(args.runs):
            out = Path(tmp) / f"run{i}.mcap"
            t0 = time.monotonic()
            run = subprocess.run([sys.executable, "launch.py", "--json", "--no-progress", "--out", str(out),
                                  *args.launch_args], cwd=REPO, capture_output=True, text=True)
            walls.append(time.monotonic() - t0)
            lines = run.stdout.strip().splitlines() or [""]
            try:
                summary = json.loads(lines[-1])
            except json.JSONDecodeError:
                summary = {}
            ok = run.returncode == 0 and summary.get("complete") is True and "steady_rmse_pct" in summary
            if not ok:
                failed.append({"run": i, "status": run.returncode, "last_line": (lines[-2:] + [run.stderr])[0][-300:]})
            print(f"run {i}: {'ok' if ok else 'FAILED'} (exit {run.returncode}, {walls[-1]:.1f} s, "
                  f"RMSE {summary.get('steady_rmse_pct')} %)", flush=True)
            out.unlink(missing_ok=True)
    print(json.dumps({"runs": args.runs, "passed": args.runs - len(failed), "failed": failed,
                      "wall_s_median": round(statistics.median(walls), 1), "loadavg_1min_at_start": round(load, 2),
                      "launch_args": args.launch_args}))
    return 0 if not failed else 1


if __name__ == "__main__":
    sys.exit(main())
