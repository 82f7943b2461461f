"""How much the watch server takes (docs/runtime.md, "Watching a run"): how many connections it keeps open, how long
it waits for a request, and how much it logs, so that slow or idle clients, or any number of them, neither lock the
page out nor fill the disk.

Every accepted connection goes through Connections. At max_connections open, a new one closes the connection that
has waited longest for a request (a slow or an idle client's), or is answered 503 when every open one is busy with
a request or a page; either is counted as refused. A connection must complete its first request's headers within
request_timeout_s, and a kept-alive one its next within idle_timeout_s, or it is closed and counted.

The server's, aiohttp's and asyncio's log records pass RateLimit: at most LOG_BURST of a kind in LOG_INTERVAL_S, then
one line that says how many more there were. asyncio's own errors (loop_errors) are one line each, and the traceback
of one that is no client going away or the process running out of files (a bug) is logged at debug.
"""

from __future__ import annotations

import asyncio
import errno
import logging
import resource
import time
from collections import Counter, OrderedDict
from collections.abc import Callable
from dataclasses import dataclass

from aiohttp import web
from aiohttp.web_protocol import RequestHandler

from hmdrt.errors import ConfigError

log = logging.getLogger(__name__)

MAX_CONNECTIONS = 256
MAX_PAGES = 32
REQUEST_TIMEOUT_S = 10.0
IDLE_TIMEOUT_S = 60.0
BACKLOG = 1024  # connections the kernel completes before they are accepted: a flood's newest are not dropped
FILES_RESERVED = 64  # open files beside the connections: the listening socket, ZeroMQ's sockets, the page's files
LOG_BURST = 10
LOG_INTERVAL_S = 10.0
MAX_LOG_KINDS = 256  # kinds counted apart; records of any further kind share one count
SUMMARY = "hmdrt_rate_limit_summary"  # set on RateLimit's own lines, which it passes
SCARCE = (errno.EMFILE, errno.ENFILE, errno.ENOBUFS, errno.ENOMEM)
_BUSY_TEXT = b"refused: too many connections are busy\n"
# what a connection over the cap is answered when every open one is busy
BUSY = (
    b"HTTP/1.1 503 Service Unavailable\r\nContent-Type: text/plain\r\nContent-Length: %d\r\n"
    b"Connection: close\r\nX-Content-Type-Options: nosniff\r\n\r\n%s" % (len(_BUSY_TEXT), _BUSY_TEXT)
)


def check_limits(max_connections: int, max_pages: int, request_timeout_s: float, idle_timeout_s: float) -> None:
    """ConfigError unless the limits make sense together: the pages leave a connection for the page's files and
    API, and the timeouts are positive."""
    if not 1 <= max_pages < max_connections:
        raise ConfigError(f"max_pages must be 1 or more and below max_connections ({max_connections}), got {max_pages}")
    for name, value in (("request_timeout_s", request_timeout_s), ("idle_timeout_s", idle_timeout_s)):
        if not value > 0:
            raise ConfigError(f"{name} must be above 0 s, got {value}")


def ensure_files(max_connections: int) -> None:
    """Raise this process's limit of open files to max_connections + FILES_RESERVED where it is lower (up to its
    hard limit); ConfigError when the hard limit is lower still, since accepting would then run out of files."""
    needed = max_connections + FILES_RESERVED
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft == resource.RLIM_INFINITY or soft >= needed:
        return
    if hard != resource.RLIM_INFINITY and hard < needed:
        raise ConfigError(f"{max_connections} connections need {needed} open files; this process may open {hard}")
    resource.setrlimit(resource.RLIMIT_NOFILE, (needed, hard))


