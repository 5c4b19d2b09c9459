"""``autotune apply RUN_ID [--rule RULE] [--no-verify]``: apply a recorded run's gains later.

The approval step commercial tuners give (Rockwell, ABB: the engineer accepts the result
before it is loaded): ``autotune tune LOOP --no-apply`` leaves a run's recommended and
alternative gains on record in the logger's change history (``--runs``); ``apply`` loads
them. Before anything is sent it checks that the loop is still the one the run identified
(the same plant instance, model and model parameters, sample time) and that the gains are
within the safety envelope the run judged them by (the recommended rule always is; another
rule must have been judged within it, or be below the run's K_u where no model judged it).
The autotuner then applies them bumplessly and verifies them exactly as a tune would (a
setpoint step and a load step against the acceptance limits, the previous gains restored if
they fail), unless ``--no-verify`` (the run then ends ``unverified``, not ``ok``); the result
is a run of its own (``applied_from`` names the recorded run), and the logger records the
change. Exit 0 when the gains were applied and verified (or applied unverified, as
``--no-verify`` asks); 1 when the autotuner rejected them (the loop restored); 2 when nothing
was sent.
"""

from __future__ import annotations

import argparse
import re
from pathlib import Path
from typing import Any

import pydantic
import zenoh

from services.autotuner.commands.logger_dirs import elsewhere_asked
from services.autotuner.commands.tune import add_units_option, figure, run_and_report
from shared import keys, wire
from shared.cli import add_common_arguments, check_ids, check_tuner_node
from shared.errors import AutotuneError, ConfigError
from shared.history_file import HISTORY_FILE, applicable_rule, proposed_rule, read_history
from shared.messages import APPLICABLE_STATUSES, LoopInfo, PidGains, TuneRequest
from shared.session import settings_from_args

HELP = "apply (and verify) the gains a recorded run recommended, e.g. after tune --no-apply"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run_id", metavar="RUN_ID", help="the run whose gains to apply")
    parser.add_argument(
        "--rule",
        help="one of the run's other rules (default: the one it proposed: the rule its tune "
        "asked for, else the recommended one)",
    )
    parser.add_argument("--no-verify", action="store_true", help="apply without verifying")
    parser.add_argument(
        "--runs",
        default="runs",
        metavar="DIR",
        help="the logger's runs directory, where history.jsonl is (default: %(default)s)",
    )
    parser.add_argument("--node", default="*", help="which autotuner (default: any)")
    parser.add_argument("--json", action="store_true", help="print the result as JSON")
    parser.add_argument(
        "--wait",
        type=float,
        default=3600.0,
        help="seconds to wait for the result (default: %(default)s)",
    )
    add_units_option(parser)
    add_common_arguments(parser)


# what a run id is (``shared.messages.RunId``)
RUN_ID = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_run_id(run_id: str) -> None:
    """ConfigError naming RUN_ID when it cannot be a run's id at all."""
    if not RUN_ID.match(run_id):
        raise ConfigError(
            f"RUN_ID {run_id!r}: not a run id (1-64 letters, digits, '_' or '-'; `autotune "
            "runs` lists them)"
        )


def recorded_run(runs: Path, run_id: str) -> dict[str, Any]:
    """The run's ``tune`` record in the change history; ConfigError when there is none, or
    when ``run_id`` cannot be a run's id at all (``../x`` was "no run of that id": helper
    review)."""
    check_run_id(run_id)
    found = [
        r
        for r in read_history(runs / HISTORY_FILE)
        if r.get("record") == "tune" and r.get("run_id") == run_id
    ]
    if not found:
        raise ConfigError(f"{run_id}: no run of that id in {runs / HISTORY_FILE}")
    return found[-1]


def choose(run: dict[str, Any], rule: str | None) -> tuple[str, PidGains, float | None]:
    """The rule, its gains and their predicted overshoot (%); ConfigError naming ``--rule``
    or the run when they may not be applied."""
    if run.get("status") not in APPLICABLE_STATUSES:
        raise ConfigError(f"run {run.get('run_id')}: {run.get('status')}, no gains to apply")
    if run.get("contradiction"):  # no rule's gains: the identification contradicts itself
        raise ConfigError(
            f"run {run.get('run_id')}: {run['contradiction']}; tune again (with --force if "
            "you must)"
        )
    rule = rule or proposed_rule(run)
    gains = run.get("gains") or {}
    if rule not in gains or not gains[rule]:
        raise ConfigError(f"--rule {rule}: the run has no gains for it ({', '.join(gains)})")
    isa = gains[rule]
    judged = (run.get("robustness") or {}).get(rule)
    if judged is not None:
        if judged.get("within_envelope") is not True:
            usable = applicable_rule(run)
            other = f"; --rule {usable} is within it" if usable and usable != rule else ""
            raise ConfigError(
                f"--rule {rule}: outside the safety envelope the run judged it by "
                f"(predicted Ms {figure(judged.get('ms'))}){other}; tune again with --force "
                "if you must"
            )
    elif run.get("ku") is None or not isa["kc"] < run["ku"]:
        raise ConfigError(f"--rule {rule}: not judged by the run, and Kc not below its K_u")
    predicted = judged.get("overshoot_pct") if judged else None
    return rule, PidGains(kc=isa["kc"], ti=isa.get("ti"), td=isa.get("td") or 0.0), predicted


def predicted_ms(run: dict[str, Any], rule: str) -> float | None:
    """The Ms the run's model predicted for ``rule``'s gains (None: not judged by one)."""
    ms = ((run.get("robustness") or {}).get(rule) or {}).get("ms")
    return float(ms) if isinstance(ms, int | float) and ms > 0 else None


