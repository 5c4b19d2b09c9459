"""`autotune runs` tells a run a logger is still writing from a broken file."""

from __future__ import annotations

from pathlib import Path

import pytest

from services.logger.commands.runs import summarize
from services.logger.mcap_io import MAGIC, being_written, read_run
from shared.errors import AutotuneError


def test_a_footerless_file_held_open_is_recording_and_unreadable_once_closed(tmp_path: Path):
    path = tmp_path / "20261202T061216Z_hx1_relay_c57d84e83047.mcap"
    f = path.open("wb")
    f.write(MAGIC + b"\x01\x02\x03")  # a header started, no footer yet
    f.flush()
    try:
        assert being_written(path)
        row = summarize(path)
        assert row["status"] == "recording", row
        assert (row["loop"], row["method"], row["started"]) == ("hx1", "relay", "20261202T061216Z")
        # analyze, report, replay: a run in progress, not "try recover" (noticed last stop)
        with pytest.raises(AutotuneError, match=r"still being recorded .* wait for the run"):
            read_run(path)
    finally:
        f.close()
    assert not being_written(path)  # nobody has it open: a logger killed mid-run
    assert summarize(path)["status"] == "unreadable"
    with pytest.raises(AutotuneError, match="try: autotune recover"):
        read_run(path)


def test_a_finished_file_is_never_recording(tmp_path: Path):
    path = tmp_path / "x.mcap"
    with path.open("wb") as f:
        f.write(MAGIC + b"body" + MAGIC)
        f.flush()
        assert not being_written(path)  # ends with the magic: finished, open or not