class _Connection(asyncio.Protocol):
    """One accepted connection: aiohttp's handler behind it, told to Connections when it goes."""

    def __init__(self, owner: Connections, handler: RequestHandler):
        self.owner, self.handler = owner, handler
        self.busy = False  # a request (or a page) is being handled
        self.timer: asyncio.TimerHandle | None = None
        self.peer = "an address not yet known"
        self.made = False  # asyncio has handed over the transport
        self.closed = False

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        self.made = True
        peer = transport.get_extra_info("peername")
        self.peer = str(peer[0]) if isinstance(peer, tuple) else "?"
        if self.closed:  # closed to make room before asyncio handed it over
            transport.close()
        else:
            self.handler.connection_made(transport)

    def close(self) -> None:
        self.closed = True
        if self.made:
            self.handler.force_close()

    def connection_lost(self, exc: Exception | None) -> None:
        self.owner.forget(self)
        self.handler.connection_lost(exc)

    def data_received(self, data: bytes) -> None:
        self.handler.data_received(data)

    def eof_received(self) -> bool | None:
        return self.handler.eof_received()

    def pause_writing(self) -> None:
        self.handler.pause_writing()

    def resume_writing(self) -> None:
        self.handler.resume_writing()


class _Busy(asyncio.Protocol):
    """A connection refused because every open one is busy: 503, then closed."""

    def connection_made(self, transport: asyncio.BaseTransport) -> None:
        transport.write(BUSY)
        transport.close()


class Connections:
    """The open connections of one server: its cap and timeouts, and what they refused and closed."""

    def __init__(self, max_connections: int, request_timeout_s: float, idle_timeout_s: float):
        self.max_connections = max_connections
        self.request_timeout_s, self.idle_timeout_s = request_timeout_s, idle_timeout_s
        # by handler; those waiting for a request in the order they began to, busy ones anywhere
        self._open: OrderedDict[RequestHandler, _Connection] = OrderedDict()
        self.refused = 0  # connections closed or answered 503 because max_connections were open
        self.timed_out: Counter[str] = Counter(request=0, idle=0)

    @property
    def count(self) -> int:
        """Connections open now."""
        return len(self._open)

    def factory(self, server: web.Server) -> Callable[[], asyncio.Protocol]:
        """The protocol factory for loop.create_server: aiohttp's handlers of `server`, each tracked here."""

        def accept() -> asyncio.Protocol:
            if len(self._open) >= self.max_connections and not self._make_room():
                self.refused += 1
                log.warning(
                    "%d connections open (max_connections), all busy: refused a connection (503); %d refused so far",
                    len(self._open),
                    self.refused,
                )
                return _Busy()
            connection = _Connection(self, server())
            self._open[connection.handler] = connection
            self._wait(connection, "request")
            return connection

        return accept

    def _make_room(self) -> bool:
        """Close the connection that has waited longest for a request; False when every one is busy."""
        waiting = next((c for c in self._open.values() if not c.busy), None)
        if waiting is None:
            return False
        self.refused += 1
        log.warning(
            "%d connections open (max_connections): closed the one that waited longest for a request (from %s); "
            "%d refused so far",
            len(self._open),
            waiting.peer,
            self.refused,
        )
        self._close(waiting)
        return True

    def _wait(self, connection: _Connection, kind: str) -> None:
        """Close `connection` unless a request comes within the request or idle timeout."""
        if connection.timer is not None:
            connection.timer.cancel()
        delay = self.request_timeout_s if kind == "request" else self.idle_timeout_s
        connection.timer = asyncio.get_running_loop().call_later(delay, self._expire, connection, kind)

    def _expire(self, connection: _Connection, kind: str) -> None:
        if connection.busy or connection.handler not in self._open:
            return
        what = "no request" if kind == "request" else "no further request"
        self.count_timeout(kind, f"closed the connection from {connection.peer}: {what}")
        self._close(connection)

    def count_timeout(self, kind: str, what: str) -> None:
        """Count a request (`kind` "request") or idle ("idle") timeout, and log it at debug."""
        self.timed_out[kind] += 1
        timeout = self.request_timeout_s if kind == "request" else self.idle_timeout_s
        log.debug("%s in %g s (%s timeout)", what, timeout, kind)

    def _close(self, connection: _Connection) -> None:
        self.forget(connection)
        connection.close()

    def forget(self, connection: _Connection) -> None:
        """A connection gone: no longer counted or timed."""
        self._open.pop(connection.handler, None)
        if connection.timer is not None:
            connection.timer.cancel()
            connection.timer = None

    @web.middleware
    async def middleware(self, request: web.Request, handler: Callable) -> web.StreamResponse:
        """Marks a connection busy while its request is handled (a page: while it is open), then waiting for the
        next for at most idle_timeout_s."""
        connection = self._open.get(request.protocol)
        if connection is None:  # closed while its request was read
            return await handler(request)
        connection.busy = True
        connection.timer.cancel()
        try:
            return await handler(request)
        finally:
            connection.busy = False
            if connection.handler in self._open:
                self._open.move_to_end(connection.handler)
                self._wait(connection, "idle")


