"""shared/keys.py: every builder read back by its parser, and malformed keys refused."""

from __future__ import annotations

import pytest
import zenoh

from shared import keys

PREFIXES = ["autotune", "site-3/line_1.a", "a/b/c"]
LOOPS = ["hx1", "lvl_2", "x.y-z", "_0"]


@pytest.mark.parametrize("prefix", PREFIXES)
@pytest.mark.parametrize("loop", LOOPS)
def test_loop_keys_round_trip(prefix: str, loop: str) -> None:
    for build, leaf in (
        (keys.pv, "pv"),
        (keys.pv_batch, "pv_batch"),
        (keys.status, "status"),
        (keys.info, "info"),
        (keys.loop_alive, "alive"),
    ):
        key = build(prefix, loop)
        assert key == f"{prefix}/plant/{loop}/{leaf}"
        assert keys.parse_loop_key(prefix, key) == (loop, leaf)
        assert keys.split_loop_key(prefix, key) == (loop, [leaf])
        assert keys.parse_tune_key(prefix, key) is None
        assert keys.parse_command(prefix, key) is None


@pytest.mark.parametrize("prefix", PREFIXES)
@pytest.mark.parametrize("loop", LOOPS)
@pytest.mark.parametrize("user", [None, "tuner", "op.1"])
def test_command_keys_round_trip(prefix: str, loop: str, user: str | None) -> None:
    for kind in ("advance", "mode", "setpoint", "lease", "sync"):
        key = keys.command(prefix, loop, kind, user)
        assert key == f"{prefix}/plant/{loop}/cmd/{kind}" + ("" if user is None else f"/{user}")
        assert keys.parse_command(prefix, key) == (loop, kind, user)
        tail = ["cmd", kind] + ([] if user is None else [user])
        assert keys.split_loop_key(prefix, key) == (loop, tail)
        assert keys.parse_loop_key(prefix, key) is None  # a command is not a loop's leaf


@pytest.mark.parametrize("prefix", PREFIXES)
@pytest.mark.parametrize("loop", LOOPS)
def test_tune_keys_round_trip(prefix: str, loop: str) -> None:
    for build, leaf in (
        (keys.tune_progress, "progress"),
        (keys.tune_event, "event"),
        (keys.tune_result, "result"),
        (keys.tune_cancel, "cancel"),
        (keys.tune_running, "running"),
    ):
        key = build(prefix, loop)
        assert key == f"{prefix}/tune/{loop}/{leaf}"
        assert keys.parse_tune_key(prefix, key) == (loop, leaf)
        assert keys.parse_loop_key(prefix, key) is None
        assert keys.split_loop_key(prefix, key) is None


@pytest.mark.parametrize("prefix", PREFIXES)
def test_service_keys_round_trip(prefix: str) -> None:
    cases = [
        ("plant_sim", keys.service_status(prefix, "plant_sim", "p1"), "status", "p1"),
        ("plant_sim", keys.service_alive(prefix, "plant_sim", "p1"), "alive", "p1"),
        ("tuner", keys.tuner_request(prefix, "t-2"), "tune", "t-2"),
        ("tuner", keys.tuner_alive(prefix, "t-2"), "alive", "t-2"),
        ("logger", keys.logger_status(prefix, "log.3"), "status", "log.3"),
        ("logger", keys.logger_alive(prefix, "log.3"), "alive", "log.3"),
    ]
    for service, key, leaf, node in cases:
        assert key == f"{prefix}/{service}/{node}/{leaf}"
        assert keys.service_node(prefix, service, key) == node
        other = "logger" if service != "logger" else "tuner"
        assert keys.service_node(prefix, other, key) is None


@pytest.mark.parametrize(
    "key",
    [
        "autotune/plant/hx1",  # no leaf
        "autotune/plant/hx1/",  # an empty leaf
        "autotune/plant//pv",  # an empty loop
        "autotune/plant/hx1/pv/extra",
        "autotune/plant/hx1/cmd/mode",  # a command: parse_command's
        "autotune2/plant/hx1/pv",  # another prefix that starts alike
        "other/autotune/plant/hx1/pv",
        "autotune/tune/hx1/pv",
        "autotune/plant",
        "",
    ],
)
def test_parse_loop_key_refuses(key: str) -> None:
    assert keys.parse_loop_key("autotune", key) is None


@pytest.mark.parametrize(
    "key",
    [
        "autotune/tune/hx1",
        "autotune/tune/hx1/",
        "autotune/tune//result",
        "autotune/tune/hx1/result/more",
        "autotune/tuner/t1/tune",
        "autotunex/tune/hx1/result",
        "autotune/plant/hx1/status",
        "autotune/tune",
        "",
    ],
)
def test_parse_tune_key_refuses(key: str) -> None:
    assert keys.parse_tune_key("autotune", key) is None


@pytest.mark.parametrize(
    "key",
    [
        "autotune/plant/hx1/cmd",  # no kind
        "autotune/plant/hx1/cmd/",  # an empty kind
        "autotune/plant/hx1/cmd/mode/",  # an empty user
        "autotune/plant/hx1/cmd/mode/u/extra",
        "autotune/plant/hx1/pv",
        "autotune/plant//cmd/mode",
        "autotune/plant/hx1/command/mode",
        "autotune2/plant/hx1/cmd/mode",
        "autotune/tune/hx1/cmd/mode",
    ],
)
def test_parse_command_refuses(key: str) -> None:
    assert keys.parse_command("autotune", key) is None


