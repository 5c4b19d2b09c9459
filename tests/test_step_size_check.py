"""A step test's output step is judged when the request arrives, against the loop's output
limits: ``tune lvl1 --method step --step-size 60`` (output 50 %) was refused only after the
600 s wait for rest, as an aborted run."""

from __future__ import annotations

import pytest

from services.autotuner.service import _check_limits, _check_step_size
from shared.messages import LoopStatus, TuneRequest
from tests.test_loops_set import status


def _status(mode: str, op: float) -> LoopStatus:
    """A loop at output ``op`` % in ``mode``, its output limits 0–100 %."""
    return status(mode=mode, op=op, op_limits=(0.0, 100.0))


def test_a_step_beyond_the_limits_of_a_manual_loop_is_refused_naming_the_field():
    req = TuneRequest(loop="lvl1", method="step", step_size=60.0)
    with pytest.raises(ValueError, match=r"^step_size \+60 %: the output would go from 50 to 110"):
        _check_step_size(req, _status("manual", 50.0))
    _check_step_size(
        TuneRequest(loop="lvl1", method="step", step_size=-50.0), _status("manual", 50.0)
    )


def test_an_auto_loop_is_refused_only_a_step_no_output_could_take():
    """Its step starts from the controller's mean output, not known before the rest wait."""
    _check_step_size(TuneRequest(loop="lvl1", method="step", step_size=60.0), _status("auto", 50.0))
    with pytest.raises(ValueError, match="more than the loop's whole output range"):
        _check_step_size(
            TuneRequest(loop="lvl1", method="step", step_size=-120.0), _status("auto", 50.0)
        )


def test_other_methods_and_the_default_step_pass():
    _check_step_size(TuneRequest(loop="lvl1", method="relay"), _status("manual", 99.0))
    with pytest.raises(ValueError, match=r"step_size \+5 %"):  # the default step, 5 %
        _check_step_size(TuneRequest(loop="lvl1", method="step"), _status("manual", 99.0))


# --- the PV limits' settings, judged when the request arrives -------------------------------


def test_a_hysteresis_the_limits_cannot_take_is_refused_naming_the_field():
    """``tune hx1 --hysteresis 1000`` ended a run ``failed`` (exit 1, two lines of result);
    refused at the request it is bad input: one line, exit 2 at the client."""
    on_hx1 = status()  # PV 59.5 in a range of 0-150
    with pytest.raises(ValueError, match=r"^hysteresis: 1000 is at least half the PV limits' wi"):
        _check_limits(TuneRequest(loop="hx1", method="relay", hysteresis=1000.0), on_hx1)
    with pytest.raises(ValueError, match=r"half the PV limits' width \(2\)"):
        req = TuneRequest(loop="hx1", method="relay", hysteresis=1.0, pv_limits=(59.0, 61.0))
        _check_limits(req, on_hx1)
    # limits past the range are kept to it (0-150 wide: 75 is half)
    with pytest.raises(ValueError, match=r"width \(150\)"):
        req = TuneRequest(loop="hx1", method="relay", hysteresis=75.0, pv_limits=(-500.0, 500.0))
        _check_limits(req, on_hx1)
    _check_limits(TuneRequest(loop="hx1", method="relay", hysteresis=74.0), on_hx1)
    _check_limits(TuneRequest(loop="hx1", method="ramp", hysteresis=1000.0), on_hx1)  # unused


def test_limits_the_pv_is_already_outside_are_refused():
    with pytest.raises(ValueError, match=r"^pv_limits: the PV 59\.5 is already outside \[60, 70\]"):
        _check_limits(TuneRequest(loop="hx1", pv_limits=(60.0, 70.0)), status())
    _check_limits(TuneRequest(loop="hx1", pv_limits=(50.0, 70.0)), status())


def test_a_ramp_bump_or_start_gain_no_loop_could_take_is_refused_naming_the_field():
    """``tune hx1 --method ramp --bump 1e308`` (or ``--kc-start 1e308``) took the lease and
    ran the drift check before the plant refused the setpoint (or the gains): bad input,
    refused at the request in one line. A bump of half the PV limits' width cannot be taken
    within them; a start gain above 1000 % of output per % of span (a proportional band of
    0.1 %) is what no write of gains may ask."""
    on_hx1 = status()  # PV 59.5 in a range of 0-150
    with pytest.raises(ValueError, match=r"^bump: 1e\+308 is at least half the PV limits' width"):
        _check_limits(TuneRequest(loop="hx1", method="ramp", bump=1e308), on_hx1)
    with pytest.raises(ValueError, match=r"^bump: 1 is at least half .* width \(2\)"):
        _check_limits(TuneRequest(loop="hx1", method="ramp", bump=1.0, pv_limits=(59, 61)), on_hx1)
    _check_limits(TuneRequest(loop="hx1", method="ramp", bump=74.0), on_hx1)
    # 1000 % per % of a 150 span is 1000·100/150 = 666.67 % per PV unit
    with pytest.raises(ValueError, match=r"^kc_start: 667 \(1000\.5 % of output per % of span\)"):
        _check_limits(TuneRequest(loop="hx1", method="ramp", kc_start=667.0), on_hx1)
    _check_limits(TuneRequest(loop="hx1", method="ramp", kc_start=666.0), on_hx1)
    # the other methods do not use them
    _check_limits(TuneRequest(loop="hx1", method="relay", bump=1e308, kc_start=1e308), on_hx1)


def test_the_run_refuses_them_too_before_anything_is_sent():
    """A run given them by another way than the service's request (in process): ``failed``,
    the loop untouched."""
    from services.autotuner.tuning import RunHooks, TuningRun
    from services.offline.local_loop import LocalLoopClient
    from services.plant_sim.plant_file import build_plant

    for field in ({"bump": 1e308}, {"kc_start": 1e308}):
        sim = build_plant({"seed": 1, "loops": {"hx1": {"model": "heat_exchanger"}}})["hx1"]
        req = TuneRequest(loop="hx1", method="ramp", **field)
        r = TuningRun(LocalLoopClient(sim), req, "x", RunHooks()).run()
        (name,) = field
        assert r.status == "failed" and r.reason.startswith(f"{name}: 1e+308"), r.reason
        assert r.untouched and sim.t == 0.0