@dataclass
class _Kind:
    """One kind of record's current interval."""

    start: float  # when its interval began
    passed: int = 0
    suppressed: int = 0
    level: int = logging.DEBUG  # the highest of those suppressed


class RateLimit(logging.Filter):
    """At most `burst` records of a kind (a logger and a message format) in each `interval_s`; the rest are counted,
    and one line at the interval's end (the next record of that kind, or flush()) says how many there were."""

    def __init__(self, burst: int = LOG_BURST, interval_s: float = LOG_INTERVAL_S):
        super().__init__()
        self.burst, self.interval_s = burst, interval_s
        self._kinds: dict[tuple[str, str], _Kind] = {}

    def filter(self, record: logging.LogRecord) -> bool:
        if getattr(record, SUMMARY, False):
            return True
        now = time.monotonic()
        key = (record.name, str(record.msg).partition("\n")[0][:120])
        if key not in self._kinds and len(self._kinds) >= MAX_LOG_KINDS:
            key = (record.name, "records of other kinds")
        kind = self._kinds.setdefault(key, _Kind(now))
        if now - kind.start >= self.interval_s:
            self._report(key, kind, now)
        if kind.passed < self.burst:
            kind.passed += 1
            return True
        kind.suppressed += 1
        kind.level = max(kind.level, record.levelno)
        return False

    def flush(self, everything: bool = False) -> None:
        """Say what was suppressed in the intervals that have ended (`everything`: in all, as the server stops)."""
        now = time.monotonic()
        for key, kind in list(self._kinds.items()):
            if everything or now - kind.start >= self.interval_s:
                self._report(key, kind, now)
                del self._kinds[key]

    def _report(self, key: tuple[str, str], kind: _Kind, now: float) -> None:
        """The line for what a kind's interval suppressed, if anything; the kind begins a new interval."""
        if kind.suppressed:
            logging.getLogger(key[0]).log(
                kind.level,
                "suppressed %d more like %r in %.1f s",
                kind.suppressed,
                key[1],
                now - kind.start,
                extra={SUMMARY: True},
            )
        kind.start, kind.passed, kind.suppressed, kind.level = now, 0, 0, logging.DEBUG


# asyncio's errors, rate-limited for as long as the process runs: out of files, asyncio schedules a retry for each
# connection it failed to accept, and those that come due after the server closed fail too
loop_log = logging.getLogger(f"{__name__}.loop")
LOOP_RATE = RateLimit()
loop_log.addFilter(LOOP_RATE)


def loop_errors(loop: asyncio.AbstractEventLoop, context: dict) -> None:
    """The event loop's exception handler: a client gone is one debug line, running out of files or memory one
    warning line (asyncio pauses accepting and retries), anything else one error line, with its traceback at debug."""
    error = context.get("exception")
    message = str(context.get("message", "")).partition("\n")[0][:200]
    if isinstance(error, ConnectionError):
        loop_log.debug("%s: %s", message, error)
    elif isinstance(error, OSError) and error.errno in SCARCE:
        loop_log.warning("%s: %s; retrying", message, error.strerror)
    else:
        what = repr(error) if error else "no exception"
        loop_log.error("%s: %s (its traceback at --log-level debug)", message, what)
        loop_log.debug("%s", message, exc_info=error)
