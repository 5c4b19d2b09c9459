"""The marks a relay run's figure shows for its stage 2: its start, and, where it got stuck,
its setting again; never its end (abandoned or out of patience). Flags are 0/1, as the bus
carries them."""

from __future__ import annotations

from services.logger.run_marks import experiment_marks
from shared.messages import TunerEvent


def _event(t: float, **data) -> TunerEvent:
    return TunerEvent(run_id="r", loop="hx1", t=t, kind="stage", data=data)


def test_stage_two_is_marked_where_it_starts_and_where_it_is_set_again():
    events = [
        _event(10.0, stage=2, level=-0.28, low_ratio=1.0),
        _event(16.7, stage=2, rearmed=1, level=-0.18, amplitude=0.59),
        _event(25.7, stage=2, unsettled=1),
    ]
    marks = experiment_marks(events, "degC")
    assert [(m.t, m.kind, m.label) for m in marks] == [
        (10.0, "stage 2", "stage 2"),
        (16.7, "stage 2 again", "stage 2 set again"),
    ]


def test_an_abandoned_stage_two_is_marked_at_its_start_only():
    events = [
        _event(10.0, stage=2, level=-0.28, low_ratio=1.0),
        _event(22.4, stage=2, abandoned=1),
    ]
    assert [m.t for m in experiment_marks(events, "degC")] == [10.0]


def test_a_growth_of_the_relays_amplitude_is_marked_from_and_to():
    """The relay's d grew (its cycle rode on the hysteresis): the output's swing changes
    there, which the figure shows (helper 51: no mark, as for a widening of ε)."""
    grew = TunerEvent(
        run_id="r", loop="lvl2", t=72.0, kind="amplitude",
        data={"relay_amplitude": 20.0, "from": 5.0, "amplitude": 0.0062, "hysteresis": 0.0068},
    )  # fmt: skip
    marks = experiment_marks([grew], "m")
    assert [(m.t, m.kind, m.label) for m in marks] == [
        (72.0, "relay amplitude", "relay amplitude 5 → 20 %")
    ]
