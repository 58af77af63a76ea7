"""Closed-loop performance from any recording (paper Table 4 and Fig. 5), over one fixed window.

Reads only the contract channels ``/plant/state``, ``/controller/diagnostics`` (for the set
point) and ``/run/events`` (for the plant's announced number of steps), plus the recorder's
completeness mark, so it works on FE and hardware recordings alike.

Evaluation window
-----------------
One fixed window for every controller and every run: all plant states with
``t_k − t_0 ≥ WINDOW_START_S`` (1 ms, i.e. 20 steps of 50 µs), where ``t_0`` is the process time
of the first state (laser on, step 0), to the end of the run. The window does not depend on the
area trajectory, so a controller cannot shorten its own evaluation by building the pool slowly.
A multi-layer build (states carrying ``layer``) switches the laser on again on every layer's
fresh powder: there ``t_0`` is the first state of the state's own layer, so every layer's pool
build-up is left out alike (a single layer: the same window as above).

Metrics
-------
With the relative error ``e_k = A_k / A_set − 1`` of the melt-pool area ``A_k`` over the window
``W`` (in % of the set point ``A_set``; paper section IV.B for the first three):

- max overshoot            = 100 · max_W e_k
- max undershoot           = −100 · min_W e_k
- steady-state RMSE        = 100 · sqrt(mean_W e_k²)
- turnaround RMSE          = 100 · sqrt(mean_T e_k²), ``T = W ∩ {turnaround states}``: the first
  ``TURNAROUND_STEPS`` (50) states of every track except the first one of each layer (2.5 ms; at another
  frame period the same time, rounded up: 3 states at 1 ms)
- along-track RMSE         = 100 · sqrt(mean_(W∖T) e_k²)
- turnaround share         = 100 · Σ_T e_k² / Σ_W e_k² (share of the squared error in ``T``)

so that ``RMSE² = (n_T · RMSE_T² + n_along · RMSE_along²) / (n_T + n_along)``. A subset without
states (e.g. ``T`` of a single track) gives ``None`` (JSON ``null``), as does the share when
``T`` is empty or the error is zero everywhere.

Completeness
------------
A run that did not finish is reported as ``INCOMPLETE (<reason>)``, never as a Table-4 line, and
its JSON carries ``"complete": false``: when the recorder did not mark the recording complete,
or when the plant recorded fewer states than it announced (``total_steps`` of its ``start``
event, plus the initial state; the replay node announces the number of states itself). The
FE plant announces its steps at the profile's lowest speed, an upper bound when the speed
varies; its end event ``finished at step N`` with exactly ``N + 1`` states recorded is
therefore accepted as the end of its scan plan.

Run: ``python -m controller_node.report RECORDING [--setpoint-mm2 X] [--json]``; it writes the
Fig. 5-style PNG (area with set point, power, T ahead vs time) next to the recording. Exit
status 1 for an incomplete run (its metrics are still printed in the JSON).
"""

from __future__ import annotations

import json
import re
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from gp_model.build_up import REFERENCE_PERIOD_S, steps_at
from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main
from messages.recording import RecordingError, RecordingLimitError, is_complete, read_messages

WINDOW_START_S = 1.0e-3  # the evaluation window opens this long after laser-on (first state) [s]
TURNAROUND_STEPS = 50  # states at the start of every track but the first counted as turnaround (at 50 µs: 2.5 ms)
_TIME_TOL_S = 1e-9  # float tolerance on process times (far below one 50 µs step)
_FINISHED = re.compile(r"^finished at step (\d+)\b")


@dataclass(frozen=True)
class Trace:
    """Time series of one run (arrays of shape (n,)), in the contract's units."""

    time_s: np.ndarray
    area_mm2: np.ndarray
    power_w: np.ndarray
    t_ahead_k: np.ndarray
    track: np.ndarray
    layer: np.ndarray | None = None
    """Layer of every state (``None``: one layer)."""

    def layers(self) -> np.ndarray:
        """Layer index of every state, shape (n,) (zeros for a single layer)."""
        return np.zeros(self.track.shape, dtype=int) if self.layer is None else np.asarray(self.layer)


@dataclass(frozen=True)
class Metrics:
    """Table 4 metrics of one run over the fixed window, in percent of the set point.

    Attributes
    ----------
    setpoint_mm2 : float
        Set point A_set [mm²].
    overshoot_pct, undershoot_pct, steady_rmse_pct : float
        Max overshoot, max undershoot and RMSE over the window [% of A_set].
    window_start_s : float
        Where the window opens, after laser-on (the first state) [s]: ``WINDOW_START_S``.
    steps : int
        Plant states in the run (window or not).
    rmse_turnaround_pct, rmse_along_pct : float or None
        RMSE over the turnaround states of the window and over the rest [% of A_set];
        ``None`` for an empty subset.
    turnaround_share_pct : float or None
        Share of the window's squared error in the turnaround states [%].
    n_turnaround, n_along : int
        States of the window in either subset.
    """

    setpoint_mm2: float
    overshoot_pct: float
    undershoot_pct: float
    steady_rmse_pct: float
    window_start_s: float
    steps: int
    rmse_turnaround_pct: float | None
    rmse_along_pct: float | None
    turnaround_share_pct: float | None
    n_turnaround: int
    n_along: int


