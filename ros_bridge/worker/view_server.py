"""The web view's server: viser's, with what a view of a fleet must never do taken out.

A view shows the whole fleet to whoever connects to its websocket. Two things viser allows
would hand that to strangers:
- **Any web page** open in a browser on the machine could connect (browsers do not stop a
  page's script from opening a websocket to another origin) and read every world. The
  handshake is refused unless the request's `Origin` is the page's own: the same host and
  port as its `Host`, and that host a name a rebinding attack cannot take (an address, or
  `localhost`, or this machine's name). A client with no `Origin` (a script, not a browser
  page) is let through: it runs on a machine that can reach the port anyway.
- **A share tunnel**: one unauthenticated `ShareUrlRequest` message from any client made
  viser publish the view to the internet through its share server (and the thread waiting on
  it kept the process alive after SIGTERM). `ViewServer` never opens one: the request gets a
  log line and nothing else, whatever asks for it.

`serve(host, port)` makes the view's server with both in place.
"""

from __future__ import annotations

import contextlib
import http
import ipaddress
import logging
import socket
from collections.abc import Iterator
from typing import Any
from urllib.parse import urlsplit

import viser
import websockets.asyncio.server as ws_server

log = logging.getLogger("batchsim.view")


class ViewServer(viser.ViserServer):
    """viser's server, without its share tunnel: `request_share_url` refuses, whoever calls it
    (its handler for the page's message included)."""

    def request_share_url(self, verbose: bool = True) -> str | None:
        log.warning("batchsim view: a client asked to share the view on the internet; refused (the view never does)")
        return None

    def disconnect_share_url(self) -> None:
        return None


def serve(host: str, port: int, **kwargs: Any) -> ViewServer:
    """The view's server on `host:port`, refusing websockets from other origins (see above)."""
    with _same_origin_websockets():
        return ViewServer(host=host, port=port, **kwargs)


def _local_names() -> set[str]:
    names = {"localhost", "localhost.localdomain"}
    with contextlib.suppress(OSError):
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    return names


def same_origin(origin: str | None, host: str | None, local_names: set[str] | None = None) -> bool:
    """Whether a websocket handshake with these `Origin` and `Host` headers comes from the view's
    own page (or from no browser page at all: no `Origin`)."""
    if origin is None:
        return True
    if not host:
        return False
    try:
        netloc = urlsplit(origin).netloc.lower()
    except ValueError:
        return False
    if netloc != host.strip().lower():
        return False
    name = urlsplit(f"//{netloc}").hostname or ""
    try:
        ipaddress.ip_address(name)
        return True  # an address cannot be rebound to another site
    except ValueError:
        return name in (local_names if local_names is not None else _local_names())


@contextlib.contextmanager
def _same_origin_websockets() -> Iterator[None]:
    """While viser starts its server (it calls `websockets.asyncio.server.serve` once, before its
    constructor returns), every websocket handshake goes through `same_origin` first."""
    original = ws_server.serve
    names = _local_names()

    def guarded(*args: Any, process_request: Any = None, **kwargs: Any) -> Any:
        def check(connection: Any, request: Any) -> Any:
            headers = request.headers
            if headers.get("Upgrade", "").lower() == "websocket" and not same_origin(
                headers.get("Origin"), headers.get("Host"), names
            ):
                log.warning("batchsim view: refused a websocket from origin %s", headers.get("Origin"))
                return connection.respond(http.HTTPStatus.FORBIDDEN, "batchsim view: other origins are refused\n")
            return process_request(connection, request) if process_request is not None else None

        return original(*args, process_request=check, **kwargs)

    ws_server.serve = guarded
    try:
        yield
    finally:
        ws_server.serve = original
