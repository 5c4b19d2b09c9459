"""The console's HTTP side and flags, without the bus: the page and its assets from the
package, the runs listed, bad requests and bad flags refused in one line."""

from __future__ import annotations

import asyncio
import json
import socket

import pytest
from websockets.datastructures import Headers
from websockets.http11 import Request

from services.cli import main
from services.console.server import ASSETS, Hub, console_hosts, dumps


def get(hub: Hub, path: str):
    return asyncio.run(hub.route(None, Request(path, Headers())))


def test_the_page_and_its_assets_come_from_the_package(tmp_path):
    hub = Hub(tmp_path)
    page = get(hub, "/")
    assert page.status_code == 200 and b'src="/static/console.js"' in page.body
    assert b"http" not in page.body.replace(b"http-equiv", b"")  # nothing from elsewhere
    for name, kind in ASSETS.items():
        r = get(hub, f"/static/{name}")
        assert (r.status_code, r.headers["Content-Type"]) == (200, kind) and r.body
    assert get(hub, "/static/../command.py").status_code == 404
    assert get(hub, "/ws") is None  # the websocket's handshake goes on


@pytest.mark.parametrize(
    ("origin", "allowed"),
    [(None, True), ("http://127.0.0.1:8050", True), ("http://evil.example", False),
     ("http://127.0.0.1:9999", False), ("http://[::1", False)],
)  # fmt: skip
def test_the_websocket_is_for_the_console_s_own_page(tmp_path, origin, allowed):
    headers = Headers({"Host": "127.0.0.1:8050"})
    if origin is not None:
        headers["Origin"] = origin
    r = asyncio.run(Hub(tmp_path).route(None, Request("/ws", headers)))
    assert (r is None) == allowed and (allowed or r.status_code == 403)


def test_runs_are_listed_and_a_bad_file_name_is_refused_in_one_line(tmp_path):
    (tmp_path / "20260101T000000Z_hx1_relay_x.mcap").write_bytes(b"not mcap")
    hub = Hub(tmp_path)
    (row,) = json.loads(get(hub, "/api/runs").body)
    assert row["file"] == "20260101T000000Z_hx1_relay_x.mcap" and row["status"] == "unreadable"
    for query in ("file=../secret.mcap", "file=x.txt", "file=missing.mcap", ""):
        r = get(hub, f"/api/report.svg?{query}")
        assert r.status_code == 400 and r.body.decode().count("\n") == 1, r.body
    assert get(hub, "/api/compare?a=x.mcap").status_code == 400


def test_json_for_the_page_has_no_nan():
    assert json.loads(dumps({"a": [1.0, float("nan")], "b": float("inf")})) == {
        "a": [1.0, None],
        "b": None,
    }


@pytest.fixture
def taken_port():
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        s.listen()
        yield s.getsockname()[1]


@pytest.mark.parametrize(
    ("argv", "says"),
    [
        (["console", "--port", "70000"], "--port 70000: must be 0 to 65535"),
        (["console", "--history", "-1"], "--history -1.0: must be > 0"),
        (["console", "--prefix", "a/*"], "prefix 'a/*' is not valid"),
        (["console", "--port", "{port}"], "--port {port}: cannot serve on 127.0.0.1:{port}"),
        (["up", "--console", "--console-port", "{port}"], "--console-port {port}: 127.0.0.1"),
        (["demo", "--console", "--console-port", "0"], "--console-port 0: must be 1 to 65535"),
        # without --console it meant nothing, and was taken (helper trial)
        (["demo", "--console-port", "70000"], "--console-port 70000: only with --console"),
        (["up", "--console-port", "8051"], "--console-port 8051: only with --console"),
    ],
)
def test_bad_flags_and_a_port_in_use_exit_2_in_one_line(argv, says, taken_port, capsys):
    argv = [a.format(port=taken_port) for a in argv]
    assert main(argv) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and says.format(port=taken_port) in err, err


@pytest.mark.parametrize(
    ("host", "allowed"),
    [("127.0.0.1:8050", True), ("localhost:8050", True), ("[::1]:8050", True),
     ("10.0.0.5:8050", True), ("evil.example:8050", False), ("evil.example", False),
     ("console.plant:8050", False), ("", False), ("[::1", False), ("[x]:80", False)],
)  # fmt: skip
def test_a_page_reaching_the_console_by_another_sites_name_is_refused(tmp_path, host, allowed):
    """DNS rebinding: evil.example made to resolve to 127.0.0.1 reached the console from that
    site's page with Host and Origin both evil.example, and a cancel went through (helper
    trial). Every request must name the console by an address, localhost or the name it is
    served on; the websocket as well as the runs' data."""
    hub = Hub(tmp_path)
    for path in ("/ws", "/api/runs", "/"):
        headers = Headers({"Host": host, "Origin": f"http://{host}"})
        r = asyncio.run(hub.route(None, Request(path, headers)))
        refused = r is not None and r.status_code == 403
        assert refused != allowed, (path, host)
    served = Hub(tmp_path, console_hosts("console.plant"))  # --host console.plant
    r = asyncio.run(served.route(None, Request("/api/runs", Headers({"Host": "console.plant"}))))
    assert r.status_code == 200
