"""``python -m services.plant_sim``: the same as ``autotune plant``."""

from services.plant_sim.service import main
from shared.cli import exit_now

exit_now(main())
