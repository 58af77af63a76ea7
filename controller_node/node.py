"""The controller as a zenoh node: ``python -m controller_node``.

A thin shell around :func:`controller_node.registry.make_controller`: it subscribes to
``MeltPoolState``, converts it to an SI :class:`~controller_node.types.Measurement`, asks the
controller, and publishes the ``LaserCommand`` for the next step plus a
``ControllerDiagnostics``. The same loop serves a lockstep plant (the FE node waits for each
command) and a free-running one (a sensor publishes at its own rate): it always answers the
newest state and counts the older ones it skipped. Invalid messages are dropped and counted,
never acted on; a power outside the configured bounds is never published. It stops when the
plant's liveliness token disappears (the plant ended or died), or on SIGINT/SIGTERM.
"""

from __future__ import annotations

import argparse
import gc
import json
import sys
import threading
import time
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from controller_node.process import process_table
from controller_node.registry import CONTROLLERS, MODELS, make_controller, model_class
from controller_node.settings import ControllerSettings, merged_over
from controller_node.types import ConfigurationError, Measurement
from gp_model.atomic import atomic_write_bytes
from gp_model.files import load_for_node
from messages import ControllerDiagnostics, LaserCommand, LogLevel, MeltPoolState
from messages.bus import (
    Inbox,
    NewestInbox,
    NodeBus,
    StopFlag,
    TopicPublisher,
    add_bus_arguments,
    bus_settings_from_args,
    run_node,
    single_threaded_blas,
)
from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main
from messages.config import as_dict, build, load_toml
from messages.spare_core import SpareCore
from messages.topics import CONTROLLER_DIAGNOSTICS, LASER_COMMAND, PLANT_STATE, RUN_EVENTS
from messages.types import MAX_STEP, MAX_STEPS_AHEAD

NODE_NAME = "controller"


def measurement_from_state(state: MeltPoolState) -> Measurement:
    """Contract message (mm², mm/s) → SI measurement (m², m/s)."""
    return Measurement(
        step=state.step,
        time_s=state.time_s,
        area_m2=state.area_mm2 * 1e-6,
        t_ahead_k=state.t_ahead_k,
        power_w=state.power_w,
        speed_m_s=state.speed_mm_s * 1e-3,
        track=state.track,
        track_elapsed_s=state.track_elapsed_s,
        track_remaining_s=state.track_remaining_s,
        next_track=state.next_track,
        layer=state.layer,
    )


def default_model_path(name: str) -> Path | None:
    """The shipped model file of controller ``name`` (``None``: it runs no model)."""
    return MODELS[name][1] if name in MODELS else None


def load_model(name: str, path: Path | None):
    """The model of controller ``name`` (:data:`~controller_node.registry.MODELS`; ``path``, else the
    shipped one), or ``None`` for a controller that runs none; :class:`UsageError` if it cannot be
    loaded, or if ``path`` is given for a controller that uses no model."""
    if name not in MODELS:
        if path is not None:
            raise UsageError(f"--model: the {name} controller uses no model")
        return None
    return load_for_node(model_class(name), path or MODELS[name][1])


def inadmissible(step: int, last_step: int | None) -> str | None:
    """Why a schema-valid state with this step cannot be answered, or None.

    Its answer ``step + 1`` must exist in the contract; a state not newer than the last answered
    one (a duplicate, or late) was answered already and gets no second command; and a state more than
    :data:`MAX_STEPS_AHEAD` after the last answered one is impossible for a plant in lockstep or
    free-running at its frame period (a forged or corrupted step); both are dropped and counted,
    never passed to the controller.
    """
    if step >= MAX_STEP:
        return f"step {step} has no next step in the contract"
    if last_step is not None and step <= last_step:
        return f"step {step} is not newer than the last answered step {last_step} (duplicate or late)"
    if last_step is not None and step > last_step + MAX_STEPS_AHEAD:
        return f"step {step} is more than {MAX_STEPS_AHEAD} steps after the last answered step {last_step}"
    return None


