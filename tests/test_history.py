"""The change history (issue 14): services/logger/history.py fed statuses and results as the
bus would, the file read back; and the pure parts of `revert` and `apply`."""

from __future__ import annotations

import re
import threading
import time
from datetime import UTC, datetime
from pathlib import Path
from types import SimpleNamespace

import pytest

from services.autotuner.commands.apply import choose, same_loop
from services.autotuner.commands.revert import target
from services.logger.commands.history import entries, format_entries
from services.logger.history import ChangeHistory
from services.logger.service import LoggerService
from shared import json_text, keys, wire
from shared.errors import ConfigError
from shared.history_file import HISTORY_FILE, loop_changes, read_history
from shared.messages import LoopInfo, LoopStatus, PidGains, TuneResult

P, LOOP = "hist", "hx1"
G0 = PidGains(kc=2.0, ti=60.0)
G1 = PidGains(kc=6.9, ti=96.0, td=6.9)


def status(gains: PidGains, reason: str = "query", **kw) -> LoopStatus:
    base = dict(
        loop=LOOP,
        node="plant",
        seq=1,
        t=10.0,
        pv=60.0,
        sp=60.0,
        op=40.0,
        mode="auto",
        action="reverse",
        gains=gains,
        op_limits=(0.0, 100.0),
        pv_range=(0.0, 150.0),
        disturbances={},
        clock="lockstep",
        accepted=0,
        rejected=0,
        reason=reason,
    )
    return LoopStatus(**{**base, **kw})


def feed(h: ChangeHistory, msg) -> None:
    key = keys.status(P, LOOP) if isinstance(msg, LoopStatus) else keys.tune_result(P, LOOP)
    h.handle(key, wire.encode(msg))


def history(tmp_path: Path) -> ChangeHistory:
    return ChangeHistory(tmp_path, P, now=lambda: datetime(2026, 12, 2, 3, 0, tzinfo=UTC))


def changes(tmp_path: Path) -> list[dict]:
    return loop_changes(tmp_path / HISTORY_FILE, LOOP)


def test_a_loop_first_seen_is_learned_and_a_set_is_a_change_by_its_sender(tmp_path):
    h = history(tmp_path)
    feed(h, status(G0))
    assert changes(tmp_path) == []
    feed(h, status(G1, "gains", by_source="autotune-set", by_user="operator1", t=12.5))
    feed(h, status(G1, "sync"))  # the same gains again: nothing
    (c,) = changes(tmp_path)
    assert (c["by_source"], c["by_user"], c["cause"], c["t"]) == (
        "autotune-set",
        "operator1",
        "gains",
        12.5,
    )
    assert c["before"] == G0.model_dump() and c["after"] == G1.model_dump()
    assert c["utc"] == "2026-12-02T03:00:00Z" and c["run_id"] is None


def test_a_runs_experiment_is_not_a_change_its_applied_gains_are_one(tmp_path):
    h = history(tmp_path)
    feed(h, status(G0))
    src = "tuner:abc123"
    feed(h, status(G0, "lease", leased_by=src, by_source=src))
    for kc in (1.0, 3.0, 5.0):  # a ramp's P-only trials, the verification's gains
        feed(h, status(PidGains(kc=kc), "gains", leased_by=src, by_source=src))
    feed(h, status(G1, "gains", leased_by=src, by_source=src))
    feed(h, status(G1, "release", by_source=src))
    (c,) = changes(tmp_path)
    assert (c["run_id"], c["cause"]) == ("abc123", "release")
    assert c["before"] == G0.model_dump() and c["after"] == G1.model_dump()


def test_a_rejected_run_restores_and_changes_nothing(tmp_path):
    h = history(tmp_path)
    feed(h, status(G0))
    src = "tuner:r2"
    feed(h, status(G0, "lease", leased_by=src))
    feed(h, status(G1, "gains", leased_by=src))
    feed(h, status(G0, "gains", leased_by=src))  # restored
    feed(h, status(G0, "release", by_source=src))
    assert changes(tmp_path) == []


def _result(run_id: str, applied: bool, left: PidGains) -> TuneResult:
    return TuneResult(
        run_id=run_id,
        loop=LOOP,
        t=300.0,
        method="relay",
        rule="zn-pi",
        status="ok" if applied else "rejected",
        applied=applied,
        previous_gains=G0,
        chosen={"isa": {"kc": 6.9, "ti": 96.0, "td": 6.9}},
        left={"mode": "auto", "gains": left.model_dump()},
    )


