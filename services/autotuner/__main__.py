"""``python -m services.autotuner``: the same as ``autotune tuner``."""

import sys

from services.cli import main

sys.exit(main(["tuner", *sys.argv[1:]]))
