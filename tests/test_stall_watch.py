"""A stall of this process (no thread ran) is told from a silence of the plant."""

import time

from services.autotuner.stall_watch import StallWatch


def test_a_stall_in_progress_counts_before_the_ticker_is_back():
    w = StallWatch(period=3600.0, threshold=1.0)  # the ticker asleep: the record is ours
    now = time.monotonic()
    w._last = now - 5.0  # the last tick, 5 s ago: the process was stopped since
    assert w.stalled(now - 10.0) >= 5.0
    assert 2.0 <= w.stalled(now - 3.0) < 3.5  # only the part since the moment asked
    w._last = now - 0.5  # a tick half a second ago: a busy machine, not a stall
    assert w.stalled(now - 10.0) == 0.0


def test_stalls_seen_are_counted_where_they_overlap():
    w = StallWatch(period=3600.0, threshold=1.0)
    now = time.monotonic()
    w._last = now
    w._stalls.extend([(now - 20.0, now - 14.0), (now - 8.0, now - 6.0)])
    assert w.stalled(now - 30.0) == 8.0
    assert w.stalled(now - 10.0) == 2.0
    assert w.stalled(now - 16.0) == 4.0
    assert w.stalled(now - 5.0) == 0.0


def test_a_plant_lost_is_blamed_on_a_stall_only_within_the_run_and_before_the_loss():
    """A tuner paused 12 s before a run, its plant then killed mid-run: "cut off from it: its
    own process did not run for 12 s" (helper trial); a stall counts only since the client
    began and within CUT_OFF_WINDOW before the token vanished."""
    from services.autotuner.loop_client import CUT_OFF_WINDOW, stalled_before

    w = StallWatch(period=3600.0, threshold=1.0)
    now = time.monotonic()
    w._last = now
    w._stalls.append((now - 25.0, now - 13.0))  # paused 12 s, idle, before the run
    assert stalled_before(w, born=now - 10.0, gone=now - 1.0) == 0.0  # the run began after
    assert stalled_before(w, born=now - 40.0, gone=now - 1.0) == 12.0  # within the run
    # a stall after the loss is not its cause; one beyond the window before it neither
    w._stalls.append((now - 0.8, now - 0.1))
    assert stalled_before(w, born=now - 40.0, gone=now - 1.0) == 12.0
    old = StallWatch(period=3600.0, threshold=1.0)
    old._last = now
    old._stalls.append((now - CUT_OFF_WINDOW - 20.0, now - CUT_OFF_WINDOW - 8.0))
    assert stalled_before(old, born=now - 100.0, gone=now - 1.0) == 0.0
