"""``python -m services.plant_sim``: the same as ``autotune plant``. A Ctrl-C before it serves
(its modules and its plant file loading: scipy, Zenoh, the models) is one line and exit 130,
as for the other services, not a traceback through the imports; once it serves, its own stop
handlers (``shared.cli.install_stop_handlers``) take SIGINT over."""

import signal

from services.entry import quit_while_loading

signal.signal(signal.SIGINT, quit_while_loading)

from services.plant_sim.service import main  # noqa: E402
from shared.cli import exit_now  # noqa: E402

exit_now(main())
