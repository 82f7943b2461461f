"""The one small interface every device driver implements, and what drivers share.

A driver is opened, read in a loop, and closed; its samples are already normalised (docs/architecture.md, Conventions:
host-clock nanoseconds, right-handed head frame, unit gaze directions per eye, validity). read()
returns the samples that arrived within a timeout (possibly none) and raises DeviceLost when the
device went away, so a host can reconnect. Drivers count what they publish, what was invalid, what
they lost and what did not parse; status() reports that with the clock-sync estimate.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar
from urllib.parse import parse_qsl, quote, unquote, urlencode, urlsplit

from hmdrt.bus.messages import Gaze, Pose, Status
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.clocksync import ClockSync
from hmdrt.errors import ConfigError, HmdrtError

Sample = Gaze | Pose
PATH_SAFE = "/:@!$&'()*+,;=~"  # what a URL's path may hold unquoted (RFC 3986 pchar): a location keeps them


class DriverError(HmdrtError):
    """A driver cannot be found, configured or opened."""


class DriverNotFound(DriverError):
    """No driver is registered for a URL scheme."""


class DeviceLost(DriverError):
    """The device stopped answering or the connection dropped; reopening may bring it back."""


@dataclass(frozen=True)
class DriverUrl:
    """A parsed driver URL: scheme://host:port/path?key=value&..."""

    text: str
    scheme: str
    host: str
    netloc: str
    path: str
    options: dict[str, str]

    @classmethod
    def parse(cls, text: str) -> DriverUrl:
        """The one parser of driver URLs; a ConfigError says what is wrong with one."""
        try:
            parts = urlsplit(text)
        except ValueError as exc:  # a netloc with an unbalanced [ or ]
            raise ConfigError(f"driver URL {text!r}: {exc}") from None
        if not parts.scheme:
            raise ConfigError(f"driver URL needs a scheme (e.g. synthetic://?seed=1), got {text!r}")
        try:
            options = dict(parse_qsl(parts.query, keep_blank_values=True, strict_parsing=bool(parts.query)))
        except ValueError as exc:
            raise ConfigError(f"driver URL {text!r}: {exc}") from None
        return cls(text, parts.scheme, parts.hostname or "", parts.netloc, parts.path, options)

    @property
    def location(self) -> str:
        """What comes between scheme:// and ?, unquoted and as written: replay://traces/a.jsonl gives
        traces/a.jsonl (a URL parser would take "traces" for a host name, which the host field lower-cases)."""
        return unquote(self.netloc + self.path)

    def replace(self, location: str | None = None, **options: str) -> DriverUrl:
        """This URL with another location and the given options set (both quoted here), the rest as it was."""
        where = self.netloc + self.path if location is None else quote(location, safe=PATH_SAFE)
        query = urlsplit(self.text).query
        if options:
            query = urlencode({**self.options, **options}, safe="/:,", quote_via=quote)
        return DriverUrl.parse(f"{self.scheme}://{where}" + (f"?{query}" if query else ""))

    @property
    def port(self) -> int | None:
        """The URL's port; a ConfigError when it is not one (hid://VVVV:PPPP reads netloc instead)."""
        try:
            return urlsplit(self.text).port
        except ValueError:
            raise ConfigError(f"driver URL {self.text!r}: the port must be a number within 0-65535") from None


@dataclass
class Counters:
    """What a driver made of its device (docs/architecture.md, Drivers); its status carries all but crashes."""

    samples: int = 0  # samples passed on by read(), valid or not
    invalid: int = 0  # of those, marked invalid: blinks, lost tracking
    dropped: int = 0  # lost: gaps in the device's sequence, a full send queue
    malformed: int = 0  # device messages that did not decode (serial trackers: bytes)
    reconnects: int = 0  # the device went away and was opened again
    crashes: int = 0  # unexpected errors in the driver's own code; the host restarts it with backoff

    def summary(self) -> str:
        """The counts in a line, as `hmdrt driver` prints them when it stops."""
        return (
            f"{self.samples} samples ({self.invalid} invalid), {self.dropped} dropped, {self.malformed} malformed, "
            f"{self.reconnects} reconnects, {self.crashes} crashes"
        )