def run(bus: NodeBus, controller, settings: ControllerSettings, stop: StopFlag, plant: str, config: dict,
        busy_wait: bool = False) -> int:
    """Answer plant states until the plant goes away or a stop is requested.

    The states are answered on a thread of their own that blocks in zenoh until a state arrives
    (:class:`~messages.bus.NewestInbox`: no poll timeout, no queue hop; for a steady sensor faster
    than :data:`PREPARE_LATE_MIN_S` it polls from :data:`POLL_AT` of the interval on, or from its
    answer on while the machine has a core to spare (:meth:`AnswerLoop.poll_window`);
    ``busy_wait``: it polls all the time and keeps its core) and
    publishes the command before anything else; this thread waits
    for a stop request (signals are handled here) or the plant's departure, then wakes it.
    """
    states = bus.newest_inbox(PLANT_STATE)
    commands = bus.publisher(LASER_COMMAND)
    diagnostics = bus.publisher(CONTROLLER_DIAGNOSTICS)
    plant_gone = bus.watch_presence(plant)
    plant_events = bus.inbox(RUN_EVENTS)
    bus.ready(config=config, stop=stop)
    loop = AnswerLoop(bus, controller, settings, states, commands, diagnostics,
                      done=lambda: stop.is_set() or plant_gone.is_set(), busy_wait=busy_wait)
    worker = threading.Thread(target=loop.serve, name="answer-states", daemon=True)
    gc.collect()
    gc.freeze()  # what exists now lives to the end: keep it out of the collections on the hot path
    worker.start()
    while worker.is_alive() and not loop.done():
        stop.wait(0.05)
    states.wake()
    worker.join()
    if loop.error is not None:
        raise loop.error
    if loop.status != 0:
        return loop.status
    lost = not stop.is_set() and not ended(plant_events, plant, PLANT_END_WAIT_S)
    reason = "stopped" if stop.is_set() else f"plant '{plant}' " + ("lost (no end event)" if lost else "ended")
    summary = (f"{reason}; {controller.n_fallbacks} fallbacks, {states.n_invalid} invalid and "
               f"{loop.n_impossible} impossible states dropped, {loop.n_skipped} skipped; kept its core "
               f"between states {loop.n_kept_core} times (a core to spare)")
    bus.log(LogLevel.ERROR if lost else LogLevel.INFO, summary, time_s=loop.last_time_s)
    bus.end_detail(summary)
    return 1 if lost else 0


PLANT_END_WAIT_S = 0.5
"""How long after the plant's token went its ``end`` event may still arrive (it is published
about 50 ms before the token goes)."""


def ended(events: Inbox, node: str, wait_s: float) -> bool:
    """Whether ``node``'s ``end`` event is among the run events received (waiting up to ``wait_s``)."""
    deadline = time.monotonic() + wait_s
    while (event := events.get(timeout=max(0.0, deadline - time.monotonic()))) is not None:
        if event.node == node and event.event == "end":
            return True
    return False


PREPARE_AT = 0.9
"""The controller's preparation for the next state (:meth:`Controller.prepare`) runs this fraction
of the shortest of the last :data:`PREPARE_WINDOW` state intervals after a state arrived, not right
after its command: what it touches is then still in the caches when the next state comes (in a
``launch.py`` layer every state waits for an FE step, whose work evicts the controller's code and
data; ``docs/controller.md``, Real-time iteration)."""
PREPARE_WINDOW = 8
PREPARE_LATE_MIN_S = 2e-3
"""States closer than this (a free-running sensor): the preparation runs right after the command,
and the answering thread polls for the next state from :data:`POLL_AT` of the shortest recent
interval after the last arrival (no wake-up on the state's path, a fraction of a core spent), or
from its answer on while the machine has a core to spare (:meth:`AnswerLoop.poll_window`)."""
POLL_AT = 0.6
POLL_SPAN = 3.0
"""Polling for the next state ends this many shortest intervals after the last arrival; the thread
then sleeps in zenoh until a state comes."""


