"""``autotune tune LOOP``: ask the running autotuner to tune a loop; show progress and the result.

With ``--json`` the result is printed as one JSON object (the TuneResult message): ``ku``
(% per PV unit), ``pu`` (s), ``gains`` (every rule, every form), ``chosen``, ``before`` and
``after`` (verification figures), ``status``, ``reason``, ``applied``, ``restored``; and the
same figures in % of the PV's span (``pv_range``): ``ku_percent``, ``step_percent``,
``model_gain_percent`` and per rule ``isa_percent`` (kc in % per %, ti, td in s, pb in %).
``--units percent`` prints the tables in % of span, the engineering figures beside them.
Ctrl-C cancels the run; the tuner restores the loop before it answers.
"""

from __future__ import annotations

import argparse
import math
import queue
import signal
import sys
import threading
import time
from collections.abc import Callable

import pydantic
import zenoh

from services.autotuner.commands.step import parse_repeat
from services.autotuner.design.request_check import validate_request
from services.autotuner.design.rules import RULES, fopdt_of
from services.autotuner.identify.model_fit import ProcessFit
from services.autotuner.identify.reaction_curve import drift_beyond_noise
from services.autotuner.loop_client import wait_for_token
from services.autotuner.recorder_watch import incomplete_line, incomplete_record
from shared import json_text, keys, wire
from shared.cli import add_common_arguments, check_ids, check_tuner_node
from shared.control.forms import (
    IsaGains,
    kc_percent,
    process_gain_percent,
    pv_span,
    to_percent,
    unit,
)
from shared.errors import AutotuneError, ConfigError, DecodeError
from shared.history_file import same_gains
from shared.messages import (
    ANSWERED_LATE,
    DONE_STATUSES,
    LoopStatus,
    TuneAccepted,
    TuneProgress,
    TuneRequest,
    TuneResult,
    Verification,
)
from shared.session import open_session, settings_from_args, unreached

HELP = "tune a loop through the running autotuner (relay, ramp or step test)"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("loop", metavar="LOOP", help="loop id, e.g. hx1")
    add_tune_options(parser)
    add_units_option(parser)
    parser.add_argument("--json", action="store_true", help="print the result as one JSON object")
    parser.add_argument("--node", default="*", help="which autotuner (default: any)")
    parser.add_argument(
        "--wait",
        type=float,
        default=3600.0,
        help="wall seconds to wait for the result (default: %(default)s); past them the run "
        "is cancelled, the loop restored, and tune exits 2 (--detach leaves a run going)",
    )
    parser.add_argument(
        "--detach",
        action="store_true",
        help="submit the run and exit, leaving it going (print its acceptance); otherwise "
        "Ctrl-C, SIGTERM and SIGHUP cancel it and wait for the loop's restore",
    )
    add_common_arguments(parser)


UNITS = ("engineering", "percent")


def add_units_option(parser: argparse.ArgumentParser) -> None:
    """``--units engineering|percent``: what ``format_result``'s tables print."""
    parser.add_argument(
        "--units",
        choices=UNITS,
        default="engineering",
        help="what the tables print: engineering (Kc in %% of output per PV unit, process "
        "gains in PV units per %%) or percent (Kc in %% of output per %% of the PV's span, "
        "the proportional band PB = 100/Kc in %%, process gains in %% of span per %%; the "
        "engineering figures beside them). --json carries both (default: %(default)s)",
    )


def add_tune_options(parser: argparse.ArgumentParser) -> None:
    parser.add_argument(
        "--method",
        choices=("relay", "ramp", "step"),
        default="relay",
        help="experiment (default: %(default)s)",
    )
    parser.add_argument(
        "--rule",
        default="auto",
        choices=["auto", *RULES],
        metavar="RULE",
        help=f"tuning rule to apply: auto (the recommended rule), {', '.join(RULES)} "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--ms-bound",
        type=float,
        default=2.0,
        help="refuse gains whose maximum sensitivity Ms on the sampled loop of the identified "
        "model exceeds this (default: %(default)s)",
    )
    parser.add_argument(
        "--lambda",
        "--lambda-s",
        dest="lambda_s",
        type=float,
        metavar="SECONDS",
        help="lambda rules: the closed-loop time constant λ (default: the larger of the "
        "model's lag and 3 × its dead time; integrating: 3 × the dead time)",
    )
    parser.add_argument(
        "--aim",
        choices=("balanced", "robust", "fast"),
        default="balanced",
        help="what the recommended rule (auto) favours: balanced, robust (lambda rules first) "
        "or fast (README; default: %(default)s)",
    )
    parser.add_argument(
        "--max-overshoot",
        type=float,
        default=35.0,
        help="verification: refuse gains whose setpoint overshoot exceeds this, %% "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--max-decay-ratio",
        type=float,
        default=0.35,
        help="verification: refuse gains whose decay ratio exceeds this (default: %(default)s)",
    )
    parser.add_argument(
        "--overshoot-miss",
        type=float,
        default=20.0,
        help="verification: refuse gains whose measured overshoot exceeds the predicted one by "
        "more than this many percentage points: the model is wrong (default: %(default)s)",
    )
    parser.add_argument(
        "--max-op-noise",
        type=float,
        metavar="PCT",
        help="verification: refuse gains that turn the PV's noise into more output noise "
        "than this, %% of output (σ of the sample-to-sample change over √2, at rest); the "
        "recommended rule keeps within it where one can (default: 10)",
    )
    parser.add_argument(
        "--rest-window",
        type=float,
        help="seconds of PV the drift check before the test watches (default: the loop's "
        "integral time, 40 samples at least, 900 s at most)",
    )
    parser.add_argument(
        "--force",
        action="store_true",
        help="apply the rule's gains even if predicted unstable or above --ms-bound",
    )
    parser.add_argument(
        "--amplitude",
        type=float,
        help="relay amplitude d, %% (default 5, grown where the cycle rides on the hysteresis; "
        "one given is kept)",
    )
    parser.add_argument(
        "--hysteresis", type=float, help="relay hysteresis, PV units (default: 3σ of the PV noise)"
    )
    parser.add_argument(
        "--relay-bias",
        type=float,
        help="relay: make stage 2 asymmetric, its low output b − (1 − FRACTION)·d, for a "
        "static-gain estimate (costs K_u accuracy on non-minimum-phase plants; default off)",
    )
    parser.add_argument(
        "--cycles",
        type=int,
        default=3,
        help="relay: how many of the last cycles must agree (default: %(default)s)",
    )
    parser.add_argument(
        "--tolerance",
        type=float,
        default=0.02,
        help="relay: their allowed spread; ramp: twice the final gain bracket "
        "(default: %(default)s)",
    )
    parser.add_argument(
        "--bump", type=float, help="ramp setpoint bump, PV units (default: 1 %% of the PV range)"
    )
    parser.add_argument(
        "--kc-start", type=float, help="ramp first gain (default: half the loop's present Kc)"
    )
    parser.add_argument("--step-size", type=float, help="step test output step, %% (default 5)")
    parser.add_argument(
        "--repeat",
        type=parse_repeat,
        metavar="N|auto",
        help="step test: N tests, up and down in turn, their mean used (auto: until every "
        "figure's mean is known to ± 5 %%, at most 6; default: one test)",
    )
    parser.add_argument(
        "--pv-limits",
        type=float,
        nargs=2,
        metavar=("LO", "HI"),
        help="abort if the PV leaves [LO, HI] (default: the loop's PV range)",
    )
    parser.add_argument("--max-time", type=float, help="experiment budget, sim seconds")
    parser.add_argument("--no-verify", action="store_true", help="apply without verifying")
    parser.add_argument(
        "--no-apply",
        action="store_true",
        help="identify and compute only; leave the loop as it was",
    )


