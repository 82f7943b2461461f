"""What the compositor's start-up is doing and how long each of its steps took: compiling the method's kernels
and the timewarp (half a minute or more on a first run, about a second from numba's cache), then connecting the
drivers (up to a few seconds), so that the wait before the first VSync says what it waits for."""

from __future__ import annotations

import logging
import threading
import time

log = logging.getLogger(__name__)


class Startup:
    """The start-up's steps in order, each with when it began; read by the status line's thread."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self._steps: list[tuple[str, float]] = []
        self._ended: float | None = None

    def step(self, what: str) -> None:
        """Begin the step `what`, ending the one before (logged with its time)."""
        with self._lock:
            self._finish(time.monotonic())
            self._steps.append((what, time.monotonic()))

    def end(self) -> None:
        with self._lock:
            self._finish(time.monotonic())
            self._ended = time.monotonic()

    def _finish(self, now: float) -> None:
        if self._steps and self._ended is None:
            what, began = self._steps[-1]
            log.info("%s: %.1f s", what, now - began)

    def now(self) -> str:
        """The step under way and its time so far, after the finished steps' times."""
        with self._lock:
            if not self._steps:
                return "starting"
            now = time.monotonic()
            done = [f"{what} {self._seconds(k, now):.0f} s" for k, (what, _) in enumerate(self._steps[:-1])]
            what = self._steps[-1][0]
            return "; ".join([*done, f"{what}: {now - self._steps[-1][1]:.0f} s"])

    def summary(self) -> str:
        """Each step with its time, once the start-up has ended: "compiling ... 61 s, connecting drivers 0 s"."""
        with self._lock:
            now = self._ended or time.monotonic()
            return ", ".join(f"{what} {self._seconds(k, now):.1f} s" for k, (what, _) in enumerate(self._steps))

    def _seconds(self, k: int, now: float) -> float:
        end = self._steps[k + 1][1] if k + 1 < len(self._steps) else now
        return end - self._steps[k][1]
