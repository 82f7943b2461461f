"""Progress on a terminal: one status line rewritten in place while long work runs, and nothing at all when the
stream is not a terminal (a log file or a pipe keeps only what the command prints at the end)."""

from __future__ import annotations

import sys
import threading
import time
from collections.abc import Callable
from typing import TextIO

CLEAR_LINE = "\r\x1b[K"  # carriage return, then erase to the end of the line (ECMA-48 EL)


class StatusLine:
    """A context that rewrites one line of `stream` (sys.stderr by default) every `interval_s` with `text(elapsed_s)`
    and clears it on exit; a no-op when the stream is not a terminal."""

    def __init__(self, text: Callable[[float], str], stream: TextIO | None = None, interval_s: float = 1.0) -> None:
        self._text, self._stream, self._interval_s = text, stream, interval_s
        self._stop = threading.Event()
        self._thread: threading.Thread | None = None

    def __enter__(self) -> StatusLine:
        stream = self._stream if self._stream is not None else sys.stderr
        if stream.isatty():
            self._stream = stream
            self._thread = threading.Thread(target=self._loop, args=(time.monotonic(),), name="status", daemon=True)
            self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._thread is None:
            return
        self._stop.set()
        self._thread.join()
        self._stream.write(CLEAR_LINE)
        self._stream.flush()

    def _loop(self, start: float) -> None:
        while True:
            try:
                line = self._text(time.monotonic() - start)
            except Exception as exc:  # a status that cannot be read now is shown as such, not raised in a thread
                line = f"status unavailable: {exc}"
            self._stream.write(CLEAR_LINE + line)
            self._stream.flush()
            if self._stop.wait(self._interval_s):
                return