def request_from_args(args: argparse.Namespace, source: str) -> TuneRequest:
    try:
        req = TuneRequest(
            loop=args.loop,
            method=args.method,
            rule=args.rule,
            amplitude=args.amplitude,
            hysteresis=args.hysteresis,
            cycles=args.cycles,
            relay_bias=args.relay_bias,
            tolerance=args.tolerance,
            bump=args.bump,
            kc_start=args.kc_start,
            step_size=args.step_size,
            repeat=args.repeat,
            pv_limits=tuple(args.pv_limits) if args.pv_limits else None,
            max_time=args.max_time,
            verify=not args.no_verify,
            apply=not args.no_apply,
            force=args.force,
            ms_bound=args.ms_bound,
            lambda_s=args.lambda_s,
            aim=args.aim,
            max_overshoot=args.max_overshoot,
            max_decay_ratio=args.max_decay_ratio,
            overshoot_miss=args.overshoot_miss,
            max_op_noise=args.max_op_noise,
            rest_window=args.rest_window,
            source=source,
        )
    except pydantic.ValidationError as err:
        e = err.errors()[0]
        flag = "--" + str(e["loc"][0]).replace("_", "-") if e["loc"] else "request"
        raise ConfigError(f"{flag}: {e['msg']}") from None
    try:  # what the tuner would refuse, refused here before anything is sent
        validate_request(req)
    except ValueError as err:
        field, _, why = str(err).partition(": ")
        raise ConfigError(f"--{field.replace('_', '-')}: {why}") from None
    return req


ANSWER_WAY = 1.0  # s: of a request's wait, left for the tuner's answer to come back
# what a tuner of a version before ``TuneRequest.answer_by`` answers a request carrying it
UNKNOWN_ANSWER_BY = "answer_by: Extra inputs are not permitted"
# the error reply Zenoh itself gives a query no queryable finalised within its timeout (a
# tuner's refusals are sentences)
ZENOH_TIMEOUT = "Timeout"


# s: the least share of the wait one of several tuners is given to answer before the next
# is asked (a healthy tuner answers in milliseconds; a new peer's queryable may take a
# moment to route)
TRY_AT_LEAST = 2.0
RUN_SEEN_WAIT = 0.3  # s: after a silent tuner, for a run's token on the loop (it accepted)


# s: how long a loop's token may take to be seen before it is taken not to be there (the
# tuner's own ``service.ANNOUNCE_WAIT``)
LOOP_ANNOUNCE_WAIT = 4.0


class _Silent(AutotuneError):
    """The tuner asked did not answer within its share of the wait (``_ask``)."""


def _say_as_tune(line: str) -> None:
    print(f"autotune tune: {line}", file=sys.stderr)


def submit(
    session: zenoh.Session,
    prefix: str,
    node: str,
    req: TuneRequest,
    timeout: float = 10.0,
    say: Callable[[str], None] = _say_as_tune,
) -> TuneAccepted:
    """Send the request to an autotuner; return its acceptance or raise with its reason.

    ``node`` with a ``*`` is one tuner, not all of them (asking them all started a run on
    each): the live ones, first by name, each asked in turn for its share of ``timeout``
    until one answers. One chosen tuner only was asked before: a paused one, or a token
    another client declared with no tuner behind it, failed tune after 10 s with a working
    tuner on the bus (helper trial). Each request carries its own ``answer_by``, the end of
    its share: a tuner passed over that reads it later (resumed) refuses it, so the next
    one's run is the only one. A refusal is an answer, not passed over. ``say``: where a
    tuner passed over is told (the command's own stderr line: the demo's and the console's
    read "autotune tune:" before)."""
    key = keys.tuner_request(prefix, node)
    deadline = time.monotonic() + timeout

    def missing() -> AutotuneError:
        return AutotuneError(
            f"no autotuner answered at {key} within {timeout:g} s (is "
            f"`autotune tuner` running and reachable?){unreached(session)}"
        )

    if not wait_for_token(session, keys.tuner_alive(prefix, node), timeout):
        raise missing()
    if "*" not in node:
        return _ask(session, prefix, node, req, deadline, timeout)
    # a loop no plant serves, told here: each tuner takes its ANNOUNCE_WAIT (4 s) to say so,
    # longer than its share of the wait among three, and `autotune tune nosuch` with three
    # healthy tuners said after 10 s that all three were "paused or starved"
    loop_key = keys.loop_alive(prefix, req.loop)
    if not wait_for_token(
        session, loop_key, max(0.1, min(LOOP_ANNOUNCE_WAIT, deadline - time.monotonic()))
    ):
        raise AutotuneError(f"loop: no plant serves {req.loop!r} (nothing announces {loop_key})")
    nodes = tuner_candidates(session, prefix, node, max(0.1, deadline - time.monotonic()))
    silent: list[str] = []
    for i, name in enumerate(nodes):
        left = deadline - time.monotonic()
        if left <= 0:
            break
        share = max(min(TRY_AT_LEAST, left), left / (len(nodes) - i))
        try:
            return _ask(session, prefix, name, req, time.monotonic() + share, timeout)
        except _Silent:
            if len(nodes) == 1:
                raise
            silent.append(name)
            running = keys.tune_running(prefix, req.loop)
            if i + 1 < len(nodes) and wait_for_token(session, running, RUN_SEEN_WAIT):
                # the silent one accepted, and its answer was lost or late: another tuner's
                # run would be refused the loop's lease, and this one left unfollowed
                raise AutotuneError(
                    f"autotuner {name!r} did not answer within {share:.3g} s, and a run on "
                    f"{req.loop} is now under way ({running}): its answer may have been "
                    "lost, so no other tuner is asked (its run would be refused the loop); "
                    "`autotune loops` shows who holds the loop, the console's Cancel (or a put "
                    f"on {keys.tune_cancel(prefix, req.loop)}) stops the run"
                ) from None
            nxt = f": asking {nodes[i + 1]!r}" if i + 1 < len(nodes) else ""
            say(
                f"autotuner {name!r} did not answer within {share:.3g} s "
                f"(paused, starved, or a token with no tuner behind it){nxt}"
            )
    untried = [n for n in nodes if n not in silent]
    raise AutotuneError(
        f"{len(nodes)} autotuners are there ({', '.join(repr(n) for n in nodes)} at "
        f"{keys.tuner_alive(prefix, node)}) but "
        + f"{', '.join(repr(n) for n in silent)} did not answer the request"
        + (f" ({len(untried)} not asked)" if untried else "")
        + f" within {timeout:g} s: paused or starved, or the router does not let this "
        "session send requests (in the secure deployment, the operator's credentials do)"
        f"{unreached(session)}"
    )


def _ask(
    session: zenoh.Session,
    prefix: str,
    node: str,
    req: TuneRequest,
    until: float,
    timeout: float,
) -> TuneAccepted:
    """Ask tuner ``node`` until ``until`` (monotonic); its acceptance, AutotuneError for its
    refusal, _Silent for no answer. The request it reads after ``until`` it refuses
    (``answer_by``), the second before it left for its answer's way back."""
    key = keys.tuner_request(prefix, node)
    bounded = True  # sent with ``answer_by`` (not to a tuner of a version before it)
    late = False  # it said it read the request past its ``answer_by``
    while time.monotonic() < until:  # a new peer's queryable may take a moment to route
        left = until - time.monotonic()
        # answered by then or not at all: the tuner refuses it later (``answer_by``), the
        # second before the wait ends (half what is left, if less) left for its answer's way
        # back. Never past the wait's end: with 0.5 s at least, a request sent with 0.3 s left
        # was started by a tuner after its client had given up on it and asked the next
        by = time.time() + left - min(ANSWER_WAY, 0.5 * left) if bounded else None
        asked = req.model_copy(update={"answer_by": by})
        replies = session.get(
            key,
            payload=wire.encode(asked),
            encoding=wire.encoding_for(TuneRequest),
            target=zenoh.QueryTarget.BEST_MATCHING,
            timeout=max(0.1, until - time.monotonic()),
        )
        for reply in replies:
            if reply.ok is not None:
                accepted = wire.decode_sample(TuneAccepted, reply.ok)
                # whose run it is (``_confirmed``), and whose liveliness ``follow`` watches
                zid = str(reply.replier_id.zid) if reply.replier_id is not None else None
                _accepted_by[accepted.run_id] = (zid, node)
                while len(_accepted_by) > 64:
                    _accepted_by.pop(next(iter(_accepted_by)))
                return accepted
            why = reply.err.payload.to_bytes().decode(errors="replace")
            if why == ZENOH_TIMEOUT:  # Zenoh's own, no tuner's word: a paused tuner the
                # session knows (its queryable routed) was said to have "refused the
                # request: Timeout"
                break
            if ANSWERED_LATE in why:  # read past its ``answer_by``, in the second kept for
                # the answer's way back: as good as silent, not asked again, and the next tuner
                # is (it was taken for a refusal, and tune failed with a live tuner next)
                late = True
                break
            if not (bounded and UNKNOWN_ANSWER_BY in why):
                raise AutotuneError(f"the autotuner refused the request: {why}")
            # a tuner of a version before ``answer_by`` refuses the field: asked again
            # without it (that tuner starts a request however late it reads it)
            bounded = False
            break
        else:
            time.sleep(0.05)
        if late:
            break
    # its token seen, its queryable silent: paused or starved, or (a secure deployment) the
    # router drops this session's requests, which it may not send (a viewer's `autotune
    # tune` was asked whether the tuner was running: helper 52)
    raise _Silent(
        f"an autotuner is there ({keys.tuner_alive(prefix, node)}) but did not answer the "
        f"request at {key} within {timeout:g} s: it is paused or starved, or the router does "
        "not let this session send requests (in the secure deployment, the operator's "
        f"credentials do){unreached(session)}"
    )


