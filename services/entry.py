"""The ``autotune`` console script. Ctrl-C while the product's modules load (numpy, scipy,
Zenoh: a second or more on a busy machine) ends in one line and exit 130, as it does once a
command runs (``services.cli.main``), not in a traceback through the imports."""

from __future__ import annotations

import os
import signal
import sys


def quit_while_loading(signum: int, frame: object) -> None:
    """SIGINT while the modules load and the command line is parsed: one line, exit 130 at
    once. Why a handler, not ``except KeyboardInterrupt``: a Ctrl-C that lands while
    pydantic builds a model's validator comes out as its SchemaError ("… KeyboardInterrupt"),
    and ran past that clause as a traceback, exit 1 (a fresh-clone CI run's Ctrl-C test).
    Nothing is open or sent before a command runs, so there is nothing to undo.
    ``services.cli.main`` puts Python's own handler back before the command runs."""
    os.write(sys.stderr.fileno(), b"autotune: interrupted\n")
    # at once, not through the interpreter's teardown: with modules half loaded (Zenoh's
    # native library among them) it ended, now and then, killed by SIGINT instead of 130
    os._exit(130)


def entry() -> None:
    previous = signal.signal(signal.SIGINT, quit_while_loading)
    try:
        from services import cli
    except KeyboardInterrupt:  # raised before the handler was in (or by a test)
        signal.signal(signal.SIGINT, previous)
        print("autotune: interrupted", file=sys.stderr, flush=True)
        os._exit(130)
    except BaseException:
        signal.signal(signal.SIGINT, previous)
        raise
    cli.entry()
