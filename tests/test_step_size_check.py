"""A step test's output step is judged when the request arrives, against the loop's output
limits: ``tune lvl1 --method step --step-size 60`` (output 50 %) was refused only after the
600 s wait for rest, as an aborted run."""

from __future__ import annotations

import pytest

from services.autotuner.service import _check_step_size
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
