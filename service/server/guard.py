"""Requests the service refuses before any route sees them: foreign Host headers, foreign WebSocket origins,
oversized bodies.

A page on another site can make a browser send requests to 127.0.0.1 under the site's own name (DNS
rebinding): the Host header then names that site, so only the names the service is bound as (setting
``allowed_hosts``) are accepted. A browser's WebSocket carries the page's Origin: only the service's own
origin (the Host it was reached by) and ``allowed_origins`` may connect. Non-browser clients send no
Origin and are let through. A plain ASGI middleware, so that the frame path pays no per-request wrapper.
"""

from __future__ import annotations

import ipaddress
import json
import socket
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import urlsplit

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
ASGIApp = Callable[[Scope, Receive, Send], Awaitable[None]]

#: Largest request body accepted, bytes (the only body is PUT /api/v1/config's few fields).
MAX_BODY = 64 * 1024
LOOPBACK_NAMES = ("localhost", "127.0.0.1", "::1")


def default_hosts(bind: str) -> list[str]:
    """The Host names a service bound to ``bind`` answers to: loopback names on loopback, the machine's name
    and the address beside it (no DNS lookup: an edge PC may have no resolver); every name ("*") when bound
    to all interfaces."""
    try:
        address = ipaddress.ip_address(bind)
    except ValueError:
        address = None
    if bind == "localhost" or (address is not None and address.is_loopback):
        return [*LOOPBACK_NAMES, bind]
    if address is not None and address.is_unspecified:
        return ["*"]
    return [bind, *LOOPBACK_NAMES, socket.gethostname()]


def host_name(value: str) -> str:
    """The name in a Host header value: port and IPv6 brackets removed, lower case."""
    value = value.strip().lower()
    if value.startswith("["):
        return value[1:].split("]", 1)[0]
    return value.rsplit(":", 1)[0] if value.count(":") == 1 else value


class Guard:
    """Wraps the app: refuses a Host outside ``hosts``, a WebSocket Origin that is neither the service's own nor
    in ``origins``, and a body over :data:`MAX_BODY`."""

    def __init__(self, app: ASGIApp, hosts: list[str], origins: list[str]) -> None:
        self.app = app
        self.any_host = "*" in hosts
        self.hosts = {h.lower() for h in hosts}
        self.origins = {o.lower().rstrip("/") for o in origins}

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] not in ("http", "websocket"):
            return await self.app(scope, receive, send)
        headers = {k.decode("latin-1"): v.decode("latin-1") for k, v in scope["headers"]}
        host = headers.get("host", "")
        problem = None
        if not self.any_host and host_name(host) not in self.hosts:
            problem = (400, f"host {host!r} is not one this service answers to (setting allowed_hosts)")
        elif scope["type"] == "websocket" and not self._origin_allowed(headers.get("origin"), host):
            problem = (403, f"origin {headers.get('origin')!r} may not open the WebSocket (setting allowed_origins)")
        elif scope["type"] == "http" and _too_long(headers.get("content-length")):
            problem = (413, f"request body over {MAX_BODY} bytes")
        elif (
            scope["type"] == "http" and "content-length" not in headers and scope["method"] in ("POST", "PUT", "PATCH")
        ):
            receive = await _bounded_body(receive)  # chunked: read up to the limit before the app sees it
            if receive is None:
                problem = (413, f"request body over {MAX_BODY} bytes")
        if problem is None:
            return await self.app(scope, receive, send)
        status, detail = problem
        if scope["type"] == "websocket":  # refused at the handshake: HTTP 403
            await send({"type": "websocket.close", "code": 1008, "reason": detail[:120]})
            return
        body = json.dumps({"detail": detail}).encode()
        await send(
            {
                "type": "http.response.start",
                "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode())],
            }
        )
        await send({"type": "http.response.body", "body": body})

    def _origin_allowed(self, origin: str | None, host: str) -> bool:
        if origin is None:
            return True  # not a browser
        origin = origin.lower().rstrip("/")
        return origin in self.origins or urlsplit(origin).netloc == host.lower()


async def _bounded_body(receive: Receive) -> Receive | None:
    """A body of unknown length read in full while it stays within :data:`MAX_BODY`; a receive that hands it
    over again, or None when it is longer."""
    messages: list[Message] = []
    size, more = 0, True
    while more:
        message = await receive()
        messages.append(message)
        if message["type"] != "http.request":
            break
        size += len(message.get("body", b""))
        if size > MAX_BODY:
            return None
        more = message.get("more_body", False)

    async def replay() -> Message:
        return messages.pop(0) if messages else await receive()

    return replay


def _too_long(length: str | None) -> bool:
    try:
        return length is not None and int(length) > MAX_BODY
    except ValueError:
        return True
