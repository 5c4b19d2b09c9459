"""``python -m services.logger``: the same as ``autotune logger``."""

import sys

from services.cli import entry

entry(["logger", *sys.argv[1:]])
