"""``python -m services.autotuner``: the same as ``autotune tuner``."""

import sys

from services.cli import entry

entry(["tuner", *sys.argv[1:]])
