"""Incremental framing of a serial byte stream, shared by the Razor and HATIRE codecs."""

from __future__ import annotations

from abc import ABC, abstractmethod
from typing import Generic, TypeVar

Frame = TypeVar("Frame")


class FrameFormatError(ValueError):
    """Bytes that are not a valid frame of a serial tracker protocol."""


class Framer(ABC, Generic[Frame]):
    """feed() byte chunks of any size, get decoded frames; `discarded` counts the bytes that belong to none."""

    def __init__(self) -> None:
        self._buf = bytearray()
        self.discarded = 0

    def _drop(self, n: int) -> None:
        del self._buf[:n]
        self.discarded += n

    def feed(self, chunk: bytes) -> list[Frame]:
        self._buf += chunk
        frames: list[Frame] = []
        while (size := self._next_size()) is not None:
            try:
                frames.append(self._decode(bytes(self._buf[:size])))
                del self._buf[:size]
            except FrameFormatError:
                self._drop(size)
        return frames

    @abstractmethod
    def _next_size(self) -> int | None:
        """Drop what cannot start a frame; the size of the candidate frame now at the buffer's start, or
        None while more bytes are needed."""

    @staticmethod
    @abstractmethod
    def _decode(data: bytes) -> Frame:
        """One candidate frame, decoded; FrameFormatError when it is not valid."""
