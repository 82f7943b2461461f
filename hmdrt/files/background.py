"""Writing off the render and display threads: items go through a short queue to a thread of their own.

In real time a full queue drops the item and counts it (`skipped`), so that the display never waits for a disk;
in virtual time (`block`) the caller waits until there is room instead, so that nothing is lost for lack of time
and a run writes the same files every time. An item that cannot be written is counted (`failed`) and the first
failure logged, never an exception on the caller's thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from typing import Generic, TypeVar

from hmdrt.errors import HmdrtError

log = logging.getLogger(__name__)

Item = TypeVar("Item")
WAIT_S = 0.5  # a blocked caller looks this often whether the writer thread is still there to make room


class BackgroundWriter(Generic[Item]):
    """A queue of `size` items and the thread that writes them with `_write` (subclasses implement it)."""

    def __init__(self, name: str, size: int, block: bool = False):
        self.block = block
        self._queue: queue.Queue[Item | None] = queue.Queue(size)
        self.skipped = 0  # items that found the queue full (real time)
        self.failed = 0  # items that could not be written
        self._thread = threading.Thread(target=self._run, name=name, daemon=True)

    @property
    def lost(self) -> int:
        """Items dropped for want of room (real time) or that could not be written: the run report's count."""
        return self.skipped + self.failed

    def start(self) -> None:
        self._thread.start()

    def _put(self, item: Item) -> None:
        """Queue `item`: wait for room when blocking and the writer runs, else skip it when the queue is full."""
        while self.block and self._thread.is_alive():
            try:
                self._queue.put(item, timeout=WAIT_S)
                return
            except queue.Full:
                continue
        try:
            self._queue.put_nowait(item)
        except queue.Full:
            self.skipped += 1

    def _run(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            try:
                self._write(item)
            except HmdrtError as exc:
                if not self.failed:
                    log.error("%s; later items that cannot be written are counted", exc)
                self.failed += 1
            del item  # held by no one while the next is awaited

    def _write(self, item: Item) -> None:
        """Write one item; HmdrtError when it cannot be written."""
        raise NotImplementedError

    def close(self) -> None:
        """Write what is queued and stop the thread; safe to call more than once and before start()."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
