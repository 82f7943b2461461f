"""What the watch server tells its open pages, from one compositor link: frame points batched FLUSH_S apart, the run
report as it comes (each second), the compositor's status polled each second with each driver's rate worked out,
log records, and the previews while a page is open.

Each page has a bounded queue of outgoing messages: a page that cannot keep up loses messages (counted on its
Page), never the server or another page.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Callable
from dataclasses import dataclass, field

from hmdrt.bus.security import LOCAL_TRANSPORTS
from hmdrt.compositor.samples import KINDS
from hmdrt.watch.link import STATUS, CompositorLink
from hmdrt.watch.protocol import MAX_FRAMES_PER_BATCH, BadMessage, frame_point, preview_message

log = logging.getLogger(__name__)

FLUSH_S = 0.05  # frame points go out at most 20 times a second, batched
STATUS_S = 1.0
PAGE_QUEUE = 64  # messages waiting for a page
COUNTS = ("samples", "dropped", "invalid", "malformed", "reconnects")  # a driver's counts, as the report has them


@dataclass(eq=False)
class Page:
    """An open page: its outgoing queue, whether it holds the token, and what it lost."""

    privileged: bool
    queue: asyncio.Queue = field(default_factory=lambda: asyncio.Queue(PAGE_QUEUE))
    dropped: int = 0

    def send(self, message: dict | bytes) -> None:
        try:
            self.queue.put_nowait(message)
        except asyncio.QueueFull:
            self.dropped += 1


def control_allows(status: dict, control: str, has_keys: bool) -> str:
    """Why the control socket would refuse this server the commands that change the compositor ("": it would not):
    a compositor with [security] answers them for CURVE clients only, one without for ipc:// clients only."""
    if status.get("security", {}).get("curve"):
        return "" if has_keys else "the compositor has [security]: start hmdrt watch with --server-key and --client-key"
    if control.partition("://")[0] not in LOCAL_TRANSPORTS:
        return "the control socket is tcp:// without [security]: it only answers what reads"
    return ""


def _maps(value: object) -> dict[str, dict]:
    """The entries of a {name: map} value that are maps (none when it is no map)."""
    return {k: v for k, v in value.items() if isinstance(v, dict)} if isinstance(value, dict) else {}


class DriverRates:
    """Each device's gaze and pose sample rates from the counts of successive run reports (their `samples`, which
    count each kind), per second of the run's own clock (its VSyncs over the refresh rate): in real time the wall
    clock's, and a 250 Hz trace reads 250 Hz also in virtual time, however fast or slow the run goes."""

    def __init__(self) -> None:
        self._last: tuple[float, dict[str, dict]] | None = None  # the run's seconds at a report, and its counts
        self.rates: dict[str, dict[str, float | None]] = {}

    def update(self, report: dict) -> None:
        """rates: {device: {kind: Hz}} since the previous report of the run (None: no count of that kind yet, or no
        report before); kept while the run's clock has not moved."""
        vsyncs, hz = report.get("vsyncs"), report.get("vsync_hz")
        if not isinstance(vsyncs, int) or not isinstance(hz, int | float) or not hz > 0:
            return
        now_s, counts = vsyncs / hz, _maps(report.get("samples"))
        if self._last is not None and now_s < self._last[0]:  # a new run
            self._last = None
        if self._last is None or now_s > self._last[0]:
            before_s, before = self._last or (now_s, {})
            self.rates = {
                device: {
                    kind: _rate(count.get(kind), before.get(device, {}).get(kind), now_s - before_s) for kind in KINDS
                }
                for device, count in counts.items()
            }
            self._last = (now_s, counts)


def _rate(count: object, before: object, seconds: float) -> float | None:
    """Samples a second from two counts `seconds` apart; None without both, or with none of the kind yet."""
    if not isinstance(count, int) or not isinstance(before, int) or not count or seconds <= 0:
        return None
    return (count - before) / seconds


