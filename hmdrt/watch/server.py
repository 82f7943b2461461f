"""`hmdrt watch`: a live view of a running compositor in the browser (README "Watching a run").

An aiohttp server, in a process of its own, serves the page (static/index.html, plain HTML and JS with uPlot
vendored, so it works without the internet) and a websocket (/ws) over which the page gets the compositor's
frames, reports, status, log and previews (hmdrt.watch.hub) and sends its commands (hmdrt.watch.protocol).
GET /api/state gives the newest of it all and POST /api/command takes a command, for clients without a browser.
hmdrt.watch.access checks every request; a page without the run's token is read-only. hmdrt.watch.limits caps the
connections and pages, times out slow and idle ones, and keeps the log short.
"""

from __future__ import annotations

import asyncio
import logging
import signal
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import msgspec
from aiohttp import WSMsgType, web
from aiohttp.http_exceptions import HttpProcessingError

from hmdrt.bus.security import ClientKeys, is_loopback
from hmdrt.compositor.commands import Command, to_request
from hmdrt.errors import ConfigError
from hmdrt.foveation import METHODS
from hmdrt.version import __version__
from hmdrt.watch.access import Access, add_headers, host_name
from hmdrt.watch.hub import Hub, Page
from hmdrt.watch.limits import (
    BACKLOG,
    IDLE_TIMEOUT_S,
    LOG_INTERVAL_S,
    LOOP_RATE,
    MAX_CONNECTIONS,
    MAX_PAGES,
    REQUEST_TIMEOUT_S,
    Connections,
    RateLimit,
    check_limits,
    ensure_files,
    loop_errors,
)
from hmdrt.watch.link import CONTROL_TIMEOUT_S, CompositorLink
from hmdrt.watch.protocol import MAX_MESSAGE_BYTES, BadMessage, parse_command

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
DEFAULT_PORT = 8765
WILDCARDS = ("0.0.0.0", "::", "[::]")
# the loggers whose records RateLimit keeps short: this package's, aiohttp's server side and asyncio's
LOGGERS = (
    *(f"{__package__}.{name}" for name in ("access", "hub", "limits", "link", "server")),
    "aiohttp.server",
    "aiohttp.web",
    "aiohttp.websocket",
    "asyncio",
)


def _one_line(record: logging.LogRecord, level: int, message: str, *args: object) -> None:
    record.msg, record.args, record.exc_info, record.exc_text = message, args, None, None
    record.levelno, record.levelname = level, logging.getLevelName(level)


