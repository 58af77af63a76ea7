"""Test node: sends malformed payloads on contract keys during a run, from its own process.

``python -m tests.nodes.fuzzer --count N --seed S [--topic SUFFIX ...] [--after-step K]``.
Once the plant has published state ``--after-step``, it sends N payloads spread over the
topics: truncated, random bytes, empty, non-object JSON, oversized, NaN/Infinity/1e999, out of
range, wrong types, missing and unknown fields. Each one is checked to be rejected by
:func:`messages.codec.decode` before it is sent, so every payload it sends must be counted as
dropped by its receivers. It then waits for ``--settle-states`` more plant states (so that
everything was delivered and consumed), prints ``fuzz done: sent {...} at plant step S`` and
stays until the plant is gone (``--count 0``: a clean run with the same nodes). Exit 1 if the
plant ends before the fuzzing settled.
"""

from __future__ import annotations

import json
import random
import sys
import time

import zenoh

from messages import ControllerDiagnostics, LaserCommand, MeltPoolState, RunEvent, encode
from messages.bus import NodeBus, StopFlag, add_bus_arguments, bus_settings_from_args
from messages.cli import ArgumentParser
from messages.codec import MessageError, decode
from messages.topics import PLANT_STATE, TOPICS, Topic, key_expr

NON_FINITE = (b"NaN", b"Infinity", b"-Infinity", b"1e999", b"-1e999", b"nan", b"inf")


def valid_example(topic: Topic, run_id: str) -> dict:
    """A valid message of ``topic`` as a JSON object (the base of most mutations)."""
    msg = {
        "plant/state": MeltPoolState(
            run_id=run_id,
            step=3,
            time_s=1.5e-4,
            laser_x_mm=0.1,
            laser_y_mm=0.0,
            scan_dir_x=1.0,
            scan_dir_y=0.0,
            track=0,
            area_mm2=0.06,
            t_ahead_k=500.0,
            power_w=250.0,
            speed_mm_s=800.0,
        ),
        "controller/command": LaserCommand(
            run_id=run_id, step=4, time_s=1.5e-4, power_w=250.0, speed_mm_s=800.0, controller="fuzz"
        ),
        "controller/diagnostics": ControllerDiagnostics(
            run_id=run_id, step=4, time_s=0.0, controller="fuzz", status="ok", solve_time_us=1.0
        ),
        "run/events": RunEvent(run_id=run_id, node="fuzz", event="end", time_s=0.0, published={"plant/state": 10**6}),
    }[topic.suffix]
    return json.loads(encode(msg))


OUT_OF_RANGE = (-1, -1e-9, 2e5, 1e30, 2**40, -(2**40))
WRONG_TYPE = ("250", None, [], {}, True, "NaN")


def mutate(rng: random.Random, topic: Topic, base: dict) -> bytes:
    """One malformed payload (not guaranteed invalid: the caller checks)."""
    raw = json.dumps(base).encode()
    numeric = [k for k, v in base.items() if isinstance(v, (int, float)) and not isinstance(v, bool)]
    kind = rng.randrange(11)
    if kind == 0:
        return raw[: rng.randrange(len(raw))]
    if kind == 1:
        return bytes(rng.getrandbits(8) for _ in range(rng.randrange(1, 64)))
    if kind == 2:
        return rng.choice((b"", b"null", b"[]", b"42", b'"state"', b"{", b"}", b"\xff\xfe"))
    if kind == 3:  # oversized: padding in a string field beyond the topic's limit
        return json.dumps({**base, "run_id": "x" * (topic.max_bytes + rng.randrange(1, 100))}).encode()
    if kind == 4:  # non-finite literal in a numeric field
        key = rng.choice(numeric)
        return raw.replace(f'"{key}":{json.dumps(base[key])}'.encode(), f'"{key}":'.encode() + rng.choice(NON_FINITE))
    if kind == 5:
        return json.dumps({**base, rng.choice(numeric): rng.choice(OUT_OF_RANGE)}).encode()
    if kind == 6:
        return json.dumps({**base, rng.choice(list(base)): rng.choice(WRONG_TYPE)}).encode()
    if kind == 7:
        return json.dumps({k: v for k, v in base.items() if k != rng.choice(list(base))}).encode()
    if kind == 8:
        return json.dumps({**base, f"extra_{rng.randrange(99)}": 1}).encode()
    if kind == 9:
        return json.dumps({**base, "run_id": rng.choice(("", "-bad", "a b", "x" * 65, "ü"))}).encode()
    return raw.replace(b":", b"=", 1)


def payloads(rng: random.Random, topic: Topic, run_id: str, n: int) -> list[bytes]:
    """``n`` payloads of ``topic``, each rejected by the codec."""
    base = valid_example(topic, run_id)
    out: list[bytes] = []
    while len(out) < n:
        payload = mutate(rng, topic, base)
        try:
            decode(topic, payload)
        except MessageError:
            out.append(payload)
    return out


def main(argv: list[str] | None = None) -> int:
    parser = ArgumentParser(prog="fuzzer")
    parser.add_argument("--count", type=int, default=10_000)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--topic", action="append", default=[],
                        help="topic suffix (default: plant/state, controller/command)")
    parser.add_argument("--after-step", type=int, default=2)
    parser.add_argument("--settle-states", type=int, default=5)
    add_bus_arguments(parser)
    args = parser.parse_args(argv)
    topics = [TOPICS[s] for s in (args.topic or ["plant/state", "controller/command"])]
    stop = StopFlag()
    rng = random.Random(args.seed)
    with NodeBus("fuzzer", bus_settings_from_args(args)) as bus:
        assert bus.session is not None
        share = [args.count // len(topics) + (i < args.count % len(topics)) for i in range(len(topics))]
        batches = {t.suffix: payloads(rng, t, bus.run_id, n) for t, n in zip(topics, share)}
        pubs = {t.suffix: bus.session.declare_publisher(  # blocking: every payload is delivered, none dropped
            key_expr(bus.run_id, t, bus.node), congestion_control=zenoh.CongestionControl.BLOCK,
            reliability=zenoh.Reliability.RELIABLE) for t in topics}
        states = bus.inbox(PLANT_STATE)
        plant_gone = bus.watch_presence("plant")
        bus.ready(config={"count": args.count, "seed": args.seed})

        def plant_step(after: int) -> int | None:
            while not stop.is_set() and not plant_gone.is_set():
                s = states.get(timeout=0.1)
                if s is not None and s.step >= after:
                    return s.step
            return None

        if args.count:
            if plant_step(args.after_step) is None:
                print("error: the plant ended before the fuzzing started", flush=True)
                return 1
            order = [(suffix, p) for suffix, batch in batches.items() for p in batch]
            rng.shuffle(order)
            t0 = time.monotonic()
            for suffix, payload in order:
                pubs[suffix].put(payload)
            sent_s = time.monotonic() - t0
            start = max((s.step for s in states.drain()), default=args.after_step)
            done_at = plant_step(start + args.settle_states)
            if done_at is None:
                print("error: the plant ended before the fuzz payloads settled", flush=True)
                return 1
            counts = {k: len(v) for k, v in batches.items()}
            print(f"fuzz done: sent {json.dumps(counts, sort_keys=True)} in {sent_s:.2f} s at plant step {done_at}",
                  flush=True)
        while not stop.is_set() and not plant_gone.is_set():  # stay present until the plant is done
            stop.wait(0.1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