@pytest.mark.parametrize("result_first", [False, True])
def test_a_loop_first_heard_under_a_runs_lease_has_no_baseline_until_its_result(
    tmp_path, result_first
):
    """A logger that came up as a run went on first heard the loop under its lease, the
    rejected gains under test in force: taken as the baseline, the restore was filed as the
    run's change (G1 → G0), and `autotune revert` put the rejected gains back, exit 0
    (helper trial). The gains before such a run are known only from its result: a rejected
    run changed nothing, an applied one changed its previous gains to those it left, whether
    its result or its release is heard first."""
    src = "tuner:r9"
    h = history(tmp_path)
    feed(h, status(G1, "gains", leased_by=src, by_source=src))  # the first heard: mid-run
    msgs = [status(G0, "release", by_source=src), _result("r9", False, G0)]
    for m in reversed(msgs) if result_first else msgs:
        feed(h, m)
    assert changes(tmp_path) == []
    with pytest.raises(ConfigError, match="no change of the loop's gains by that run"):
        target(changes(tmp_path), "r9", 1)
    feed(h, status(G0, "sync"))
    assert changes(tmp_path) == []
    # an applied run, first heard under its lease: its change is its result's
    (tmp_path / "b").mkdir()
    h2 = history(tmp_path / "b")
    feed(h2, status(PidGains(kc=1.0), "gains", leased_by=src, by_source=src))  # a trial's
    msgs = [status(G1, "release", by_source=src), _result("r9", True, G1)]
    for m in reversed(msgs) if result_first else msgs:
        feed(h2, m)
    (c,) = changes(tmp_path / "b")
    assert (c["run_id"], c["cause"], c["by_source"]) == ("r9", "release", src)
    assert c["before"] == G0.model_dump() and c["after"] == G1.model_dump()
    feed(h2, status(G1, "sync"))
    assert len(changes(tmp_path / "b")) == 1


def test_a_plant_restart_with_other_gains_is_recorded_as_start(tmp_path):
    h = history(tmp_path)
    feed(h, status(G1))
    feed(h, status(G0, "start"))
    (c,) = changes(tmp_path)
    assert c["cause"] == "start" and c["by_source"] is None and c["after"] == G0.model_dump()


def test_after_a_logger_restart_the_record_is_the_baseline(tmp_path):
    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    again = history(tmp_path)  # restarted: nothing seen yet
    feed(again, status(G1))  # as on record: nothing
    assert len(changes(tmp_path)) == 1
    third = history(tmp_path)
    feed(third, status(G0))  # moved while no logger ran
    last = changes(tmp_path)[-1]
    assert (last["cause"], last["before"], last["after"]) == (
        "unseen",
        G1.model_dump(),
        G0.model_dump(),
    )


def test_a_missed_release_is_not_charged_to_the_next_sender(tmp_path):
    # the logger paused through a run's release: the next status it sees (an operator's
    # setpoint) shows the run's gains; the change is the run's (by its result), not hers
    h = history(tmp_path)
    feed(h, status(G0))
    src = "tuner:r7"
    feed(h, status(G0, "lease", leased_by=src, by_source=src))
    feed(h, status(G1, "gains", leased_by=src, by_source=src))
    g1 = G1.model_dump()
    feed(
        h,
        TuneResult(
            run_id="r7",
            loop=LOOP,
            t=90.0,
            method="relay",
            rule="tl-pid",
            status="ok",
            applied=True,
            chosen={"isa": {k: g1[k] for k in ("kc", "ti", "td")}},
        ),
    )
    feed(h, status(G1, "setpoint", by_source="autotune-set", by_user="operator1"))
    (c,) = changes(tmp_path)
    assert (c["cause"], c["by_source"], c["by_user"], c["run_id"]) == ("unseen", None, None, "r7")
    assert c["before"] == G0.model_dump() and c["after"] == g1
    (item,) = entries(tmp_path, LOOP)
    text = format_entries(LOOP, tmp_path / HISTORY_FILE, [item])
    assert "the gains run r7 applied, by its result" in text and "operator1" not in text
    # and a change no result explains: unseen, who not known
    feed(h, status(G0, "sync", by_source="autotune-loops"))
    last = changes(tmp_path)[-1]
    assert (last["cause"], last["by_source"], last["run_id"]) == ("unseen", None, None)


def test_a_result_is_a_tune_record_with_what_apply_needs(tmp_path):
    h = history(tmp_path)
    r = TuneResult(
        run_id="r9",
        loop=LOOP,
        t=100.0,
        method="relay",
        rule="tl-pid",
        status="ok",
        ku=15.2,
        recommended={"rule": "tl-pid"},
        gains={"tl-pid": {"isa": {"kc": 6.9, "ti": 96.0, "td": 6.9}}},
        robustness={"tl-pid": {"ms": 1.7, "within_envelope": True, "overshoot_pct": 0.0}},
        identified_on={"node": "plant", "instance": "a1", "model": "heat_exchanger"},
        timescale=43.6,
        noise=0.02,
        pv_units="degC",
    )
    feed(h, r)
    (rec,) = [x for x in read_history(tmp_path / HISTORY_FILE) if x["record"] == "tune"]
    assert rec["gains"] == {"tl-pid": {"kc": 6.9, "ti": 96.0, "td": 6.9}}
    # the verification's IAE in the PV's units (it read "IAE 88.81", then "PV units·s")
    assert rec["pv_units"] == "degC"
    from services.logger.commands.history import _verification

    assert "IAE 53.75 degC·s" in _verification({"iae_sp": 53.75}, rec["pv_units"])
    assert "IAE 53.75 PV units·s" in _verification({"iae_sp": 53.75})  # an older record
    assert rec["robustness"]["tl-pid"]["within_envelope"] is True
    assert (rec["timescale"], rec["noise"], rec["ku"]) == (43.6, 0.02, 15.2)


def test_a_tune_record_keeps_the_ms_bound_apply_verifies_its_gains_within(tmp_path):
    """`autotune apply` takes the run's --ms-bound from its ``tune`` record (recorded_bound):
    the record did not carry it, so an apply of a run tuned with --ms-bound 3 was checked at
    Kc × 2, the default bound's factor, not the 1.5 its own bound admits."""
    from services.autotuner.commands.apply import recorded_bound

    h = history(tmp_path)
    r = TuneResult(run_id="r9", loop=LOOP, t=100.0, method="relay", rule="tl-pid", status="ok")
    feed(h, r.model_copy(update={"ms_bound": 3.0}))
    (rec,) = [x for x in read_history(tmp_path / HISTORY_FILE) if x["record"] == "tune"]
    assert recorded_bound(rec) == {"ms_bound": 3.0}