def loop_state(session: zenoh.Session, prefix: str, loop: str, timeout: float = 2.0) -> str:
    """The loop as its plant has it now, in one phrase (an operator's first question)."""
    st = wire.query_one(session, keys.status(prefix, loop), LoopStatus, timeout)
    if st is None:
        return f"the loop's plant did not answer within {timeout:g} s"
    g = st.gains
    held = f", still held by {st.leased_by}" if st.leased_by else ""
    return (
        f"loop {loop} now: {st.mode}, SP {st.sp:.4g}, OP {st.op:.4g} %, PV {st.pv:.4g}, "
        f"Kc {g.kc:.4g}, Ti {'off' if g.ti is None else f'{g.ti:.4g} s'}, Td {g.td:.4g} s{held}"
    )


def tuner_candidates(
    session: zenoh.Session, prefix: str, pattern: str, timeout: float
) -> list[str]:
    """The live autotuners matching ``pattern``, by name (so a choice is repeatable).

    Asked again until ``timeout``: a session just opened in client mode gets an empty answer
    before its router has told it the tokens it knows."""
    deadline = time.monotonic() + timeout
    key = keys.tuner_alive(prefix, pattern)
    while True:
        nodes = sorted(
            {
                n
                for r in session.liveliness().get(
                    key, timeout=max(0.1, deadline - time.monotonic())
                )
                if r.ok is not None
                and (n := keys.service_node(prefix, "tuner", str(r.ok.key_expr))) is not None
            }
        )
        if nodes:
            return nodes
        if time.monotonic() > deadline:
            raise AutotuneError(f"no autotuner announces {key}")
        time.sleep(0.05)


RESULT_GRACE = 2.0  # s to wait for a result after the run's token vanished
# s: each link's handshake, at most (Zenoh's own is 10 s): a peer that is paused (its port
# accepts, its process does not answer) held tune 12 s before it could even say so
HANDSHAKE = 3.0


RECONNECT_WAIT = 20.0  # s to wait for the bus when this client sees nothing of it
REJOIN_GRACE = 5.0  # s to ask for a late result once the plant answers again
# s for a run cancelled when ``--wait`` ran out to say it restored the loop (the tuner's own
# restore is bounded; a run between the cancel and its end still ends)
CANCEL_WAIT = 60.0


def _cut_off(session: zenoh.Session, prefix: str, loop: str) -> bool:
    """Neither the loop's plant nor any tuner is in sight: this client lost the bus (its
    router restarting), rather than the run its tuner."""
    return not wait_for_token(session, keys.loop_alive(prefix, loop), 0.3) and not (
        wait_for_token(session, keys.tuner_alive(prefix, "*"), 0.3)
    )


STOP_SIGNALS = (signal.SIGINT, signal.SIGTERM, signal.SIGHUP)


def _held_start(start: Callable[[], TuneAccepted]) -> tuple[TuneAccepted, bool]:
    """``start()`` with Ctrl-C, SIGTERM and SIGHUP held until it answers; and whether one came.

    A run can begin before its acceptance reaches this client: a signal then had no run to
    name, and the client left while the tuner was still restoring the loop (seen: a loop left
    manual that was in auto). Held, the signal cancels the run by its id once known and the
    restore is waited for. A second one leaves at once (KeyboardInterrupt). Outside the main
    thread (the console) signals are not this thread's to hold."""
    if threading.current_thread() is not threading.main_thread():
        return start(), False
    held: list[int] = []

    def hold(signum: int, frame: object) -> None:
        held.append(signum)
        if len(held) > 1:
            raise KeyboardInterrupt
        print("\ncancelling once the run is accepted (again to leave at once)…", file=sys.stderr)

    # a signal this process ignores (SIGINT of a job a script put in the background, nohup's
    # SIGHUP) stays ignored: held, it would cancel the run
    before = {
        sig: signal.signal(sig, hold)
        for sig in STOP_SIGNALS
        if signal.getsignal(sig) is not signal.SIG_IGN
    }
    try:
        accepted = start()
    finally:
        for sig, handler in before.items():  # None: a handler not set from Python
            signal.signal(sig, signal.SIG_DFL if handler is None else handler)
    return accepted, bool(held)


class TimedOut(AutotuneError):
    """``--wait`` ran out, the run was cancelled and its result came: the one line of why,
    and the ``result`` (``--json`` printed nothing: a script read no object, though the
    tuner had sent one)."""

    def __init__(self, message: str, result: TuneResult):
        super().__init__(message)
        self.result = result


class Interrupted(KeyboardInterrupt):
    """A signal ended the wait and the cancelled run's ``result`` came: what it did, and the
    loop's ``state`` as the client leaves it. A run can end ok just before its cancel
    reaches it: its gains are then in the loop, and the client must say so, not "restored"."""

    def __init__(self, result: TuneResult, state: str):
        super().__init__(result.run_id)
        self.result, self.state = result, state

    def summary(self) -> str:
        r = self.result
        if r.applied and r.status in DONE_STATUSES:
            return (
                f"run {r.run_id} had ended {r.status} before the cancel reached it: its gains "
                f"are in the loop (`autotune revert {r.loop}` puts the earlier ones back); "
                f"{self.state}"
            )
        why = f": {r.reason}" if r.reason else ""
        back = "restored" if r.restored else "NOT restored"
        if r.untouched:  # cancelled before its lease: "loop restored" of a loop it never
            # wrote to followed "nothing was sent to the loop" (helper trial)
            back = "untouched (nothing was sent to it)"
        lf = r.left or {}
        restored_off = lf.get("pv_target") is not None and lf.get("returned") is False
        if r.restored and not r.untouched and restored_off:
            # restored, but its PV not back (a level in manual stays where the test left it:
            # helper trial, lvl2's ramp cancelled, 1.525 m for 1.5, said only "restored")
            band = f" ± {lf['band']:.2g}" if lf.get("band") is not None else ""
            back += f", but its PV not back where it was (target {lf['pv_target']:.4g}{band})"
        if r.status != "aborted":  # it ended on its own first (proposed, rejected, failed)
            return (
                f"run {r.run_id} had ended {r.status} before the cancel reached it{why}; loop "
                f"{back}; {self.state}"
            )
        return f"run {r.run_id} cancelled, {r.status}{why}; loop {back}; {self.state}"


class TunerGone(AutotuneError):
    """The run's tuner vanished before its result (killed, or cut off from the bus)."""


MALFORMED_SAID = 3  # malformed messages on the run's keys said one by one; the rest counted
_malformed_seen = [0]


def _malformed(key: str, err: DecodeError) -> None:
    """A message on the run's keys that is not valid (not the tuner's: another client on
    the bus): said on stderr, the first few, and otherwise ignored; the run is followed on
    (one such message killed the client, the run going on with no one to cancel it)."""
    _malformed_seen[0] += 1
    n = _malformed_seen[0]
    if n <= MALFORMED_SAID:
        print(f"autotune tune: ignored a malformed message on {key}: {err}", file=sys.stderr)
    if n == MALFORMED_SAID:
        print("autotune tune: more malformed messages are ignored unsaid", file=sys.stderr)


CONFIRM_WAIT = 2.0  # s: the accepting tuner's own copy of a run's result, asked for
# run id → the tuner that accepted the run (``submit``): its Zenoh id (None: not known),
# whose word its result must be, and its node name, whose liveliness token ``follow``
# watches beside the run's own
_accepted_by: dict[str, tuple[str | None, str]] = {}


