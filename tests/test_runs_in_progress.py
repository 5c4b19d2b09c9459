"""`autotune runs` tells a run a logger is still writing from a broken file."""

from __future__ import annotations

from pathlib import Path

from services.logger.commands.runs import being_written, summarize
from services.logger.mcap_io import MAGIC


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
    finally:
        f.close()
    assert not being_written(path)  # nobody has it open: a logger killed mid-run
    assert summarize(path)["status"] == "unreadable"


def test_a_finished_file_is_never_recording(tmp_path: Path):
    path = tmp_path / "x.mcap"
    with path.open("wb") as f:
        f.write(MAGIC + b"body" + MAGIC)
        f.flush()
        assert not being_written(path)  # ends with the magic: finished, open or not