def test_the_listing_offers_apply_only_for_a_run_with_gains_to_apply():
    """A proposed (or rejected) run's gains can be applied later; an aborted run has none:
    the listing told the operator to `autotune apply` it, which then refused."""
    gains = {"tl-pid": {"kc": 6.9, "ti": 96.0, "td": 6.9}}
    base = {"record": "tune", "utc": "2026-12-02T22:00:00", "t": 1.0, "method": "relay"}
    items = [
        {**base, "run_id": "p1", "status": "proposed", "recommended": "tl-pid", "gains": gains},
        {**base, "run_id": "a1", "status": "aborted", "recommended": None, "gains": {}},
    ]
    # a run refused the loop another held: it never ran, and the line says why (it showed as
    # an aborted run whose record `autotune runs` then did not have)
    held = "hx1 is held by run b2 (autotune-tune): not started"
    items.append({**base, "run_id": "h1", "status": "aborted", "reason": held, "gains": {}})
    # an apply run whose verification rejected run p1's gains: it offered `autotune apply r1`,
    # which then refused with a confusing flag (noticed last stop)
    items.append(
        {**base, "run_id": "r1", "status": "rejected", "rule": "tl-pid", "gains": gains}
        | {"applied_from": "p1"}
    )
    # a tune whose verification rejected its gains on the loop: applying them again would run
    # the same test (it was offered: helper 52); one refused before any try still offers
    why = "new gains are worse than before on iae_sp: previous gains restored"
    items.append(
        {**base, "run_id": "v1", "status": "rejected", "rule": "tl-pid", "gains": gains}
        | {"reason": why, "verification_after": {"overshoot": 12.0}}
    )
    items.append({**base, "run_id": "e1", "status": "rejected", "rule": "tl-pid", "gains": gains})
    lines = format_entries(LOOP, Path("runs"), items).splitlines()[1:]
    assert lines[0].endswith("proposed, not applied; recommended tl-pid: `autotune apply p1`")
    assert lines[1].endswith("run a1 (relay): aborted, no gains to apply")
    assert lines[2].endswith(f"run h1 (relay): aborted ({held}), no gains to apply")
    assert lines[3].endswith(
        "run r1 (apply of run p1): rejected, not applied (the gains of run p1, tl-pid)"
    )
    assert lines[4].endswith(f"run v1 (relay): rejected, tried on the loop and rejected ({why})")
    assert lines[5].endswith("rejected, not applied; recommended tl-pid: `autotune apply e1`")


def _apply_run(h: ChangeHistory, run_id: str, before: PidGains, status_: str) -> None:
    """An `autotune apply` run of run r1's gains (G1) as the bus carries it: lease, gains,
    release, result."""
    src = f"tuner:{run_id}"
    feed(h, status(before, "lease", leased_by=src, by_source=src))
    feed(h, status(G1, "gains", leased_by=src, by_source=src))
    feed(h, status(G1, "release", by_source=src))
    feed(
        h,
        TuneResult.model_validate(
            _result(run_id, True, G1).model_dump()
            | {
                "status": status_,
                "previous_gains": before.model_dump(),
                "applied_from": "r1",
            }
        ),
    )


def test_a_second_apply_of_the_same_gains_says_they_were_unchanged_not_not_applied(tmp_path):
    """Helper trial: `apply RUN --rule simc-pi` a second time said "new gains applied" and
    exited 0, and `history` said "ok, not applied": the run applied the gains the loop held
    already, no change, and the listing now says so."""
    h = history(tmp_path)
    feed(h, status(G0))
    _apply_run(h, "a1", G0, "ok")
    _apply_run(h, "a2", G1, "ok")
    lines = format_entries(LOOP, tmp_path / HISTORY_FILE, entries(tmp_path, LOOP)).splitlines()
    assert "run a1 (relay, zn-pi, from run r1)" in lines[1] and "Kc 2 → 6.9" in lines[2]
    assert lines[3].endswith(
        "run a2 (apply of run r1): ok, gains unchanged (the gains of run r1, zn-pi: the loop "
        "held them already)"
    )
    assert len(lines) == 4 and "not applied" not in "\n".join(lines)
    assert "unverified" not in "\n".join(lines)


def test_an_unverified_apply_is_marked_so_in_the_history(tmp_path):
    """`apply --no-verify` (the run ends ``unverified``): its change showed nothing saying
    the gains were never tried on the loop."""
    h = history(tmp_path)
    feed(h, status(G0))
    _apply_run(h, "u1", G0, "unverified")
    lines = format_entries(LOOP, tmp_path / HISTORY_FILE, entries(tmp_path, LOOP)).splitlines()
    assert "run u1 (relay, zn-pi, from run r1)" in lines[1]
    assert lines[3] == "      unverified (--no-verify): the gains were not tried on the loop"
    # applied unverified where the loop held them already: the status says it
    _apply_run(h, "u2", G1, "unverified")
    last = format_entries(LOOP, tmp_path / HISTORY_FILE, entries(tmp_path, LOOP)).splitlines()[-1]
    assert last.endswith(
        "run u2 (apply of run r1): unverified, gains unchanged (the gains of "
        "run r1, zn-pi: the loop held them already)"
    )


