"""Did the nodes of a recording keep the node contract? ``python -m messages.conformance RECORDING``.

The checker reads an MCAP written by the recorder and applies the rules of
``docs/node-contract.md`` to what was recorded, without trusting any node:

========================  ==================================================================
rule                      a violation is
========================  ==================================================================
``finished``              a file the recorder did not finish (no footer)
``schema``                a message on an unknown channel or not valid against its topic's schema
``run_id``                a message whose ``run_id`` is not the recording's run
``state_steps``           a plant state whose step is not the previous one + 1 (the first is 0)
``state_time``            a state whose ``time_s`` does not advance by the sample period (±1 %)
``command_answers``       a command whose step is not a recorded state's step + 1, whose
                          ``time_s`` is not that state's, or that repeats or precedes a step
``power_bounds``          a state's applied power or a command's power outside the bounds of
                          its node's ``start`` configuration (``power_min_w``/``power_max_w``, at
                          its top level or in its ``policy`` table), if it states them
``lifecycle``             a node message before the node's ``start`` event, after its ``end``
                          event, or a node (but the recorder) without exactly one of each
``node_names``            a log line naming no node of the run
``counts``                ``meltloop.counts`` missing, not complete, or not reconciling with the
                          ``end`` events' ``published`` counts and the messages in the file
========================  ==================================================================

The sample period is the plant's ``start`` configuration ``sample_period_s`` [s] if it states
one, else the median step of ``time_s``. A node of a role topic (``plant/...``,
``controller/...``) is the node whose ``end`` event reports publishing it, else the node named
like the role. ``--node NAME`` reports only that node's violations.

Prints one line per violated rule (how many violations, the first offending step or message)
and a verdict line; ``--json`` prints one JSON object instead. Exit status 0 conforming,
1 violations or a file beyond the reader's bounds (:class:`~messages.recording.RecordingLimitError`),
2 bad command line, missing file or not an MCAP.
"""

from __future__ import annotations

import json
import statistics
from collections import Counter, defaultdict
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from messages.cli import ArgumentParser, UsageError, exit_error, exit_usage, run_main
from messages.codec import MessageError, decode, loads
from messages.recording import Recording, RecordingError, RecordingLimitError, read_recording
from messages.topics import LASER_COMMAND, LOG, PLANT_STATE, RUN_EVENTS, TOPICS, Topic, message_node

RULES = ("finished", "schema", "run_id", "state_steps", "state_time", "command_answers", "power_bounds",
         "lifecycle", "node_names", "counts")
RECORDER = "recorder"
PERIOD_TOLERANCE = 0.01
"""Largest relative deviation of one step's ``time_s`` advance from the sample period."""
TIME_TOLERANCE_S = 1e-9
"""Largest difference [s] between a command's ``time_s`` and its state's (JSON float round trip)."""


@dataclass
class Violations:
    """Summary of one rule's violations: how many, by which nodes, and the first one."""

    count: int = 0
    nodes: set[str] = field(default_factory=set)
    first_step: int | None = None
    first: str = ""


@dataclass(frozen=True)
class Item:
    """One decoded message: its place in the file, topic, message and the node it comes from."""

    index: int
    topic: Topic
    msg: Any
    node: str


@dataclass(frozen=True)
class Violation:
    """One broken rule: which, by which node, where (step, if any) and how."""

    rule: str
    node: str
    detail: str
    step: int | None = None


