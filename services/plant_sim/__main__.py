"""``python -m services.plant_sim``: the same as ``autotune plant``."""

import sys

from services.plant_sim.service import main

sys.exit(main())
