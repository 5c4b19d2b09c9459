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
