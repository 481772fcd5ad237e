"""Who may talk to the dashboard: requests for its own names only, and beyond loopback only with its token.

DNS rebinding: a web page from `evil.example`, whose name is then rebound to 127.0.0.1, reaches the dashboard
with `Host: evil.example:8998` (and `Origin: http://evil.example:8998` on its WebSocket). So every request's
`Host` must be one of the dashboard's names (127.0.0.1, localhost, [::1], what `dashboard.host` names; for a
wildcard bind also this machine's host names and any IP literal, which no rebinding can produce) or it gets 421,
and an `Origin`, when sent, must name one of them too or it gets 403, HTTP and WebSocket alike.

A dashboard that listens beyond loopback also needs its token: the URL the console prints carries `?token=...`;
the page's first request sets it as a strict same-site cookie, which the page's later requests (static files,
state, WebSocket) carry. A request with neither gets 403.
"""

from __future__ import annotations

import hmac
import ipaddress
import secrets
import socket
from collections.abc import Awaitable, Callable
from urllib.parse import urlsplit

from aiohttp import web

LOOPBACK_HOSTS = frozenset({"127.0.0.1", "localhost", "::1"})
WILDCARD_HOSTS = frozenset({"0.0.0.0", "::", ""})
TOKEN_PARAM = "token"
TOKEN_COOKIE = "ecas_dashboard_token"

Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]


def new_token() -> str:
    return secrets.token_urlsafe(18)


def served_names(host: str) -> frozenset[str]:
    """The host names (lower case, IPv6 without brackets) a request may address the dashboard by."""
    names = set(LOOPBACK_HOSTS)
    if host in WILDCARD_HOSTS:
        names |= {socket.gethostname().lower(), socket.getfqdn().lower()}
    else:
        names.add(host.strip("[]").lower())
    return frozenset(names)


def _hostname(netloc: str) -> str | None:
    """'Host: a.b:8998' -> 'a.b'; '[::1]:8998' -> '::1'; None when malformed."""
    try:
        return urlsplit(f"//{netloc}").hostname
    except ValueError:
        return None


def name_allowed(name: str | None, names: frozenset[str], wildcard: bool) -> bool:
    if not name:
        return False
    if name.lower() in names:
        return True
    if not wildcard:
        return False
    try:
        ipaddress.ip_address(name)
    except ValueError:
        return False
    return True


def access_middleware(host: str, token: str | None) -> Callable:
    """aiohttp middleware refusing requests for other names (421), from other sites (403) or without the token
    (403, only when `token` is set)."""
    names, wildcard = served_names(host), host in WILDCARD_HOSTS

    @web.middleware
    async def check(request: web.Request, handler: Handler) -> web.StreamResponse:
        if not name_allowed(_hostname(request.headers.get("Host", "")), names, wildcard):
            return web.Response(status=421, text="the dashboard answers only its own names\n")
        origin = request.headers.get("Origin")
        if origin is not None and not name_allowed(_hostname(urlsplit(origin).netloc), names, wildcard):
            return web.Response(status=403, text="the dashboard accepts requests from its own page only\n")
        if token is None:
            return await handler(request)
        offered = request.query.get(TOKEN_PARAM) or request.cookies.get(TOKEN_COOKIE) or ""
        if not hmac.compare_digest(offered.encode(), token.encode()):
            return web.Response(status=403, text="open the dashboard with the URL (and its token) the console shows\n")
        response = await handler(request)
        if TOKEN_PARAM in request.query and not response.prepared:
            response.set_cookie(TOKEN_COOKIE, token, httponly=True, samesite="Strict")
        return response

    return check
