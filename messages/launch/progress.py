"""Progress of a run for the terminal: the plant's latest step against its announced total.

The zenoh callbacks only enqueue raw payloads; :meth:`ProgressObserver.poll`, called from the
supervision loop, decodes them and moves a tqdm bar on stderr.
"""

from __future__ import annotations

import queue
import sys
from collections.abc import Callable
from typing import Any

from messages.codec import MessageError, decode
from messages.topics import PLANT_STATE, RUN_EVENTS, key_expr


class ProgressObserver:
    """Follows ``/plant/state`` steps and the plant's ``start`` event (``total_steps``)."""

    def __init__(self, session: Any, run_id: str) -> None:
        self._inbox: queue.SimpleQueue[tuple[Any, bytes]] = queue.SimpleQueue()
        self.step = 0
        self.total = 0
        self._bar: Any = None
        for topic in (RUN_EVENTS, PLANT_STATE):
            session.declare_subscriber(key_expr(run_id, topic, "plant"),
                                       lambda s, t=topic: self._inbox.put((t, s.payload.to_bytes())))

    def poll(self) -> None:
        """Take in what arrived and update the bar."""
        while True:
            try:
                topic, payload = self._inbox.get_nowait()
            except queue.Empty:
                break
            try:
                msg = decode(topic, payload)
            except MessageError:
                continue
            if topic is RUN_EVENTS and msg.event == "start" and msg.total_steps:
                self.total = msg.total_steps
            elif topic is PLANT_STATE:
                self.step = max(self.step, min(msg.step, self.total or msg.step))
        if self.total and self._bar is None:
            from tqdm import tqdm

            self._bar = tqdm(total=self.total, desc="[launch] steps", unit="step", file=sys.stderr, dynamic_ncols=True)
        if self._bar is not None:
            self._bar.update(self.step - self._bar.n)

    def writer(self, fallback: Callable[[str], None]) -> Callable[[str], None]:
        """A line printer that does not break the bar."""
        return lambda line: self._bar.write(line) if self._bar is not None else fallback(line)

    def close(self) -> None:
        """Remove the bar."""
        if self._bar is not None:
            self._bar.close()
            self._bar = None
