"""Compositors under test: one that keeps every frame it showed, a context that closes it, and its run on a
thread with a time limit, so that a hung run fails its test rather than the whole session. Imports the
compositor (about a second): hmdrt.testing loads this module on first use only."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import zmq

from hmdrt.compositor.config import load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.telemetry.report import FrameRecord


class Recording(Compositor):
    """The compositor, keeping every record the display shows with the images it showed."""

    def __init__(self, *args: Any, **kwargs: Any):
        self.shown: list[tuple[FrameRecord, list[np.ndarray]]] = []
        super().__init__(*args, **kwargs)

    def _shown(self, record: FrameRecord, images: list[np.ndarray]) -> None:
        self.shown.append((record, images))
        super()._shown(record, images)

    @property
    def records(self) -> list[FrameRecord]:
        """The records shown so far, in VSync order (a copy: safe to read while the run goes on)."""
        return [record for record, _ in list(self.shown)]


@contextmanager
def compositor(path: Path, context: zmq.Context, **run: Any) -> Iterator[Recording]:
    """A started Recording of the config at `path`, `run` overriding its [run] keys (frames=30,
    virtual_time=True, seed=1, duration_s=...); closed when the block ends."""
    comp = Recording(load_config(path, **run), context=context)
    try:
        yield comp
    finally:
        comp.close()


class Background:
    """compositor.run() on a thread; `report` once it has returned."""

    def __init__(self, comp: Compositor):
        self.comp: Compositor = comp
        self.report: dict | None = None
        self.error: BaseException | None = None
        self.thread = threading.Thread(target=self._run, name="test-compositor")
        self.started = time.monotonic()
        self.thread.start()

    def _run(self) -> None:
        try:
            self.report = self.comp.run()
        except BaseException as exc:  # handed to the test thread
            self.error = exc

    def join(self, timeout_s: float) -> tuple[dict, float]:
        """The report and the wall seconds run() took; fails the test when it has not returned by timeout_s."""
        self.thread.join(timeout_s)
        if self.thread.is_alive():
            self.comp.stop.set()
            self.thread.join(10)
            pytest.fail(f"compositor.run() still running after {timeout_s} s")
        if self.error is not None:
            raise self.error
        return self.report, time.monotonic() - self.started


def run_bounded(comp: Compositor, timeout_s: float = 60.0) -> tuple[dict, float]:
    """Run the compositor to its frame count or duration; its report and the wall seconds the run took. Fails the
    test when it has not ended by timeout_s."""
    return Background(comp).join(timeout_s)
