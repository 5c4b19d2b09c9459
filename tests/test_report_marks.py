"""The report's marks and its before/after verifications, from hand-made messages: which
verification is which, its setpoint and load steps, and the traces cut and shifted to them."""

from __future__ import annotations

import numpy as np

from services.logger.before_after import figures_rows, verify_traces
from services.logger.run_marks import experiment_marks, gains_marks, verify_windows
from shared.messages import (
    DisturbanceCommand,
    GainsCommand,
    PidGains,
    SetpointCommand,
    TuneProgress,
    TunerEvent,
    Verification,
    verify_message,
)


def progress(t: float, phase: str, message: str = "") -> TuneProgress:
    return TuneProgress(run_id="r", loop="x1", t=t, phase=phase, message=message)


def verification(overshoot: float) -> Verification:
    return Verification(
        gains=PidGains(kc=1.0, ti=10.0),
        sp_step=2.0,
        overshoot=overshoot,
        decay_ratio=None,
        rise_time=5.0,
        settling_time=None,
        iae_sp=3.0,
        load_step=5.0,
        iae_load=None,
        max_deviation_load=None,
        recovery_time=None,
        stable=True,
        saturated=False,
        score=1.0,
    )


PROGRESS = [
    progress(0, "relay"),
    progress(100, "verify", "Kc 1"),
    progress(300, "verify", "Kc 2"),
    progress(500, "done"),
]
SETPOINTS = [
    SetpointCommand(loop="x1", t=t, sp=sp)
    for t, sp in ((100, 60.0), (150, 62.0), (250, 60.0), (300, 60.0), (350, 62.0), (450, 60.0))
]
LOADS = [
    DisturbanceCommand(loop="x1", t=t, name="load", value=v)
    for t, v in ((200, 5.0), (240, 0.0), (400, 5.0), (440, 0.0))
]


def test_the_last_verification_is_after_and_the_one_before_it_before():
    before, after = verify_windows(PROGRESS, SETPOINTS, LOADS, 600.0, with_before=True)
    assert (before.label, before.start, before.end, before.gains) == ("before", 100, 300, "Kc 1")
    assert (after.label, after.start, after.end, after.gains) == ("after", 300, 500, "Kc 2")
    assert (before.sp0, before.step_t, before.sp) == (60.0, 150, 62.0)
    assert (after.load_t, after.load, after.load_off_t) == (400, 5.0, 440)
    (only,) = verify_windows(PROGRESS[:2], SETPOINTS[:3], LOADS[:2], 280.0, with_before=False)
    assert (only.label, only.end, only.load) == ("after", 280.0, 5.0)


def test_a_run_that_ended_within_its_verifications_has_them_named_by_their_gains():
    """A run cancelled in its verification of the loop's own gains: its one window was
    drawn as "after", titled with the old gains (helper review). With the gains the loop had
    before the run (``cut_short``), a first window of those is "before"; one of other gains
    (the loop was in manual: no "before") is "after"."""
    old, new = PidGains(kc=6.879, ti=94.83, td=6.842), PidGains(kc=6.91, ti=95.95, td=6.922)
    own = [progress(0, "relay"), progress(100, "verify", verify_message(old))]
    (only,) = verify_windows(own, SETPOINTS, LOADS, 120.0, False, cut_short=old)
    assert (only.label, only.gains) == ("before", "Kc 6.879, Ti 94.83 s, Td 6.842")
    both = [*own, progress(300, "verify", verify_message(new))]
    first, second = verify_windows(both, SETPOINTS, LOADS, 320.0, False, cut_short=old)
    assert (first.label, second.label) == ("before", "after")
    theirs = [progress(0, "relay"), progress(100, "verify", verify_message(new))]
    (only,) = verify_windows(theirs, SETPOINTS, LOADS, 120.0, False, cut_short=old)
    assert only.label == "after"
    # without it (the run's result has its verifications) the last is "after", as before
    (only,) = verify_windows(own, SETPOINTS, LOADS, 120.0, False)
    assert only.label == "after"


def test_traces_start_at_their_setpoint_step_as_deviations_and_rows_sit_side_by_side():
    t = np.arange(0.0, 600.0, 1.0)
    sp = np.interp(t, [s.t for s in SETPOINTS], [s.sp for s in SETPOINTS])
    pv = sp + 0.1
    windows = verify_windows(PROGRESS, SETPOINTS, LOADS, 600.0, with_before=True)
    before, after = verify_traces(t, pv, sp, np.full(t.size, 40.0), windows)
    assert before.t[0] == 100 - 150 and before.t[-1] == 300 - 150
    assert after.t[0] == 300 - 350 and after.load_t == 400 - 350
    assert np.allclose(after.pv, sp[300:501] - 60.0 + 0.1)
    rows = figures_rows(verification(12.5), verification(4.0), "degC")
    assert ("overshoot (%)", "12.5", "4") in rows and ("setpoint step (degC)", "2", "2") in rows
    assert not any(r[0].startswith("IAE, load") for r in rows)  # neither has it


def test_every_kind_of_experiment_mark_is_labelled():
    events = [
        TunerEvent(run_id="r", loop="x1", t=t, kind=k, data=d)
        for t, k, d in (
            (1.0, "switch", {"op": 45.0}),
            (2.0, "cycle", {"n": 1}),
            (3.0, "stage", {"stage": 2, "level": -0.1}),
            (4.0, "trial", {"n": 3, "kc": 2.25}),
            (5.0, "bias", {"bias": 39.9}),
            (6.0, "step", {"op": 45.0, "pv_before": 60.0}),
        )
    ]
    marks = [(m.t, m.kind, m.label) for m in experiment_marks(events, "degC")]
    assert marks == [
        (1.0, "switch", "relay to 45 %"),
        (2.0, "cycle", "cycle 1"),
        (3.0, "stage 2", "stage 2"),
        (4.0, "trial", "trial 3: Kc 2.25 %/degC"),
        (6.0, "output step", "output step to 45 %"),
    ]


