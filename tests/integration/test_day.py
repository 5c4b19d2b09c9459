"""The whole day as a user has it (issue 14's acceptance), over the bus: plant, autotuner and
logger as processes, the CLI as a fourth.

tune hx1 (applied) → `history` shows the change with the previous gains → `revert` restores
them exactly (read back with `loops --json`) → `tune --no-apply`, then `apply RUN_ID` applies
exactly the run's recommended gains → `set` changes the gains → the logger restarts → a second
`revert` undoes the set → every step is in `history`, the revert after the restart too.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time

import pytest

from services.launcher import stop_service
from shared.history_file import HISTORY_FILE, loop_changes

pytestmark = pytest.mark.integration

LOOP = "hx1"


def cli(plant, *args: str, check: bool = True) -> subprocess.CompletedProcess:
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", *args, *plant.cli_args()],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert "Traceback" not in run.stderr, run.stderr
    if check:
        assert run.returncode == 0, (args, run.stdout, run.stderr)
    return run


def local(*args: str) -> subprocess.CompletedProcess:
    """A command that reads the runs directory only (no bus)."""
    run = subprocess.run(
        [sys.executable, "-m", "services.cli", *args], capture_output=True, text=True, timeout=60
    )
    assert run.returncode == 0, (args, run.stdout, run.stderr)
    return run


def gains(plant) -> dict:
    g = json.loads(cli(plant, "loops", LOOP, "--json").stdout)["gains"]
    return {k: g[k] for k in ("kc", "ti", "td", "n", "beta")}


def changes_seen(runs, n: int, timeout: float = 10.0) -> list[dict]:
    """The loop's change records once there are ``n`` (the logger writes as it sees them)."""
    deadline = time.monotonic() + timeout
    while True:
        found = loop_changes(runs / HISTORY_FILE, LOOP)
        if len(found) >= n or time.monotonic() > deadline:
            return found
        time.sleep(0.05)