class BadRequests(logging.Filter):
    """Turns aiohttp's record of a request it could not parse (answered 4xx) into one warning line, counted, and
    of a client that went away mid-request into one debug line, neither with a traceback; records of anything else
    pass unchanged."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, HttpProcessingError):
            self.count += 1
            reason = " ".join(str(error.message).split())[:200]
            _one_line(record, logging.WARNING, "bad HTTP request (answered %d): %s", error.code, reason)
        elif isinstance(error, ConnectionError):
            _one_line(record, logging.DEBUG, "a client went away mid-request: %s", error)
        return True


@dataclass(frozen=True)
class WatchOptions:
    """Where the compositor is and where to serve; checked on construction (ConfigError)."""

    control: str
    telemetry: str = ""  # "": the endpoint the compositor's status names
    bind: str = "127.0.0.1"
    port: int = DEFAULT_PORT
    allow_hosts: tuple[str, ...] = ()
    keys: ClientKeys | None = None
    control_timeout_s: float = CONTROL_TIMEOUT_S
    max_connections: int = MAX_CONNECTIONS
    max_pages: int = MAX_PAGES  # open websockets
    request_timeout_s: float = REQUEST_TIMEOUT_S  # for a request's headers from connecting, and for its body
    idle_timeout_s: float = IDLE_TIMEOUT_S  # for a kept-alive connection's next request, and a page's pong

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"--port must be in 0..65535 (0: any free port), got {self.port}")
        check_limits(self.max_connections, self.max_pages, self.request_timeout_s, self.idle_timeout_s)
        if not is_loopback(f"tcp://{self.bind}:0") and self.keys is None:
            raise ConfigError(
                f"--bind {self.bind} is not loopback: serving beyond this host needs the compositor's [security] "
                "keys for the watch's own connection (--server-key and --client-key); the page then needs the token"
            )
        if self.bind in WILDCARDS and not self.allow_hosts:
            raise ConfigError(f"--bind {self.bind} needs --allow-host NAME: the host name the page is opened by")


class WatchServer:
    """The page, its websocket and API for one compositor; start() in a running event loop, then stop()."""

    def __init__(self, options: WatchOptions):
        self.options = options
        self.access = Access(options.bind, options.allow_hosts)
        self.link: CompositorLink | None = None
        self.hub: Hub | None = None
        self._runner: web.AppRunner | None = None
        self.bad_requests = BadRequests()
        self.rate_limit = RateLimit()
        self.connections = Connections(options.max_connections, options.request_timeout_s, options.idle_timeout_s)
        self.pages_refused = 0  # websockets refused because max_pages were open
        self._flusher: asyncio.Task | None = None

    def url(self, token: bool = False) -> str:
        """The page's address (with the token: the one that may change the compositor)."""
        name = self.options.allow_hosts[0] if self.options.bind in WILDCARDS else host_name(self.options.bind)
        return f"http://{name}:{self.access.port}/" + (f"?token={self.access.token}" if token else "")

    def counts(self) -> dict:
        """What the server refused and closed, and how many connections it has open (the pages' "watch")."""
        refused = {
            **self.access.counts(),
            "bad_http": self.bad_requests.count,
            "connections": self.connections.refused,
            "pages": self.pages_refused,
        }
        return {
            "refused": refused,
            "connections": self.connections.count,
            "timed_out": dict(self.connections.timed_out),
        }

    async def start(self) -> None:
        """Connect to the compositor and serve; ConfigError when the address cannot be bound."""
        o = self.options
        ensure_files(o.max_connections)
        self.link = CompositorLink(o.control, o.keys, o.control_timeout_s)
        try:
            await self.link.connect(o.telemetry)
        except ConfigError:
            await self.stop()
            raise
        self.hub = Hub(self.link, self.counts)
        logging.getLogger("aiohttp.server").addFilter(self.bad_requests)  # before the rate limit: one line first
        for name in LOGGERS:
            logging.getLogger(name).addFilter(self.rate_limit)
        asyncio.get_running_loop().set_exception_handler(loop_errors)  # for as long as the loop runs (its own)
        self._flusher = asyncio.create_task(self._flush_log())
        app = web.Application(
            middlewares=[
                self.connections.middleware,
                self.access.middleware(lambda request: request.path == "/api/command"),
            ],
            client_max_size=MAX_MESSAGE_BYTES,
        )
        app.on_response_prepare.append(add_headers)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._socket)
        app.router.add_get("/api/state", self._state)
        app.router.add_post("/api/command", self._command)
        app.router.add_static("/static/", STATIC)
        # lingering_time 0: a body that has not come when its request is answered is not waited for;
        # shutdown_timeout: stopping waits for a request in flight at most as long as for the compositor's reply
        self._runner = web.AppRunner(
            app, handle_signals=False, access_log=None, lingering_time=0, shutdown_timeout=o.control_timeout_s
        )
        await self._runner.setup()
        site = _Site(self._runner, o.bind.strip("[]"), o.port, self.connections)
        try:
            await site.start()
        except OSError as exc:
            await self.stop()
            raise ConfigError(f"cannot serve on {o.bind}:{o.port}: {exc.strerror}") from None
        self.access.port = self._runner.addresses[0][1]
        self.hub.start()
        log.info("serving %s for the compositor at %s", self.url(), o.control)

    async def stop(self) -> None:
        """Stop serving and leave the compositor; once more does nothing."""
        runner, self._runner = self._runner, None
        if runner is not None:  # first: the pages' handlers leave the hub as they end
            await runner.cleanup()
        hub, link, self.hub, self.link = self.hub, self.link, None, None
        if hub is not None:
            await hub.stop()
        if link is not None:
            link.close()
        if self._flusher is not None:
            self._flusher.cancel()
            await asyncio.gather(self._flusher, return_exceptions=True)
            self._flusher = None
        self.rate_limit.flush(everything=True)
        LOOP_RATE.flush(everything=True)
        logging.getLogger("aiohttp.server").removeFilter(self.bad_requests)
        for name in LOGGERS:
            logging.getLogger(name).removeFilter(self.rate_limit)

    async def _flush_log(self) -> None:
        """Say what the rate limit suppressed, each interval."""
        while True:
            await asyncio.sleep(LOG_INTERVAL_S)
            self.rate_limit.flush()
            LOOP_RATE.flush()

    # --- handlers -----------------------------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.hub.state(), dumps=lambda value: msgspec.json.encode(value).decode())

    async def _command(self, request: web.Request) -> web.Response:
        try:
            async with asyncio.timeout(self.options.request_timeout_s):
                body = await request.read()
        except TimeoutError:
            self.connections.count_timeout("request", f"{request.method} {request.path} from {request.remote}: no body")
            return web.Response(status=408, text="request timeout: the body did not come in time\n")
        except (ConnectionError, RuntimeError) as exc:  # RuntimeError: aiohttp's, read after the connection closed
            if request.transport is not None and not isinstance(exc, ConnectionError):
                raise
            log.debug(
                "%s %s from %s: the client went away mid-request (%s)",
                request.method,
                request.path,
                request.remote,
                exc,
            )
            return web.Response(status=400, text="the request ended early\n")
        try:
            _, command = parse_command(body)
        except BadMessage as exc:
            self.access.count("message", request, str(exc))
            return web.json_response({"ok": False, "error": str(exc)}, status=400)
        return web.json_response(await self._execute(command))

    async def _socket(self, request: web.Request) -> web.WebSocketResponse:
        if len(self.hub.pages) >= self.options.max_pages:
            self.pages_refused += 1
            log.warning(
                "%d pages open (max_pages): refused a page from %s; %d refused so far",
                len(self.hub.pages),
                request.remote,
                self.pages_refused,
            )
            raise web.HTTPServiceUnavailable(text="refused: too many pages are open\n")
        # pinged after two thirds of the idle timeout without a message, closed without a pong by its end
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES, heartbeat=self.options.idle_timeout_s * 2 / 3)
        page = Page(privileged=self.access.has_token(request))
        page.send(self._hello(page))
        self.hub.join(page)  # before the upgrade's first await, so that pages opening at once keep to max_pages
        sender = None
        try:
            await ws.prepare(request)
            sender = asyncio.create_task(self._send(ws, page))
            async for message in ws:
                if message.type == WSMsgType.TEXT:
                    page.send(await self._page_command(message.data, page, request))
                elif message.type == WSMsgType.BINARY:
                    self.access.count("message", request, "a binary websocket message")
                    page.send({"type": "reply", "ok": False, "error": "commands are JSON text messages"})
                elif message.type == WSMsgType.ERROR and isinstance(ws.exception(), TimeoutError):
                    self.connections.count_timeout("idle", f"closed the page from {request.remote}: no pong")
                elif message.type == WSMsgType.ERROR:  # over MAX_MESSAGE_BYTES (closed 1009) or broken framing
                    self.access.count("message", request, f"websocket: {ws.exception()}")
        except ConnectionError as exc:
            log.debug("the page from %s went away as it opened: %s", request.remote, exc)
        else:
            log.debug("the page from %s closed (code %s)", request.remote, ws.close_code)
        finally:
            self.hub.leave(page)
            if sender is not None:
                sender.cancel()
                await asyncio.gather(sender, return_exceptions=True)
        return ws

    @staticmethod
    async def _send(ws: web.WebSocketResponse, page: Page) -> None:
        while True:
            message = await page.queue.get()
            try:
                if isinstance(message, bytes):
                    await ws.send_bytes(message)
                else:
                    await ws.send_str(msgspec.json.encode(message).decode())
            except ConnectionError:
                return

    def _hello(self, page: Page) -> dict:
        return {
            "type": "hello",
            "hmdrt": __version__,
            "privileged": page.privileged,
            "telemetry": self.link.telemetry,
            "control": self.options.control,
            "methods": {name: msgspec.to_builtins(cls.Params()) for name, cls in METHODS.items()},
        }

    async def _page_command(self, data: str, page: Page, request: web.Request) -> dict:
        try:
            number, command = parse_command(data)
        except BadMessage as exc:
            self.access.count("message", request, str(exc))
            return {"type": "reply", "ok": False, "error": str(exc)}
        if command.mutating and not page.privileged:
            self.access.count("token", request, f"{command.name()} from a page without the token")
            return {"type": "reply", "id": number, "ok": False, "error": "read-only: open the URL with ?token="}
        return {"type": "reply", "id": number, **await self._execute(command)}

    async def _execute(self, command: Command) -> dict:
        """Forward a command to the control socket."""
        request = to_request(command)
        reply = await self.link.request(request)
        log.info("%s: %s", request["cmd"], reply)
        return reply


class _Site(web.BaseSite):
    """aiohttp's TCPSite, with each connection going through Connections."""

    def __init__(self, runner: web.BaseRunner, host: str, port: int, connections: Connections):
        super().__init__(runner, backlog=BACKLOG)
        self.host, self.port, self.connections = host, port, connections

    @property
    def name(self) -> str:
        return f"http://{self.host}:{self.port}"

    async def start(self) -> None:
        await super().start()
        factory = self.connections.factory(self._runner.server)
        self._server = await asyncio.get_running_loop().create_server(
            factory, self.host, self.port, backlog=self._backlog
        )


def serve(options: WatchOptions, ready: Callable[[WatchServer], None]) -> None:
    """Serve until SIGINT or SIGTERM; ready(server) once it listens."""

    async def main() -> None:
        server = WatchServer(options)
        await server.start()
        stop = asyncio.Event()
        loop = asyncio.get_running_loop()
        for sig in (signal.SIGINT, signal.SIGTERM):
            loop.add_signal_handler(sig, stop.set)
        try:
            ready(server)
            await stop.wait()
        finally:
            await server.stop()

    asyncio.run(main())