def _confirmed(
    session: zenoh.Session, prefix: str, loop: str, r: TuneResult, tuner: str
) -> tuple[TuneResult | None, str]:
    """The result to take for ``r``, a result of the followed run that came on the bus, and a
    note for the user ("" for none): the tuner that accepted the run (Zenoh id ``tuner``) is
    asked for its own copy. Any client may publish on the run's keys on a bus without access
    control (README, Security): a forged ``ok`` in the middle of a run was printed as the
    run's result, the run going on. Its tuner's copy is taken over whatever came; a result
    its tuner answers against (the run still going, or another run its last) is ignored
    (None); with no answer from the tuner within CONFIRM_WAIT s, ``r`` is taken, and said
    to be unconfirmed."""
    answered, own = False, None
    # every tuner's answer, each kept: replies on one key are consolidated to the latest by
    # default, and with two tuners on the bus the other's last result of the loop took the
    # place of the run's own (3 of 3 runs "not confirmed" once both had results)
    replies = session.get(
        keys.tune_result(prefix, loop),
        target=zenoh.QueryTarget.ALL,
        consolidation=zenoh.ConsolidationMode.NONE,
        timeout=CONFIRM_WAIT,
    )
    for reply in replies:
        if reply.replier_id is None or str(reply.replier_id.zid) != tuner:
            continue
        answered = True
        if reply.ok is not None:
            try:
                got = wire.decode_sample(TuneResult, reply.ok)
            except DecodeError:
                continue
            own = got if got.run_id == r.run_id else own
    if own is not None:
        differs = (
            ""
            if own == r
            else (
                f"a result for run {r.run_id} unlike its tuner's came on the bus (not the "
                "tuner's: forged?): the tuner's own is shown"
            )
        )
        return own, differs
    if answered:
        return None, (
            f"ignored a result for run {r.run_id} ({r.status}) that its tuner does not give "
            "(the run is still going): not the tuner's (forged?)"
        )
    # (said as what it is: "not confirmed: its tuner did not answer", then the result
    # shown as the tuner's, read as a contradiction: helper trial, a tuner stopping)
    return r, (
        f"run {r.run_id}'s result is not confirmed: it came on the bus, and its tuner did "
        f"not answer the check within {CONFIRM_WAIT:g} s (stopping, or out of reach): it is "
        "shown as it came"
    )


def follow(
    session: zenoh.Session, prefix: str, loop: str, start, wait: float, on_progress=None
) -> TuneResult:
    """Subscribe to the loop's progress and result, call ``start()`` and wait for the run's
    result. Ctrl-C at any point cancels the loop's run and still waits for its result (the
    tuner restores the loop first); a second Ctrl-C leaves at once. The run's liveliness
    token (``<prefix>/tune/<loop>/running``) is watched too: when it vanishes and no result
    follows within RESULT_GRACE s, the tuner is gone — TunerGone, at once, not after
    ``wait`` — unless this client sees neither the plant nor any tuner (it lost the bus: a
    router restarting); it then waits up to RECONNECT_WAIT s for the bus and asks for the
    run's result, which the tuner keeps. No result within ``wait``: the run is cancelled
    (the tuner restores the loop) and AutotuneError says how it ended, unless it ended ok
    before the cancel reached it (returned as any result)."""
    inbox: queue.Queue = queue.Queue()
    sub = session.declare_subscriber(
        f"{keys.tune_root(prefix, loop)}/*", zenoh.handlers.FifoChannel(4096)
    )
    token = session.liveliness().declare_subscriber(
        keys.tune_running(prefix, loop), zenoh.handlers.FifoChannel(64)
    )
    # the plant's token too: seen to vanish, this client may have lost the bus (a router
    # restarting) — a look at one moment after the grace can miss that, once it is back
    plant = session.liveliness().declare_subscriber(
        keys.loop_alive(prefix, loop), zenoh.handlers.FifoChannel(64), history=True
    )
    for src in (sub, token, plant):
        threading.Thread(target=lambda src=src: [inbox.put(s) for s in src], daemon=True).start()
    run_id: str | None = None
    tuner: str | None = None  # the Zenoh id of the tuner that accepted the run, if known
    cancelled = False
    deadline = math.inf
    gone: float | None = None
    appeared = False
    plant_lost = False  # the plant's token vanished since the run began
    # the token of the tuner that accepted the run: the run's token is the loop's, and one
    # another run holds (a second tuner waiting for the loop's rest) kept a client whose
    # tuner was killed waiting its whole --wait (helper trial)
    node: str | None = None
    alive = None
    tuner_lost = False
    timed_out: float | None = None  # when ``wait`` ran out (the run was then cancelled)
    try:
        while True:
            try:
                if run_id is None:
                    accepted, interrupted = _held_start(start)
                    run_id = accepted.run_id
                    tuner, node = _accepted_by.pop(run_id, (None, None))
                    if node is not None:
                        alive = session.liveliness().declare_subscriber(
                            keys.tuner_alive(prefix, node), zenoh.handlers.FifoChannel(64)
                        )
                        threading.Thread(
                            target=lambda src=alive: [inbox.put(s) for s in src], daemon=True
                        ).start()
                    deadline = time.monotonic() + wait
                    if interrupted:
                        raise KeyboardInterrupt
                now = time.monotonic()
                # a run's token in sight after all: that DELETE was an earlier run's goodbye,
                # late (``appeared`` may come from a progress message)
                if (
                    gone is not None
                    and now > gone + RESULT_GRACE
                    and not plant_lost
                    and not tuner_lost
                    and wait_for_token(session, keys.tune_running(prefix, loop), 0.3)
                ):
                    gone = None
                    continue
                if gone is not None and now > gone + RESULT_GRACE:
                    cut_off = plant_lost or _cut_off(session, prefix, loop)
                    if cut_off:  # the bus went, not (only) the tuner:
                        # wait, bounded, for it to come back (a router restarting)
                        print(
                            f"run {run_id} on {loop}: its plant and tuner went out of sight "
                            f"(this client lost the bus?): waiting up to {RECONNECT_WAIT:g} s "
                            "for them to come back (Ctrl-C twice leaves)",
                            file=sys.stderr,
                        )
                        late = _late_result(session, prefix, loop, run_id, deadline)
                        if late is not None:
                            return late
                    whose = (
                        f"the liveliness token of its tuner, node {node!r},"
                        if tuner_lost
                        else "the run's liveliness token"
                    )
                    raise TunerGone(
                        f"run {run_id} on {loop}: its tuner is gone or cut off ({whose} "
                        f"vanished and no result followed within "
                        f"{RESULT_GRACE:g} s): the plant's watchdog returns the loop to its "
                        "state before the test (a tuner only paused says how its run ended "
                        "when it runs again); "
                        f"{loop_state(session, prefix, loop)}"
                    )
                limit = min(deadline, gone + RESULT_GRACE if gone is not None else math.inf)
                sample = inbox.get(timeout=max(0.0, limit - now))
                key = str(sample.key_expr)
                if node is not None and key == keys.tuner_alive(prefix, node):
                    # its tuner went (whichever token's DELETE came first), or came back (a
                    # link restored: the run token's presence is then judged again)
                    tuner_lost = sample.kind == zenoh.SampleKind.DELETE
                    if tuner_lost and gone is None:
                        gone = time.monotonic()
                elif key == keys.loop_alive(prefix, loop):
                    if sample.kind == zenoh.SampleKind.DELETE and run_id is not None:
                        plant_lost = True
                elif key == keys.tune_running(prefix, loop):
                    # a token that vanishes counts once ours has appeared (a run that ended
                    # just before ours may still be saying goodbye)
                    if sample.kind == zenoh.SampleKind.PUT:
                        appeared = True
                    elif appeared and gone is None:
                        gone = time.monotonic()
                elif key == keys.tune_progress(prefix, loop):
                    try:
                        p = wire.decode_sample(TuneProgress, sample)
                    except DecodeError as err:  # not the tuner's: said, and followed on
                        _malformed(key, err)
                        continue
                    if p.run_id == run_id:
                        # the run's token is declared before its first progress: one whose
                        # appearance was missed (this subscriber not yet known to the tuner)
                        # still counts when it vanishes
                        appeared = True
                        if on_progress:
                            on_progress(p)
                elif key == keys.tune_result(prefix, loop):
                    try:
                        r = wire.decode_sample(TuneResult, sample)
                    except DecodeError as err:
                        _malformed(key, err)
                        continue
                    if r.run_id == run_id and tuner is not None:
                        taken, note = _confirmed(session, prefix, loop, r, tuner)
                        if note:
                            print(note, file=sys.stderr)
                        if taken is None:
                            continue
                        r = taken
                    if r.run_id == run_id:
                        if cancelled:
                            raise Interrupted(r, loop_state(session, prefix, loop))
                        if timed_out is not None and r.status != "ok":
                            raise TimedOut(
                                f"no result for run {run_id} within {wait:g} s: cancelled, "
                                f"{r.status}: {r.reason}; {loop_state(session, prefix, loop)}",
                                r,
                            )
                        return r  # done (ok) before the cancel reached it
            except queue.Empty:
                if gone is not None:
                    continue  # the grace is over: said at the top of the loop
                if cancelled:
                    raise AutotuneError(
                        f"run {run_id} on {loop}: cancelled, but no result within "
                        f"{CANCEL_WAIT:g} s: {loop_state(session, prefix, loop)}"
                    ) from None
                if timed_out is None:  # the wait is over: cancel the run, not leave it going
                    timed_out = time.monotonic()
                    session.put(keys.tune_cancel(prefix, loop), run_id.encode())
                    print(
                        f"\nno result for run {run_id} within {wait:g} s: cancelling it (the "
                        "tuner restores the loop)…",
                        file=sys.stderr,
                    )
                    deadline = timed_out + CANCEL_WAIT
                    continue
                raise AutotuneError(
                    f"no result for run {run_id} within {wait:g} s, nor an answer to its "
                    f"cancel within {CANCEL_WAIT:g} s more: {loop_state(session, prefix, loop)}"
                ) from None
            except Interrupted:
                raise
            except (KeyboardInterrupt, RuntimeError) as err:
                # a signal's KeyboardInterrupt raised inside a lock's release in the wait's
                # threading internals comes out as "RuntimeError: release unlocked lock"
                # (SIGTERM, once in CI: exit 70, "internal error"): the signal all the same
                if isinstance(err, RuntimeError) and not isinstance(
                    err.__context__, KeyboardInterrupt
                ):
                    raise
                if cancelled or run_id is None:
                    if run_id is None:  # interrupted while submitting: cancel whatever runs
                        session.put(keys.tune_cancel(prefix, loop), b"")
                    print(
                        f"\nleft without waiting for the run's end: {loop} may still be being "
                        f"restored (`autotune loops {loop}` shows it)",
                        file=sys.stderr,
                    )
                    raise KeyboardInterrupt from None
                cancelled = True
                session.put(keys.tune_cancel(prefix, loop), run_id.encode())
                # the restore is the tuner's, bounded: not the rest of ``wait`` (an hour by
                # default; a client whose tuner was then killed waited on so, 84 min in a test)
                deadline = min(deadline, time.monotonic() + CANCEL_WAIT)
                print("\ncancelling: the tuner restores the loop…", file=sys.stderr)
    finally:
        sub.undeclare()
        token.undeclare()
        plant.undeclare()
        if alive is not None:
            alive.undeclare()


