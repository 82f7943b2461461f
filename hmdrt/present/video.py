"""What the display showed, as a video a person can watch at the rate it was shown (`[output] video`).

Written through imageio's ffmpeg plugin (the `video` extra: imageio and imageio-ffmpeg, which brings a static
ffmpeg) as H.264 in yuv420p, which any player opens. yuv420p needs even sides, so an odd one gets its last
row or column repeated (in a buffer kept for the run) rather than the frame resized. ffmpeg writes a new hidden file
beside the video (hmdrt.files.atomic), renamed to the video's name when it is finished: a link at that name is
replaced, never written through, and a video that cannot be finished leaves no file.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.atomic import temporary_beside

INSTALL = "pip install -e '.[video]'"


class VideoWriter:
    """Appends uint8 sRGB frames of one size to a video file at fps frames per second."""

    def __init__(self, path: str | Path, fps: float):
        """Checks at once that imageio and its ffmpeg plugin are there and the folder is writable; ConfigError."""
        try:
            import imageio.v2 as imageio
            import imageio_ffmpeg  # noqa: F401  (the plugin imageio needs for these formats)
        except ImportError:
            raise ConfigError(f"output.video needs imageio and imageio-ffmpeg: {INSTALL}") from None
        self.path = Path(path)
        self._tmp: Path | None = None
        try:
            fd, self._tmp = temporary_beside(self.path, suffix=self.path.suffix)  # ffmpeg's container: by the suffix
            os.close(fd)
            self._writer = imageio.get_writer(
                self._tmp, format="FFMPEG", mode="I", fps=fps, codec="libx264", pixelformat="yuv420p",
                macro_block_size=1, quality=8,
            )  # fmt: skip
        except (OSError, ValueError, RuntimeError) as exc:
            self._discard()
            raise ConfigError(
                f"output.video: cannot write {self.path}: {getattr(exc, 'strerror', None) or exc}"
            ) from None
        self.frames = 0
        self._padded: np.ndarray | None = None  # frames with an odd side, padded to even ones

    def append(self, srgb8: np.ndarray) -> None:
        """Add one (h, w, 3) uint8 frame; HmdrtError when ffmpeg refuses it (a full disk, a changed size)."""
        h, w = srgb8.shape[:2]
        if h % 2 or w % 2:
            shape = (h + h % 2, w + w % 2, 3)
            if self._padded is None or self._padded.shape != shape:
                self._padded = np.empty(shape, np.uint8)
            padded = self._padded
            padded[:h, :w] = srgb8
            padded[h:, :w] = srgb8[h - 1 :]
            padded[:, w:] = padded[:, w - 1 : w]
            srgb8 = padded
        try:
            self._writer.append_data(srgb8)
        except (OSError, ValueError, RuntimeError) as exc:
            raise HmdrtError(f"cannot add frame {self.frames} to {self.path}: {exc}") from None
        self.frames += 1

    def close(self) -> None:
        """Finish the video and put it in place (none when no frame was added); HmdrtError when it cannot be."""
        try:
            self._writer.close()
            if self.frames:
                os.replace(self._tmp, self.path)
                self._tmp = None
        except (OSError, ValueError, RuntimeError) as exc:
            raise HmdrtError(f"cannot finish {self.path}: {getattr(exc, 'strerror', None) or exc}") from None
        finally:
            self._discard()

    def _discard(self) -> None:
        """Remove the unfinished video's file, if there is one."""
        if self._tmp is not None:
            self._tmp.unlink(missing_ok=True)
            self._tmp = None