@dataclass(frozen=True)
class Completeness:
    """Whether a run finished; ``reason`` says why not (``None`` when complete)."""

    complete: bool
    reason: str | None = None


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
        layer=np.array([s.layer or 0 for s in states]),
    )


def recorded_setpoint(path: Path) -> float | None:
    """The set point the controller reported, if any [mm²]."""
    for diag in read_messages(path, "/controller/diagnostics"):
        if diag.setpoint_mm2:
            return diag.setpoint_mm2
    return None


def update_latency_us(path: Path) -> tuple[float | None, float | None]:
    """Median and 99th percentile [µs] of the controller's update as its node timed it (each
    diagnostics' ``solve_time_us``: state in, command and diagnostics out); None without diagnostics."""
    times = np.array([d.solve_time_us for d in read_messages(path, "/controller/diagnostics")], dtype=float)
    if not times.size:
        return None, None
    return round(float(np.median(times)), 1), round(float(np.percentile(times, 99)), 1)


def _segment_starts(*keys: np.ndarray) -> np.ndarray:
    """Index of the first state of the run of equal ``keys`` each state belongs to, shape (n,)."""
    n = keys[0].size
    change = np.zeros(n, dtype=bool)
    change[:1] = True
    for key in keys:
        change[1:] |= key[1:] != key[:-1]
    return np.maximum.accumulate(np.where(change, np.arange(n), 0))


def window_mask(trace: Trace) -> np.ndarray:
    """States inside the evaluation window: ``t − t_0 ≥ WINDOW_START_S`` with ``t_0`` the first
    state of the state's layer (boolean, shape (n,))."""
    t0 = trace.time_s[_segment_starts(trace.layers())]
    return trace.time_s - t0 >= WINDOW_START_S - _TIME_TOL_S


def turnaround_mask(track: np.ndarray, layer: np.ndarray | None = None, n_states: int = TURNAROUND_STEPS
                    ) -> np.ndarray:
    """Turnaround states: the first ``n_states`` states of every track but the first of each layer.

    Parameters
    ----------
    track : ndarray of int, shape (n,)
        Track index of every state, in step order.
    layer : ndarray of int, shape (n,), optional
        Layer of every state (default: one layer).
    n_states : int
        States counted from a track's first (default ``TURNAROUND_STEPS``, at the FE step).

    Returns
    -------
    ndarray of bool, shape (n,)
        True where the state's track is not its layer's first and the state lies fewer than
        ``n_states`` states after that track's first state.
    """
    track = np.asarray(track)
    layer = np.zeros(track.shape, dtype=int) if layer is None else np.asarray(layer)
    if track.size == 0:
        return np.zeros(0, dtype=bool)
    index = np.arange(track.size)
    track_start, layer_start = _segment_starts(layer, track), _segment_starts(layer)
    return (track_start != layer_start) & (index - track_start < n_states)


def _rms_pct(err: np.ndarray) -> float | None:
    return float(100 * np.sqrt(np.mean(err**2))) if err.size else None


def metrics(trace: Trace, setpoint_mm2: float) -> Metrics:
    """Table 4 metrics and the turnaround/along-track split over the fixed window.

    Parameters
    ----------
    trace : Trace
        Plant states of the run.
    setpoint_mm2 : float
        Set point A_set [mm²].

    Returns
    -------
    Metrics

    Raises
    ------
    ValueError
        A set point that is not > 0, or a run that ended before the window opened.
    """
    if not setpoint_mm2 > 0:
        raise ValueError(f"set point must be > 0 mm², got {setpoint_mm2}")
    window = window_mask(trace)
    if not window.any():
        raise ValueError("the run ended before the evaluation window opened "
                         f"({WINDOW_START_S * 1e3:g} ms after laser-on)")
    err = trace.area_mm2 / setpoint_mm2 - 1
    period_s = float(np.median(np.diff(trace.time_s))) if trace.time_s.size > 1 else REFERENCE_PERIOD_S
    turn = turnaround_mask(trace.track, trace.layers(), steps_at(TURNAROUND_STEPS, period_s)) & window
    along = window & ~turn
    sq_total = float(np.sum(err[window] ** 2))
    share = float(100 * np.sum(err[turn] ** 2) / sq_total) if turn.any() and sq_total > 0 else None
    return Metrics(
        setpoint_mm2=setpoint_mm2,
        overshoot_pct=float(100 * err[window].max()),
        undershoot_pct=float(-100 * err[window].min()),
        steady_rmse_pct=float(_rms_pct(err[window])),
        window_start_s=WINDOW_START_S,
        steps=int(trace.time_s.size),
        rmse_turnaround_pct=_rms_pct(err[turn]),
        rmse_along_pct=_rms_pct(err[along]),
        turnaround_share_pct=share,
        n_turnaround=int(turn.sum()),
        n_along=int(along.sum()),
    )


