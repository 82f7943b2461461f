"""The native trace format: JSON Lines, one header then one sample per line (gzip allowed).

    {"format": "hmdrt-trace", "v": 1, "device": "synthetic"}
    {"kind": "gaze", "seq": 0, "t_host": 0, "valid": true, "C": [0.0, 0.0, -1.0], "depth_m": 1.5}
    {"kind": "gaze", "seq": 1, "t_host": 4000000, "valid": true, "L": [...], "R": [...]}
    {"kind": "pose", "seq": 0, "t_host": 0, "position": [0, 0, 0], "orientation": [1, 0, 0, 0]}

The samples are the bus's gaze and pose messages (hmdrt.bus.messages, which documents the fields):
t_host in integer nanoseconds, unit gaze vectors in the head frame per eye or combined, poses
relative to where the trace started. Lines that do not parse or validate are counted and skipped,
never fatal; a file without a valid header (its first line that is not blank) is an error.
"""

from __future__ import annotations

import gzip
import io
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, AnyStr

import msgspec

from hmdrt.bus.messages import Gaze, Pose, numpy_scalar, usable
from hmdrt.errors import ConfigError
from hmdrt.files.atomic import write_atomic

__all__ = [
    "Gaze",
    "Pose",
    "Sample",
    "TraceReading",
    "TraceWriter",
    "capped_lines",
    "first_line",
    "open_capped",
    "read_trace",
    "usable",
    "write_trace",
]

FORMAT = "hmdrt-trace"
VERSION = 1
MAX_LINE_BYTES = 64 * 1024
MAX_FILE_BYTES = 2 * 1024**3


class Header(msgspec.Struct, frozen=True):
    format: str
    v: int
    device: str = ""


Sample = Gaze | Pose
_decoder = msgspec.json.Decoder(Sample)
_header_decoder = msgspec.json.Decoder(Header)


@dataclass
class TraceReading:
    """Samples of a trace file in file order, with the count of lines that were dropped."""

    device: str
    samples: list[Sample]
    malformed: int = 0


def open_capped(path: Path) -> io.BufferedIOBase:
    """A trace file opened for reading (gunzipped when it ends in .gz), refused over MAX_FILE_BYTES."""
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise ConfigError(f"trace not found: {path}") from None
    except (OSError, ValueError) as exc:  # ValueError: a NUL in the path (replay://a%00b.jsonl)
        raise ConfigError(f"cannot read trace {path}: {exc}") from None
    if size > MAX_FILE_BYTES:
        raise ConfigError(f"trace {path} is {size} bytes; the limit is {MAX_FILE_BYTES}")
    return gzip.GzipFile(path, "rb") if path.suffix == ".gz" else path.open("rb")  # GzipFile(path) closes the file


def capped_lines(stream: io.BufferedIOBase) -> Iterator[bytes | None]:
    """Lines of at most MAX_LINE_BYTES; None stands for an over-long line (skipped to its end). More than
    MAX_FILE_BYTES in all (a gzip file that inflates past it) is a ConfigError."""
    total = 0
    while True:
        line = stream.readline(MAX_LINE_BYTES + 1)
        total += len(line)
        if not line:
            return
        if len(line) > MAX_LINE_BYTES and not line.endswith(b"\n"):
            line = None  # skip to the line's end
            while total <= MAX_FILE_BYTES and (rest := stream.readline(MAX_LINE_BYTES)):
                total += len(rest)
                if rest.endswith(b"\n"):
                    break
        if total > MAX_FILE_BYTES:
            raise ConfigError(f"trace {getattr(stream, 'name', '')} holds more than {MAX_FILE_BYTES} bytes")
        yield line


def first_line(lines: Iterator[AnyStr | None]) -> AnyStr | None:
    """The first line that is not blank (editors and exporters leave blank lines before a header); None when
    there is none, and for an over-long line."""
    return next((line for line in lines if line is None or line.strip()), None)


def read_trace(path: str | Path) -> TraceReading:
    """Read a native trace; malformed lines are counted in TraceReading.malformed."""
    path = Path(path)
    try:
        with open_capped(path) as stream:
            lines = capped_lines(stream)
            first = first_line(lines)
            try:
                header = _header_decoder.decode(first or b"")
            except (msgspec.DecodeError, RecursionError):  # RecursionError: nested deeper than msgspec follows
                header = None
            if header is None or header.format != FORMAT:
                raise ConfigError(f"{path} is not an {FORMAT} file (the header must come first)")
            if header.v != VERSION:
                raise ConfigError(f"{path} is {FORMAT} version {header.v}; this hmdrt reads version {VERSION}")
            reading = TraceReading(header.device, [])
            for line in lines:
                if line is None or not line.strip():
                    reading.malformed += line is None
                    continue
                try:
                    reading.samples.append(_decoder.decode(line))
                except (msgspec.DecodeError, RecursionError):
                    reading.malformed += 1
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise ConfigError(f"cannot read trace {path}: {exc}") from None
    return reading


class TraceWriter:
    """Writes a native trace to a binary stream: the header (once the device is known), then samples."""

    def __init__(self, stream: IO[bytes]):
        self._stream = stream
        self._encoder = msgspec.json.Encoder(enc_hook=numpy_scalar)
        self.started = False

    def header(self, device: str) -> None:
        self._stream.write(self._encoder.encode(Header(FORMAT, VERSION, device)) + b"\n")
        self.started = True

    def sample(self, sample: Sample) -> None:
        self._stream.write(self._encoder.encode(sample) + b"\n")


def write_trace(path: str | Path, samples: Iterable[Sample], device: str = "") -> None:
    """Write samples as a native trace (gzip when the name ends in .gz), whole or not at all (write_atomic)."""
    path = Path(path)
    buffer = io.BytesIO()
    writer = TraceWriter(buffer)
    writer.header(device)
    for sample in samples:
        writer.sample(sample)
    data = buffer.getvalue()
    write_atomic(path, gzip.compress(data, mtime=0) if path.suffix == ".gz" else data)