@dataclass
class Report:
    """The verdict on one recording: every violation, in the order found."""

    path: Path
    n_messages: int = 0
    nodes: set[str] = field(default_factory=set)
    violations: list[Violation] = field(default_factory=list)

    def add(self, rule: str, node: str, detail: str, step: int | None = None) -> None:
        """Record one violation of ``rule`` by ``node``."""
        self.violations.append(Violation(rule, node, detail, step))

    def only(self, node: str) -> Report:
        """The report restricted to the violations of ``node``."""
        return Report(self.path, self.n_messages, self.nodes, [v for v in self.violations if v.node == node])

    @property
    def found(self) -> dict[str, Violations]:
        """Per violated rule: how many violations, by which nodes, and the first one (the one of the
        lowest step, else the first found)."""
        found: dict[str, Violations] = {}
        for v in self.violations:
            summary = found.setdefault(v.rule, Violations(first_step=v.step, first=v.detail))
            summary.count += 1
            summary.nodes.add(v.node)
            if v.step is not None and (summary.first_step is None or v.step < summary.first_step):
                summary.first_step, summary.first = v.step, v.detail
        return found

    @property
    def conforming(self) -> bool:
        """Whether no rule was violated."""
        return not self.violations

    def lines(self) -> list[str]:
        """One line per violated rule, then the verdict."""
        out, found = [], self.found
        for rule in RULES:
            if (v := found.get(rule)) is not None:
                where = f"first at step {v.first_step}" if v.first_step is not None else "first"
                out.append(f"{rule} [{', '.join(sorted(v.nodes))}]: {v.count} violation{'s' * (v.count != 1)}; "
                           f"{where}: {v.first}")
        verdict = "conforming" if self.conforming else f"NOT conforming ({len(found)} of {len(RULES)} rules)"
        out.append(f"{self.path}: {verdict}; {self.n_messages} messages, nodes {', '.join(sorted(self.nodes))}")
        return out

    def as_json(self) -> dict[str, Any]:
        """JSON-able form: the verdict and, per rule, whether it held and its first violation."""
        rules, found = {}, self.found
        for rule in RULES:
            v = found.get(rule, Violations())
            rules[rule] = {"ok": v.count == 0, "violations": v.count, "nodes": sorted(v.nodes),
                           "first_step": v.first_step, "first": v.first}
        return {"recording": str(self.path), "conforming": self.conforming, "messages": self.n_messages,
                "nodes": sorted(self.nodes), "rules": rules}


def _config(event: Any) -> dict[str, Any]:
    try:
        config = loads(event.config_json, f"configuration of {event.node}") if event.config_json else {}
    except MessageError:
        return {}
    return config if isinstance(config, dict) else {}


def power_bounds(config: dict[str, Any]) -> tuple[float, float] | None:
    """``(power_min_w, power_max_w)`` a node's start configuration states (top level, else ``policy``)."""
    for table in (config, config.get("policy")):
        if isinstance(table, dict) and isinstance(table.get("power_min_w"), (int, float)) \
                and isinstance(table.get("power_max_w"), (int, float)):
            return float(table["power_min_w"]), float(table["power_max_w"])
    return None