def test_a_window_ends_where_its_gains_were_replaced_and_the_restore_is_marked():
    """A rejected run gives the old gains back before its phase ends: the "after" window ran
    on past the restore (hx1's by 144 s), the old gains' response drawn as the new ones', and
    nothing marked the restore (helper review). Gains commands at a window's start are its
    own; the one after ends it and is marked "gains restored"."""
    old, new = PidGains(kc=1.0, ti=10.0), PidGains(kc=2.0, ti=8.0, td=1.0)
    gains = [
        GainsCommand(loop="x1", t=100, gains=old),  # the "before" verification's own
        GainsCommand(loop="x1", t=300, gains=new),  # the "after" one's
        GainsCommand(loop="x1", t=460, gains=old),  # the restore, before "done" at 500
        GainsCommand(loop="x1", t=500, gains=old),  # the same again as the run ends
    ]
    trials = [GainsCommand(loop="x1", t=t, gains=PidGains(kc=t)) for t in (20.0, 40.0)]
    before, after = verify_windows(PROGRESS, SETPOINTS, LOADS, 600.0, True, trials + gains)
    assert (before.start, before.end, after.start, after.end) == (100, 300, 300, 460)
    # a ramp's trial gains come before the verifications: their marks are the trials'
    (mark,) = gains_marks(trials + gains, [before, after], old, "degC")
    assert (mark.t, mark.kind) == (460, "gains")
    assert mark.label == "gains restored: Kc 1 %/degC, Ti 10 s, Td 0 s", mark.label
    # an ok run sets its chosen gains again as it ends: no change, no mark, no end
    twice = [gains[1], gains[1].model_copy(update={"t": 500.0})]
    (after,) = verify_windows(PROGRESS[2:], SETPOINTS, LOADS, 600.0, False, twice)
    assert after.end == 500 and gains_marks(twice, [after], old, "degC") == []
    # gains that are not the loop's own before the run: set, not restored
    (mark,) = gains_marks(gains, [before, after], new, "m3/h")
    assert mark.label == "gains set: Kc 1 %/(m3/h), Ti 10 s, Td 0 s", mark.label


def test_a_mark_label_under_the_summary_box_hangs_below_it_and_window_labels_stack():
    """The first trials' Kc hung from the top of the plot under the summary box, hidden
    (hx1's ramp), and two verification labels 25 s apart overprinted each other (flow1's):
    each now reads clear of the box and of the other labels."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from services.logger.report import MARK_LABEL, WINDOW_LABEL, place_labels

    fig = Figure(figsize=(10, 4))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot()
    ax.plot([0, 700], [0, 1])
    ax.set_xlim(0, 700)
    box = ax.text(0.01, 0.98, "summary\n" * 5, transform=ax.transAxes, va="top", bbox={})
    at = ax.get_xaxis_transform()
    marks = [
        ax.text(x, 1.0, f"Kc {x}", transform=at, rotation=90, va="top", gid=MARK_LABEL)
        for x in (20, 60, 600)
    ]
    windows = [
        ax.text(x, 0.02, f" verification {w}", transform=at, va="bottom", gid=WINDOW_LABEL)
        for x, w in ((610, "before"), (635, "after"))
    ]
    fig.draw_without_rendering()
    r = fig.canvas.get_renderer()
    assert marks[0].get_window_extent(r).overlaps(box.get_window_extent(r))  # as it was drawn
    place_labels(fig)
    extents = [t.get_window_extent(r) for t in (*marks, *windows)]
    assert not any(e.overlaps(box.get_window_extent(r)) for e in extents)
    assert not extents[3].overlaps(extents[4])
    assert marks[2].get_position()[1] == 1.0  # clear of the box: where it was


def test_the_legend_names_every_output_a_repeated_step_test_went_to():
    """Six steps of a repeated test, up to 54.05 % and back down to 44.05 %: the legend said
    "output step to 54.05 %" for all six (helper review)."""
    from services.logger.report import _steps_text

    events = [
        TunerEvent(run_id="r", loop="x1", t=100.0 * i, kind="step", data={"op": op})
        for i, op in enumerate([54.05, 44.05] * 3)
    ]
    steps = [m for m in experiment_marks(events, "m") if m.kind == "output step"]
    assert _steps_text(steps) == "step test: 6 output steps, to 54.05 / 44.05 %"
    assert _steps_text(steps[:1]) == "step test: output step to 54.05 %"


def test_the_gain_margin_check_and_the_gains_back_after_it_are_marked_as_such():
    """A PID's verification runs it at Kc × 2 for a while (``margin_check``), then sets its
    gains again: both marked for what they are, not as gains set from elsewhere."""
    old, new = PidGains(kc=1.0, ti=10.0), PidGains(kc=2.0, ti=8.0, td=1.0)
    doubled = PidGains(kc=4.0, ti=8.0, td=1.0)
    gains = [
        GainsCommand(loop="x1", t=100, gains=old),
        GainsCommand(loop="x1", t=300, gains=new),
        GainsCommand(loop="x1", t=420, gains=doubled),  # the check
        GainsCommand(loop="x1", t=450, gains=new),  # the gains on trial again
        GainsCommand(loop="x1", t=500, gains=new),
    ]
    windows = verify_windows(PROGRESS, SETPOINTS, LOADS, 600.0, True, gains)
    marks = gains_marks(gains, windows, old, "degC")
    assert [(m.t, m.label.split(":")[0]) for m in marks] == [
        (420, "gain-margin check, Kc × 2"),
        (450, "gains back after the check"),
    ]