class Driver(ABC):
    """A device as a source of normalised samples.

    Subclasses set `scheme`, `grammar` (the URL forms they accept, quoted in errors) and `options`
    (name -> (type, default, low, high)); options arrive parsed and range-checked in self.opt. Every
    driver also takes name= (the bus device name) and device_latency= (ms: the device's fixed delay
    from capture to sending, which one-way timestamps cannot reveal; the clock sync takes it out).
    A driver whose URL names files declares where (`location_is_path`, `path_options`), so that a run
    config's paths are taken relative to the config file (with_paths_under).
    """

    scheme: ClassVar[str]
    grammar: ClassVar[str]
    options: ClassVar[dict[str, tuple[type, object, float | None, float | None]]] = {}
    location_is_path: ClassVar[bool] = False  # the URL's location is a file (replay://PATH)
    path_options: ClassVar[tuple[str, ...]] = ()  # options whose values are files (hid://stub?trace=PATH)
    device_latency_ms: ClassVar[float] = 0.0
    clock_wrap_ns: ClassVar[int | None] = None  # the period of a device clock that wraps

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        self.url = DriverUrl.parse(url) if isinstance(url, str) else url
        self.clock = clock
        self.counters = Counters()
        known = {
            **self.options,
            "name": (str, self.scheme, None, None),
            "device_latency": (float, self.device_latency_ms, 0.0, 10_000.0),
        }
        unknown = set(self.url.options) - set(known)
        if unknown:
            raise ConfigError(f"{self.scheme}:// has no option {sorted(unknown)[0]!r}; expected {self.grammar}")
        self.opt = {name: self._option(name, *spec) for name, spec in known.items()}
        self.device = str(self.opt["name"])
        if not (self.device.isascii() and self.device.isprintable() and self.device):
            raise ConfigError(f"{self.scheme}:// name= must be printable ASCII (a bus topic), got {self.device!r}")
        self.sync = ClockSync(wrap_ns=self.clock_wrap_ns, floor_ns=round(self.opt["device_latency"] * 1e6))
        self.state = "closed"

    @classmethod
    def with_paths_under(cls, url: DriverUrl, base: Path) -> DriverUrl:
        """`url` with the relative file paths this driver declares in it made absolute against `base`."""
        location = url.location if cls.location_is_path and _relative(url.location) else None
        options = {name: str(base / url.options[name]) for name in cls.path_options if _relative(url.options.get(name))}
        if location is None and not options:
            return url
        return url.replace(None if location is None else str(base / location), **options)

    def _option(self, name: str, kind: type, default, lo, hi):
        text = self.url.options.get(name)
        if text is None:
            return default
        try:
            value = kind(text) if kind is not bool else text.lower() in ("1", "true", "yes", "on")
        except ValueError:
            raise ConfigError(
                f"{self.scheme}:// option {name}={text!r} is not a {kind.__name__}; expected {self.grammar}"
            ) from None
        if isinstance(value, float) and not math.isfinite(value):
            raise ConfigError(f"{self.scheme}:// option {name} must be finite")
        if lo is not None and not (lo <= value <= hi):
            raise ConfigError(f"{self.scheme}:// option {name}={value} is outside [{lo}, {hi}]")
        return value

    @abstractmethod
    def open(self) -> None:
        """Connect to the device; raises DriverError (or DeviceLost, to be retried) when it cannot."""

    @abstractmethod
    def read(self, timeout_s: float) -> list[Sample]:
        """Samples that arrived within timeout_s, oldest first; DeviceLost when the device went away."""

    @abstractmethod
    def close(self) -> None:
        """Release the device; safe to call twice."""

    def count(self, samples: list[Sample]) -> list[Sample]:
        """Count samples on their way out (published, and how many of them are invalid)."""
        self.counters.samples += len(samples)
        self.counters.invalid += sum(not s.valid for s in samples)
        return samples

    def status(self) -> Status:
        c = self.counters
        return Status(
            device=self.device,
            state=self.state,
            t_host=self.clock.now_ns(),
            samples=c.samples,
            invalid=c.invalid,
            dropped=c.dropped,
            malformed=c.malformed,
            reconnects=c.reconnects,
            clock=self.sync.estimate(),
        )

    def __enter__(self) -> Driver:
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def _relative(path: str | None) -> bool:
    return bool(path) and not Path(path).is_absolute()


@dataclass
class SequenceGaps:
    """Counts samples lost between device sequence numbers (frame ids) that should be consecutive."""

    modulus: int | None = None  # a counter that wraps, e.g. 2**16
    last: int | None = None
    lost: int = field(default=0)

    def see(self, seq: int) -> int:
        """Record a sequence number; returns how many were skipped since the previous one."""
        skipped = 0
        if self.last is not None:
            step = seq - self.last
            if self.modulus:
                step %= self.modulus
            skipped = step - 1 if 1 < step < (self.modulus or 2**62) // 2 else 0
        self.last = seq
        self.lost += skipped
        return skipped
