"""A token gate in front of the view when it is served beyond this machine.

The view's page carries Plan, Execute and Stop: whoever loads it commands the arm. viser has no
authentication, so on any interface other than loopback it listens on 127.0.0.1 only and this
gate listens where asked: a connection whose first request carries the token (`?token=` once,
then a cookie) is passed through byte for byte, HTTP and the websocket alike; anything else is
answered 401 and closed. The token is compared in constant time. There is no TLS here: use it
on a trusted network, or put a TLS proxy in front.
"""

from __future__ import annotations

import asyncio
import hmac
import ipaddress
import logging
import secrets
import threading
from urllib.parse import parse_qsl, urlencode, urlsplit

log = logging.getLogger("robonav.view")

TOKEN_ENV = "ROBONAV_VIEW_TOKEN"
"""Environment variable holding the view's token (else `--token-file`, else a fresh one is printed)."""
HEAD_LIMIT_BYTES = 64 * 1024
HEAD_TIMEOUT_S = 10.0
PORT_ATTEMPTS = 100
"""A busy port moves to the next one, as viser does."""


def is_loopback(host: str) -> bool:
    """Whether `host` only reaches this machine (then the view needs no token)."""
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host).is_loopback
    except ValueError:
        return False


def new_token() -> str:
    return secrets.token_urlsafe(24)


class TokenGate:
    """Listens on `host:port` and forwards authorized connections to `127.0.0.1:upstream_port`."""

    def __init__(self, host: str, port: int, upstream_port: int, token: str) -> None:
        if not token:
            raise ValueError("the view's token must not be empty")
        self._token = token.encode()
        self._upstream_port = upstream_port
        self._cookie = f"robonav_view_{upstream_port}"
        self._loop = asyncio.new_event_loop()
        self._server: asyncio.base_events.Server | None = None
        self.denied = 0
        """Connections refused for a missing or wrong token."""
        ready = threading.Event()
        failure: list[BaseException] = []

        def run() -> None:
            asyncio.set_event_loop(self._loop)
            try:
                self._server = self._loop.run_until_complete(self._listen(host, port))
            except BaseException as exc:  # reported to the constructor's caller
                failure.append(exc)
                ready.set()
                return
            ready.set()
            self._loop.run_forever()
            # Connections still open when the gate closes end here, in their own loop; left
            # pending, they are collected later and complain that their loop is gone.
            pending = asyncio.all_tasks(self._loop)
            for task in pending:
                task.cancel()
            self._loop.run_until_complete(asyncio.gather(*pending, return_exceptions=True))
            self._loop.close()

        self._thread = threading.Thread(target=run, name="robonav-view-gate", daemon=True)
        self._thread.start()
        ready.wait()
        if failure:
            raise failure[0]
        assert self._server is not None
        self.port = int(self._server.sockets[0].getsockname()[1])

    async def _listen(self, host: str, port: int) -> asyncio.base_events.Server:
        for attempt in range(PORT_ATTEMPTS if port else 1):
            try:
                return await asyncio.start_server(self._serve, host, port + attempt if port else 0)
            except OSError:
                if attempt == PORT_ATTEMPTS - 1:
                    raise
        raise AssertionError("unreachable")

    def _authorized(self, head: bytes) -> tuple[bool, str | None]:
        """(whether the request may pass, the redirect target when it brought the token in its URL)."""
        lines = head.decode("latin-1").split("\r\n")
        parts = lines[0].split(" ")
        if len(parts) != 3:
            return False, None
        target = urlsplit(parts[1])
        query = parse_qsl(target.query, keep_blank_values=True)
        given = [v for k, v in query if k == "token"]
        if given:
            if not hmac.compare_digest(given[-1].encode(), self._token):
                return False, None
            rest = urlencode([(k, v) for k, v in query if k != "token"])
            return True, (target.path or "/") + (f"?{rest}" if rest else "")
        for line in lines[1:]:
            name, _, value = line.partition(":")
            if name.strip().lower() != "cookie":
                continue
            for cookie in value.split(";"):
                key, _, val = cookie.strip().partition("=")
                if key == self._cookie and hmac.compare_digest(val.encode(), self._token):
                    return True, None
        return False, None

    async def _serve(self, reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
        try:
            head = await asyncio.wait_for(reader.readuntil(b"\r\n\r\n"), HEAD_TIMEOUT_S)
        except (asyncio.IncompleteReadError, asyncio.LimitOverrunError, asyncio.TimeoutError, ConnectionError):
            writer.close()
            return
        allowed, redirect = self._authorized(head)
        if not allowed:
            self.denied += 1
            body = (b"robonav view: this page commands the robot; open the address with the token that "
                    b"`robonav view` printed at start (...?token=...)\n")
            writer.write(b"HTTP/1.1 401 Unauthorized\r\nContent-Type: text/plain; charset=utf-8\r\n"
                         b"Content-Length: %d\r\nConnection: close\r\n\r\n%s" % (len(body), body))
            await _close(writer)
            return
        if redirect is not None:  # keep the token out of the address bar and the page's own requests
            token = self._token.decode()
            writer.write((f"HTTP/1.1 303 See Other\r\nLocation: {redirect}\r\n"
                          f"Set-Cookie: {self._cookie}={token}; Path=/; HttpOnly; SameSite=Strict\r\n"
                          "Content-Length: 0\r\nConnection: close\r\n\r\n").encode())
            await _close(writer)
            return
        try:
            up_reader, up_writer = await asyncio.open_connection("127.0.0.1", self._upstream_port)
        except OSError:
            writer.close()
            return
        up_writer.write(head)
        await asyncio.gather(_pump(reader, up_writer), _pump(up_reader, writer))

    def close(self) -> None:
        if self._server is not None:
            self._loop.call_soon_threadsafe(self._server.close)
        self._loop.call_soon_threadsafe(self._loop.stop)
        self._thread.join(timeout=5.0)


async def _pump(reader: asyncio.StreamReader, writer: asyncio.StreamWriter) -> None:
    try:
        while data := await reader.read(1 << 16):
            writer.write(data)
            await writer.drain()
    except ConnectionError:
        pass
    finally:
        await _close(writer)


async def _close(writer: asyncio.StreamWriter) -> None:
    try:
        await writer.drain()
        writer.close()
        await writer.wait_closed()
    except ConnectionError:
        pass
