"""A rogue client, to prove the secure deployment refuses it (not part of the product).

``hammer`` sends, at ``--rate`` Hz for ``--duration`` s, every kind of write a rogue would
try against one loop, each message marked so a watcher can tell it from the real traffic:
commands to the loop (manual, output 0 %, wild gains, setpoint, lease, and a release in the
name of the run it sees; a manual and a release also on keys ending in the tuner's user), a
forged result, progress and status, a cancel of the run; a fake tuner token and status
queryable; and, 20 times a second, the run's token ``<prefix>/tune/<loop>/running`` declared
and withdrawn (its vanishing makes the plant restore the loop). ``watch`` counts the marked
messages that reach a subscriber on ``<prefix>/**`` (with a viewer's credentials: the router
hands a viewer every put it let in) and every token's comings and goings. ``connect`` counts
refused session opens. Each prints one JSON object::

    python -m tests.tools.rogue hammer --prefix autotune --loop hx1 -c viewer.json5
    python -m tests.tools.rogue watch --prefix autotune -c viewer.json5 --duration 60
    python -m tests.tools.rogue connect -m client -e tcp/127.0.0.1:7447 --duration 5
"""

from __future__ import annotations

import argparse
import contextlib
import json
import sys
import threading
import time
from collections import Counter
from collections.abc import Callable

import zenoh

from shared import keys, wire
from shared.cli import install_stop_handlers
from shared.errors import AutotuneError
from shared.messages import (
    GainsCommand,
    LeaseCommand,
    LoopStatus,
    Message,
    ModeCommand,
    OutputCommand,
    PidGains,
    ReleaseCommand,
    SetpointCommand,
    TuneProgress,
    TuneResult,
)
from shared.session import add_zenoh_arguments, open_session, settings_from_args

MARK = 4242.4242  # the sim time every rogue message claims: how a watcher tells them apart
MARK_TEXT = "rogue"
TOGGLE_EVERY = 50  # ticks between two changes of the fake run token


def attacks(prefix: str, loop: str, run: Callable[[], str]) -> list[tuple[str, str, Callable]]:
    """(name, key, payload maker) for every write the rogue tries; ``run()`` is the run id
    seen on the loop's progress (the rogue speaks in its name where it can)."""

    def cmd(
        kind: str, make: Callable[[str], Message], user: str | None = None
    ) -> tuple[str, str, Callable]:
        key = keys.command(prefix, loop, kind) + (f"/{user}" if user else "")
        return (f"cmd/{kind}" + (f"/{user}" if user else ""), key, lambda: make(run()))

    return [
        cmd("mode", lambda r: ModeCommand(loop=loop, mode="manual", t=MARK, source=r)),
        cmd("output", lambda r: OutputCommand(loop=loop, op=0.0, t=MARK, source=r)),
        cmd(
            "gains",
            lambda r: GainsCommand(loop=loop, gains=PidGains(kc=1e3), t=MARK, source=r),
        ),
        cmd("setpoint", lambda r: SetpointCommand(loop=loop, sp=1e6, t=MARK, source=r)),
        cmd("release", lambda r: ReleaseCommand(loop=loop, t=MARK, source=r)),
        # in the tuner's name: the user chunk of a command key the plant reads as the sender
        cmd("mode", lambda r: ModeCommand(loop=loop, mode="manual", t=MARK, source=r), "tuner"),
        cmd("release", lambda r: ReleaseCommand(loop=loop, t=MARK, source=r), "tuner"),
        cmd("lease", lambda r: LeaseCommand(loop=loop, t=MARK, source=MARK_TEXT)),
        (
            "result",
            keys.tune_result(prefix, loop),
            lambda: TuneResult(
                run_id=run().removeprefix("tuner:"),
                loop=loop,
                t=MARK,
                method="relay",
                rule="auto",
                status="failed",
                reason=MARK_TEXT,
            ),
        ),
        (
            "progress",
            keys.tune_progress(prefix, loop),
            lambda: TuneProgress(
                run_id=run().removeprefix("tuner:"), loop=loop, t=MARK, phase=MARK_TEXT
            ),
        ),
        ("status", keys.status(prefix, loop), lambda: fake_status(loop)),
        ("cancel", keys.tune_cancel(prefix, loop), lambda: MARK_TEXT),
    ]


def fake_status(loop: str) -> LoopStatus:
    return LoopStatus(
        loop=loop,
        node=MARK_TEXT,
        seq=0,
        t=MARK,
        pv=0.0,
        sp=0.0,
        op=0.0,
        mode="manual",
        action="reverse",
        gains=PidGains(kc=1.0),
        op_limits=(0.0, 100.0),
        pv_range=(0.0, 100.0),
        disturbances={},
        clock="realtime",
        accepted=0,
        rejected=0,
        reason=MARK_TEXT,
    )


def is_rogue(key: str, payload: bytes) -> bool:
    """A message the rogue sent (by its mark)."""
    if key.endswith("/cancel"):
        return payload == MARK_TEXT.encode()
    try:
        data = json.loads(payload)
    except ValueError:
        return False
    return isinstance(data, dict) and (data.get("t") == MARK or data.get("node") == MARK_TEXT)


