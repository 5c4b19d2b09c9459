"""``python -m services.logger``: the same as ``autotune logger``."""

import sys

from services.cli import main

sys.exit(main(["logger", *sys.argv[1:]]))