def test_a_day_with_a_loop(start_plant, start_tuner, start_logger, tmp_path):
    runs = tmp_path / "runs"
    plant = start_plant(None, loops=(LOOP,))
    start_tuner(plant)
    logger = start_logger(plant, runs)
    g0 = gains(plant)

    tuned = json.loads(cli(plant, "tune", LOOP, "--json").stdout)
    assert tuned["status"] == "ok" and tuned["applied"], tuned["reason"]
    g1 = gains(plant)
    assert g1 == {**g0, **tuned["chosen"]["isa"]}
    (first,) = changes_seen(runs, 1)
    assert (first["run_id"], first["before"], first["after"]) == (tuned["run_id"], g0, g1)
    shown = json.loads(
        local("history", LOOP, "--runs", str(runs), "--prefix", plant.prefix, "--json").stdout
    )
    assert shown[0]["tune"]["verification_after"]["overshoot"] == tuned["after"]["overshoot"]

    # looked for in another directory: none on record there, and the one line says where the
    # logger on the bus writes (it said only that there was none)
    empty = tmp_path / "elsewhere"
    empty.mkdir()
    wrong = cli(plant, "revert", LOOP, "--runs", str(empty), check=False)
    assert wrong.returncode == 2 and len(wrong.stderr.strip().splitlines()) == 1, wrong.stderr
    assert f"writes to {runs.resolve()}: --runs {runs.resolve()}" in wrong.stderr, wrong.stderr
    assert gains(plant) == g1  # nothing moved

    reverted = json.loads(cli(plant, "revert", LOOP, "--runs", str(runs), "--json").stdout)
    assert reverted["after"] == g0 and gains(plant) == g0  # exactly the previous gains
    assert changes_seen(runs, 2)[-1]["by_source"] == "autotune-revert"

    pending = json.loads(cli(plant, "tune", LOOP, "--no-apply", "--json").stdout)
    assert pending["status"] == "proposed" and not pending["applied"] and gains(plant) == g0
    rule = pending["recommended"]["rule"]
    wrong = cli(plant, "apply", pending["run_id"], "--runs", str(empty), check=False)
    assert wrong.returncode == 2 and f"--runs {runs.resolve()}" in wrong.stderr, wrong.stderr
    applied = json.loads(
        cli(plant, "apply", pending["run_id"], "--runs", str(runs), "--json").stdout
    )
    assert applied["status"] == "ok" and applied["applied_from"] == pending["run_id"]
    recommended = pending["gains"][rule]["isa"]
    assert applied["rule"] == rule and gains(plant) == {**g0, **recommended}
    g2 = gains(plant)
    assert changes_seen(runs, 3)[-1]["after"] == g2

    cli(plant, "set", LOOP, "--kc", "1.5", "--ti", "80")
    g3 = gains(plant)
    assert (g3["kc"], g3["ti"]) == (1.5, 80.0)
    assert changes_seen(runs, 4)[-1]["by_source"] == "autotune-set"
    # the console's Reject of the applied run, pressed again after the set (a reload left it
    # enabled): it wrote the run's "before" over the operator's gains (helper trial); refused
    from services.console import actions
    from shared.errors import AutotuneError
    from shared.session import open_session

    refused = r"its gains changed after run \S+ \(gains by autotune-set at .*nothing written"
    with open_session(plant.client_settings()) as s, pytest.raises(AutotuneError, match=refused):
        actions.revert(s, plant.prefix, runs, LOOP, applied["run_id"], last_only=True)
    assert gains(plant) == g3

    stop_service(logger)  # a restart: the history is a file, the new logger goes on from it
    start_logger(plant, runs)
    again = json.loads(cli(plant, "revert", LOOP, "--runs", str(runs), "--json").stdout)
    assert again["after"] == g2 and gains(plant) == g2 and again["changed"]  # the set undone
    # two steps back from there is the set's own before, which the loop has: nothing sent,
    # and said so (it read "Reverted … was … now …" with the same gains twice)
    noop = cli(plant, "revert", LOOP, "--runs", str(runs), "--steps", "2")
    assert noop.stdout.startswith(f"Nothing to revert: {LOOP} has the gains before the change")
    assert gains(plant) == g2
    # the console's Revert pressed twice at once: the second, sent with the gains the page
    # still showed (the set's), undid the first (the tuned gains back); refused
    from shared.messages import PidGains

    stale = r"its gains changed since the page showed them \(now Kc .*nothing written"
    with open_session(plant.client_settings()) as s, pytest.raises(AutotuneError, match=stale):
        actions.revert(s, plant.prefix, runs, LOOP, None, shown=PidGains(**g3))
    assert gains(plant) == g2

    final = changes_seen(runs, 5)
    assert [c["by_source"] for c in final] == [
        f"tuner:{tuned['run_id']}",
        "autotune-revert",
        f"tuner:{applied['run_id']}",
        "autotune-set",
        "autotune-revert",
    ]
    assert [c["after"] for c in final] == [g1, g0, g2, g3, g2]
    shown = json.loads(
        local("history", LOOP, "--runs", str(runs), "--prefix", plant.prefix, "--json").stdout
    )
    # the no-apply run changed nothing: listed as a run that recommended gains
    assert [e["record"] for e in shown] == ["change", "change", "tune", *["change"] * 3]
    assert shown[2]["run_id"] == pending["run_id"] and shown[2]["applied"] is False
    assert shown[3]["tune"]["applied_from"] == pending["run_id"]
    text = local("history", LOOP, "--runs", str(runs), "--prefix", plant.prefix).stdout
    assert f"run {tuned['run_id']}" in text and "autotune-set" in text

    # the history is a file anyone may edit: a gain on record that `set` would refuse is not
    # written back (a Kc of 1e+250 put there by hand was put on the loop in auto, exit 0:
    # helper review); the one line names the file and the bound, and nothing moves
    path = runs / HISTORY_FILE
    lines = path.read_text().splitlines()
    last = max(i for i, line in enumerate(lines) if '"change"' in line)
    record = json.loads(lines[last])
    record["before"]["kc"] = 1e250
    lines[last] = json.dumps(record)
    path.write_text("\n".join(lines) + "\n")
    wild = cli(plant, "revert", LOOP, "--runs", str(runs), check=False)
    assert wild.returncode == 2 and len(wild.stderr.strip().splitlines()) == 1, wild.stderr
    assert "the gains on record before that change have Kc 1e+250" in wild.stderr, wild.stderr
    assert gains(plant) == g2