def _late_result(
    session: zenoh.Session, prefix: str, loop: str, run_id: str, deadline: float
) -> TuneResult | None:
    """The run's result, published while this client was cut off: the tuner keeps its last
    result to be asked for. Asked again and again, bounded by RECONNECT_WAIT and the run's
    ``wait``; given up REJOIN_GRACE s after the plant answers again (the bus is back; each
    service rejoins its router at its own pace). Seen tokens are no proof that the bus is back:
    a client whose router is restarting still saw the tuner's token."""
    until = min(time.monotonic() + RECONNECT_WAIT, deadline)
    while True:
        # every tuner's last result of the loop (two tuners: the best-matching one alone may be
        # the other's)
        key = keys.tune_result(prefix, loop)
        for late in wire.query_all(session, key, TuneResult, 0.5, zenoh.QueryTarget.ALL):
            if late.run_id == run_id:
                return late
        if wire.query_one(session, keys.status(prefix, loop), LoopStatus, 0.3) is not None:
            until = min(until, time.monotonic() + REJOIN_GRACE)
        if time.monotonic() >= until:
            return None


def _drifts_on(step: dict, pv_units: str) -> str:
    """An integrating step test's level that drifted before the step (the output off its
    balance) went on drifting through it: the pulse gives back the step's area, not the
    drift (after a tune the loop is in auto again, so the level drifts no more)."""
    drift = step.get("drift") or 0.0
    seconds = (step.get("held") or 0.0) + (step.get("pulse_held") or 0.0)
    if drift_beyond_noise(drift, seconds, step.get("noise_std") or 0.0) is None:
        return ""
    return (
        f"; short of where it began by the drift it had before the step, {drift:.3g} "
        f"{unit(pv_units)}/s, which the pulse does not give back"
    )


# s of wall time between progress lines where stderr is not a terminal (a file, a pipe): a
# long run said nothing there for ten minutes (a level's step test on the realtime clock)
QUIET_PROGRESS = 30.0


class QuietProgress:
    """Where stderr is not a terminal, the run's last progress as a line of its own every
    QUIET_PROGRESS s of wall time (a short run prints none); on a terminal, ``line`` rewrites
    one line in place. Use as a context manager around the wait for the run."""

    def __init__(self) -> None:
        self.last: str | None = None
        self._began = time.monotonic()
        self._stop = threading.Event()

    def line(self, p: TuneProgress) -> None:
        self.last = progress_text(p)
        progress_line(p)

    def say(self) -> None:
        """The last progress as a line of its own, with the wall time so far: said as the
        last progress still (the same line repeated with only a count in brackets read as
        the run stuck at its sim time: helper trial)."""
        if self.last is not None:
            took = time.monotonic() - self._began
            print(
                f"{self.last.rstrip()}  (the last progress; {took:.0f} s of wall time so far)",
                file=sys.stderr,
                flush=True,
            )

    def _tick(self) -> None:
        while not self._stop.wait(QUIET_PROGRESS):
            self.say()

    def __enter__(self) -> QuietProgress:
        if not sys.stderr.isatty():
            threading.Thread(target=self._tick, daemon=True, name="progress").start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()


def progress_text(p: TuneProgress) -> str:
    """One line of the run's progress: phase, sim time, count, K_u and P_u so far, message.
    Before the run has identified them, K_u and P_u are the last cycle's or trial's, marked
    ≈ (the relay's first cycles on hx1 read K_u 11.61 for 15.29, shown as figures: helper
    trial)."""
    so_far = "" if p.phase in ("identified", "verify", "done") else "≈"
    ku = f"K_u {so_far}{p.ku:.4g}" if p.ku else ""
    pu = f"P_u {so_far}{p.pu:.4g} s" if p.pu else ""
    return (
        f"  {p.phase:<10} t = {p.t:8.1f} s  n = {p.cycles:<3} {ku:<12} {pu:<14} "
        f"{p.message[:40]:<40}"
    )


def progress_line(p: TuneProgress) -> None:
    """The run's progress rewritten in place on a terminal (nothing elsewhere)."""
    if sys.stderr.isatty():
        print("\r" + progress_text(p), end="", file=sys.stderr, flush=True)


def figure(v, unit: str = "", digits: int = 4) -> str:
    """A figure as the tables print it (``digits`` significant), "—" when there is none."""
    if v is None:
        return "—"
    return f"{v:.{digits}g}{unit}"


def _fixed(v, decimals: int) -> str:
    return "—" if v is None else f"{v:.{decimals}f}"


def _noise_column(rob: dict) -> bool:
    """Whether the rules table has the predicted output noise's column: some rule has one
    (judged on the sampled loop)."""
    return any(a.get("op_noise_pct") is not None for a in rob.values())


def _robust_head(rob: dict) -> str:
    if not rob:
        return ""
    noise = f"{'OP σ %':>8}" if _noise_column(rob) else ""
    return f"{'Ms':>7}{'GM':>7}{'PM °':>7}{'OS %':>7}{'DR':>6}{noise}"


