"""The native trace format: JSON Lines, one header then one sample per line (gzip allowed).

    {"format": "hmdrt-trace", "v": 1, "device": "synthetic"}
    {"kind": "gaze", "seq": 0, "t_host": 0, "valid": true, "C": [0.0, 0.0, -1.0], "depth_m": 1.5}
    {"kind": "gaze", "seq": 1, "t_host": 4000000, "valid": true, "L": [...], "R": [...]}
    {"kind": "pose", "seq": 0, "t_host": 0, "position": [0, 0, 0], "orientation": [1, 0, 0, 0]}

The samples are the bus's gaze and pose messages (hmdrt.bus.messages, which documents the fields):
t_host in integer nanoseconds, unit gaze vectors in the head frame per eye or combined, poses
relative to where the trace started. Lines that do not parse or validate are counted and skipped,
never fatal; a file without a valid header (its first line that is not blank) is an error.

Traces are read a line at a time into a SampleTable (replay/table.py) and written a batch of samples at a time, so
neither takes memory in proportion to the file beyond the table's columns; a file over MAX_FILE_BYTES, or a gzip
file that inflates past it, is refused with one line naming the cap.
"""

from __future__ import annotations

import gzip
import io
import zlib
from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass
from itertools import chain, islice
from pathlib import Path
from typing import IO, AnyStr

import msgspec

from hmdrt.bus.messages import Gaze, Pose, numpy_scalar, usable
from hmdrt.errors import ConfigError
from hmdrt.files.atomic import write_atomic
from hmdrt.replay.table import PACK, Sample, SampleTable

__all__ = [
    "Gaze",
    "Pose",
    "Sample",
    "SampleTable",
    "TraceReading",
    "TraceWriter",
    "capped_lines",
    "first_line",
    "open_capped",
    "read_trace",
    "usable",
    "write_chunks",
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


_decoder = msgspec.json.Decoder(Sample)
_header_decoder = msgspec.json.Decoder(Header)
_encoder = msgspec.json.Encoder(enc_hook=numpy_scalar)


@dataclass
class TraceReading:
    """Samples of a trace file in file order (the readers' are SampleTables), with the count of lines that were
    dropped."""

    device: str
    samples: Sequence[Sample]
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
            raise ConfigError(
                f"trace {getattr(stream, 'name', '')} holds more than {MAX_FILE_BYTES} bytes (once inflated), "
                "the most hmdrt reads of a trace"
            )
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
            samples = SampleTable(f"trace {path}")
            reading = TraceReading(header.device, samples)
            for line in lines:
                if line is None or not line.strip():
                    reading.malformed += line is None
                    continue
                try:
                    samples.append(_decoder.decode(line))
                except (ValueError, RecursionError):  # msgspec.DecodeError is a ValueError, as is a seq past 64 bits
                    reading.malformed += 1
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise ConfigError(f"cannot read trace {path}: {exc}") from None
    return reading


class TraceWriter:
    """Writes a native trace to a binary stream: the header (once the device is known), then samples."""

    def __init__(self, stream: IO[bytes]):
        self._stream = stream
        self.started = False

    def header(self, device: str) -> None:
        self._stream.write(_header_line(device))
        self.started = True

    def sample(self, sample: Sample) -> None:
        self._stream.write(_encoder.encode(sample) + b"\n")


def _header_line(device: str) -> bytes:
    return _encoder.encode(Header(FORMAT, VERSION, device)) + b"\n"


def batches(items: Iterable, size: int = PACK) -> Iterator[list]:
    """`items` in lists of `size` (the last one shorter)."""
    it = iter(items)
    while batch := list(islice(it, size)):
        yield batch


def write_chunks(path: Path, chunks: Iterable[bytes]) -> None:
    """Write the chunks whole or not at all (write_atomic), gzip-compressed when the name ends in .gz, holding one
    chunk at a time."""
    if path.suffix == ".gz":
        chunks = _gzipped(chunks)
    write_atomic(path, chunks)


def _gzipped(chunks: Iterable[bytes]) -> Iterator[bytes]:
    deflate = zlib.compressobj(9, zlib.DEFLATED, 31)  # gzip.compress(data, mtime=0) a chunk at a time
    for chunk in chunks:
        if out := deflate.compress(chunk):
            yield out
    yield deflate.flush()


def write_trace(path: str | Path, samples: Iterable[Sample], device: str = "") -> None:
    """Write samples as a native trace (gzip when the name ends in .gz), whole or not at all, a batch at a time."""
    lines = (_encoder.encode_lines(batch) for batch in batches(samples))
    write_chunks(Path(path), chain([_header_line(device)], lines))