@dataclass
class AnswerLoop:
    """The controller's hot path: newest state in, command out first, its diagnostics after."""

    bus: NodeBus
    controller: Any
    settings: ControllerSettings
    states: NewestInbox
    commands: TopicPublisher
    diagnostics: TopicPublisher
    done: Callable[[], bool]
    n_skipped: int = 0
    n_impossible: int = 0
    last_step: int | None = None
    last_time_s: float = 0.0
    status: int = 0
    error: BaseException | None = None
    busy_wait: bool = False
    spare: SpareCore = field(default_factory=SpareCore)
    n_kept_core: int = 0
    _last_arrival: float | None = None
    _intervals: deque = field(default_factory=lambda: deque(maxlen=PREPARE_WINDOW))
    _prepare_timer: threading.Timer | None = None
    _prepare_due: bool = False
    _prepare_pending: bool = False
    _prepare_generation: int = 0

    def serve(self) -> None:
        """Answer states until ``done()`` (checked after every wake-up); errors are kept for the caller.

        A state is answered with its command first, then the answer's diagnostics; the controller
        then prepares its next update (:meth:`schedule_prepare`).
        """
        try:
            while not self.done():
                # free-running plant: answer the newest state only
                state, skipped = self.states.newest(busy=self.busy_wait, poll=self.poll_window())
                self.n_skipped += skipped
                if state is None:
                    if self._prepare_due and self._prepare_pending:   # woken by the preparation's timer
                        self._prepare_due = self._prepare_pending = False
                        self.controller.prepare()
                    continue
                arrived, on_path_s = time.monotonic(), 0.0
                if self._prepare_pending:        # the state came before the timer: prepare first, on its path
                    self._cancel_prepare()
                    t0 = time.perf_counter()
                    self.controller.prepare()
                    on_path_s = time.perf_counter() - t0
                self._cancel_prepare()
                self._arrived(arrived, self.states.queued)
                answered, diag = self.answer(state, on_path_s)
                if diag is not None:
                    self.diagnostics.put(diag)
                if not answered:
                    return
                self.schedule_prepare()
        except BaseException as err:  # re-raised on the node's main thread
            self.error = err
        finally:
            self._cancel_prepare()

    def _arrived(self, t: float, queued: bool = False) -> None:
        """A state was taken at monotonic time ``t`` [s]. One found waiting when the poll window
        opened (``queued``) came at some time before: it counts as arrived when expected (the last
        arrival plus the shortest recent interval) if that is earlier, else a late wake-up would
        open the next window later, and the next, until the windows lag a steady sensor."""
        if queued and self._last_arrival is not None and self._intervals:
            t = min(t, self._last_arrival + min(self._intervals))
        if self._last_arrival is not None:
            self._intervals.append(t - self._last_arrival)
        self._last_arrival = t

    def poll_window(self) -> tuple[float, float] | None:
        """When to poll for the next state (monotonic ``(start, end)`` [s]): only for states that come
        steadily closer than :data:`PREPARE_LATE_MIN_S` (a free-running sensor), else ``None``
        (sleep in zenoh until one arrives). The window opens at :data:`POLL_AT` of the shortest
        recent interval after the last arrival, or at once while the machine has a core to spare
        (:class:`~messages.spare_core.SpareCore`): the thread then keeps its core between states and
        its caches stay warm for the next update (each such window counted in :attr:`n_kept_core`)."""
        intervals = self._intervals
        if self.busy_wait or len(intervals) < intervals.maxlen or (period := min(intervals)) >= PREPARE_LATE_MIN_S:
            return None
        end = self._last_arrival + POLL_SPAN * period
        if self.spare.spare(time.monotonic()):
            self.n_kept_core += 1
            return self._last_arrival, end
        return self._last_arrival + POLL_AT * period, end

    def schedule_prepare(self) -> None:
        """Prepare the controller's next update (after a command): at :data:`PREPARE_AT` of the
        shortest recent state interval after the state's arrival, by a timer that wakes this
        thread; at once while fewer than :data:`PREPARE_WINDOW` intervals are known or states come
        closer than :data:`PREPARE_LATE_MIN_S`. A state that arrives first has the preparation run
        before its update, on its path (counted in its ``solve_time_us``): every state is then
        answered as if prepared right after the command, whatever the timing (same run, same
        recording)."""
        intervals = self._intervals
        delay = -1.0
        if len(intervals) == intervals.maxlen and min(intervals) >= PREPARE_LATE_MIN_S:
            delay = PREPARE_AT * min(intervals) - (time.monotonic() - self._last_arrival)
        if delay <= 0.0:
            self.controller.prepare()
            return
        self._prepare_pending = True
        generation = self._prepare_generation
        self._prepare_timer = threading.Timer(delay, self._prepare_wake, args=(generation,))
        self._prepare_timer.daemon = True
        self._prepare_timer.start()

    def _prepare_wake(self, generation: int) -> None:
        """The timer's end: mark the preparation due and wake the answering thread (unless a state
        came first)."""
        if generation == self._prepare_generation:
            self._prepare_due = True
            self.states.wake()

    def _cancel_prepare(self) -> None:
        self._prepare_generation += 1
        self._prepare_due = self._prepare_pending = False
        if self._prepare_timer is not None:
            self._prepare_timer.cancel()
            self._prepare_timer = None

    def answer(self, state: MeltPoolState, on_path_s: float = 0.0) -> tuple[bool, ControllerDiagnostics | None]:
        """Answer one state (or drop it, counted): publish its command; (``False`` if the controller
        refused the plant, the diagnostics to publish). ``on_path_s`` [s]: a preparation that ran
        between the state's arrival and its update, added to the update's ``solve_time_us``."""
        bus, settings = self.bus, self.settings
        reason = inadmissible(state.step, self.last_step)
        if reason is not None:
            self.n_impossible += 1
            if self.n_impossible == 1:
                bus.log(LogLevel.WARNING, f"state dropped: {reason} (further ones are only counted)",
                        time_s=state.time_s)
            return True, None
        self.last_time_s = state.time_s
        controller = self.controller
        try:
            command, diag = controller.update(measurement_from_state(state))
        except ConfigurationError as err:
            bus.log(LogLevel.ERROR, str(err), time_s=state.time_s)
            bus.end_detail(f"refused: {err}")
            print(f"python -m controller_node: error: {err}", file=sys.stderr)
            self.status = 2
            return False, None
        self.last_step = state.step
        power = command.power_w
        # the core guarantees this; never trust it blindly
        if not settings.power_min_w <= power <= settings.power_max_w:
            bus.log(LogLevel.ERROR, f"controller produced {power} W outside bounds; not published", time_s=state.time_s)
            return True, None
        self.commands.put(LaserCommand(
            run_id=bus.run_id, step=command.step, time_s=state.time_s, power_w=power,
            speed_mm_s=command.speed_m_s * 1e3, controller=controller.name,
        ))
        return True, ControllerDiagnostics(
            run_id=bus.run_id, step=command.step, time_s=state.time_s, controller=controller.name,
            status=diag.status[:64], solve_time_us=(diag.solve_time_s + on_path_s) * 1e6, fallback=diag.fallback,
            n_fallbacks=diag.n_fallbacks, n_dropped=self.states.n_invalid + self.n_skipped + self.n_impossible,
            setpoint_mm2=settings.set_point_m2 * 1e6,
            predicted_area_mm2=[a * 1e6 for a in diag.predicted_area_m2],
            predicted_power_w=list(diag.predicted_power_w),
            model_std_mm2=None if diag.model_std_m2 is None else diag.model_std_m2 * 1e6,
            feedforward_w=diag.feedforward_w,
        )