def _robust_row(a: dict, noise: bool = False) -> str:
    """A rule's predicted Ms, margins, overshoot and decay ratio, and with ``noise`` the
    output noise its gains make of the PV's (% of output, σ) (blank without them)."""
    if not a:
        return ""
    if a.get("stable") is False:  # margins and overshoot of an unstable loop mean nothing
        # across the output noise's column too, so the mark after it stays in its column
        return f"{'UNSTABLE on the model':>{34 + (8 if noise else 0)}}"
    # an Ms the measured point alone set (the model misses the plant there): marked, its
    # margins and step figures being the model's (``floor_note``)
    star = "*" if a.get("ms_from_point") else ""
    cells = (
        (figure(a.get("ms"), digits=3) + star, 7),
        (figure(a.get("gain_margin"), digits=3), 7),
        (figure(a.get("phase_margin_deg"), digits=3), 7),
        (_fixed(a.get("overshoot_pct"), 1), 7),
        (_fixed(a.get("decay_ratio"), 2), 6),
    )
    if noise:
        cells += ((_fixed(a.get("op_noise_pct"), 2), 8),)
    # a cell wider than its column still gets a space before it (overshoot 16491.6 %)
    return "".join(f" {c:>{w - 1}}" if len(c) < w else f" {c}" for c, w in cells)


def floor_note() -> str:
    """The table's footnote to an Ms marked ``*``."""
    return (
        "  * Ms from the measured ultimate point alone: the model misses the plant there, so "
        "the GM, PM, OS and DR beside it are the model's, not the plant's"
    )


def _percent_table(r: TuneResult, span: float, pv_units: str) -> list[str]:
    """The rules' gains in % of span: Kc (% of output per % of span), PB = 100/Kc (% of
    span), Ti and Td (s), and the engineering Kc (% per PV unit) beside them."""
    rob = r.robustness
    eng = f"Kc %/{unit(pv_units)}"
    lines = [
        f"  {'rule':<15}{'Kc %/%':>10}{'PB %':>10}{'Ti (s)':>10}{'Td (s)':>10}{eng:>14}"
        + _robust_head(rob)
    ]
    for name, g in r.gains.items():
        isa = g["isa"]
        pct = to_percent(IsaGains(isa["kc"], isa["ti"], isa["td"]), span)
        mark = "←" if name == r.rule else ""
        lines.append(
            f"  {name:<15}{pct.kc:>10.4g}{figure(pct.pb):>10}{figure(pct.ti):>10}"
            f"{pct.td:>10.4g}{isa['kc']:>14.4g}"
            f"{_robust_row(rob.get(name, {}), _noise_column(rob))} {mark}"
        )
    return lines


def _result_span(r: TuneResult) -> float | None:
    """The span of the result's PV range (PV units); None without a usable range."""
    try:
        return pv_span(r.pv_range)
    except ValueError:
        return None


_REPEAT_FIGURES = {
    "gain": "K",
    "dead_time": "L",
    "time_constant_tangent": "T",
    "time_constant_63": "T63",
    "reaction_rate": "R",
}


def _model_l_over_t(model: dict) -> float | None:
    """The stated model's own L/T, of its first-order equivalent (the half rule,
    ``fopdt_of``): a step run's ``l_over_t`` is its tangent's, and the model line gave that
    one (hx1: 0.124 beside a model whose own is 0.153; helper trial). None for an IPDT."""
    kind, lags = (
        model.get("model"),
        [v for k, v in sorted(model.items()) if k.startswith("model_lag")],
    )
    if kind not in ("fopdt", "sopdt") or not lags:
        return None
    try:
        fo = fopdt_of(ProcessFit(kind, model["model_gain"], tuple(lags), model["model_delay"], 0.0))
    except (KeyError, TypeError, ValueError):
        return None
    return fo.dead_time / fo.time_constant if fo.time_constant > 0 else None


def _repeats_lines(r: TuneResult) -> list[str]:
    """Repeated step tests: every test's figures in one line each, and per figure the mean
    (the figures above), the spread and the mean's precision."""
    if not r.repeats:
        return []
    e = r.experiment
    names = [n for n in _REPEAT_FIGURES if f"{n}_mean" in e]
    lines = [
        f"  {len(r.repeats)} step tests, up and down in turn; the figures above are their mean"
        + ("" if e.get("settled", True) else " (NOT within the tolerance: see the warning)")
    ]
    for i, t in enumerate(r.repeats, 1):
        figures = "  ".join(f"{_REPEAT_FIGURES[n]} = {t[n]:.4g}" for n in names)
        lines.append(f"    test {i} ({t['step_size']:+g} %): {figures}")
    lines.append(
        "    spread (mean ±): "
        + "  ".join(
            f"{_REPEAT_FIGURES[n]} {100 * e[f'{n}_spread']:.2g} % "
            f"({100 * e[f'{n}_precision']:.2g} %)"
            for n in names
        )
    )
    return lines


