"""The ``autotune`` console script. Ctrl-C while the product's modules load (numpy, scipy,
Zenoh: a second or more on a busy machine) ends in one line and exit 130, as it does once a
command runs (``services.cli.main``), not in a traceback through the imports."""

from __future__ import annotations

import os
import sys


def entry() -> None:
    try:
        from services import cli
    except KeyboardInterrupt:
        print("autotune: interrupted", file=sys.stderr, flush=True)
        # at once, not through the interpreter's teardown: with modules half loaded (Zenoh's
        # native library among them) it ended, now and then, killed by SIGINT instead of 130
        os._exit(130)
    cli.entry()