class Checker:
    """Applies every rule to one read recording; the result is :attr:`report`."""

    def __init__(self, recording: Recording) -> None:
        self.rec = recording
        self.report = Report(recording.path, len(recording.messages))
        self.run_id = recording.metadata.get("meltloop", {}).get("run_id")
        self.events = self._decode_events()
        self.owner = self._owners()
        self.items = self._decode_all()
        self.starts = {e.node: e for e in self.events if e.event == "start"}
        self.report.nodes = set(self.starts) | {i.node for i in self.items}

    # -- decoding and attribution ---------------------------------------------------------------
    def _decode_events(self) -> list[Any]:
        events = []
        for message in self.rec.messages:
            if self.rec.channels[message.channel_id].topic == RUN_EVENTS.channel:
                try:
                    events.append(decode(RUN_EVENTS, message.data))
                except MessageError:
                    pass  # reported by _decode_all
        return events

    def _owners(self) -> dict[str, str]:
        """Per role topic, the node that reports publishing it (else the role's name)."""
        owner = {t.suffix: t.suffix.split("/")[0] for t in TOPICS.values() if not t.per_node}
        for event in self.events:
            if event.event == "end":
                for suffix, n in event.published.items():
                    if suffix in owner and n > 0:
                        owner[suffix] = event.node
        return owner

    def _decode_all(self) -> list[Item]:
        items = []
        for index, message in enumerate(self.rec.messages):
            channel = self.rec.channels[message.channel_id].topic
            topic = TOPICS.get(channel.lstrip("/"))
            if topic is None:
                self.report.add("schema", "?", f"message {index} on unknown channel {channel!r}")
                continue
            try:
                msg = decode(topic, message.data)
            except MessageError as err:
                node = "?" if topic.per_node else self.owner[topic.suffix]
                self.report.add("schema", node, f"message {index}: {err}")
                continue
            node = message_node(msg) if topic.per_node else self.owner[topic.suffix]
            items.append(Item(index, topic, msg, str(node)))
        return items

    def _of(self, topic: Topic) -> list[Item]:
        return [i for i in self.items if i.topic is topic]

    # -- rules -----------------------------------------------------------------------------------
    def check(self) -> Report:
        """Apply every rule; returns :attr:`report`."""
        if self.rec.truncated:
            self.report.add("finished", RECORDER, self.rec.detail)
        for rule in (self._run_id, self._state_steps, self._state_time, self._command_answers,
                     self._power_bounds, self._lifecycle, self._node_names, self._counts):
            rule()
        return self.report

    def _run_id(self) -> None:
        run_ids = Counter(i.msg.run_id for i in self.items if hasattr(i.msg, "run_id"))
        expected = self.run_id or (run_ids.most_common(1)[0][0] if run_ids else None)
        for i in self.items:
            if getattr(i.msg, "run_id", expected) != expected:
                self.report.add("run_id", i.node, f"{i.topic.channel} run_id {i.msg.run_id!r}, the recording's is "
                                f"{expected!r}", getattr(i.msg, "step", None))

    def _state_steps(self) -> None:
        states = self._of(PLANT_STATE)
        if not states:
            self.report.add("state_steps", self.owner[PLANT_STATE.suffix], "no plant state recorded")
        expected = 0
        for i in states:
            step = i.msg.step
            if step != expected:
                kind = "repeat" if step < expected else "gap"
                self.report.add("state_steps", i.node, f"step {step} where {expected} was due ({kind})", step)
            expected = step + 1

    def _period(self, states: list[Item]) -> float | None:
        stated = _config(self.starts[states[0].node]).get("sample_period_s") if states[0].node in self.starts else None
        if isinstance(stated, (int, float)) and stated > 0:
            return float(stated)
        steps = [(b.msg.time_s - a.msg.time_s) / (b.msg.step - a.msg.step)
                 for a, b in zip(states, states[1:]) if b.msg.step > a.msg.step]
        return statistics.median(steps) if steps else None

    def _state_time(self) -> None:
        states = self._of(PLANT_STATE)
        period = self._period(states) if len(states) > 1 else None
        if period is None:
            return
        if period <= 0:
            self.report.add("state_time", states[0].node, f"time_s does not advance (period {period} s)")
            return
        for a, b in zip(states, states[1:]):
            steps = b.msg.step - a.msg.step
            advance = b.msg.time_s - a.msg.time_s
            if steps <= 0 or abs(advance / steps / period - 1.0) > PERIOD_TOLERANCE:
                self.report.add("state_time", b.node, f"time_s {b.msg.time_s!r} s after {a.msg.time_s!r} s at step "
                                f"{a.msg.step}; sample period {period!r} s", b.msg.step)

    def _command_answers(self) -> None:
        state_time = {i.msg.step: i.msg.time_s for i in self._of(PLANT_STATE)}
        last = -1
        for i in self._of(LASER_COMMAND):
            step = i.msg.step
            answered = state_time.get(step - 1)
            if step <= last:
                self.report.add("command_answers", i.node, f"command step {step} after step {last}", step)
            elif answered is None:
                self.report.add("command_answers", i.node, f"command step {step} answers no recorded state "
                                f"(no state {step - 1})", step)
            elif abs(i.msg.time_s - answered) > TIME_TOLERANCE_S:
                self.report.add("command_answers", i.node, f"command step {step} has time_s {i.msg.time_s!r} s, "
                                f"state {step - 1} {answered!r} s", step)
            last = max(last, step)

    def _power_bounds(self) -> None:
        for topic, what in ((PLANT_STATE, "applied power"), (LASER_COMMAND, "commanded power")):
            for i in self._of(topic):
                bounds = power_bounds(_config(self.starts[i.node])) if i.node in self.starts else None
                if bounds is not None and not bounds[0] <= i.msg.power_w <= bounds[1]:
                    self.report.add("power_bounds", i.node, f"{what} {i.msg.power_w!r} W at step {i.msg.step} "
                                    f"outside {i.node}'s [{bounds[0]!r}, {bounds[1]!r}] W", i.msg.step)

    def _lifecycle(self) -> None:
        by_node: dict[str, list[Item]] = defaultdict(list)
        for i in self.items:
            by_node[i.node].append(i)
        for node, items in sorted(by_node.items()):
            events = [i for i in items if i.topic is RUN_EVENTS]
            starts = [i for i in events if i.msg.event == "start"]
            ends = [i for i in events if i.msg.event == "end"]
            if len(starts) != 1:
                self.report.add("lifecycle", node, f"{node}: {len(starts)} start events")
            elif items[0] is not starts[0]:
                self.report.add("lifecycle", node, f"{node}: {items[0].topic.channel} (message {items[0].index}) "
                                "before its start event", getattr(items[0].msg, "step", None))
            if node == RECORDER:
                continue
            if len(ends) != 1:
                self.report.add("lifecycle", node, f"{node}: {len(ends)} end events")
            elif items[-1] is not ends[0]:
                after = items[-1]
                self.report.add("lifecycle", node, f"{node}: {after.topic.channel} (message {after.index}) after "
                                "its end event", getattr(after.msg, "step", None))

    def _node_names(self) -> None:
        for i in self._of(LOG):
            if i.msg.name not in self.starts:
                self.report.add("node_names", i.msg.name or "?", f"log line {i.index} names {i.msg.name!r}, "
                                "which is no node of the run (no start event)")

    def _counts(self) -> None:
        counts = self.rec.metadata.get("meltloop.counts")
        if counts is None:
            self.report.add("counts", RECORDER, "no meltloop.counts metadata")
            return
        if counts.get("complete") != "true":
            self.report.add("counts", RECORDER, f"complete = {counts.get('complete')!r}: "
                            f"{counts.get('incomplete_reason') or counts.get('stopped_by')}")
        recorded = Counter(self.rec.channels[m.channel_id].topic.lstrip("/") for m in self.rec.messages)
        published: Counter[str] = Counter()
        per_node: dict[tuple[str, str], int] = Counter((i.node, i.topic.suffix) for i in self.items)
        for i in self.items:
            if i.topic is RUN_EVENTS and i.msg.event == "end":
                published.update(i.msg.published)
                for suffix, n in sorted(i.msg.published.items()):
                    if per_node[(i.node, suffix)] != n:
                        self.report.add("counts", i.node, f"{i.node} published {n} {suffix}, "
                                        f"{per_node[(i.node, suffix)]} recorded")
                for (node, suffix), n in sorted(per_node.items()):
                    if node == i.node and suffix not in i.msg.published:
                        self.report.add("counts", node, f"{node} recorded {n} {suffix}, published none")
        for key, expected in (("published", published), ("recorded", recorded)):
            try:
                stated = Counter(loads(counts.get(key, ""), f"meltloop.counts {key}"))
            except (ValueError, TypeError):
                stated = None
            if stated != expected:
                self.report.add("counts", RECORDER, f"meltloop.counts {key} = {counts.get(key)!r}, the file's "
                                f"{'end events' if key == 'published' else 'messages'} say "
                                f"{json.dumps(dict(sorted(expected.items())))}")


