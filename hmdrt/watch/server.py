"""`hmdrt watch`: a live view of a running compositor in the browser (README "Watching a run").

An aiohttp server, in a process of its own, serves the page (static/index.html, plain HTML and JS with uPlot
vendored, so it works without the internet) and a websocket (/ws) over which the page gets the compositor's
frames, reports, status, log and previews (hmdrt.watch.hub) and sends its commands (hmdrt.watch.protocol).
GET /api/state gives the newest of it all and POST /api/command takes a command, for clients without a browser.
hmdrt.watch.access checks every request; a page without the run's token is read-only.
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
from hmdrt.watch.link import CONTROL_TIMEOUT_S, CompositorLink
from hmdrt.watch.protocol import MAX_MESSAGE_BYTES, BadMessage, parse_command

log = logging.getLogger(__name__)

STATIC = Path(__file__).parent / "static"
DEFAULT_PORT = 8765
WILDCARDS = ("0.0.0.0", "::", "[::]")


class BadRequests(logging.Filter):
    """Turns aiohttp's record of a request it could not parse (answered 4xx) into one line without a traceback, and
    counts them; records of anything else pass unchanged."""

    def __init__(self) -> None:
        super().__init__()
        self.count = 0

    def filter(self, record: logging.LogRecord) -> bool:
        error = record.exc_info[1] if record.exc_info else None
        if isinstance(error, HttpProcessingError):
            self.count += 1
            reason = " ".join(str(error.message).split())[:200]
            record.msg, record.args, record.exc_info = "bad HTTP request (answered %d): %s", (error.code, reason), None
            record.levelno, record.levelname = logging.WARNING, "WARNING"
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

    def __post_init__(self) -> None:
        if not 0 <= self.port <= 65535:
            raise ConfigError(f"--port must be in 0..65535 (0: any free port), got {self.port}")
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

    def url(self, token: bool = False) -> str:
        """The page's address (with the token: the one that may change the compositor)."""
        name = self.options.allow_hosts[0] if self.options.bind in WILDCARDS else host_name(self.options.bind)
        return f"http://{name}:{self.access.port}/" + (f"?token={self.access.token}" if token else "")

    async def start(self) -> None:
        """Connect to the compositor and serve; ConfigError when the address cannot be bound."""
        o = self.options
        self.link = CompositorLink(o.control, o.keys, o.control_timeout_s)
        try:
            await self.link.connect(o.telemetry)
        except ConfigError:
            await self.stop()
            raise
        self.hub = Hub(self.link, lambda: {**self.access.counts(), "bad_http": self.bad_requests.count})
        logging.getLogger("aiohttp.server").addFilter(self.bad_requests)
        app = web.Application(
            middlewares=[self.access.middleware(lambda request: request.path == "/api/command")],
            client_max_size=MAX_MESSAGE_BYTES,
        )
        app.on_response_prepare.append(add_headers)
        app.router.add_get("/", self._index)
        app.router.add_get("/ws", self._socket)
        app.router.add_get("/api/state", self._state)
        app.router.add_post("/api/command", self._command)
        app.router.add_static("/static/", STATIC)
        self._runner = web.AppRunner(app, handle_signals=False, access_log=None)
        await self._runner.setup()
        site = web.TCPSite(self._runner, o.bind.strip("[]"), o.port)
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
        hub, runner, link, self.hub, self._runner, self.link = self.hub, self._runner, self.link, None, None, None
        if hub is not None:
            await hub.stop()
        if runner is not None:
            await runner.cleanup()
        if link is not None:
            link.close()
        logging.getLogger("aiohttp.server").removeFilter(self.bad_requests)

    # --- handlers -----------------------------------------------------------------------------------------------

    async def _index(self, request: web.Request) -> web.FileResponse:
        return web.FileResponse(STATIC / "index.html")

    async def _state(self, request: web.Request) -> web.Response:
        return web.json_response(self.hub.state(), dumps=lambda value: msgspec.json.encode(value).decode())

    async def _command(self, request: web.Request) -> web.Response:
        try:
            _, command = parse_command(await request.read())
        except BadMessage as exc:
            self.access.count("message", request, str(exc))
            return web.json_response({"ok": False, "error": str(exc)}, status=400)
        return web.json_response(await self._execute(command))

    async def _socket(self, request: web.Request) -> web.WebSocketResponse:
        ws = web.WebSocketResponse(max_msg_size=MAX_MESSAGE_BYTES, heartbeat=30.0)
        await ws.prepare(request)
        page = Page(privileged=self.access.has_token(request))
        page.send(self._hello(page))
        self.hub.join(page)
        sender = asyncio.create_task(self._send(ws, page))
        try:
            async for message in ws:
                if message.type == WSMsgType.TEXT:
                    page.send(await self._page_command(message.data, page, request))
                elif message.type == WSMsgType.BINARY:
                    self.access.count("message", request, "a binary websocket message")
                    page.send({"type": "reply", "ok": False, "error": "commands are JSON text messages"})
                elif message.type == WSMsgType.ERROR:  # over MAX_MESSAGE_BYTES (closed 1009) or broken framing
                    self.access.count("message", request, f"websocket: {ws.exception()}")
        finally:
            self.hub.leave(page)
            sender.cancel()
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