class Hub:
    """Takes the compositor's telemetry and status and sends them on to the open pages (start(), then stop())."""

    def __init__(self, link: CompositorLink, counts: Callable[[], dict]):
        self.link = link
        self._counts = counts  # () -> the server's counts (refusals, connections, timeouts), shown on the pages
        self.pages: set[Page] = set()
        self.status: dict = {}
        self.report: dict = {}
        self._rates = DriverRates()
        self._points: list[dict] = []
        self.skipped_points = 0  # frame points that arrived faster than a batch takes
        self._tasks: list[asyncio.Task] = []

    def start(self) -> None:
        self._tasks = [asyncio.create_task(job()) for job in (self._telemetry, self._flush, self._poll)]

    async def stop(self) -> None:
        for task in self._tasks:
            task.cancel()
        await asyncio.gather(*self._tasks, return_exceptions=True)

    def join(self, page: Page) -> None:
        self.pages.add(page)
        self.link.want_previews(True)
        if self.status:
            page.send(self._status_message())

    def leave(self, page: Page) -> None:
        self.pages.discard(page)
        self.link.want_previews(bool(self.pages))

    def _broadcast(self, message: dict | bytes) -> None:
        for page in self.pages:
            page.send(message)

    async def _telemetry(self) -> None:
        async for topic, fields in self.link.messages():
            try:
                self._take(topic, fields)
            except (BadMessage, TypeError, AttributeError) as exc:  # fields of the wrong shape: counted, skipped
                self.link.malformed += 1
                log.debug("%s message skipped: %s", topic, exc)

    def _take(self, topic: str, fields: dict) -> None:
        if topic == "frame":
            if len(self._points) < MAX_FRAMES_PER_BATCH:
                self._points.append(frame_point(fields))
            else:
                self.skipped_points += 1
        elif topic == "stats":
            self._rates.update(fields)
            self.report = fields
            self._broadcast({"type": "stats", "report": fields})
        elif topic == "log":
            self._broadcast({"type": "log", "record": fields})
        elif topic == "preview":
            self._broadcast(preview_message(fields))

    async def _flush(self) -> None:
        while True:
            await asyncio.sleep(FLUSH_S)
            if self._points:
                points, self._points = self._points, []
                self._broadcast({"type": "frames", "frames": points, "skipped": self.skipped_points})

    async def _poll(self) -> None:
        while True:
            reply = await self.link.request(STATUS)
            self.status = reply
            self._broadcast(self._status_message())
            await asyncio.sleep(STATUS_S)

    def drivers(self) -> dict[str, dict]:
        """Each driver's state and clock estimate (its newest status on the bus), counts (the run report) and its
        gaze and pose rates."""
        statuses, counts = _maps(self.status.get("drivers")), _maps(self.report.get("drivers"))
        out = {}
        for device in sorted(set(statuses) | set(counts)):
            status, count = statuses.get(device, {}), counts.get(device, {})
            clock = status.get("clock") if isinstance(status.get("clock"), dict) else {}
            offset = clock.get("offset_ns")
            out[device] = {
                "state": status.get("state"),
                **{f"{kind}_hz": self._rates.rates.get(device, {}).get(kind) for kind in KINDS},
                **{k: count.get(k, status.get(k)) for k in COUNTS},
                "offset_ms": offset / 1e6 if isinstance(offset, int | float) else None,
                "drift_ppm": clock.get("drift_ppm"),
            }
        return out

    def _status_message(self) -> dict:
        why = control_allows(self.status, self.link.control, self.link.keys is not None) if self.status else ""
        return {
            "type": "status",
            "connected": bool(self.status.get("ok")),
            "status": self.status,
            "drivers": self.drivers(),
            "control_allows": self.status.get("ok", False) and not why,
            "control_why": why or self.status.get("error", ""),
            "watch": {
                **self._counts(),
                "pages": len(self.pages),
                "dropped": sum(page.dropped for page in self.pages),  # messages pages were too slow to take
                "malformed": self.link.malformed,
            },
        }

    def state(self) -> dict:
        """The newest of everything, for GET /api/state."""
        return {**self._status_message(), "type": "state", "report": self.report}
