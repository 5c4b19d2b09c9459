"""Where the loggers on the bus write their runs: the hint a command that read another
``--runs`` directory (``revert``, ``apply``) adds to its one line."""

from __future__ import annotations

from pathlib import Path

import zenoh

from services.autotuner.loop_client import wait_for_token
from shared import keys, wire
from shared.messages import LoggerStatus
from shared.session import ZenohSettings, open_session


def elsewhere(session: zenoh.Session, prefix: str, runs: Path) -> str:
    """``; the logger on the bus under PREFIX writes to DIR: --runs DIR`` for each logger
    under ``prefix`` whose runs directory is not ``runs`` (empty if none answers within 2 s,
    or all write there)."""
    here = runs.resolve()
    dirs = {
        st.runs_dir
        for st in wire.query_all(session, keys.logger_status(prefix, "*"), LoggerStatus, 2.0)
        if Path(st.runs_dir).resolve() != here
    }
    return "".join(
        f"; the logger on the bus under {prefix!r} writes to {d}: --runs {d}" for d in sorted(dirs)
    )


def elsewhere_asked(settings: ZenohSettings, prefix: str, runs: Path) -> str:
    """``elsewhere`` through a session of its own (empty if no logger is seen within 5 s)."""
    try:
        with open_session(settings, 5.0) as session:
            # a logger's token seen first: the session has reached the bus before it asks
            # (a query at once, on a loaded machine, went out before it had, and none answered)
            if not wait_for_token(session, keys.logger_alive(prefix, "*"), 5.0):
                return ""
            return elsewhere(session, prefix, runs)
    except Exception:  # a hint, not the error: the line it adds to is said either way
        return ""