def format_result(r: TuneResult, units: str = "engineering") -> str:
    """The result as text; ``units`` "percent" prints K_u, the process gains and the rules'
    table in % of the PV's span (Kc in % per %, PB = 100/Kc in %), engineering beside."""
    pv_units = r.pv_units or "PV unit"
    what = (
        f"Applying run {r.applied_from}'s {r.rule} gains to {r.loop}"
        if r.applied_from
        else f"Tuning of {r.loop} by {r.method} test, rule {r.rule}"
    )
    lines = [f"{what}: {r.status}" + (f" ({r.reason})" if r.reason else "")]
    span = _result_span(r) if units == "percent" else None
    if units == "percent" and span is None:
        lines.append("  no PV range in the result: the figures are in engineering units")
    elif span is not None and r.pv_range is not None:
        lo, hi = r.pv_range
        lines.append(
            f"  in % of span: PV range {lo:g} to {hi:g} {pv_units} (span {span:g}), "
            "Kc in %/% (dimensionless), PB = 100/Kc in %"
        )
    if r.ku is not None:
        ku = f"{r.ku:.4g} %/{unit(pv_units)}"
        if span is not None:
            ku = f"{kc_percent(r.ku, span):.4g} %/% ({ku})"
        lines.append(
            f"  K_u = {ku}"
            + (f" (spread {100 * r.ku_spread:.2g} %)" if r.ku_spread is not None else "")
            + f"    P_u = {r.pu:.4g} s"
            + (f" (spread {100 * r.pu_spread:.2g} %)" if r.pu_spread is not None else "")
        )
    if r.step and r.step.get("method") == "integrating" and span is not None:
        s = r.step
        lines.append(
            f"  integrating: R = K' = {process_gain_percent(s['reaction_rate'], span):.4g} "
            f"%/s per % ({s['reaction_rate']:.4g} {unit(pv_units)}/s per %) "
            f"(± {100 * s['reaction_rate_precision']:.2g} %)  L = {s['dead_time']:.4g} s  "
            f"a = R·L = {process_gain_percent(s['a'], span):.4g} %/% ({s['a']:.4g} "
            f"{unit(pv_units)}/%)  (level given back to {s['pv_after']:.4g} {pv_units}"
            f"{_drifts_on(s, pv_units)})"
        )
    elif r.step and r.step.get("method") == "integrating":
        s = r.step
        lines.append(
            f"  integrating: R = K' = {s['reaction_rate']:.4g} {unit(pv_units)}/s per % "
            f"(± {100 * s['reaction_rate_precision']:.2g} %)  L = {s['dead_time']:.4g} s  "
            f"a = R·L = {s['a']:.4g} {unit(pv_units)}/%  (level given back to {s['pv_after']:.4g}"
            f"{_drifts_on(s, pv_units)})"
        )
    elif r.step and span is not None:
        s = r.step
        lines.append(  # the curve as read; the model below is what the rules rest on
            f"  step curve: K = {process_gain_percent(s['gain'], span):.4g} %/% ({s['gain']:.4g} "
            f"{unit(pv_units)}/%)  L = {s['dead_time']:.4g} s  T = "
            f"{s['time_constant_tangent']:.4g} s  R = "
            f"{process_gain_percent(s['reaction_rate'], span):.4g} %/s per % "
            f"({s['reaction_rate']:.4g} {unit(pv_units)}/s per %)  L/T = {s['l_over_t']:.3f}"
        )
    elif r.step:
        s = r.step
        lines.append(  # with their units, as the % of span line and `analyze` give them
            f"  step curve: K = {s['gain']:.4g} {unit(pv_units)}/%  L = {s['dead_time']:.4g} s  "
            f"T = {s['time_constant_tangent']:.4g} s  R = {s['reaction_rate']:.4g} "
            f"{unit(pv_units)}/s per %  L/T = {s['l_over_t']:.3f}"
        )
    lines.extend(_repeats_lines(r))
    model = {k: v for k, v in r.experiment.items() if k.startswith("model")}
    if model:
        lags = [f"{model[k]:.4g}" for k in sorted(model) if k.startswith("model_lag")]
        gain = f"{model['model_gain']:.4g}"
        if span is not None:  # an integrator's K' is per second
            per = "/s per %" if model["model"] == "ipdt" else "/%"
            gain = (
                f"{process_gain_percent(model['model_gain'], span):.4g} %{per} "
                f"({gain} {unit(pv_units)}{per})"
            )
        lines.append(
            f"  model {str(model['model']).upper()}: K = {gain}"
            + (f"  T = {', '.join(lags)} s" if lags else "")
            + f"  L = {model['model_delay']:.4g} s"
            + (
                f"  L/T = {ratio:.3f}" + (" (its FOPDT's, half rule)" if lags[1:] else "")
                if (ratio := _model_l_over_t(model)) is not None
                else ""
            )
        )
        if (slow := _integrating_lag(model)) is not None:
            lines.append(slow)
        ts = (r.identified_on or {}).get("sample_time")
        if r.gains and isinstance(ts, int | float) and ts > 0:
            # the model rules are designed with the hold's half sample added (``selection``):
            # SIMC PI from K 2, T 20 s, L 4 s read Kc 1.126 where 1.139 follows from the
            # printed L (helper audit)
            lines.append(
                f"  the model's rules are designed with L + T/2 = "
                f"{model['model_delay'] + 0.5 * ts:.4g} s (the hold's half sample at T = "
                f"{ts:g} s)"
            )
    if r.gains and span is not None:
        lines.extend(_percent_table(r, span, pv_units))
    elif r.gains:
        rob = r.robustness
        lines.append(
            f"  {'rule':<15}{'Kc':>10}{'Ti (s)':>10}{'Td (s)':>10}{'Ki':>10}{'Kd':>10}"
            + _robust_head(rob)
        )
        for name, g in r.gains.items():
            isa, par = g["isa"], g["parallel"]
            mark = "←" if name == r.rule else ""
            lines.append(
                f"  {name:<15}{isa['kc']:>10.4g}{figure(isa['ti']):>10}"
                f"{isa['td']:>10.4g}{par['ki']:>10.4g}{par['kd']:>10.4g}"
                f"{_robust_row(rob.get(name, {}), _noise_column(rob))} {mark}"
            )
    if any(a.get("ms_from_point") for a in r.robustness.values()):
        lines.append(floor_note())
    if r.gains:
        lam = next((a["lambda_s"] for a in r.robustness.values() if "lambda_s" in a), None)
        if lam is not None:
            lines.append(f"  lambda rules: closed-loop time constant λ = {lam:.4g} s")
    if r.recommended:
        lines.append(f"  recommended: {r.recommended['rule']} ({r.recommended['reason']})")
    lines.extend(f"  warning: {w}" for w in r.warnings)
    if r.after is not None:
        rows = [
            ("overshoot %", "overshoot"),
            ("decay ratio", "decay_ratio"),
            ("ringing /period", "ringing"),
            ("settling time s", "settling_time"),
            ("IAE setpoint", "iae_sp"),
            ("IAE load", "iae_load"),
            ("output noise σ %", "op_noise"),
            ("stable", "stable"),
        ]
        if span is not None:  # an IAE in PV units·s as % of span·s
            rows[4:6] = [("IAE setpoint %·s", "iae_sp"), ("IAE load %·s", "iae_load")]
        if any(v is not None and (v.settling_band or 0) > 2.0 + 1e-9 for v in (r.before, r.after)):
            # read within the noise's 3σ, wider than 2 % of the step: said beside it (a
            # level's step of 8σ settles "in 6 s" to within 37.5 % of itself)
            rows.insert(4, ("settling band %", "settling_band"))
        if any(v is not None and v.unmodelled_ringing is not None for v in (r.before, r.after)):
            rows.insert(3, ("fast ring /period", "unmodelled_ringing"))  # beyond the model
        x = f"x{r.after.margin_factor or 2:.3g}"  # 2, less under a --ms-bound past 2
        if r.after.margin_swing is not None:  # the gain-margin check's (of its step)
            rows.insert(len(rows) - 1, (f"swing at Kc {x}", "margin_swing"))
        if r.after.margin_ringing is not None:  # the fast mode's, read in that check
            rows.insert(len(rows) - 1, (f"fast ring Kc {x}", "margin_ringing"))
        lines.append(f"  {'verification':<18}{'before':>12}{'after':>12}")
        for label, field in rows:
            b = getattr(r.before, field) if r.before else None
            a = getattr(r.after, field)
            if span is not None and field.startswith("iae"):
                b, a = process_gain_percent(b, span), process_gain_percent(a, span)
            if field in ("ringing", "unmodelled_ringing"):  # gone within a period: none
                b, a = (0.0 if v is not None and v < 0.005 else v for v in (b, a))
            lines.append(
                f"  {label:<18}{_cell(b, field, r.before):>12}{_cell(a, field, r.after):>12}"
            )
    if r.acceptance and r.acceptance.get("passed") is not None:
        a = r.acceptance
        pred = a.get("predicted_overshoot")
        lines.append(
            f"  acceptance: overshoot ≤ {a['max_overshoot']:g} %, decay ratio ≤ "
            f"{a['max_decay_ratio']:g}"
            + (
                # an overshoot of a few 1e-5 % is none: printed 5.32e-05 % (helper trial E)
                f", within {a['overshoot_miss']:g} points of the "
                f"{'0' if abs(pred) < 0.005 else f'{pred:.3g}'} % predicted"
                if pred is not None
                else ""
            )
            + (
                f", output noise ≤ {a['max_op_noise']:g} %"
                if a.get("max_op_noise") is not None
                else ""
            )
            + (": passed" if a["passed"] else f": failed ({a['problems']})")
        )
        if a.get("setpoint_weight") is not None:
            lines.append(
                f"  setpoint weight: β {a['setpoint_weight']:g} (the step overshot "
                f"{figure(a.get('overshoot_full_weight'))} % at full weight; "
                f"{figure(a.get('overshoot_weight_predicted'))} % predicted at β "
                f"{a['setpoint_weight']:g}, {figure(r.after.overshoot if r.after else None)} % "
                "measured)"
            )
    if r.rest and r.rest.get("waited") is not None:
        window = r.rest.get("window") or 0.0
        if r.rest.get("at_rest") and (r.rest.get("waited") or 0.0) > 1.01 * window:
            lines.append(
                f"  waited {r.rest['waited']:.4g} s for the PV to come to rest before the test"
            )
    state = (
        (
            "new gains applied"
            if not _held_already(r)
            else "gains applied (the loop held them already: nothing changed)"
        )
        + ", loop in auto"
        + (", NOT verified (--no-verify)" if r.status == "unverified" else "")
        + (", FORCED outside the safety envelope (--force)" if r.status == "forced" else "")
        if r.applied
        else "nothing was sent to the loop"
        if r.untouched
        else "loop restored to its state before the test"
        if r.restored
        else "WARNING: the loop may not have been restored"
    )
    lines.append(f"  {state}; {r.sim_duration:.0f} s of sim time in {r.wall_time:.2f} s")
    if r.left:
        lf = r.left
        if r.untouched:  # nothing was sent: where the PV is was none of the run's doing
            # (a run refused at its start said "not back where it was" of the PV the last
            # run's test had left moving: helper review)
            back = "as the run found it: nothing was sent to it"
        elif lf.get("pv_target") is None:  # seen by a query after the plant was lost
            back = "as its plant shows it once back in reach"
            was, band = lf.get("pv_before"), lf.get("band")
            if was is not None and band is not None and abs(lf["pv"] - was) > band:
                back += (
                    f"; the PV is {lf['pv'] - was:+.3g} {pv_units} from where it was before the "
                    f"test ({was:.4g}), not waited for"
                    # (an integrating loop in manual never comes back by itself)
                    + (
                        ": a level in manual stays where it is"
                        if lf["mode"] == "manual" and _integrating(r)
                        else ""
                    )
                )
        else:
            where = (
                "back where it was"
                if lf.get("returned")
                # judged at rest (no trend beyond its noise), but off its target
                else "not back where it was, at rest off it"
                if lf.get("pv_rest") is not None
                else _on_the_way(lf, pv_units, lf["mode"] == "manual" and _integrating(r))
                if lf.get("waited")
                # cancelled, or --no-wait: a level in manual never comes back by itself
                else "not back where it was, not waited for"
                if lf.get("returned") is False
                else "not known to be back where it was, not waited for"
            )
            within = f" ± {lf['band']:.2g}" if lf.get("band") is not None else ""
            back = f"the PV is {where}: target {lf['pv_target']:.4g}{within}"
            if lf.get("cut"):  # the figures are the last seen before the plant fell silent
                back += f"; the wait for it was cut short, the figures the last seen: {lf['cut']}"
        if lf.get("fault"):  # its PV held at its last value: where it is says nothing
            back = f"the loop is FAULTED ({lf['fault']}): its PV is held, not measured"
        # the mean at rest is what was judged; the last sample alone carries the noise
        pv = (
            f"PV {lf['pv_rest']:.4g} {pv_units} at rest (last sample {lf['pv']:.4g})"
            if lf.get("pv_rest") is not None
            else f"PV {lf['pv']:.4g} {pv_units}"
        )
        lines.append(
            f"  left: {lf['mode']}, SP {lf['sp']:.4g} {pv_units}, OP {lf['op']:.4g} %, "
            f"{pv} ({back})"
        )
    return "\n".join(lines)


