"""``autotune up``'s settings: where it listens when nothing says."""

from __future__ import annotations

import argparse

import pytest

from services import up
from shared.errors import ConfigError
from shared.session import RENDEZVOUS, RENDEZVOUS_ENV


def _config(*argv: str) -> up.UpConfig:
    parser = argparse.ArgumentParser()
    up.add_arguments(parser)
    return up.load_config(parser.parse_args(list(argv)))


def test_up_listens_on_the_rendezvous_the_commands_meet_on(monkeypatch):
    """With AUTOTUNE_RENDEZVOUS set in the shell, `up` stayed on 7447 and the next `autotune
    tune` in that shell met on the moved point: "no autotuner answered … reached no peer or
    router at all" (user trial). `up` listens where the commands meet, unless told."""
    monkeypatch.delenv(RENDEZVOUS_ENV, raising=False)
    assert _config().endpoint == RENDEZVOUS
    monkeypatch.setenv(RENDEZVOUS_ENV, "tcp/127.0.0.1:17947")
    assert _config().endpoint == "tcp/127.0.0.1:17947"
    assert _config("--endpoint", "tcp/127.0.0.1:17000").endpoint == "tcp/127.0.0.1:17000"
    monkeypatch.setenv(RENDEZVOUS_ENV, "tcp/127.0.0.1:99999")
    with pytest.raises(ConfigError, match=RENDEZVOUS_ENV):
        _config()


def test_an_endpoint_given_does_not_read_the_rendezvous(monkeypatch):
    """`--endpoint` says where: the environment's rendezvous is not read, and a malformed one
    does not refuse it (it did: the default was worked out, and checked, either way), as every
    other command with `-e` ignores it."""
    monkeypatch.setenv(RENDEZVOUS_ENV, "garbage")
    assert _config("--endpoint", "tcp/127.0.0.1:17000").endpoint == "tcp/127.0.0.1:17000"
