"""Run report of ``launch.py``: one run's summary (JSON-able), its Table-4 line, and the
comparison table of several controllers, all over the fixed window of
:mod:`controller_node.report`."""

from __future__ import annotations

from pathlib import Path
from typing import Any

from controller_node.report import (
    TURNAROUND_STEPS,
    WINDOW_START_S,
    metrics,
    read_trace,
    recorded_setpoint,
    recording_completeness,
    update_latency_us,
)
from messages.recording import RecordingError


def summarise(out: Path, scenario: str, controller: str, status: int, wall_s: float) -> dict[str, Any]:
    """Summary of a run: completeness and, for a closed loop, the Table-4 metrics at the set point
    the controller recorded (none recorded: no metrics); ``complete`` is false for a run that did
    not finish or whose recording cannot be read."""
    summary: dict[str, Any] = {"status": status, "wall_s": round(wall_s, 2), "recording": str(out),
                               "scenario": scenario, "controller": controller}
    try:
        trace = read_trace(out)
        done = recording_completeness(out, int(trace.time_s.size))
        setpoint_mm2 = recorded_setpoint(out)
    except RecordingError as err:
        summary.update(error=str(err), complete=False, incomplete_reason=f"unreadable recording: {err}")
        return summary
    summary.update(steps=int(trace.time_s.size - 1), complete=done.complete, incomplete_reason=done.reason)
    if setpoint_mm2 is not None:
        try:
            m = metrics(trace, setpoint_mm2)
        except ValueError as err:
            summary["error"] = str(err)
            return summary
        summary.update(setpoint_mm2=m.setpoint_mm2, window_start_s=m.window_start_s,
                       overshoot_pct=round(m.overshoot_pct, 2), undershoot_pct=round(m.undershoot_pct, 2),
                       steady_rmse_pct=round(m.steady_rmse_pct, 2),
                       rmse_turnaround_pct=_round(m.rmse_turnaround_pct), rmse_along_pct=_round(m.rmse_along_pct),
                       turnaround_share_pct=_round(m.turnaround_share_pct, 1),
                       n_turnaround=m.n_turnaround, n_along=m.n_along)
        summary["update_median_us"], summary["update_p99_us"] = update_latency_us(out)
    return summary


def table_line(summary: dict[str, Any]) -> str:
    """A run's Table-4 line, or ``INCOMPLETE (<reason>)`` for a run that did not finish."""
    run = f"[launch] {summary['controller']} on {summary['scenario']}:"
    if summary.get("complete") is False:
        return f"{run} INCOMPLETE ({summary['incomplete_reason']})"
    if "steady_rmse_pct" not in summary:
        return f"{run} {summary.get('steps', 0)} steps in {summary['wall_s']:.1f} s"
    return (f"{run} set point {summary['setpoint_mm2']:.4f} mm² | "
            f"max overshoot {summary['overshoot_pct']:.1f} % | max undershoot {summary['undershoot_pct']:.1f} % | "
            f"steady-state RMSE {summary['steady_rmse_pct']:.2f} % | "
            f"turnaround RMSE {_cell(summary['rmse_turnaround_pct'])} % ({summary['n_turnaround']} states) | "
            f"along-track RMSE {_cell(summary['rmse_along_pct'])} % ({summary['n_along']} states) | "
            f"window from {summary['window_start_s'] * 1e3:g} ms after laser-on | "
            f"{summary['steps']} steps in {summary['wall_s']:.1f} s")


def comparison_table(scenario: str, setpoint_mm2: float, rows: list[dict[str, Any]]) -> str:
    """Markdown comparison of several runs' summaries, with the window stated (and each controller's
    update median in its node, state in to command out)."""
    heading = (f"Scenario `{scenario}`, set point {setpoint_mm2:.4f} mm². Every figure in % of the set point, "
               f"over one fixed window for every controller: from {WINDOW_START_S * 1e3:g} ms after laser-on to the "
               f"end of the run; turnaround = the first {TURNAROUND_STEPS} states of every track after the first, "
               "along-track = the rest of the window.")
    lines = [("| controller | max overshoot [%] | max undershoot [%] | steady-state RMSE [%] | turnaround RMSE [%] "
              "| along-track RMSE [%] | update median [µs] | wall time [s] |"),
             "|---|---:|---:|---:|---:|---:|---:|---:|"]
    lines += [f"| {r['controller']} | {r['overshoot_pct']:.1f} | {r['undershoot_pct']:.1f} "
              f"| {r['steady_rmse_pct']:.2f} | {_cell(r['rmse_turnaround_pct'])} | {_cell(r['rmse_along_pct'])} "
              f"| {_cell(r.get('update_median_us'), 0)} | {r['wall_s']:.1f} |" for r in rows]
    return heading + "\n\n" + "\n".join(lines) + "\n"


def _round(value: float | None, digits: int = 2) -> float | None:
    return None if value is None else round(value, digits)


def _cell(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f}"
