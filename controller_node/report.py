"""Closed-loop performance from any recording (paper Table 4 and Fig. 5).

Reads only the contract channels ``/plant/state`` and ``/controller/diagnostics`` (for the set
point), so it works on FE and hardware recordings alike.

Metrics (paper section IV.B), in % of the set point A_set, over the *evaluation window*: every
step after the first melt-pool build-up, i.e. from the first step at which the area reaches
90 % of A_set (or, if it never does, after the first 2 ms) to the end of the run:

- max overshoot  = max(A) / A_set − 1
- max undershoot = 1 − min(A) / A_set
- steady-state error = RMSE(A − A_set) / A_set

Run: ``python -m controller_node.report RECORDING [--setpoint-mm2 X] [--json]``; it writes the
Fig. 5-style PNG (area with set point, power, T ahead vs time) next to the recording.
"""

from __future__ import annotations

import json
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from messages.cli import ArgumentParser, UsageError, exit_usage
from messages.recording import RecordingError, read_messages

BUILD_UP_FRACTION = 0.9
BUILD_UP_FALLBACK_S = 2e-3


@dataclass(frozen=True)
class Trace:
    """Time series of one run (arrays of shape (n,)), in the contract's units."""

    time_s: np.ndarray
    area_mm2: np.ndarray
    power_w: np.ndarray
    t_ahead_k: np.ndarray
    track: np.ndarray


@dataclass(frozen=True)
class Metrics:
    """Table 4 metrics of one run, in percent of the set point."""

    setpoint_mm2: float
    overshoot_pct: float
    undershoot_pct: float
    steady_rmse_pct: float
    window_start_s: float
    steps: int


def read_trace(path: Path) -> Trace:
    """The plant states of a recording as arrays, in step order."""
    states = sorted(read_messages(path, "/plant/state"), key=lambda s: s.step)
    if len(states) < 2:
        raise RecordingError(f"{path}: fewer than 2 plant states recorded")
    return Trace(
        time_s=np.array([s.time_s for s in states]),
        area_mm2=np.array([s.area_mm2 for s in states]),
        power_w=np.array([s.power_w for s in states]),
        t_ahead_k=np.array([s.t_ahead_k for s in states]),
        track=np.array([s.track for s in states]),
    )


def recorded_setpoint(path: Path) -> float | None:
    """The set point the controller reported, if any [mm²]."""
    for diag in read_messages(path, "/controller/diagnostics"):
        if diag.setpoint_mm2:
            return diag.setpoint_mm2
    return None


def metrics(trace: Trace, setpoint_mm2: float) -> Metrics:
    """Table 4 metrics over the evaluation window (see module docstring)."""
    if not setpoint_mm2 > 0:
        raise ValueError(f"set point must be > 0 mm², got {setpoint_mm2}")
    reached = np.flatnonzero(trace.area_mm2 >= BUILD_UP_FRACTION * setpoint_mm2)
    start = reached[0] if reached.size else int(np.searchsorted(trace.time_s, trace.time_s[0] + BUILD_UP_FALLBACK_S))
    area = trace.area_mm2[start:]
    if area.size == 0:
        raise ValueError("the run ended before the melt pool built up")
    rel = area / setpoint_mm2
    return Metrics(
        setpoint_mm2=setpoint_mm2,
        overshoot_pct=float(100 * (rel.max() - 1)),
        undershoot_pct=float(100 * (1 - rel.min())),
        steady_rmse_pct=float(100 * np.sqrt(np.mean((rel - 1) ** 2))),
        window_start_s=float(trace.time_s[start]),
        steps=int(trace.time_s.size),
    )


def plot(traces: dict[str, Trace], setpoint_mm2: float, out: Path) -> Path:
    """Fig. 5-style figure: area with set point, laser power and T ahead vs time, one line per run."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(3, 1, figsize=(9, 8), sharex=True)
    for label, tr in traces.items():
        t_ms = tr.time_s * 1e3
        axes[0].plot(t_ms, tr.area_mm2, lw=1.2, label=label)
        axes[1].plot(t_ms, tr.power_w, lw=1.2, label=label)
        axes[2].plot(t_ms, tr.t_ahead_k, lw=1.2, label=label)
    axes[0].axhline(setpoint_mm2, color="k", ls="--", lw=1, label="set point")
    axes[0].set_ylabel("melt-pool area [mm²]")
    axes[1].set_ylabel("laser power [W]")
    axes[2].set_ylabel("T ahead [K]")
    axes[2].set_xlabel("process time [ms]")
    axes[0].legend(loc="best", fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    fig.tight_layout()
    out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return out


def report(path: Path, setpoint_mm2: float | None = None, figure: Path | None = None) -> dict:
    """Metrics of one recording and its figure; returns the JSON-able summary."""
    trace = read_trace(path)
    setpoint = setpoint_mm2 or recorded_setpoint(path)
    if setpoint is None:
        raise UsageError(f"{path}: no set point recorded (open-loop run?); pass --setpoint-mm2")
    result = asdict(metrics(trace, setpoint))
    result["figure"] = str(plot({path.stem: trace}, setpoint, figure or path.with_suffix(".png")))
    result["recording"] = str(path)
    return result


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m controller_node.report``."""
    parser = ArgumentParser(prog="python -m controller_node.report", description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, help="MCAP recording of a run")
    parser.add_argument("--setpoint-mm2", type=float, help="set point [mm²] (default: the one the controller recorded)")
    parser.add_argument("--figure", type=Path, help="PNG to write (default: next to the recording)")
    parser.add_argument("--json", action="store_true", help="print the metrics as JSON (last line)")
    args = parser.parse_args(argv)
    try:
        if args.setpoint_mm2 is not None and not args.setpoint_mm2 > 0:
            raise UsageError("--setpoint-mm2 must be > 0")
        result = report(args.recording, args.setpoint_mm2, args.figure)
    except (UsageError, RecordingError, ValueError) as err:
        return exit_usage(parser.prog, err)
    print(
        f"set point {result['setpoint_mm2']:.4f} mm²: max overshoot {result['overshoot_pct']:.1f} %, "
        f"max undershoot {result['undershoot_pct']:.1f} %, steady-state RMSE {result['steady_rmse_pct']:.2f} % "
        f"(window from {result['window_start_s'] * 1e3:.2f} ms; figure {result['figure']})"
    )
    if args.json:
        print(json.dumps(result))
    return 0


if __name__ == "__main__":
    sys.exit(main())
