"""The web view's server (ros_bridge/worker/view_server.py): a websocket from another origin is
refused at the handshake, and no client can make it open viser's share tunnel (issue 47's review:
any web page open on the machine could read the fleet, and one message published the view).

Real viser and websockets, on a free local port; no ROS.
"""

from __future__ import annotations

import asyncio
import socket
import time

import pytest
from conftest import need

viser = need("viser")
msgpack = need("msgspec.msgpack")
import websockets.asyncio.client as ws_client  # noqa: E402
import websockets.exceptions  # noqa: E402

from ros_bridge.worker import view_server  # noqa: E402
from ros_bridge.worker.view_server import same_origin  # noqa: E402


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_same_origin_takes_the_pages_own_origin_only():
    names = {"localhost", "robolab"}
    assert same_origin(None, "127.0.0.1:8080", names)  # no browser page: a script
    assert same_origin("http://127.0.0.1:8080", "127.0.0.1:8080", names)
    assert same_origin("http://LOCALHOST:8080", "localhost:8080", names)
    assert same_origin("http://[::1]:8080", "[::1]:8080", names)
    assert same_origin("http://robolab:8080", "robolab:8080", names)  # this machine's name, from another
    assert not same_origin("https://evil.example", "127.0.0.1:8080", names)  # another site's page
    assert not same_origin("http://127.0.0.1:9999", "127.0.0.1:8080", names)  # another port: another origin
    assert not same_origin("null", "127.0.0.1:8080", names)  # a sandboxed frame or a file:// page
    assert not same_origin("http://evil.example:8080", "evil.example:8080", names)  # DNS rebinding
    assert not same_origin("http://127.0.0.1:8080", None, names)


async def _handshake(port: int, origin: str | None, then: bytes | None = None) -> str:
    """'accepted' or the refusal's status; `then`: a message sent once accepted."""
    headers = {"Origin": origin} if origin else None
    try:
        async with ws_client.connect(
            f"ws://127.0.0.1:{port}", origin=origin, additional_headers=None if origin else headers,
            subprotocols=[f"viser-v{viser.__version__}"], open_timeout=10,
        ) as connection:  # fmt: skip
            if then is not None:
                await connection.send(then)
                await asyncio.sleep(1.0)
            return "accepted"
    except websockets.exceptions.InvalidStatus as e:
        return str(e.response.status_code)


@pytest.fixture
def server():
    port = _free_port()
    s = view_server.serve("127.0.0.1", port, verbose=False)
    try:
        yield s, port
    finally:
        s.stop()


def test_a_websocket_from_another_origin_is_refused_and_the_pages_own_accepted(server):
    _, port = server
    assert asyncio.run(_handshake(port, "https://evil.example")) == "403"
    assert asyncio.run(_handshake(port, f"http://127.0.0.1:{port}")) == "accepted"
    assert asyncio.run(_handshake(port, None)) == "accepted"


def test_no_client_message_opens_a_share_tunnel(server, monkeypatch, caplog):
    import viser._viser

    opened = []

    class Tunnel:  # viser's share tunnel, stood in for: where it would dial out, it is recorded
        def __init__(self, *args, **kwargs):
            opened.append(args)

        def __getattr__(self, name):
            raise RuntimeError("the share tunnel was used")

    monkeypatch.setattr(viser._viser, "ViserTunnel", Tunnel)
    s, port = server
    request = msgpack.encode({"type": "ShareUrlRequest"})
    assert asyncio.run(_handshake(port, f"http://127.0.0.1:{port}", then=request)) == "accepted"
    time.sleep(0.5)
    assert opened == []
    assert s.request_share_url() is None  # nor from code
    assert opened == []
    assert "refused" in caplog.text