def _held_already(r: TuneResult) -> bool:
    """The applied gains are the ones the loop held before the run (``same_gains``): an
    `autotune apply` of the same run twice said "new gains applied" where `history` says
    "gains unchanged" (walkthrough)."""
    if r.previous_gains is None or not r.applied:
        return False
    if r.after is not None:
        applied = r.after.gains.model_dump()
    else:
        applied = (r.chosen or {}).get("isa") or {}
        if "kc" not in applied:
            return False
    return same_gains(applied, r.previous_gains.model_dump())


# a measured step's figures that are None where the response has none: no crest after its
# largest (the decay ratio), no oscillatory mode (a ring); "—" is kept for not measured
_NONE_SEEN = ("decay_ratio", "ringing", "unmodelled_ringing")


def _cell(value: object, field: str, v: Verification | None) -> str:
    """One figure of the verification table: "none" for a measured setpoint step's decay
    ratio or ring that it did not have (a 5.5 % overshoot with no second crest printed
    "decay ratio —", as if not measured: walkthrough), "—" for what was not measured."""
    if isinstance(value, bool):
        return str(value)
    if value is None and field in _NONE_SEEN and v is not None and v.overshoot is not None:
        return "none"
    return figure(value)


def _interrupt(signum: int, frame: object) -> None:
    raise KeyboardInterrupt


def cancel_on_stop_signals() -> None:
    """A terminal closed (SIGHUP) or a service manager's stop (SIGTERM) cancels the run like
    Ctrl-C: the tuner restores the loop, and the result is still waited for. A signal the
    process was started ignoring stays so (``nohup autotune tune …``: the run outlives the
    terminal, as asked)."""
    for sig in (signal.SIGTERM, signal.SIGHUP):
        if signal.getsignal(sig) is not signal.SIG_IGN:
            signal.signal(sig, _interrupt)


def run(args: argparse.Namespace) -> int:
    check_ids(args.prefix, loop=args.loop)
    check_tuner_node(args.node)
    if not (args.wait > 0 and args.wait < float("inf")):
        raise ConfigError(f"--wait {args.wait}: must be a finite number of seconds > 0")
    req = request_from_args(args, source="autotune-tune")
    if args.detach:
        with open_session(settings_from_args(args), HANDSHAKE) as session:
            accepted = submit(session, args.prefix, args.node, req)
        print(
            accepted.model_dump_json(indent=2)
            if args.json
            else f"run {accepted.run_id} on {accepted.loop} submitted ({accepted.method}, rule "
            f"{accepted.rule}); left going: `autotune tune` was detached"
        )
        return 0
    return run_and_report(args, req)


def run_and_report(
    args: argparse.Namespace,
    req: TuneRequest,
    check: Callable[[zenoh.Session], None] | None = None,
) -> int:
    """Submit ``req``, follow the run to its result and print it (``--json`` or text in
    ``--units``); exit 0 for ``ok`` (and ``unverified``: applied as ``--no-verify`` asked), 1
    otherwise. ``check`` runs on the open session first
    (raising stops it before anything is sent)."""
    cancel_on_stop_signals()
    with open_session(settings_from_args(args), HANDSHAKE) as session:
        if check is not None:
            check(session)
        try:
            with QuietProgress() as shown:
                result = follow(
                    session,
                    args.prefix,
                    req.loop,
                    # the tuner's discovery within --wait too (it took 10 s with --wait 3)
                    lambda: submit(session, args.prefix, args.node, req, min(10.0, args.wait)),
                    args.wait,
                    None if args.json else shown.line,
                )
        except Interrupted as stop:  # cancelled: the result all the same, and what it did
            _print_result(args, stop.result)
            print(stop.summary(), file=sys.stderr)
            raise KeyboardInterrupt from None
        except TimedOut as late:  # cancelled by --wait: the result all the same, then why
            _print_result(args, late.result)
            raise
        # the run's file is finished after its result: a disk full at its last write is
        # said by the logger only then (a tune ended ok with no word of it, 6127 messages
        # lost with the file's end, only the logger's log said so: helper trial)
        incomplete = (
            None if result.untouched else incomplete_record(session, args.prefix, result.run_id)
        )
    _print_result(args, result)
    if incomplete is not None:
        command = getattr(args, "command", None) or "tune"  # `apply` reports through here too
        print(f"autotune {command}: {incomplete_line(incomplete)}", file=sys.stderr)
    return 0 if result.status in DONE_STATUSES else 1


def _on_the_way(left: dict, pv_units: str, level: bool) -> str:
    """A PV not found at rest after the wait: on its way back where its trend heads for the
    target, beyond 3 standard errors; else said to be moving away or not moving back
    (``level``: a process the run found integrating, in manual: it stays where it is). A
    run recorded before (no ``drift``) said "still on its way back"."""
    drift = left.get("drift")
    if drift is None:
        return "still on its way back"
    off = left["pv"] - left["pv_target"]
    sure = abs(drift) > 3.0 * (left.get("drift_error") or 0.0)
    rate = f"{drift:+.3g} {pv_units}/s"
    if sure and drift * off < 0:
        return f"still on its way back ({rate})"
    how = "moving away from it" if sure and drift * off > 0 else "not moving back"
    stays = ": a level held at a constant output stays where it is" if level else ""
    return f"not back where it was, and {how} ({rate} over the last window watched){stays}"


# a model's slowest lag this many times its other lags and dead time is an integrator over
# any time a loop works on
INTEGRATING_LAG = 1000.0


def _integrating_lag(model: dict) -> str | None:
    """What a fitted lag far slower than the rest of its model is: an integrator, K/T per
    second. Why: a ramp of 0.05·e^{−2s}/(s(10s + 1)) printed "model SOPDT: K = 1.364e+07
    T = 2.72e+08, 10.02 s" and an L/T of 2.58e-08, and never called it integrating (helper
    review); the rules took it as it is, and its gains were verified."""
    lags = sorted(
        (float(v) for k, v in model.items() if k.startswith("model_lag") and v), reverse=True
    )
    gain, delay = model.get("model_gain"), model.get("model_delay") or 0.0
    if not lags or not gain or model.get("model") == "ipdt":
        return None
    rest = sum(lags[1:]) + float(delay)
    if not (rest > 0 and lags[0] > INTEGRATING_LAG * rest):
        return None
    behind = f", behind {', '.join(f'{t:.4g}' for t in lags[1:])} s" if lags[1:] else ""
    return (
        f"  (its T = {lags[0]:.4g} s is an integrator over any time that matters: K/T = "
        f"{gain / lags[0]:.4g} per s per %{behind}, dead time {float(delay):.4g} s)"
    )


def _integrating(r: TuneResult) -> bool:
    """The run found the process integrating (an IPDT model, or an integrating step)."""
    return (r.experiment or {}).get("model") == "ipdt" or (r.step or {}).get(
        "method"
    ) == "integrating"


def _print_result(args: argparse.Namespace, result: TuneResult) -> None:
    if sys.stderr.isatty() and not args.json:
        print("\r" + " " * 100 + "\r", end="", file=sys.stderr)
    print(
        json_text.dumps(result.model_dump(mode="json"), indent=2)
        if args.json
        else format_result(result, args.units)
    )
