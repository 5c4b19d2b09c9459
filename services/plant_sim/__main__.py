"""``python -m services.plant_sim``: the same as ``autotune plant``, flags checked the same way
(a bad one is one line on stderr and exit code 2, before anything starts)."""

import argparse
import sys

from services.plant_sim.service import add_arguments, main
from shared.cli import check_flags
from shared.errors import ConfigError


def flags_problem(argv: list[str]) -> str | None:
    """Why the flags cannot run a plant (the bounds ``autotune plant`` holds them to), else
    None; what argparse itself refuses is left to the service's own parser to say."""
    parser = argparse.ArgumentParser(add_help=False, exit_on_error=False)
    add_arguments(parser)
    try:
        args, _ = parser.parse_known_args(argv)
        check_flags("plant", args)
    except argparse.ArgumentError:
        return None
    except ConfigError as err:
        return str(err)
    return None


problem = flags_problem(sys.argv[1:])
if problem:
    print(f"plant_sim: error: {problem}", file=sys.stderr)
    sys.exit(2)
sys.exit(main())