def recorded_bound(run: dict[str, Any]) -> dict[str, float]:
    """The run's ``--ms-bound`` as a request's field (empty: none on record, or not one a
    request may carry): its gains verified later within the bound they were judged in, the
    gain-margin check at its factor (a run tuned with --ms-bound 3 and applied later was
    checked at Kc × 2)."""
    bound = run.get("ms_bound")
    if isinstance(bound, int | float) and not isinstance(bound, bool) and 1.0 < bound <= 10.0:
        return {"ms_bound": float(bound)}
    return {}


# the acceptance limits a run records where asked (``TuneResult``)
RECORDED_LIMITS = ("max_op_noise", "max_overshoot", "max_decay_ratio", "overshoot_miss")


def recorded_limits(run: dict[str, Any]) -> dict[str, float]:
    """The run's acceptance limits as a request's fields (``--max-op-noise``,
    ``--max-overshoot``, ``--max-decay-ratio``, ``--overshoot-miss``; each left out where
    none is on record, or not one a request may carry: ``TuneRequest``'s own bounds judge
    it): its gains verified later within the limits they were tuned within (a run tuned with
    --max-op-noise 60 proposed SIMC PI, 36 % predicted, and its apply rejected the same gains
    at the default 10 %; one tuned with --max-overshoot 10 was applied within the default
    35 %)."""
    out: dict[str, float] = {}
    for name in RECORDED_LIMITS:
        limit = run.get(name)
        if limit is None:
            continue
        try:
            TuneRequest.model_validate({"loop": "x", name: limit})
        except pydantic.ValidationError:
            continue
        out[name] = float(limit)
    return out


def recorded_request(
    run: dict[str, Any],
    run_id: str,
    choice: tuple[str, PidGains, float | None],
    verify: bool,
    source: str,
) -> TuneRequest:
    """The request that applies run ``run_id``'s gains (``choice``: ``choose``'s rule, gains
    and predicted overshoot), judged as that run judged them: one statement for ``autotune
    apply`` and the console's Apply (the console's left out the run's ``--ms-bound``, so a run
    tuned with --ms-bound 3 and applied from the page was checked at Kc × 2). ConfigError
    where the run has no time scale."""
    rule, gains, predicted = choice
    return TuneRequest(
        loop=str(run.get("loop")),
        method=run.get("method") or "relay",
        rule=rule,
        verify=verify,
        apply_from=run_id,
        apply_gains=gains,
        apply_predicted_overshoot=predicted,
        apply_predicted_ms=predicted_ms(run, rule),
        apply_timescale=recorded_timescale(run),
        apply_noise=run.get("noise"),
        source=source,
        **recorded_bound(run),
        **recorded_limits(run),
    )


def recorded_timescale(run: dict[str, Any]) -> float:
    """The time scale (s) the run identified, which an apply's verification and its wait for
    the PV's return are sized on; ConfigError naming the run when it has none."""
    scale = run.get("timescale")
    if not scale:
        raise ConfigError(
            f"run {run.get('run_id')}: no time scale on record (the run ended before it "
            "identified one), which the verification and the wait for the PV's return are "
            "sized on"
        )
    return float(scale)


def same_loop(recorded: dict[str, Any] | None, info: LoopInfo) -> str | None:
    """Why ``info`` is not the loop the run identified, or None when it is."""
    if not recorded:
        return "the run did not record the loop it identified"
    now = {
        "node": info.node,
        "instance": info.instance,
        "model": info.model,
        "model_params": info.model_params,
        "sample_time": info.sample_time,
    }
    for key, what in (
        ("node", "plant node"),
        ("instance", "plant instance (it restarted since the run)"),
        ("model", "model"),
        ("model_params", "model parameters"),
        ("sample_time", "sample time"),
    ):
        if recorded.get(key) != now[key]:
            return f"another {what}: {recorded.get(key)!r} then, {now[key]!r} now"
    return None


def run(args: argparse.Namespace) -> int:
    check_ids(args.prefix)
    check_tuner_node(args.node)
    check_run_id(args.run_id)
    runs = Path(args.runs)
    if not runs.is_dir():
        raise ConfigError(f"--runs {runs}: not a directory (the logger's runs directory)")
    if not 0 < args.wait < float("inf"):
        raise ConfigError(f"--wait {args.wait}: must be a finite number of seconds > 0")
    try:
        rec = recorded_run(runs, args.run_id)
    except ConfigError as err:
        hint = elsewhere_asked(settings_from_args(args), args.prefix, runs)
        raise ConfigError(f"{err}{hint}") from None
    loop = str(rec.get("loop"))
    choice = choose(rec, args.rule)
    if args.no_verify and rec.get("model_misses"):
        # as the run itself refuses --no-verify on such a model (``TuningRun``): the gains
        # of a model known wrong are not put in the loop untried (review: apply was the way
        # around it)
        raise ConfigError(
            f"--no-verify: run {args.run_id}'s model misses the plant ({rec['model_misses']}): "
            "its gains are not applied without verification; apply them verified (without "
            "--no-verify)"
        )
    req = recorded_request(rec, args.run_id, choice, not args.no_verify, "autotune-apply")

    def same_as_identified(session: zenoh.Session) -> None:
        info = wire.query_one(session, keys.info(args.prefix, loop), LoopInfo, 5.0)
        if info is None:
            raise AutotuneError(f"loop {loop}: no plant answers for it")
        if (why := same_loop(rec.get("identified_on"), info)) is not None:
            raise AutotuneError(f"loop {loop} is not the loop run {args.run_id} identified: {why}")

    return run_and_report(args, req, same_as_identified)
