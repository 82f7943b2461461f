"""Who may use the watch server (README "Watching a run", Access).

Every HTTP request and websocket upgrade must name the server in its Host header (the bound address, a loopback
name, or a name given with --allow-host, with the bound port): a page of another site whose name was made to
resolve to this host (DNS rebinding) is refused. A request that carries an Origin header (browsers send one with
every websocket upgrade and POST) must come from this same origin: another site's page cannot drive the server.
What changes the compositor needs the per-run token (`?token=` on the page's URL, or the X-Hmdrt-Token header);
a server bound beyond loopback needs it for everything but its static files. Refusals get 403 and are counted and
logged; the count is on the page.
"""

from __future__ import annotations

import hmac
import ipaddress
import logging
import secrets
from collections import Counter
from collections.abc import Awaitable, Callable, Iterable

from aiohttp import web

from hmdrt.bus.security import is_loopback

log = logging.getLogger(__name__)

TOKEN_HEADER = "X-Hmdrt-Token"
LOOPBACK_NAMES = frozenset({"localhost", "127.0.0.1", "[::1]"})
Handler = Callable[[web.Request], Awaitable[web.StreamResponse]]
REASONS = ("host", "origin", "token", "message")  # what refusals are counted by
# sent with every response: no framing (a click on shutdown from another site's frame), no referrer (the token)
HEADERS = {
    "Content-Security-Policy": "default-src 'self'; img-src 'self' blob: data:; frame-ancestors 'none'",
    "X-Frame-Options": "DENY",
    "Referrer-Policy": "no-referrer",
    "X-Content-Type-Options": "nosniff",
    "Cache-Control": "no-store",
}


def host_name(bind: str) -> str:
    """The bind address as it appears in a Host header (IPv6 in brackets), lower case."""
    try:
        address = ipaddress.ip_address(bind.strip("[]"))
    except ValueError:
        return bind.lower()
    return f"[{address}]" if address.version == 6 else str(address)


class Access:
    """Host, Origin and token checks for a server bound to `bind`, and the refusals counted by reason."""

    def __init__(self, bind: str, allow_hosts: Iterable[str] = ()):
        self.remote = not is_loopback(f"tcp://{bind}:0")
        self.names = LOOPBACK_NAMES | {host_name(bind)} | {name.lower() for name in allow_hosts}
        self.names -= {"0.0.0.0", "[::]"}  # a wildcard bind is reached by a name of its own: --allow-host
        self.token = secrets.token_urlsafe(24)  # per run: printed in the page's URL
        self.port = 0  # the bound port, once bound
        self.refused: Counter[str] = Counter(dict.fromkeys(REASONS, 0))

    def host_ok(self, host: str | None) -> bool:
        """Whether a Host header names this server: an allowed name and the bound port."""
        if not host:
            return False
        host = host.lower()
        name, port = host.rsplit(":", 1) if host.rfind(":") > host.rfind("]") else (host, "80")
        return name in self.names and port == str(self.port)

    @staticmethod
    def origin_ok(origin: str | None, host: str) -> bool:
        """Whether an Origin header, if there is one, is this server's own (http:// and the Host it asked for)."""
        return origin is None or origin.lower() == f"http://{host.lower()}"

    def token_given(self, request: web.Request) -> str | None:
        """The token a request carries (query or header), None if none."""
        return request.query.get("token") or request.headers.get(TOKEN_HEADER)

    def has_token(self, request: web.Request) -> bool:
        given = self.token_given(request)
        return given is not None and hmac.compare_digest(given.encode(), self.token.encode())

    def count(self, reason: str, request: web.Request, detail: str = "") -> None:
        """Count a refusal and log it."""
        self.refused[reason] += 1
        what = detail or f"{request.method} {request.path[:80]!r}"
        log.warning("refused (%s) %s from %s; %d refused so far", reason, what, request.remote, self.total_refused)

    def refuse(self, reason: str, request: web.Request, detail: str = "") -> web.HTTPForbidden:
        """Count a refusal, log it, and the 403 to answer with."""
        self.count(reason, request, detail)
        return web.HTTPForbidden(text=f"refused: {reason}\n")

    @property
    def total_refused(self) -> int:
        return sum(self.refused.values())

    def counts(self) -> dict[str, int]:
        return {**self.refused, "total": self.total_refused}

    def middleware(
        self, needs_token: Callable[[web.Request], bool]
    ) -> Callable[[web.Request, Handler], Awaitable[web.StreamResponse]]:
        """The aiohttp middleware: Host, Origin, then a token where `needs_token(request)` says one is needed (and
        everywhere but static files when bound beyond loopback); a wrong token is always refused."""

        @web.middleware
        async def check(request: web.Request, handler: Handler) -> web.StreamResponse:
            host = request.headers.get("Host")
            if not self.host_ok(host):
                raise self.refuse("host", request, f"Host {str(host)[:80]!r}")
            if not self.origin_ok(request.headers.get("Origin"), host):
                raise self.refuse("origin", request, f"Origin {request.headers['Origin'][:80]!r}")
            given = self.token_given(request) is not None
            static = request.path.startswith("/static/")
            if (given and not self.has_token(request)) or (
                not given and (needs_token(request) or (self.remote and not static))
            ):
                raise self.refuse("token", request)
            return await handler(request)

        return check


async def add_headers(request: web.Request, response: web.StreamResponse) -> None:
    """HEADERS on every response, refusals and websocket upgrades too (the application's on_response_prepare)."""
    response.headers.update(HEADERS)