def hammer(
    session: zenoh.Session,
    prefix: str,
    loop: str,
    rate: float,
    duration: float,
    stop: threading.Event | None = None,
) -> dict:
    """Send the attacks round-robin at ``rate`` Hz for ``duration`` s (or until ``stop``);
    count what was sent."""
    seen_run = ["tuner:unknown"]

    def learn(sample: zenoh.Sample) -> None:
        with contextlib.suppress(ValueError, KeyError, TypeError):
            seen_run[0] = "tuner:" + json.loads(sample.payload.to_bytes())["run_id"]

    sub = session.declare_subscriber(keys.tune_progress(prefix, loop), learn)
    token = session.liveliness().declare_token(keys.tuner_alive(prefix, MARK_TEXT))
    fakes = session.declare_queryable(
        keys.status(prefix, loop),
        lambda q: wire.reply(q, keys.status(prefix, loop), fake_status(loop)),
    )
    plan = attacks(prefix, loop, lambda: seen_run[0])
    sent: Counter[str] = Counter()
    errors: Counter[str] = Counter()
    period = 1.0 / rate
    start = time.monotonic()
    n = 0
    stop = stop or threading.Event()
    running: zenoh.LivelinessToken | None = None
    while (now := time.monotonic()) - start < duration and not stop.is_set():
        name, key, make = plan[n % len(plan)]
        msg = make()
        try:
            if isinstance(msg, Message):
                wire.put(session, key, msg)
            else:
                session.put(key, msg)
            sent[name] += 1
        except Exception as err:  # count, never stop: a rogue keeps trying
            errors[type(err).__name__] += 1
        if n % TOGGLE_EVERY == 0:  # the run's token appears and vanishes
            if running is None:
                running = session.liveliness().declare_token(keys.tune_running(prefix, loop))
            else:
                running.undeclare()
                running = None
            sent["token/running"] += 1
        n += 1
        wait = start + n * period - now
        if wait > 0:
            time.sleep(wait)
    elapsed = time.monotonic() - start
    if running is not None:
        running.undeclare()
    fakes.undeclare()
    token.undeclare()
    sub.undeclare()
    return {
        "sent": sum(sent.values()),
        "rate": round(sum(sent.values()) / elapsed, 1),
        "by_kind": dict(sent),
        "errors": dict(errors),
        "seconds": round(elapsed, 2),
        "run_seen": seen_run[0],
    }


def watch(session: zenoh.Session, prefix: str, duration: float, stop: threading.Event) -> dict:
    """Count the rogue's messages (by key) that reach a subscriber on ``<prefix>/**``, and
    the liveliness events of every token (a run's token comes and goes once per run)."""
    got: Counter[str] = Counter()
    events: Counter[str] = Counter()
    total = [0]

    def on_sample(sample: zenoh.Sample) -> None:
        total[0] += 1
        key = str(sample.key_expr)
        if is_rogue(key, sample.payload.to_bytes()):
            got[key.removeprefix(prefix + "/")] += 1

    def on_token(sample: zenoh.Sample) -> None:
        kind = "PUT" if sample.kind == zenoh.SampleKind.PUT else "DELETE"
        events[f"{str(sample.key_expr).removeprefix(prefix + '/')} {kind}"] += 1

    sub = session.declare_subscriber(f"{prefix}/**", on_sample)
    live = session.liveliness().declare_subscriber(f"{prefix}/**", on_token)
    tokens = [
        str(r.ok.key_expr)
        for r in session.liveliness().get(keys.tuner_alive(prefix, MARK_TEXT), timeout=1.0)
        if r.ok is not None
    ]
    stop.wait(duration)
    live.undeclare()
    sub.undeclare()
    return {
        "rogue_delivered": sum(got.values()),
        "by_key": dict(got),
        "seen": total[0],
        "rogue_tokens": tokens,
        "token_events": dict(events),
    }


def connect(args: argparse.Namespace, stop: threading.Event) -> dict:
    """Try to open a session every ``1/rate`` s for ``duration`` s (or until ``stop``);
    count the refusals."""
    refused = opened = 0
    start = time.monotonic()
    while time.monotonic() - start < args.duration and not stop.is_set():
        try:
            open_session(settings_from_args(args)).close()
            opened += 1
        except AutotuneError:
            refused += 1
        stop.wait(1.0 / args.rate)
    return {"opened": opened, "refused": refused, "seconds": round(time.monotonic() - start, 2)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m tests.tools.rogue", description=__doc__)
    parser.add_argument("action", choices=("hammer", "watch", "connect"))
    parser.add_argument("--prefix", default=keys.DEFAULT_PREFIX)
    parser.add_argument("--loop", default="hx1")
    parser.add_argument("--rate", type=float, default=1000.0, help="Hz (default: %(default)s)")
    parser.add_argument("--duration", type=float, default=10.0, help="s (default: %(default)s)")
    add_zenoh_arguments(parser)
    args = parser.parse_args(argv)
    stop = threading.Event()  # until --duration or SIGINT/SIGTERM, then the counts
    install_stop_handlers(stop)
    if args.action == "connect":
        out = connect(args, stop)
    else:
        try:
            session = open_session(settings_from_args(args))
        except AutotuneError as err:
            print(json.dumps({"open": "refused", "reason": str(err)}))
            return 0
        with session:
            if args.action == "hammer":
                out = hammer(session, args.prefix, args.loop, args.rate, args.duration, stop)
            else:
                out = watch(session, args.prefix, args.duration, stop)
    print(json.dumps(out))
    return 0


if __name__ == "__main__":
    sys.exit(main())
