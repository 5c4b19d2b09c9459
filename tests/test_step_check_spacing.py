"""A step test's rest checks thin out as its record grows (``step_test.check_spacing``).

Each check is a regression over a window of the whole record: one every 8 samples made a long
record's checks grow as its square. 1.43·e^{−0.056s}/(866s² + 348s + 1) sampled every 0.02 s
ran 65,000 samples and its step test took 490 s of wall time (12 s now), to the same rule."""

from itertools import pairwise

from services.autotuner.identify.step_test import (
    SETTLE_CHECK_EVERY,
    check_due,
    check_spacing,
    samples_to_check,
)


def test_short_records_are_checked_every_8_samples_as_before():
    assert [n for n in range(1, 2048) if check_due(n)] == list(range(8, 2048, 8))
    assert check_spacing(2047) == SETTLE_CHECK_EVERY


def test_the_spacing_doubles_with_the_record_and_a_check_is_never_far_behind():
    due = [n for n in range(1, 70_000) if check_due(n)]
    # 255 checks up to 2,048 samples, then 128 per doubling: 5 doublings to 65,536
    assert len([n for n in due if n < 65_536]) == 255 + 128 * 5
    assert all(b - a <= max(SETTLE_CHECK_EVERY, a // 64) for a, b in pairwise(due))


def test_the_horizon_lands_on_every_check_and_skips_none():
    due = [n for n in range(1, 20_000) if check_due(n)]
    n, seen = 0, []
    while n < due[-1]:
        n += samples_to_check(n)
        seen.append(n)
    assert seen == due
