"""The shown frames on disk: every `every`th VSync as a PNG in a folder and/or a frame of a video
(`[output] frames_dir`, `video`, `every`), written on a thread of their own (hmdrt.files.background).

Frames wait in a short queue; in real time one that finds it full is skipped and counted, so the display never
waits, in virtual time the display waits for room, so every frame is written. One that cannot be written is
counted (the first failure said once on stderr), never an exception on the display thread.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.background import BackgroundWriter
from hmdrt.present.encode import side_by_side_srgb8, write_png
from hmdrt.present.video import VideoWriter

log = logging.getLogger(__name__)

QUEUE = 8  # shown frames waiting to be written; in real time more are skipped and counted


def check_folder(folder: str) -> None:
    """Create the frames folder (if one is asked for) or raise ConfigError."""
    if folder:
        try:
            Path(folder).mkdir(parents=True, exist_ok=True)
        except OSError as exc:
            raise ConfigError(f"output.frames_dir: cannot create {folder}: {exc.strerror}") from None


class FrameWriter(BackgroundWriter[list]):
    """Writes every `every`th offered frame (the eyes side by side, sRGB) to `folder` as vsync_NNNNNN.png and to
    `video` at video_hz frames per second (the display's rate over `every`, fixed for the video's life); ConfigError
    at once when the video cannot be written. The folder and `every` are configure()'s: none, and every frame, until
    it is called. With `block` (virtual time) offer() waits for room in the queue rather than skip a frame."""

    def __init__(self, video: str, video_hz: float, block: bool = False):
        super().__init__("frame-writer", QUEUE, block)
        self.folder, self.every = "", 1
        self._video = VideoWriter(video, video_hz) if video else None
        self._srgb8: np.ndarray | None = None  # the encoded frame, one buffer reused

    def configure(self, folder: str, every: int) -> None:
        """The folder (check_folder first) and the rate, at start and on a reload: the video's rate stays as it
        started."""
        self.folder, self.every = folder, every

    def offer(self, vsync: int, images: list[np.ndarray]) -> None:
        """Queue the frame shown at VSync `vsync` if it is one to write; called on the display thread."""
        if (self.folder or self._video) and vsync % self.every == 0:
            self._put([vsync, images])

    def _write(self, item: list) -> None:
        """Encode the queued frame into the reused buffer, then write it."""
        vsync, images = item
        width = sum(image.shape[1] for image in images)
        if self._srgb8 is None or self._srgb8.shape != (images[0].shape[0], width, 3):
            self._srgb8 = np.empty((images[0].shape[0], width, 3), np.uint8)
        side_by_side_srgb8(images, self._srgb8)
        item.clear()  # the shown images' buffers go back to their pools while this one is written
        del images
        folder = self.folder
        if folder:
            write_png(Path(folder) / f"vsync_{vsync:06d}.png", self._srgb8)
        if self._video is not None:
            self._video.append(self._srgb8)

    def close(self) -> None:
        """Write what is queued, then finish the video; safe to call more than once and before start()."""
        super().close()
        video, self._video = self._video, None
        if video is not None:
            try:
                video.close()
            except HmdrtError as exc:
                log.error("%s", exc)
