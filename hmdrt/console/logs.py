"""Logging: the standard `logging` module, a logger per module (`logging.getLogger(__name__)` under hmdrt,
its drivers and replay included), configured once by the command line (`hmdrt -v`, `--log-level`).

While a compositor runs, its process's records also go out on the telemetry `log` topic as {"level", "message",
"logger"} (as Pupil Capture publishes its log on its IPC backbone), at INFO and above whatever the console
shows. A user's mistake stays a one-line error on stderr from the CLI, not a log record.
"""

from __future__ import annotations

import logging
import sys
from collections.abc import Callable
from typing import TextIO

LEVELS = ("debug", "info", "warning", "error")
PACKAGES = ("hmdrt",)
FORMAT = "hmdrt: %(levelname)s: %(name)s: %(message)s"


class _Console(logging.StreamHandler):
    """A StreamHandler on whatever sys.stderr is when a record is written, as logging's last resort is: a program
    (or a test) that swaps sys.stderr after configure() still gets its records, and none go to a closed stream."""

    def __init__(self) -> None:
        super().__init__(sys.stderr)

    @property
    def stream(self) -> TextIO:
        return sys.stderr

    @stream.setter
    def stream(self, _value: TextIO) -> None:  # StreamHandler assigns it; the property always reads sys.stderr
        pass


def configure(level: str = "warning") -> None:
    """Records of the packages at `level` and above on stderr (one console handler, however often called)."""
    root = logging.getLogger()
    for handler in [h for h in root.handlers if isinstance(h, _Console)]:
        root.removeHandler(handler)
    console = _Console()
    console.setLevel(level.upper())
    console.setFormatter(logging.Formatter(FORMAT))
    root.addHandler(console)
    for name in PACKAGES:
        logging.getLogger(name).setLevel(min(logging.INFO, console.level))


class TelemetryHandler(logging.Handler):
    """Publishes each record of the packages' loggers through publish(topic, fields) while attached."""

    def __init__(self, publish: Callable[[str, dict], None], level: int = logging.INFO):
        super().__init__(level)
        self._publish = publish
        self.dropped = 0  # records that could not be published (the socket closing under them)
        self._levels: dict[str, int] = {}  # the packages' logger levels before attach, restored by detach

    def emit(self, record: logging.LogRecord) -> None:
        try:
            fields = {"level": record.levelname.lower(), "message": record.getMessage(), "logger": record.name}
            self._publish("log", fields)
        except Exception:  # noqa: BLE001 - a record that cannot be sent must not take its thread down: counted
            self.dropped += 1

    def attach(self) -> None:
        for name in PACKAGES:
            logger = logging.getLogger(name)
            logger.addHandler(self)
            self._levels[name] = logger.level
            if logger.getEffectiveLevel() > self.level:
                logger.setLevel(self.level)

    def detach(self) -> None:
        for name, level in self._levels.items():
            logger = logging.getLogger(name)
            logger.removeHandler(self)
            logger.setLevel(level)
        self._levels.clear()