def test_a_torn_last_line_is_skipped(tmp_path):
    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    with (tmp_path / HISTORY_FILE).open("a") as f:
        f.write('{"record": "change", "loop": "hx1", "bef')  # a crash mid-line
    assert len(changes(tmp_path)) == 1


def test_unreadable_lines_are_counted_and_the_history_command_says_so(tmp_path, capsys):
    """A torn line, an edited one, bad bytes: skipped as before, but ``autotune history``
    says how many and which (it passed over them without a word: noticed last stop)."""
    from services.cli import main

    h = history(tmp_path)
    feed(h, status(G0))
    with (tmp_path / HISTORY_FILE).open("ab") as f:
        f.write(b'{"record": "change", "loop": "hx1", "bef\n[1, 2]\n\xff\xfe{\n\n')
    feed(h, status(G1, "gains", by_source="autotune-set"))
    skipped: list[tuple[int, str]] = []
    assert len(list(read_history(tmp_path / HISTORY_FILE, skipped))) == 1  # the change
    assert [n for n, _ in skipped] == [1, 2, 3]  # the blank line is no record, nor damage
    code = main(["history", LOOP, "--runs", str(tmp_path), "--prefix", P])
    err = capsys.readouterr().err
    assert code == 0
    assert "3 line(s) not readable as a record (line 1, 2, 3): skipped" in err


def test_a_record_whose_fields_are_not_of_their_types_is_skipped_and_named(tmp_path, capsys):
    """A record edited to hold ``"before": "x"`` stopped `autotune history` with an internal
    error (exit 70); one with a number as text would be formatted as a number. Such records
    are skipped like a torn line, the first one's field and reason said; a file's text that
    is printed shows its control characters as escapes."""
    from services.cli import main

    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    good = changes(tmp_path)[-1]
    bad = [
        {**good, "before": "notadict"},
        {**good, "after": {**good["after"], "kc": "2.5"}},
        {**good, "t": [1]},
        {"record": "tune", "loop": LOOP, "prefix": P, "gains": {"zn-pid": {"kc": True}}},
        {"record": "tune", "loop": LOOP, "prefix": P, "verification_after": 3},
        {"record": "change", "prefix": P},  # no loop
    ]
    shown = {**good, "by_source": "set\x1b[31mRED\nX"}
    with (tmp_path / HISTORY_FILE).open("a") as f:
        for rec in [*bad, shown]:
            f.write(json_text.dumps(rec) + "\n")
    skipped: list[tuple[int, str]] = []
    read = list(read_history(tmp_path / HISTORY_FILE, skipped))
    assert len(read) == 2  # the start is no change: the set, and the one shown
    assert [n for n, _ in skipped] == [2, 3, 4, 5, 6, 7]
    assert skipped[0][1].startswith("before: ") and skipped[1][1].startswith("after.kc: ")
    assert skipped[3][1].startswith("gains.zn-pid.kc: ")
    assert skipped[5][1].startswith("loop: ")
    code = main(["history", LOOP, "--runs", str(tmp_path), "--prefix", P])
    out, err = capsys.readouterr()
    assert code == 0
    said = "6 line(s) not readable as a record (line 2, 3, 4, 5, 6, …): skipped; line 2: "
    assert said + "before: not a JSON object" in err
    assert "set\\x1b[31mRED\\nX" in out and "\x1b" not in out
    assert len(out.splitlines()) == 1 + 2 * 2  # the heading, two changes of two lines each


def test_one_runs_directory_two_buses_a_loop_id_is_a_loop_within_its_prefix(tmp_path):
    """The demo records under its own prefix beside `autotune up`'s: their hx1s are two."""
    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    other = ChangeHistory(tmp_path, "other", now=h.now)  # another bus, the same file
    other.handle(keys.status("other", LOOP), wire.encode(status(G0)))  # learned, not a change
    assert len(changes(tmp_path)) == 1
    assert loop_changes(tmp_path / HISTORY_FILE, LOOP, "other") == []
    assert len(loop_changes(tmp_path / HISTORY_FILE, LOOP, P)) == 1
    assert entries(tmp_path, LOOP, "other") == [] and len(entries(tmp_path, LOOP, P)) == 1


# --- revert and apply, their pure parts -----------------------------------------------------


def test_revert_picks_the_change_to_undo_or_names_the_flag():
    cs = [{"run_id": "a", "before": 1}, {"run_id": None, "before": 2}, {"run_id": "b", "before": 3}]
    assert target(cs, None, 1)["before"] == 3
    assert target(cs, None, 3)["before"] == 1
    assert target(cs, "a", 1)["before"] == 1
    with pytest.raises(ConfigError, match="--steps 4: only 3 change"):
        target(cs, None, 4)
    with pytest.raises(ConfigError, match="--to zz: no change"):
        target(cs, "zz", 1)
    # an approved run's gains, written by `autotune apply` (run "c"): either id names it
    applied = [*cs, {"run_id": "c", "applied_from": "b", "before": 4}]
    assert target(applied, "c", 1)["before"] == 4
    assert target(applied, "b", 1)["before"] == 4
    with pytest.raises(ConfigError, match="--steps 0"):
        target(cs, None, 0)


