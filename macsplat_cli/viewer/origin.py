"""The viewer's WebSocket takes only its own page: a handshake whose ``Origin`` is another web site is refused.

A browser lets any page open a WebSocket to ``ws://127.0.0.1:8080``, and sends the page's origin with the handshake
(``Origin: http://evil.example``); without a check, any site the user visits while ``macsplat view`` runs could read
the scene, the cameras and the photos. Accepted origins are the viewer's own page as it can be reached: ``http://``
with the viewer's port and, as host, the ``--host`` the user chose, ``localhost``, ``127.0.0.1``, ``[::1]``, or the
address the client connected to (a page on another machine that reached ``--host 0.0.0.0`` at 192.168.1.5 has the
origin ``http://192.168.1.5:PORT``; a DNS-rebinding page has a name of its own, refused). A handshake without
``Origin`` is accepted: browsers always send it, other clients (scripts) need not.

viser (1.1) creates its server with ``websockets.asyncio.server.serve(..., process_request=...)`` in its own thread
and takes no hook; :func:`origin_checked_serve` puts the check in front of viser's ``process_request`` by replacing
that one function while viser starts (a lock, and restored at once), and says whether viser called it, so that a
viser which starts otherwise is refused rather than served unchecked.
"""

from __future__ import annotations

import contextlib
import http
import ipaddress
import logging
import threading
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any
from urllib.parse import urlsplit

__all__ = ["OriginGuard", "origin_allowed", "origin_checked_serve"]

logger = logging.getLogger(__name__)

MAX_LOGGED_ORIGINS = 32
"""Refused origins logged, each once: a page may retry for ever, the log stays short."""
SHOWN_ORIGIN_CHARS = 100
"""An origin in a log line is cut to this many characters (a client writes the header it likes)."""
LOCAL_NAMES = ("localhost", "127.0.0.1", "::1")
"""The spellings of this machine's loopback that a page served on loopback may have."""

_PATCH_LOCK = threading.Lock()


def _host_key(host: str) -> str:
    """``host`` as compared: lower case, no brackets, an IPv4-mapped IPv6 address as its IPv4 form."""
    host = host.strip().strip("[]").lower()
    try:
        ip = ipaddress.ip_address(host)
    except ValueError:
        return host
    mapped = getattr(ip, "ipv4_mapped", None)
    return str(mapped or ip)


def origin_allowed(origin: str | None, host: str, local_address: tuple[Any, ...]) -> bool:
    """True when a handshake with the ``Origin`` header ``origin`` (None: no header) may open the viewer's WebSocket.

    Args:
        origin: the header's value, as the client sent it.
        host: the address the viewer serves on (``--host``).
        local_address: the connection's own end, ``(address, port, ...)``: the port the viewer serves and the
            address the client reached it at.
    """
    if origin is None:
        return True
    try:
        parts = urlsplit(origin.strip())
        port = parts.port or 80
    except ValueError:
        return False
    if parts.scheme != "http" or not parts.hostname or parts.path not in ("", "/"):
        return False
    allowed = {_host_key(h) for h in (host, str(local_address[0]), *LOCAL_NAMES)}
    return port == int(local_address[1]) and _host_key(parts.hostname) in allowed


@dataclass
class OriginGuard:
    """What :func:`origin_checked_serve` did: whether viser's server was created through it, and the origins it
    refused so far (the first :data:`MAX_LOGGED_ORIGINS`)."""

    host: str
    installed: bool = False
    refused: list[str] = field(default_factory=list)

    def check(self, connection: Any, request: Any) -> Any:
        """websockets' ``process_request`` step: None to go on, or the 403 response that refuses a WebSocket
        handshake from another origin (before any message is sent)."""
        headers = request.headers
        upgrade = "websocket" in str(headers.get("Upgrade", "")).lower() or "Sec-WebSocket-Key" in headers
        origins = headers.get_all("Origin")
        origin = origins[0] if len(origins) == 1 else (None if not origins else "")  # two headers: refused
        if origin is None or not upgrade or origin_allowed(origin, self.host, connection.local_address):
            return None
        shown = origin[:SHOWN_ORIGIN_CHARS] + ("…" if len(origin) > SHOWN_ORIGIN_CHARS else "")
        if shown not in self.refused and len(self.refused) < MAX_LOGGED_ORIGINS:
            self.refused.append(shown)
            logger.warning("viewer: refused a connection from the web page at %r (not this viewer's page)", shown)
        return connection.respond(http.HTTPStatus.FORBIDDEN, "this viewer serves its own page only\n")

    def wrap(self, serve: Callable[..., Any]) -> Callable[..., Any]:
        """``serve`` (websockets' ``serve``) with :meth:`check` before the ``process_request`` it is given."""

        def checked_serve(*args: Any, process_request: Callable[..., Any] | None = None, **kwargs: Any) -> Any:
            def process(connection: Any, request: Any) -> Any:
                refusal = self.check(connection, request)
                if refusal is not None or process_request is None:
                    return refusal
                return process_request(connection, request)

            self.installed = True
            return serve(*args, process_request=process, **kwargs)

        return checked_serve


@contextlib.contextmanager
def origin_checked_serve(host: str) -> Iterator[OriginGuard]:
    """Within the block, a WebSocket server created with ``websockets.asyncio.server.serve`` (viser's, started in
    the block) checks the ``Origin`` of every handshake (:class:`OriginGuard`); restored on the way out."""
    import websockets.asyncio.server as ws_server

    guard = OriginGuard(host)
    with _PATCH_LOCK:
        original = ws_server.serve
        # the patch itself: mypy types a module's function as fixed
        ws_server.serve = guard.wrap(original)  # type: ignore[assignment,misc]
        try:
            yield guard
        finally:
            ws_server.serve = original  # type: ignore[misc]