def check(path: str | Path) -> Report:
    """The conformance report of one recording.

    Raises
    ------
    RecordingError
        Missing, empty or non-MCAP file.
    """
    return Checker(read_recording(path)).check()


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``python -m messages.conformance``."""
    parser = ArgumentParser(prog="python -m messages.conformance", description=__doc__.split("\n\n")[0])
    parser.add_argument("recording", type=Path, help="MCAP file written by the recorder")
    parser.add_argument("--node", help="report only this node's violations (e.g. plant, controller)")
    parser.add_argument("--json", action="store_true", help="print one JSON object instead of lines")
    args = parser.parse_args(argv)
    try:
        report = check(args.recording)
        if args.node is not None and args.node not in report.nodes:
            raise UsageError(f"--node {args.node}: not a node of {args.recording} "
                             f"(nodes: {', '.join(sorted(report.nodes))})")
    except RecordingLimitError as err:  # a hostile file: a failure, not a bad command line
        return exit_error(parser.prog, err)
    except (RecordingError, UsageError) as err:
        return exit_usage(parser.prog, err)
    if args.node is not None:
        report = report.only(args.node)
    if args.json:
        print(json.dumps(report.as_json()))
    else:
        print("\n".join(report.lines()))
    return 0 if report.conforming else 1


if __name__ == "__main__":
    run_main(main)
