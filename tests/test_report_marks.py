"""The report's marks and its before/after verifications, from hand-made messages: which
verification is which, its setpoint and load steps, and the traces cut and shifted to them."""

from __future__ import annotations

import numpy as np

from services.logger.before_after import figures_rows, verify_traces
from services.logger.run_marks import experiment_marks, verify_windows
from shared.messages import (
    DisturbanceCommand,
    PidGains,
    SetpointCommand,
    TuneProgress,
    TunerEvent,
    Verification,
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
