"""``autotune tune``'s progress where stderr is not a terminal."""

from __future__ import annotations

from services.autotuner.commands.tune import QuietProgress
from shared.messages import TuneProgress


def test_progress_goes_to_a_file_as_lines_of_their_own(capsys):
    """A long run piped to a file said nothing for ten minutes (a level's step test on the
    realtime clock): off a terminal the last progress is a line of its own every
    QUIET_PROGRESS s (``say``), nothing before the first progress, and nothing rewritten."""
    shown = QuietProgress()
    shown.say()
    assert capsys.readouterr().err == ""
    shown.line(TuneProgress(run_id="r1", loop="hx1", t=812.5, phase="verify", message="Kc 5"))
    assert capsys.readouterr().err == ""  # a file is not rewritten in place
    shown.say()
    err = capsys.readouterr().err
    assert err.startswith("  verify     t =    812.5 s") and err.endswith(
        " s of wall time so far)\n"
    ), err
    assert "(the last progress; " in err
    assert "\r" not in err
