"""`robonav view` beyond loopback: the page and its websocket only for a browser with the token.

A real view (viser, fed by a Zenoh session on loopback) served on 0.0.0.0 behind its token gate,
asked with plain HTTP and a websocket handshake over real sockets.
"""

from __future__ import annotations

import http.client
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path
from urllib.parse import urlsplit

import pytest

pytest.importorskip("viser", reason="the `view` extra (viser) is not installed")

from robonav.services.common import open_session  # noqa: E402
from robonav.services.config import ZenohConfig, load_config  # noqa: E402
from robonav.services.view.app import ViewNode, ViewOptions  # noqa: E402
from robonav.services.view.gate import is_loopback  # noqa: E402

from ..conftest import free_port  # noqa: E402

TOKEN = "a-token-for-the-test"


@pytest.fixture
def gated_view() -> Iterator[ViewNode]:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))), \
            open_session(ZenohConfig(mode="client", connect=(endpoint,))) as session:
        node = ViewNode(load_config(), session, ViewOptions(host="0.0.0.0", port=0, token=TOKEN))
        try:
            yield node
        finally:
            node.close()


def get(port: int, path: str, cookie: str | None = None) -> http.client.HTTPResponse:
    connection = http.client.HTTPConnection("127.0.0.1", port, timeout=10)
    connection.request("GET", path, headers={"Cookie": cookie} if cookie else {})
    response = connection.getresponse()
    response.read()
    connection.close()
    return response


def websocket_status(port: int, cookie: str | None) -> str:
    """The status line of a websocket handshake with viser's subprotocol."""
    request = ("GET / HTTP/1.1\r\nHost: 127.0.0.1\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
               "Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
               "Sec-WebSocket-Protocol: viser-v1.1.1\r\n" + (f"Cookie: {cookie}\r\n" if cookie else "") + "\r\n")
    with socket.create_connection(("127.0.0.1", port), timeout=10) as s:
        s.sendall(request.encode())
        return s.recv(4096).split(b"\r\n", 1)[0].decode()


def test_the_page_and_its_websocket_need_the_token(gated_view: ViewNode) -> None:
    port = gated_view.port
    assert gated_view.url == f"http://127.0.0.1:{port}/?token={TOKEN}"
    # viser itself listens on loopback only, on a port of its own.
    assert int(gated_view.server.get_port()) != port
    for path in ("/", "/index.html", "/?token=wrong"):
        assert get(port, path).status == 401
    assert websocket_status(port, None).startswith("HTTP/1.1 401")
    assert websocket_status(port, "robonav_view_1=nope").startswith("HTTP/1.1 401")
    # The token in the address is traded for a cookie, and dropped from the address.
    welcome = get(port, f"/?fixedDpr=1&token={TOKEN}")
    assert welcome.status == 303 and welcome.getheader("Location") == "/?fixedDpr=1"
    cookie = welcome.getheader("Set-Cookie").split(";")[0]
    assert "HttpOnly" in welcome.getheader("Set-Cookie")
    page = get(port, "/", cookie)
    assert page.status == 200 and "text/html" in page.getheader("Content-Type")
    assert websocket_status(port, cookie) == "HTTP/1.1 101 Switching Protocols"
    assert gated_view.gate is not None and gated_view.gate.denied == 5


def test_beyond_loopback_a_view_without_a_token_is_refused() -> None:
    assert is_loopback("127.0.0.1") and is_loopback("localhost") and is_loopback("::1")
    assert not is_loopback("0.0.0.0") and not is_loopback("192.168.1.20")
    with pytest.raises(ValueError, match="anyone who reaches it"):
        ViewOptions(host="0.0.0.0")
    assert ViewOptions().host == "127.0.0.1" and ViewOptions().token is None


def test_the_command_prints_the_address_with_a_new_token(tmp_path: Path) -> None:
    """`robonav view --host 0.0.0.0` makes up a token and prints the address that carries it."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    config = tmp_path / "view.yaml"
    config.write_text(f"zenoh: {{connect: ['{endpoint}']}}\n", encoding="utf-8")
    with open_session(ZenohConfig(mode="router", listen=(endpoint,))):
        proc = subprocess.Popen([sys.executable, "-m", "robonav.services.cli", "view", "--host", "0.0.0.0", "--port", "0",
                                 "--config", str(config), "--log-level", "WARNING"],
                                stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
        try:
            assert proc.stdout is not None
            line = ""
            while not line.startswith("view: ") and (more := proc.stdout.readline()):  # viser prints a banner
                line = more
        finally:
            proc.terminate()
            proc.communicate(timeout=30)
    assert line.startswith("view: http://127.0.0.1:") and "/?token=" in line, line
    address = urlsplit(line.split(" ", 1)[1].strip())
    assert address.port and address.port > 0 and len(address.query.removeprefix("token=")) >= 32
