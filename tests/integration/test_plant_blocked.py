"""A plant held up publishing to a subscriber that stopped reading (a paused logger: its
link's queue full, Zenoh's reliable publications block) hears no command meanwhile; its
watchdog does not take that for its supervisor's silence. Seen: a lockstep ramp lost its lease
while the logger was paused for 2 s (pause-logger-trial-lockstep, on a loaded machine)."""

from __future__ import annotations

import signal
import threading
import time

import pytest

from services.autotuner.loop_client import LoopClient
from shared.messages import LeaseCommand, ModeCommand, OutputCommand
from shared.session import open_session
from tests.integration.tuning_cli import plant_toml

pytestmark = pytest.mark.integration

LEASE = 1.0  # s of wall time: the lease the client asks for
FAST = {"num": [1.0], "den": [1.0, 1.0], "delay": 0.0, "sample_time": 0.01}


def test_a_plant_blocked_by_a_paused_subscriber_keeps_its_supervisors_lease(
    start_plant, start_logger, tmp_path
):
    p = start_plant(plant_toml("x1", FAST), loops=("x1",))
    logger = start_logger(p, tmp_path / "runs")
    with (
        open_session(p.client_settings()) as s,
        LoopClient(s, p.prefix, "x1", lease_timeout=LEASE) as c,
    ):
        c.command(LeaseCommand(loop="x1", source=c.source, timeout=LEASE))
        c.command(ModeCommand(loop="x1", mode="manual", source=c.source))
        advancing: list[float] = []  # when the advance under way began
        done = threading.Event()

        def resume_once_held_up() -> None:
            """SIGCONT once an advance has waited 2 leases: well after the lease, within
            Zenoh's 5 s before it drops a link that stays blocked (and the client's own 5 s
            wait for the plant); however long the buffers took to fill on this machine."""
            while not done.wait(0.05):
                if advancing and time.monotonic() - advancing[-1] > 2 * LEASE:
                    break
            logger.send_signal(signal.SIGCONT)

        logger.send_signal(signal.SIGSTOP)
        resumer = threading.Thread(target=resume_once_held_up, daemon=True)
        resumer.start()
        try:
            started, slowest, op = time.monotonic(), 0.0, 50.0
            # advance until the logger is back: the plant's publications to it fill the
            # link's buffers, then block, and the plant hears no command meanwhile
            while resumer.is_alive() and time.monotonic() - started < 60.0:
                op = 100.0 - op
                c.send(OutputCommand(loop="x1", op=op, source=c.source))
                advancing.append(time.monotonic())
                c.advance(1000)
                slowest = max(slowest, time.monotonic() - advancing[-1])
        finally:
            done.set()
            resumer.join()
        assert slowest >= 1.5 * LEASE, f"the plant was never held up (slowest {slowest:.2f} s)"
        st = c.sync()
        assert st.leased_by == c.source and st.reason != "watchdog", st