def build_parser() -> argparse.ArgumentParser:
    """Command line of ``python -m controller_node``."""
    parser = ArgumentParser(prog="python -m controller_node", description=__doc__.split("\n\n")[0])
    parser.add_argument("--controller", default="preview-mpc", choices=CONTROLLERS,
                        help="control law (default: %(default)s)")
    parser.add_argument("--model", type=Path,
                        help="model file (default: the controller's shipped model in gp_model/models/)")
    parser.add_argument("--setpoint-mm2", type=float, help="melt-pool area set point [mm²]")
    parser.add_argument("--nominal-power-w", type=float,
                        help="power at laser-on and during the pool build-up [W] (default: [controller] "
                             "nominal_power_w, else 250 W)")
    parser.add_argument("--nominal-speed-m-s", type=float,
                        help="scan speed every command carries [m/s] (default: [controller] nominal_speed_m_s, else "
                             "0.8 m/s; launch.py passes the plant's)")
    parser.add_argument("--config", type=Path,
                        help="TOML run configuration; its [controller] table holds ControllerSettings fields")
    parser.add_argument("--process", type=Path, metavar="MODEL",
                        help="a model learned by `python -m gp_trainer learn`: its recorded operating power and PID "
                             "tuning (controller_node.process) under --config's [controller] values (launch.py passes "
                             "the model of the run's plant)")
    parser.add_argument("--plant", default="plant", help="name of the plant node to follow (default: %(default)s)")
    parser.add_argument("--busy-wait", action="store_true",
                        help="poll for the plant's states instead of sleeping until one arrives: keeps one core "
                             "busy for the whole run, answers sooner (a dedicated core, e.g. a kHz sensor)")
    parser.add_argument("--learning-state", type=Path, metavar="FILE",
                        help="preview-mpc: start from what a previous layer learned (if FILE exists) and write "
                             "what this one learned to FILE at the end")
    add_bus_arguments(parser)
    return parser