def completeness(n_states: int, total_steps: int | None, recorded_complete: bool = True,
                 finished_at_step: int | None = None, total_counts_states: bool = False) -> Completeness:
    """Whether a run finished (module docstring, "Completeness").

    Parameters
    ----------
    n_states : int
        Plant states recorded.
    total_steps : int or None
        Steps the plant announced in its ``start`` event (``None``: not announced).
    recorded_complete : bool
        The recorder's mark (:func:`messages.recording.is_complete`).
    finished_at_step : int or None
        ``N`` of the plant's end event ``finished at step N`` (the end of its scan plan), if any.
    total_counts_states : bool
        ``total_steps`` counts states, not steps (the replay node).

    Returns
    -------
    Completeness
    """
    if not recorded_complete:
        return Completeness(False, "the recorder did not mark the recording complete (run stopped or messages lost)")
    if total_steps is None:
        return Completeness(True)
    expected = total_steps if total_counts_states else total_steps + 1
    if n_states >= expected or (finished_at_step is not None and n_states == finished_at_step + 1):
        return Completeness(True)
    return Completeness(False, f"{n_states} of {expected} plant states recorded")


def recording_completeness(path: Path, n_states: int) -> Completeness:
    """:func:`completeness` of a recording holding ``n_states`` plant states, from its run events
    (the plant is the node whose ``start`` event announces ``total_steps``) and the recorder's mark."""
    events = list(read_messages(path, "/run/events"))
    plant = next((e for e in events if e.event == "start" and e.total_steps is not None), None)
    finished_at = None
    for event in events:
        if (plant is not None and event.event == "end" and event.node == plant.node
                and (m := _FINISHED.match(event.detail))):
            finished_at = int(m.group(1))
    states = read_messages(path, "/plant/state")
    first = next(states, None)
    states.close()  # only the first state is needed
    return completeness(n_states, plant.total_steps if plant else None, is_complete(path), finished_at,
                        total_counts_states=first is not None and first.source == "replay")


def table4_line(result: dict) -> str:
    """The human line of a report or run summary: Table-4 figures, or ``INCOMPLETE (<reason>)``."""
    if result.get("complete") is False:
        return f"INCOMPLETE ({result.get('incomplete_reason')})"
    split = (f"turnaround RMSE {_fmt_pct(result['rmse_turnaround_pct'])} ({result['n_turnaround']} states, "
             f"{_fmt_pct(result['turnaround_share_pct'], 1)} of the squared error), along-track RMSE "
             f"{_fmt_pct(result['rmse_along_pct'])} ({result['n_along']} states)")
    return (f"set point {result['setpoint_mm2']:.4f} mm²: max overshoot {result['overshoot_pct']:.1f} %, "
            f"max undershoot {result['undershoot_pct']:.1f} %, steady-state RMSE {result['steady_rmse_pct']:.2f} %; "
            f"{split}; window from {result['window_start_s'] * 1e3:g} ms after laser-on")


def _fmt_pct(value: float | None, digits: int = 2) -> str:
    return "n/a" if value is None else f"{value:.{digits}f} %"


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
    if traces:
        t0_ms = min(float(tr.time_s[0]) for tr in traces.values()) * 1e3
        axes[0].axvline(t0_ms + WINDOW_START_S * 1e3, color="0.5", ls=":", lw=1, label="window start")
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
    """Metrics, completeness and figure of one recording; returns the JSON-able summary.

    An incomplete run keeps whatever metrics can be computed, with ``complete`` false and the
    ``incomplete_reason``; a complete run that ends before the window opens raises ``ValueError``.
    """
    trace = read_trace(path)
    setpoint = setpoint_mm2 or recorded_setpoint(path)
    if setpoint is None:
        raise UsageError(f"{path}: no set point recorded (open-loop run?); pass --setpoint-mm2")
    done = recording_completeness(path, int(trace.time_s.size))
    try:
        result = asdict(metrics(trace, setpoint))
    except ValueError:
        if done.complete:
            raise
        result = {"setpoint_mm2": setpoint, "window_start_s": WINDOW_START_S, "steps": int(trace.time_s.size)}
    result.update(complete=done.complete, incomplete_reason=done.reason)
    result["update_median_us"], result["update_p99_us"] = update_latency_us(path)
    result["figure"] = str(plot({path.stem: trace}, setpoint, figure or path.with_suffix(".png")))
    result["recording"] = str(path)
    return result


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m controller_node.report`` (exit status 1 for an incomplete run or
    a recording beyond the reader's bounds, 2 for a bad command line or an unreadable recording)."""
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
    except RecordingLimitError as err:  # a hostile file: a failure, not a bad command line
        return exit_error(parser.prog, err)
    except (UsageError, RecordingError, ValueError) as err:
        return exit_usage(parser.prog, err)
    print(f"{table4_line(result)} (figure {result['figure']})")
    if args.json:
        print(json.dumps(result))
    return 0 if result["complete"] else 1


if __name__ == "__main__":
    run_main(main)
