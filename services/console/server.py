"""The console's web server: the page and its assets, the runs' reports, and the websocket.

One asyncio server (``websockets``) answers plain HTTP GETs through ``process_request`` and
upgrades ``/ws`` to the websocket the page's live data and buttons use:

    GET /                       the page (static/index.html)
    GET /static/NAME            its script and style, shipped in the package (no CDN)
    GET /api/runs               the runs directory as ``autotune runs --json`` lists it
    GET /api/report.svg?file=F  run F's report figure (``autotune report``'s) as SVG
    GET /api/compare?a=F&b=G    two runs' figures side by side (JSON)
    GET /ws                     the websocket: the bridge's messages out, requests in

The bridge works in threads; what it emits is handed to the event loop and broadcast to every
page. Every few tenths of a second the loop asks the bridge for what changed (``tick``).
"""

from __future__ import annotations

import asyncio
import contextlib
import ipaddress
import json
import logging
import socket
from collections.abc import Callable
from http import HTTPStatus
from importlib import resources
from pathlib import Path
from typing import Any
from urllib.parse import parse_qs, urlsplit

from websockets.asyncio.server import ServerConnection, broadcast
from websockets.datastructures import Headers
from websockets.exceptions import ConnectionClosed
from websockets.http11 import Request, Response

from services.console import reports
from shared import json_text
from shared.errors import AutotuneError, one_line

log = logging.getLogger("console")

TICK = 0.25  # s between two pushes of trends and faceplates
MAX_MESSAGE = 64 * 1024  # bytes a page's request may take at most
ASSETS = {  # the page's files: name → content type
    "index.html": "text/html; charset=utf-8",
    "console.js": "text/javascript; charset=utf-8",
    "console.css": "text/css; charset=utf-8",
}


def dumps(msg: Any) -> str:
    """JSON for the page: a NaN or an infinity (which JSON.parse refuses) becomes null."""
    try:
        return json.dumps(msg, allow_nan=False, separators=(",", ":"))
    except ValueError:
        return json_text.dumps(msg, separators=(",", ":"))


def asset(name: str) -> bytes | None:
    """A file of the page (``static/``), None for any other name."""
    if name not in ASSETS:
        return None
    return resources.files("services.console").joinpath("static", name).read_bytes()


def console_hosts(bind: str) -> frozenset[str]:
    """The names a page may reach this console by, besides an IP address (``host_allowed``):
    localhost, the address it is bound to, and (bound to every interface) this machine's
    name."""
    names = {"localhost", bind.lower()}
    if bind in ("0.0.0.0", "::", ""):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    return frozenset(names)


def host_allowed(headers: Headers, hosts: frozenset[str]) -> bool:
    """The request's Host names this console: an IP address, or one of ``hosts``. Against DNS
    rebinding: another site's name made to resolve to 127.0.0.1 reaches the console from that
    site's page with its own name as Host (and as Origin, which ``same_origin`` then passes:
    a cancel went through so, helper trial); a browser sends an address as Host only when
    the page was opened by that address. No Host (not a browser): allowed."""
    host = headers.get("Host")
    if host is None:
        return True
    try:  # a Host that is no host at all ("[::1") raised here: a 500, traceback in the log
        name = urlsplit(f"//{host}").hostname
    except ValueError:
        return False
    if not name:
        return False
    try:
        ipaddress.ip_address(name)
        return True
    except ValueError:
        return name.lower() in hosts


def same_origin(headers: Headers) -> bool:
    """The websocket is for the console's own page: a browser names the page's origin, which
    must be this server (another site's script in the same browser would otherwise start
    tunes through it); a client that is not a browser sends no Origin."""
    origin = headers.get("Origin")
    if origin is None:
        return True
    try:  # an Origin that is no URL ("http://[::1") raised here: a 500
        netloc = urlsplit(origin).netloc
    except ValueError:
        return False
    return netloc.lower() == (headers.get("Host") or "").lower()


def _response(status: HTTPStatus, body: bytes, content_type: str) -> Response:
    headers = Headers()
    headers["Content-Type"] = content_type
    headers["Content-Length"] = str(len(body))
    headers["Cache-Control"] = "no-store"
    return Response(status.value, status.phrase, headers, body)


def _error(status: HTTPStatus, text: str) -> Response:
    return _response(status, (text + "\n").encode(), "text/plain; charset=utf-8")


