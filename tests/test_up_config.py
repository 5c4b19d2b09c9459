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


@pytest.mark.parametrize(
    ("content", "says"),
    [
        (b"\xff\xfe", "not UTF-8 text (byte 0xff at offset 0)"),
        (b'prefix = "x"\n\xe9\n', "not UTF-8 text (byte 0xe9 at offset 13)"),
        (b'prefix = "a/*"\n', "prefix 'a/*' is not valid"),
        (b"prefix = \n", "not valid TOML"),
    ],
)
def test_a_config_file_that_cannot_be_used_is_named_with_the_reason(tmp_path, content, says):
    """A file of other bytes than UTF-8 was an internal error (exit 70: helper trial), and a
    bad prefix in the file was said without naming the file."""
    path = tmp_path / "up.toml"
    path.write_bytes(content)
    with pytest.raises(ConfigError) as err:
        _config("--config", str(path))
    assert str(err.value).startswith(f"--config {path}: ") and says in str(err.value)