RUN = {
    "run_id": "r1",
    "status": "ok",
    "recommended": "tl-pid",
    "rule": "tl-pid",
    "ku": 15.2,
    "gains": {
        "tl-pid": {"kc": 6.9, "ti": 96.0, "td": 6.9},
        "zn-pid": {"kc": 9.1, "ti": 21.8, "td": 5.5},
        "zn-p": {"kc": 7.6, "ti": None, "td": 0.0},
        "tl-pi": {"kc": 4.75, "ti": 96.0, "td": 0.0},
    },
    "robustness": {
        "tl-pid": {"within_envelope": True, "overshoot_pct": 1.0, "ms": 1.7},
        "zn-pid": {"within_envelope": False, "overshoot_pct": 59.0, "ms": 2.3},
    },
}


def test_apply_takes_the_recommended_rule_and_refuses_one_outside_the_envelope():
    rule, gains, predicted = choose(RUN, None)
    assert (rule, gains, predicted) == ("tl-pid", PidGains(kc=6.9, ti=96.0, td=6.9), 1.0)
    with pytest.raises(ConfigError, match="--rule zn-pid: outside the safety envelope"):
        choose(RUN, "zn-pid")
    assert choose(RUN, "tl-pi")[1].kc == 4.75  # not judged, but below K_u
    with pytest.raises(ConfigError, match="--rule cc-pi: the run has no gains"):
        choose(RUN, "cc-pi")
    with pytest.raises(ConfigError, match="aborted, no gains"):
        choose({**RUN, "status": "aborted"}, None)


def test_apply_takes_the_rule_the_tune_proposed():
    """``tune --no-apply --rule tl-pi`` proposed TL-PI, and its hint said `autotune apply`
    applies them: apply took the recommended TL-PID instead (seen: AMIGO-PI proposed, SIMC-PI
    applied at 2.3× its Kc). The listing names both."""
    proposed = {**RUN, "status": "proposed", "rule": "tl-pi"}
    assert choose(proposed, None)[:2] == ("tl-pi", PidGains(kc=4.75, ti=96.0, td=0.0))
    assert choose(proposed, "tl-pid")[0] == "tl-pid"
    base = {"record": "tune", "utc": "2026-12-04T19:00:00", "t": 1.0, "method": "relay"}
    line = format_entries(LOOP, Path("runs"), [{**base, **proposed}]).splitlines()[1]
    assert line.endswith("not applied; proposed tl-pi (recommended tl-pid): `autotune apply r1`")


def test_a_refused_rule_is_not_offered_the_recommended_one_is():
    """``tune --rule zn-pid`` refused (outside the envelope): the listing offered `autotune
    apply ID`, which applies the proposed zn-pid and so was refused too (a dead end). It
    now offers the recommended rule by name, and apply's refusal names it."""
    refused = {**RUN, "status": "rejected", "rule": "zn-pid", "timescale": 43.6}
    base = {"record": "tune", "utc": "2026-12-04T19:00:00", "t": 1.0, "method": "relay"}
    line = format_entries(LOOP, Path("runs"), [{**base, **refused}]).splitlines()[1]
    assert line.endswith(
        "not applied; proposed zn-pid, outside the safety envelope; recommended tl-pid: "
        "`autotune apply r1 --rule tl-pid`"
    )
    said = re.escape("Ms 2.3); --rule tl-pid is within it; tune again")
    with pytest.raises(ConfigError, match=said):
        choose(refused, None)
    assert choose(refused, "tl-pid")[0] == "tl-pid"
    # neither within the envelope: nothing offered
    worse = {**refused, "recommended": "zn-pid"}
    line = format_entries(LOOP, Path("runs"), [{**base, **worse}]).splitlines()[1]
    assert line.endswith("none within the safety envelope: nothing to apply")


def test_apply_checks_the_loop_is_the_one_identified():
    info = LoopInfo(
        loop="hx1", node="plant", t=0.0, model="heat_exchanger", description="",
        model_params={"gain": 1.0}, sample_time=0.25, pv_units="degC", pv_range=(0.0, 150.0),
        op_limits=(0.0, 100.0), disturbances=[], noise_std=0.02, clock="lockstep", speed=1.0,
        instance="a1",
    )  # fmt: skip
    rec = {"node": "plant", "instance": "a1", "model": "heat_exchanger",
           "model_params": {"gain": 1.0}, "sample_time": 0.25}  # fmt: skip
    assert same_loop(rec, info) is None
    assert "plant instance" in same_loop({**rec, "instance": "b2"}, info)
    assert "model parameters" in same_loop({**rec, "model_params": {"gain": 2.0}}, info)
    assert "did not record" in same_loop(None, info)


def test_a_loop_asked_for_at_start_is_learned_unless_a_live_status_came_first(tmp_path):
    """The logger asks every loop's status at its start (``learn``): a change made while it
    was not running is recorded then, not at the loop's next status; a live status that
    came first is newer than the answer and stands."""
    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    again = history(tmp_path)  # the logger restarted; the gains moved meanwhile
    again.learn(keys.status(P, LOOP), wire.encode(status(G0)))
    c = changes(tmp_path)[-1]
    assert (c["cause"], c["before"], c["after"]) == ("unseen", G1.model_dump(), G0.model_dump())
    third = history(tmp_path)
    feed(third, status(G1))  # live first: it stands
    seen = changes(tmp_path)
    third.learn(keys.status(P, LOOP), wire.encode(status(G0)))
    assert changes(tmp_path) == seen and seen[-1]["after"] == G1.model_dump()


