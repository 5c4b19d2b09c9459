"""A command's --timeout bounds the handshake of its session's links, not Zenoh's own 10 s: a
peer that is paused (its port accepts, its process does not answer) held `autotune loops
--timeout 2` for 11 s."""

import json

from shared.session import OPEN_TIMEOUT, ZenohSettings, zenoh_config


def _open_timeout(settings: ZenohSettings, timeout: float | None) -> int:
    return json.loads(zenoh_config(settings, timeout).get_json(OPEN_TIMEOUT))


def test_the_command_timeout_bounds_the_handshake():
    settings = ZenohSettings(connect=("tcp/127.0.0.1:7447",))
    default = _open_timeout(settings, None)
    assert default == 10_000  # Zenoh's own, left alone without a timeout
    assert _open_timeout(settings, 2.0) == 2_000
    assert _open_timeout(settings, 0.01) == 100  # a floor: a handshake takes some time
    assert _open_timeout(settings, 60.0) == default  # never longer than Zenoh's own


def test_a_handshake_timeout_the_user_set_is_kept():
    settings = ZenohSettings(connect=("tcp/127.0.0.1:7447",), cfg=(f"{OPEN_TIMEOUT}:30000",))
    assert _open_timeout(settings, 2.0) == 30_000
