"""Who a session is on the bus: the Zenoh user its configuration authenticates as.

A secure deployment (``autotune up --secure``, deploy/zenoh/) gives each role a user and a
password, and the router's access control lets each user put commands only on keys ending in
its own name (``<prefix>/plant/<loop>/cmd/<kind>/<user>``): the last chunk of a command's key
is then an identity the router has verified, unlike a message's free-text ``source``.
"""

from __future__ import annotations

import json

from shared.session import ZenohSettings, zenoh_config

_USER_KEY = "transport/auth/usrpwd/user"


def auth_user(settings: ZenohSettings) -> str | None:
    """The user the session's config authenticates as, or None (no credentials: open bus)."""
    try:
        raw = zenoh_config(settings).get_json(_USER_KEY)
    except Exception:  # no such key, or a config that will fail to open anyway
        return None
    user = json.loads(raw) if raw else None
    return user if isinstance(user, str) and user else None
