"""The shown frames on disk: every `every`th VSync as a PNG in a folder and/or a frame of a video
(`[output] frames_dir`, `video`, `every`), written on a thread of their own so that the display never waits.

Frames wait in a short queue; one that finds it full is skipped and one that cannot be written is counted
(the first failure said once on stderr), never an exception on the display thread.
"""

from __future__ import annotations

import logging
import queue
import threading
from pathlib import Path

import numpy as np

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.present.encode import side_by_side_srgb8, write_png
from hmdrt.present.video import VideoWriter

log = logging.getLogger(__name__)

QUEUE = 8  # shown frames waiting to be written; more are skipped and counted


def check_folder(folder: str) -> None:
    """Create the frames folder (if one is asked for) or raise ConfigError."""
    if folder:
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"output.frames_dir: cannot create {folder}: {exc.strerror}") from None


class FrameWriter:
    """Writes every `every`th offered frame (the eyes side by side, sRGB) to `folder` as vsync_NNNNNN.png and to
    `video` at refresh_hz / every frames per second; ConfigError at once when either cannot be written."""

    def __init__(self, folder: str, video: str, every: int, refresh_hz: float):
        check_folder(folder)
        self.folder, self.every = folder, every
        self._video = VideoWriter(video, refresh_hz / every) if video else None
        self._queue: queue.Queue = queue.Queue(QUEUE)
        self.skipped = 0  # frames that found the queue full
        self.failed = 0  # frames that could not be written
        self._thread = threading.Thread(target=self._run, name="frame-writer", daemon=True)

    def configure(self, folder: str, every: int) -> None:
        """A new folder and rate (a reload; check_folder first): the video's rate stays as it started."""
        self.folder, self.every = folder, every

    def start(self) -> None:
        self._thread.start()

    def offer(self, vsync: int, images: list[np.ndarray]) -> None:
        """Queue the frame shown at VSync `vsync` if it is one to write; called on the display thread."""
        if (self.folder or self._video) and vsync % self.every == 0:
            try:
                self._queue.put_nowait((vsync, images))
            except queue.Full:
                self.skipped += 1

    def _run(self) -> None:
        """Encode each queued frame into one reused buffer, then write it."""
        srgb8 = None
        while True:
            item = self._queue.get()
            if item is None:
                return
            vsync, images = item
            width = sum(image.shape[1] for image in images)
            if srgb8 is None or srgb8.shape != (images[0].shape[0], width, 3):
                srgb8 = np.empty((images[0].shape[0], width, 3), np.uint8)
            side_by_side_srgb8(images, srgb8)
            del item, images  # the shown images' buffers go back to their pools while this one waits
            folder = self.folder
            try:
                if folder:
                    write_png(Path(folder) / f"vsync_{vsync:06d}.png", srgb8)
                if self._video is not None:
                    self._video.append(srgb8)
            except HmdrtError as exc:
                if not self.failed:
                    log.error("%s; later frames that cannot be written are counted", exc)
                self.failed += 1

    def close(self) -> None:
        """Write what is queued, then finish the video; safe to call more than once and before start()."""
        if self._thread.is_alive():
            self._queue.put(None)
            self._thread.join()
        video, self._video = self._video, None
        if video is not None:
            try:
                video.close()
            except HmdrtError as exc:
                log.error("%s", exc)