class Hub:
    """The pages connected, and what goes to them."""

    def __init__(self, runs: Path, hosts: frozenset[str] = console_hosts("127.0.0.1")):
        self.runs = runs
        self.hosts = hosts  # the names a page may reach it by (``host_allowed``)
        self.pages: set[ServerConnection] = set()
        self.loop: asyncio.AbstractEventLoop | None = None
        self.bridge: Any = None  # the Bridge, once on the bus: pages wait for it
        self.ready = asyncio.Event()

    def broadcast(self, msg: dict[str, Any]) -> None:
        if self.pages:
            broadcast(self.pages, dumps(msg))

    def emitter(self) -> Callable[[dict[str, Any]], None]:
        """A thread-safe ``emit``: the message handed to the event loop, then broadcast."""
        loop = asyncio.get_running_loop()
        self.loop = loop

        def emit(msg: dict[str, Any]) -> None:
            with contextlib.suppress(RuntimeError):  # the loop closed: the console is stopping
                loop.call_soon_threadsafe(self.broadcast, msg)

        return emit

    async def route(self, connection: ServerConnection, request: Request) -> Response | None:
        """Plain HTTP for everything but /ws (None lets the websocket handshake go on)."""
        url = urlsplit(request.path)
        query = {k: v[0] for k, v in parse_qs(url.query).items()}
        path = url.path
        if not host_allowed(request.headers, self.hosts):
            return _error(
                HTTPStatus.FORBIDDEN,
                f"Host {one_line(request.headers.get('Host'), 80)}: not this console's name "
                "(open it by its address, localhost or the name it serves on)",
            )
        if path == "/ws":
            return (
                None
                if same_origin(request.headers)
                else _error(
                    HTTPStatus.FORBIDDEN, "/ws: a page from another origin may not use the console"
                )
            )
        if path == "/favicon.ico":  # none: said so, rather than a 404 in the browser's log
            return _response(HTTPStatus.NO_CONTENT, b"", "image/x-icon")
        if path in ("/", "/index.html"):
            path = "/static/index.html"
        if path.startswith("/static/"):
            name = path.removeprefix("/static/")
            body = asset(name)
            if body is None:
                return _error(HTTPStatus.NOT_FOUND, f"{path}: no such file")
            return _response(HTTPStatus.OK, body, ASSETS[name])
        try:
            if path == "/api/runs":
                rows = await asyncio.to_thread(reports.run_rows, self.runs)
                return _response(HTTPStatus.OK, dumps(rows).encode(), "application/json")
            if path == "/api/report.svg":
                file = reports.run_file(self.runs, query.get("file", ""))
                svg = await asyncio.to_thread(reports.report_svg, file)
                return _response(HTTPStatus.OK, svg, "image/svg+xml")
            if path == "/api/compare":
                a = reports.run_file(self.runs, query.get("a", ""))
                b = reports.run_file(self.runs, query.get("b", ""))
                both = await asyncio.to_thread(reports.compare_runs, a, b)
                return _response(HTTPStatus.OK, dumps(both).encode(), "application/json")
        except AutotuneError as err:
            return _error(HTTPStatus.BAD_REQUEST, one_line(err, 500))
        return _error(HTTPStatus.NOT_FOUND, f"{path}: no such page")

    async def page(self, ws: ServerConnection) -> None:
        """One page: the picture so far, then its requests until it goes."""
        await self.ready.wait()
        self.pages.add(ws)
        try:
            for msg in self.bridge.snapshot():
                await ws.send(dumps(msg))

            def reply(msg: dict[str, Any]) -> None:  # from a worker thread, to this page only
                if self.loop is not None:
                    with contextlib.suppress(RuntimeError):
                        self.loop.call_soon_threadsafe(
                            lambda: asyncio.ensure_future(self._send(ws, msg))
                        )

            async for text in ws:
                try:
                    request = json_text.loads(text)
                    if not isinstance(request, dict):
                        raise ValueError("not a JSON object")
                except ValueError as err:
                    await ws.send(
                        dumps(
                            {"type": "action", "ok": False, "message": f"request: {one_line(err)}"}
                        )
                    )
                    continue
                self.bridge.act(request, reply)
        except ConnectionClosed:
            pass
        finally:
            self.pages.discard(ws)

    async def _send(self, ws: ServerConnection, msg: dict[str, Any]) -> None:
        with contextlib.suppress(ConnectionClosed):
            await ws.send(dumps(msg))