def test_no_change_under_the_prefix_asked_names_the_buses_that_have_some(tmp_path, capsys):
    """`history hx1` without --prefix on a file of another bus's hx1 said only "No change …
    on record", hiding the filter (helper finding)."""
    from services.cli import main

    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    assert main(["history", LOOP, "--runs", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "under prefix 'autotune'" in out and f"it holds hx1's under '{P}'" in out, out
    assert main(["history", LOOP, "--runs", str(tmp_path), "--prefix", P]) == 0
    assert "autotune-set" in capsys.readouterr().out


def test_a_late_result_asked_for_is_the_runs_tune_record_and_its_change(tmp_path):
    """The logger paused past the link's lease as a run ended: it missed the run's release
    status and its result, asked the tuner for the result, and wrote neither record; the
    gains were filed later as "unseen", who not known, and `revert --to RUN` found no change
    by the run (helper trial). The result asked for is the run's tune record and its change
    (cause release, the run named, from the gains it left); the next status adds nothing."""
    h = history(tmp_path)
    feed(h, status(G0))
    src = "tuner:late1"
    feed(h, status(G0, "lease", leased_by=src, by_source=src))
    feed(h, status(G1, "gains", leased_by=src, by_source=src))  # then the logger is paused
    r = TuneResult(
        run_id="late1",
        loop=LOOP,
        t=300.0,
        method="relay",
        rule="tl-pid",
        status="ok",
        applied=True,
        chosen={"isa": {"kc": 6.9, "ti": 96.0, "td": 6.9}},
        left={"mode": "auto", "gains": G1.model_dump()},
    )
    h.late_result(wire.encode(r))
    (c,) = changes(tmp_path)
    assert (c["run_id"], c["cause"], c["by_source"]) == ("late1", "release", src)
    assert c["before"] == G0.model_dump() and c["after"] == G1.model_dump()
    (tune,) = [x for x in read_history(tmp_path / HISTORY_FILE) if x["record"] == "tune"]
    assert tune["run_id"] == "late1"
    assert (
        target(loop_changes(tmp_path / HISTORY_FILE, LOOP), "late1", 1)["before"] == G0.model_dump()
    )
    feed(h, status(G1, "sync"))  # heard once the logger is back: the same gains, no change
    assert len(changes(tmp_path)) == 1
    # an operator's change heard after the run (outside any lease): the late result is the
    # run's tune record only, not a change charged to the run (review)
    (tmp_path / "b").mkdir()
    h2 = history(tmp_path / "b")
    feed(h2, status(G0))
    feed(h2, status(G0, "lease", leased_by=src, by_source=src))
    feed(h2, status(G1, "gains", leased_by=src, by_source=src))
    g2 = PidGains(kc=3.0, ti=50.0)
    feed(h2, status(g2, "gains", by_source="autotune-set", by_user="op"))
    h2.late_result(wire.encode(r))
    (only,) = changes(tmp_path / "b")
    assert (only["cause"], only["after"]) == ("gains", g2.model_dump()), only
    # a rejected run's result leaves the gains as they were: no change
    h.late_result(
        wire.encode(r.model_copy(update={"run_id": "late2", "left": {"gains": G1.model_dump()}}))
    )
    assert len(changes(tmp_path)) == 1


def test_a_fifo_where_a_file_is_expected_is_refused_not_waited_on(tmp_path):
    """`autotune runs` on a FIFO named x.mcap and `autotune history` on a FIFO named
    history.jsonl waited for a writer for ever (helper review): each says what it is, one
    line, at once. Run as processes with a timeout, so that a wait fails the test."""
    import os
    import subprocess
    import sys

    os.mkfifo(tmp_path / "x.mcap")
    os.mkfifo(tmp_path / HISTORY_FILE)
    root = Path(__file__).resolve().parents[1]
    env = {**os.environ, "PYTHONPATH": str(root)}
    cli = [sys.executable, "-m", "services.cli"]
    runs = subprocess.run([*cli, "runs", str(tmp_path)], capture_output=True, text=True,
                          timeout=60, env=env)  # fmt: skip
    assert runs.returncode == 0 and "not a regular file (a FIFO or a device)" in runs.stdout
    hist = subprocess.run([*cli, "history", "hx1", "--runs", str(tmp_path)],
                          capture_output=True, text=True, timeout=60, env=env)  # fmt: skip
    assert hist.returncode == 2 and len(hist.stderr.strip().splitlines()) == 1, hist.stderr
    assert "not a regular file" in hist.stderr and "Traceback" not in hist.stderr


def test_revert_to_the_approved_run_finds_the_change_its_apply_made(tmp_path):
    """`autotune apply A1` ran as run B2 and `history` showed the change "from run A1", but
    `revert --to A1` said "no change of the loop's gains by that run on record": the change
    record names the apply run, its `tune` record (written after it) the approved one
    (helper trial). The changes as read carry the approved run from the tune record."""
    h = history(tmp_path)
    feed(h, status(G0))
    src = "tuner:B2"
    feed(h, status(G0, "lease", leased_by=src, by_source=src))
    feed(h, status(G1, "gains", leased_by=src, by_source=src))
    feed(h, status(G1, "release", by_source=src))
    applied = _result("B2", True, G1).model_copy(update={"applied_from": "A1"})
    feed(h, applied)
    found = changes(tmp_path)
    assert target(found, "A1", 1) is found[-1] and found[-1]["run_id"] == "B2"
    assert target(found, "B2", 1) is found[-1]
    assert found[-1]["before"] == G0.model_dump()


def test_the_watch_finds_the_last_applied_tune_in_the_history_when_no_tuner_has_it(tmp_path):
    """After a tuner restart `autotune watch` had no tune to go by: T_u from Ti (1,000 s
    against the tune's P_u of 43 s) and "no applied tune to compare with" (helper trial).
    The history's tune records carry P_u, and the watch reads the last applied one (a
    rejected run after it changed nothing)."""
    from services.autotuner.commands.watch import recorded_tune
    from services.autotuner.monitor.assessment import Baseline

    h = history(tmp_path)
    feed(h, status(G0))
    applied = _result("ok1", True, G1).model_copy(update={"pu": 43.4, "noise": 0.02})
    feed(h, applied)
    feed(h, _result("rej2", False, G1).model_copy(update={"pu": 40.0}))
    last = recorded_tune(tmp_path, P, LOOP)
    assert last is not None and (last["run_id"], last["pu"]) == ("ok1", 43.4)
    base = Baseline.from_result(last)
    assert base is not None and base.run_id == "ok1" and base.gains == (6.9, 96.0, 6.9)
    assert recorded_tune(tmp_path, "another-bus", LOOP) is None
    assert recorded_tune(tmp_path / "nowhere", P, LOOP) is None


def test_the_watch_takes_t_u_from_the_run_an_apply_applied(tmp_path):
    """After the console's Apply (``autotune apply``) the last applied tune is the apply run,
    which identifies nothing (its P_u None): the watch took Ti for T_u (96 s against the
    relay's P_u of 43.7 s on hx1, helper trial). Its P_u is that of the run it applied."""
    from services.autotuner.commands.watch import recorded_tune, tuned_pu

    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, _result("prop1", False, G0).model_copy(update={"pu": 43.7, "status": "proposed"}))
    feed(h, _result("app2", True, G1).model_copy(update={"applied_from": "prop1"}))
    last = recorded_tune(tmp_path, P, LOOP)
    assert last is not None and (last["run_id"], last["pu"]) == ("app2", None)
    assert tuned_pu(tmp_path, P, last) == 43.7
    # the tuner's own result of the apply run, with no P_u: the same
    assert tuned_pu(tmp_path, P, {"pu": None, "applied_from": "prop1"}) == 43.7
    assert tuned_pu(tmp_path, P, {"pu": 40.0, "applied_from": "prop1"}) == 40.0
    assert tuned_pu(tmp_path, P, {"pu": None, "applied_from": "gone"}) is None
    assert tuned_pu(tmp_path / "nowhere", P, {"pu": None, "applied_from": "prop1"}) is None


class _Reply:
    def __init__(self, key: str, payload: bytes):
        self.ok = SimpleNamespace(key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload))


