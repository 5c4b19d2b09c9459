"""The stop test a batch asks of every sample (``signals.end_test``) answers as the rule reads:
a PV at or past a stop, or an output at or past an output stop, ends the batch; an unbounded
side never does; a PV that is not a number ends a bounded batch."""

from __future__ import annotations

import math

import pytest

from shared.control.signals import end_test, ends_batch, outside
from shared.messages import AdvanceCommand

NAN = math.nan


@pytest.mark.parametrize(
    "pv_stops, op_stops, pv, op, ends",
    [
        ((40.0, 60.0), (None, None), 50.0, 10.0, False),
        ((40.0, 60.0), (None, None), 60.0, 10.0, True),  # at a stop
        ((40.0, 60.0), (None, None), 39.9, 10.0, True),  # past one
        ((None, 60.0), (None, None), -1e300, 10.0, False),  # the unbounded side
        ((None, None), (None, None), NAN, 10.0, False),  # nothing bounded: never
        ((40.0, None), (None, None), NAN, 10.0, True),  # a PV that is not a number
        ((40.0, 60.0), (5.0, 95.0), 50.0, 95.0, True),  # the output at its stop
        ((40.0, 60.0), (5.0, 95.0), 50.0, 94.9, False),
        ((40.0, 60.0), (5.0, 95.0), 50.0, None, False),  # output not known
        ((40.0, 60.0), (None, 95.0), 50.0, -5.0, False),
    ],
)
def test_the_stop_test_of_a_batch(pv_stops, op_stops, pv, op, ends):
    assert end_test(pv_stops, op_stops)(pv, op) is ends
    assert ends_batch(pv, op, pv_stops, op_stops) is ends
    by_rule = outside(pv, *pv_stops) or (
        op is not None and op_stops != (None, None) and outside(op, *op_stops)
    )
    assert by_rule is ends
    cmd = AdvanceCommand(
        loop="x",
        steps=10,
        stop_below=pv_stops[0],
        stop_above=pv_stops[1],
        stop_op_below=op_stops[0],
        stop_op_above=op_stops[1],
    )
    assert cmd.stop_test()(pv, op) is ends