def settings_from_args(args: argparse.Namespace) -> ControllerSettings:
    """The ``[controller]`` table of ``--config`` over ``--process``'s record, then
    ``--setpoint-mm2``, ``--nominal-power-w`` and ``--nominal-speed-m-s`` (:class:`UsageError` naming a bad key)."""
    table = dict(load_toml(args.config).get("controller", {}))
    table.pop("name", None)  # the controller's name is a launch option
    if args.process is not None:
        table = merged_over(process_table(args.process), table)
    set_point = None if args.setpoint_mm2 is None else args.setpoint_mm2 * 1e-6
    return build(ControllerSettings, table, "[controller]", set_point_m2=set_point,
                 nominal_power_w=args.nominal_power_w, nominal_speed_m_s=args.nominal_speed_m_s)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m controller_node``."""
    parser = build_parser()
    args = parser.parse_args(argv)
    single_threaded_blas()
    try:
        bus_settings = bus_settings_from_args(args)
        settings = settings_from_args(args)
        model = load_model(args.controller, args.model)
        try:
            controller = make_controller(args.controller, settings, model)
        except ValueError as err:
            raise UsageError(str(err)) from None
        if args.learning_state is not None:
            load_learning_state(controller, args.learning_state)
    except UsageError as err:
        return exit_usage(parser.prog, err)
    model_file = args.model or default_model_path(args.controller)
    config = {"controller": args.controller, "model": str(model_file) if model else None, "busy_wait": args.busy_wait,
              **as_dict(settings)}
    stop = StopFlag()
    status = run_node(parser.prog, NODE_NAME, bus_settings,
                      lambda bus: run(bus, controller, settings, stop, args.plant, config, args.busy_wait))
    if args.learning_state is not None and status == 0:
        controller.finish_run()
        try:
            atomic_write_bytes(args.learning_state, json.dumps(controller.learning_state()).encode("utf-8"))
        except OSError as err:
            return exit_error(parser.prog, f"cannot write {args.learning_state}: {err.strerror or err}")
    return status


def load_learning_state(controller, path: Path) -> None:
    """Load a previous layer's learning into a ``preview-mpc`` (missing file: start fresh)."""
    if not hasattr(controller, "load_learning_state"):
        raise UsageError("--learning-state needs the preview-mpc controller")
    if not path.is_file():
        return
    try:
        controller.load_learning_state(json.loads(path.read_bytes()))
    except (OSError, ValueError) as err:
        raise UsageError(f"--learning-state {path}: {' '.join(str(err).split())}") from None


if __name__ == "__main__":
    run_main(main)
