"""``autotune watch`` against a real plant process, and the tuner's monitor of a loop it tuned,
recorded by the logger in ``monitor.jsonl`` (issue 14, item 6). Lockstep plants: ``watch``
advances the loop itself when nobody holds its lease.

The plant is e^{−s}/(s + 1) sampled at 20 ms with noise σ = 0.2 % of span; its exact ultimate
point from ω_u·L + atan(ω_u·T) = π (``tests/exact.lag_ultimate``): K_u ≈ 2.262, P_u ≈ 3.10 s.
"""

from __future__ import annotations

import json
import queue
import time

import pytest

from services.autotuner.loop_client import LoopClient
from services.logger.monitor_log import read_monitor_log
from shared import keys
from shared.messages import LoopMonitor, SetpointCommand
from shared.session import open_session
from tests.exact import lag_ultimate
from tests.integration.tuning_cli import autotune, tune

pytestmark = pytest.mark.integration

K, T, L, H = 1.0, 1.0, 1.0, 0.02
KU, PU = lag_ultimate(K, (T,), L)


def plant_toml(extra: str = "") -> str:
    return (
        f'seed = 3\n[loops.x1]\nmodel = "fopdt"\ngain = {K}\ntime_constant = {T}\n'
        f"delay = {L}\nsample_time = {H}\nnoise_std = 0.2\npv0 = 50.0\n"
        f"pv_range = [0.0, 100.0]\n{extra}"
    )


def set_point(plant, sp: float) -> None:
    with (
        open_session(plant.client_settings()) as s,
        LoopClient(s, plant.prefix, "x1", source="test") as c,
    ):
        assert c.command(SetpointCommand(loop="x1", sp=sp, source="test")).sp == sp


def test_watch_flags_p_only_at_the_ultimate_gain_with_its_period(start_plant):
    p = start_plant(plant_toml(f'mode = "auto"\npid = {{ kc = {KU!r} }}\n'), loops=("x1",))
    set_point(p, 60.0)  # a 10 % bump: the loop at K_u rings on
    run = autotune("watch", "x1", "--period", repr(PU), "--json", *p.cli_args(), timeout=120)
    assert run.returncode == 0, run.stderr
    m = json.loads(run.stdout)
    assert m["oscillating"] and "oscillating" in m["flags"], m["flags"]
    assert m["oscillation_period"] == pytest.approx(PU, rel=0.05)
    assert m["period"] == PU and m["period_source"] == "--period"
    assert m["samples"] == round(50 * PU / H) and m["auto_fraction"] == 1.0
    assert m["node"] == "watch" and m["run_id"] is None  # no tuner: nothing to compare with


def test_the_tuner_watches_what_it_tuned_and_the_logger_records_it(
    start_plant, start_tuner, start_logger, tmp_path
):
    p = start_plant(plant_toml(), loops=("x1",))
    start_tuner(p)
    runs = tmp_path / "runs"
    start_logger(p, runs)
    live = tune(p, "x1")
    assert live["status"] == "ok" and live["applied"], live["reason"]
    got: queue.Queue[bytes] = queue.Queue()
    with open_session(p.client_settings()) as s:
        sub = s.declare_subscriber(
            keys.monitor(p.prefix, "x1"), lambda x: got.put(x.payload.to_bytes())
        )
        # nobody else advances the lockstep loop: watch does (50 T_u), the tuner sees it too
        run = autotune("watch", "x1", *p.cli_args(), timeout=120)
        assert run.returncode == 0, run.stderr
        assert f"Compared with the tune {live['run_id']}" in run.stdout, run.stdout
        assert "the last tune's P_u" in run.stdout and "OSCILLATING" not in run.stdout
        first = LoopMonitor.model_validate_json(got.get(timeout=30))
        sub.undeclare()
    assert first.node == "tuner" and first.run_id == live["run_id"]
    assert first.period == live["pu"] and first.period_source == "the last tune's P_u"
    assert not first.oscillating and "oscillating" not in first.flags
    assert first.t - first.t_start >= 10 * live["pu"] - 2 * H  # one window: 10 T_u
    assert first.baseline["op_noise"] == live["after"]["op_noise"]
    deadline = time.monotonic() + 30.0  # the logger appends it as it arrives
    while not read_monitor_log(runs) and time.monotonic() < deadline:
        time.sleep(0.05)
    recorded = read_monitor_log(runs)
    assert recorded and recorded[0] == first