@pytest.mark.parametrize(
    "key", ["autotune/plant", "autotune/plant/", "autotune/plant//pv", "autotune/tune/x/pv"]
)
def test_split_loop_key_refuses(key: str) -> None:
    assert keys.split_loop_key("autotune", key) is None


@pytest.mark.parametrize(
    "key", ["autotune/tuner/", "autotune/tuner//tune", "autotune/logger/l/status", "tuner/t/x"]
)
def test_service_node_refuses(key: str) -> None:
    assert keys.service_node("autotune", "tuner", key) is None


def test_candidate_prefixes_of_each_kind_of_key() -> None:
    assert keys.candidate_prefixes(keys.pv("a/b", "hx1")) == ["a/b"]
    assert keys.candidate_prefixes(keys.tune_result("site", "lvl1")) == ["site"]
    # a prefix whose chunks are themselves "plant" or "tune": every reading, shortest first
    assert keys.candidate_prefixes("x/tune/plant/l/pv") == ["x", "x/tune"]
    # a loop or user named like a chunk: a candidate too (the caller checks each reading)
    cmd = keys.command("p", "plant", "mode", "tune")
    assert keys.candidate_prefixes(cmd) == ["p", "p/plant", "p/plant/plant/cmd/mode"]
    assert [c for c in keys.candidate_prefixes(cmd) if keys.parse_command(c, cmd)] == ["p"]
    assert keys.candidate_prefixes("plant/x/pv") == []  # no chunk before: no prefix
    assert keys.candidate_prefixes("a/b/c") == []


def test_reprefix_moves_a_key_and_refuses_one_not_under_the_old_prefix() -> None:
    key = keys.command("old/site", "hx1", "mode", "u")
    assert keys.reprefix(key, "old/site", "new") == keys.command("new", "hx1", "mode", "u")
    assert keys.reprefix(keys.tune_event("a", "x"), "a", "b/c") == keys.tune_event("b/c", "x")
    for bad in ("old/sitex/plant/hx1/pv", "new/plant/hx1/pv", "old/site"):
        with pytest.raises(ValueError, match="not under the prefix 'old/site'"):
            keys.reprefix(bad, "old/site", "new")


@pytest.mark.parametrize("value", ["hx1", "a.b-c_d", "_x", "0"])
def test_check_id_accepts(value: str) -> None:
    assert keys.check_id(value, "node") == value


@pytest.mark.parametrize("value", ["", "-x", ".x", "a/b", "a*", "a b", "$x", "é", 7])
def test_check_id_refuses_naming_what(value: object) -> None:
    with pytest.raises(ValueError, match=r"^node id .* is not valid"):
        keys.check_id(value, "node")  # type: ignore[arg-type]


@pytest.mark.parametrize("value", ["autotune", "a/b", "a.b/c-d/_e"])
def test_check_prefix_accepts(value: str) -> None:
    assert keys.check_prefix(value) == value


@pytest.mark.parametrize("value", ["", "/a", "a/", "a//b", "a/*", "a/**", "a b", "a/$x", None])
def test_check_prefix_refuses(value: object) -> None:
    with pytest.raises(ValueError, match=r"^prefix .* is not valid"):
        keys.check_prefix(value)  # type: ignore[arg-type]


def test_wildcards_cover_exactly_their_keys() -> None:
    """The subscription keys match what they are meant to, and no neighbour."""

    def hits(pattern: str, key: str) -> bool:
        return zenoh.KeyExpr(pattern).intersects(zenoh.KeyExpr(key))

    p = "autotune"
    assert hits(keys.all_commands(p), keys.command(p, "hx1", "mode"))
    assert hits(keys.all_commands(p), keys.command(p, "hx1", "mode", "tuner"))
    assert not hits(keys.all_commands(p), keys.pv(p, "hx1"))
    assert hits(keys.loop_feed(p, "hx1"), keys.pv(p, "hx1"))
    assert hits(keys.loop_feed(p, "hx1"), keys.status(p, "hx1"))
    assert not hits(keys.loop_feed(p, "hx1"), keys.pv(p, "hx2"))
    assert not hits(keys.loop_feed(p, "hx1"), keys.command(p, "hx1", "mode"))
    assert hits(keys.tune_running(p, keys.ANY), keys.tune_running(p, "lvl1"))
    assert not hits(keys.tune_running(p, keys.ANY), keys.tune_result(p, "lvl1"))
    assert hits(keys.everything(p), keys.command(p, "hx1", "mode", "tuner"))
    assert hits(keys.everything(p), keys.logger_alive(p, "logger"))
    assert not hits(keys.everything(p), keys.pv("autotune2", "hx1"))
    assert hits(keys.loop_alive(p, keys.ANY), keys.loop_alive(p, "flow1"))
    assert not hits(keys.loop_alive(p, keys.ANY), keys.service_alive(p, "plant_sim", "plant"))


def test_leaf_is_the_last_chunk():
    assert keys.leaf(keys.pv("a/b", "hx1")) == "pv"
    assert keys.leaf(keys.tune_event("p", "x1")) == "event"
    assert keys.leaf("result") == "result"