class _Session:
    """What the logger's service asks of its session here: a loop's status (``get``)."""

    def __init__(self):
        self.answer: LoopStatus | None = None
        self.asked: list[str] = []

    def get(self, key: str, timeout: float = 0.0) -> list[_Reply]:
        self.asked.append(key)
        return [_Reply(key, wire.encode(self.answer))] if self.answer is not None else []


def _on_bus(service: LoggerService, key: str, msg) -> None:
    payload = wire.encode(msg)
    service._on_sample(
        SimpleNamespace(
            key_expr=key, payload=SimpleNamespace(to_bytes=lambda: payload), attachment=None
        )
    )


def test_a_plant_restart_whose_start_status_was_lost_is_filed_at_its_first_samples(tmp_path):
    """Helper trial: `set hx1 --kc 2.5`, the plant killed and started again: its ``start``
    status is put as its session opens and never reached the logger (connecting again to
    the new plant, which held the rendezvous port), and in realtime no other status comes
    until a command; `history` still ended on Kc 2 → 2.5. Now the new
    instance's first samples (their number and sim time gone back) make the logger ask the
    loop's status, filed as the restart (``start``) with the new instance's gains."""
    from services.logger.recorder import Recorder
    from shared.messages import ProcessSample

    session = _Session()
    service = LoggerService(session, Recorder(tmp_path, P), "logger")  # type: ignore[arg-type]
    g25 = PidGains(kc=2.5, ti=60.0)
    _on_bus(service, keys.status(P, LOOP), status(G0, clock="realtime", seq=500, t=50.0))
    _on_bus(
        service,
        keys.status(P, LOOP),
        status(g25, "gains", by_source="autotune-set", clock="realtime", seq=600, t=60.0),
    )

    def sample(seq: int) -> ProcessSample:
        return ProcessSample(
            loop=LOOP, seq=seq, t=seq * 0.1, pv=60.0, sp=61.0, op=40.0, mode="auto"
        )

    for seq in range(601, 611):  # the old instance's
        _on_bus(service, keys.pv(P, LOOP), sample(seq))
    assert [c["after"]["kc"] for c in changes(tmp_path)] == [2.5]
    # kill -9, start again: no `start` status heard; the new instance's samples from 1
    session.answer = status(G0, "query", clock="realtime", seq=3, t=0.3, sp=61.0, mode="manual")
    for seq in range(1, 4):
        _on_bus(service, keys.pv(P, LOOP), sample(seq))
    stop = threading.Event()
    asker = threading.Thread(target=service._ask_restarted, args=(stop,), daemon=True)
    asker.start()
    deadline = time.monotonic() + 5.0
    while len(changes(tmp_path)) < 2 and time.monotonic() < deadline:
        time.sleep(0.02)
    stop.set()
    asker.join(2.0)
    assert session.asked == [keys.status(P, LOOP)]
    *_, c = changes(tmp_path)
    assert (c["cause"], c["by_source"], c["mode"], c["t"]) == ("start", None, "manual", 0.3)
    assert c["before"] == g25.model_dump() and c["after"] == G0.model_dump()
    text = format_entries(LOOP, tmp_path / HISTORY_FILE, entries(tmp_path, LOOP))
    assert text.splitlines()[-2].endswith("the plant (re)started with its configured gains")
    # the next status (a command's) is no restart: the set after it is the sender's
    _on_bus(
        service,
        keys.status(P, LOOP),
        status(g25, "gains", by_source="autotune-set", clock="realtime", seq=9, t=0.9),
    )
    assert [(c["cause"], c["after"]["kc"]) for c in changes(tmp_path)] == [
        ("gains", 2.5),
        ("start", 2.0),
        ("gains", 2.5),
    ]


def test_a_restart_heard_by_its_start_status_is_filed_once_and_asks_nothing(tmp_path):
    """The ``start`` status heard (it reached the logger): one change, no status asked; a
    status heard live after the evidence of a restart, before the answer, is the start and
    the answer is dropped (it is not newer)."""
    h = history(tmp_path)
    feed(h, status(G1))
    h.plant_restarted(LOOP)
    feed(h, status(G0, "start"))
    assert not h.awaits_restart_status(LOOP)
    h.restart_status(keys.status(P, LOOP), wire.encode(status(G1, "query")))  # too late
    (c,) = changes(tmp_path)
    assert (c["cause"], c["after"]) == ("start", G0.model_dump())
    h.plant_restarted("never-heard")  # a loop not known: its first status is learned
    assert not h.awaits_restart_status("never-heard")


def test_gains_unchanged_only_where_every_term_is_the_same():
    """An integral turned off (Ti None against 10 s), or a setpoint weight changed alone, is
    a change; the same Kc, Ti, Td and β are not (review: both read "gains unchanged")."""
    from services.logger.commands.history import _held_already

    before = {"kc": 2.0, "ti": 10.0, "td": 0.0, "beta": 1.0}
    same = {"previous_gains": before, "chosen": {"kc": 2.0, "ti": 10.0, "td": 0.0}}
    assert _held_already(same)
    assert not _held_already({**same, "chosen": {"kc": 2.0, "ti": None, "td": 0.0}})
    weighted = {**same, "verification_after": {"gains": {**before, "beta": 0.7}}}
    assert not _held_already(weighted)
    assert _held_already({**same, "verification_after": {"gains": before}})
    off = {"kc": 2.0, "ti": None, "td": 0.0, "beta": 1.0}
    assert _held_already({"previous_gains": off, "chosen": {"kc": 2.0, "ti": None, "td": 0.0}})


def test_a_measured_step_without_a_second_crest_says_none():
    """As the tune's table says it: "decay ratio none" where the setpoint step was measured
    and had no crest after its largest; "—" where nothing was measured (walkthrough: history
    said "—" beside the table's "none")."""
    from services.logger.commands.history import _verification

    line = _verification({"overshoot": 5.4, "decay_ratio": None, "settling_time": 65.0})
    assert "decay ratio none" in line, line
    assert "decay ratio 0.12" in _verification({"overshoot": 30.0, "decay_ratio": 0.12})
    assert "decay ratio —" in _verification({"overshoot": None, "decay_ratio": None, "iae_sp": 1})


def test_a_record_the_disk_had_no_room_for_leaves_no_cut_line(tmp_path):
    """A full disk cut a record short: the next record, once there was room again, was
    joined to the cut one, and both were lost ("1 line(s) not readable as a record": helper
    trial of a logger on a full tmpfs). The part written is taken back."""
    import json
    import resource
    import signal

    h = history(tmp_path)
    feed(h, status(G0))
    feed(h, status(G1, "gains", by_source="autotune-set"))
    path = tmp_path / HISTORY_FILE
    size = path.stat().st_size
    # room for 40 bytes more (a file limit of the process: a write past it fails as a full
    # disk's does, after what fits)
    soft, hard = resource.getrlimit(resource.RLIMIT_FSIZE)
    before = signal.signal(signal.SIGXFSZ, signal.SIG_IGN)
    resource.setrlimit(resource.RLIMIT_FSIZE, (size + 40, hard))
    try:
        with pytest.raises(OSError):
            feed(h, status(G0, "gains", by_source="autotune-set"))
    finally:
        resource.setrlimit(resource.RLIMIT_FSIZE, (soft, hard))
        signal.signal(signal.SIGXFSZ, before)
    assert path.stat().st_size == size
    g2 = PidGains(kc=9.0, ti=50.0)
    feed(h, status(g2, "gains", by_source="autotune-set"))
    lines = path.read_text().splitlines()
    assert all(isinstance(json.loads(x), dict) for x in lines), lines
    assert changes(tmp_path)[-1]["after"] == g2.model_dump()
