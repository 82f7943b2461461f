"""The native trace format: JSON Lines, one header then one sample per line (gzip allowed).

    {"format": "hmdrt-trace", "v": 1, "device": "synthetic"}
    {"kind": "gaze", "seq": 0, "t_ns": 0, "valid": true, "C": [0.0, 0.0, -1.0], "depth_m": 1.5}
    {"kind": "gaze", "seq": 1, "t_ns": 4000000, "valid": true, "L": [...], "R": [...]}
    {"kind": "pose", "seq": 0, "t_ns": 0, "position": [0, 0, 0], "orientation": [1, 0, 0, 0]}

Times are integer nanoseconds on the host clock (t_dev keeps the device's own stamp when known).
Gaze directions are unit vectors in the head frame (right-handed, +Y up, -Z forward) per eye (L, R)
or combined (C); depth_m is the vergence depth. Pose is the head position (m) and orientation
quaternion (w, x, y, z) relative to where the trace started. Lines that do not parse or validate are
counted and skipped, never fatal; a file without a valid header is an error.
"""

from __future__ import annotations

import gzip
import io
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np

from hmdrt.errors import ConfigError

FORMAT = "hmdrt-trace"
VERSION = 1
MAX_LINE_BYTES = 64 * 1024
MAX_FILE_BYTES = 2 * 1024**3

Finite = Annotated[float, msgspec.Meta(ge=-1e9, le=1e9)]
Vec3 = tuple[Finite, Finite, Finite]
Quat = tuple[Finite, Finite, Finite, Finite]
TimeNs = Annotated[int, msgspec.Meta(ge=-(2**62), le=2**62)]


class Header(msgspec.Struct, frozen=True):
    format: str
    v: int
    device: str = ""


class Gaze(msgspec.Struct, frozen=True, tag="gaze", tag_field="kind", forbid_unknown_fields=True, omit_defaults=True):
    seq: Annotated[int, msgspec.Meta(ge=0)]
    t_ns: TimeNs
    t_dev: TimeNs | None = None
    valid: bool = True
    C: Vec3 | None = None
    L: Vec3 | None = None
    R: Vec3 | None = None
    depth_m: Annotated[float, msgspec.Meta(gt=0, le=1e6)] | None = None


class Pose(msgspec.Struct, frozen=True, tag="pose", tag_field="kind", forbid_unknown_fields=True, omit_defaults=True):
    seq: Annotated[int, msgspec.Meta(ge=0)]
    t_ns: TimeNs
    position: Vec3
    orientation: Quat
    t_dev: TimeNs | None = None
    valid: bool = True


Sample = Gaze | Pose
_decoder = msgspec.json.Decoder(Sample)
_header_decoder = msgspec.json.Decoder(Header)


def _unit(v: Vec3 | None, tol: float = 1e-3) -> bool:
    return v is not None and abs(float(np.linalg.norm(v)) - 1.0) <= tol


def usable(sample: Sample) -> bool:
    """Whether a sample can drive a frame: valid, with unit gaze directions or a unit quaternion."""
    if not sample.valid:
        return False
    if isinstance(sample, Pose):
        return _unit(sample.orientation)
    eyes = [v for v in (sample.C, sample.L, sample.R) if v is not None]
    return bool(eyes) and all(_unit(v) for v in eyes)


@dataclass
class TraceReading:
    """Samples of a trace file in file order, with the count of lines that were dropped."""

    device: str
    samples: list[Sample]
    malformed: int = 0


def _open(path: Path) -> io.BufferedIOBase:
    try:
        size = path.stat().st_size
    except FileNotFoundError:
        raise ConfigError(f"trace not found: {path}") from None
    if size > MAX_FILE_BYTES:
        raise ConfigError(f"trace {path} is {size} bytes; the limit is {MAX_FILE_BYTES}")
    raw = path.open("rb")
    return gzip.GzipFile(fileobj=raw) if path.suffix == ".gz" else raw


def _lines(stream: io.BufferedIOBase) -> Iterator[bytes | None]:
    """Lines of at most MAX_LINE_BYTES; None stands for an over-long line (skipped to its end)."""
    while True:
        line = stream.readline(MAX_LINE_BYTES + 1)
        if not line:
            return
        if len(line) > MAX_LINE_BYTES and not line.endswith(b"\n"):
            while (rest := stream.readline(MAX_LINE_BYTES)) and not rest.endswith(b"\n"):
                pass
            yield None
        else:
            yield line


def read_trace(path: str | Path) -> TraceReading:
    """Read a native trace; malformed lines are counted in TraceReading.malformed."""
    path = Path(path)
    try:
        with _open(path) as stream:
            lines = _lines(stream)
            first = next(lines, None)
            try:
                header = _header_decoder.decode(first or b"")
            except msgspec.DecodeError:
                header = None
            if header is None or header.format != FORMAT:
                raise ConfigError(f"{path} is not an {FORMAT} file (its first line must be the header)")
            if header.v != VERSION:
                raise ConfigError(f"{path} is {FORMAT} version {header.v}; this hmdrt reads version {VERSION}")
            reading = TraceReading(header.device, [])
            for line in lines:
                if line is None or not line.strip():
                    reading.malformed += line is None
                    continue
                try:
                    reading.samples.append(_decoder.decode(line))
                except msgspec.DecodeError:
                    reading.malformed += 1
    except (OSError, EOFError, gzip.BadGzipFile) as exc:
        raise ConfigError(f"cannot read trace {path}: {exc}") from None
    return reading


def _numpy_scalar(obj):
    if isinstance(obj, np.generic):
        return obj.item()
    raise NotImplementedError(f"cannot write {type(obj).__name__} to a trace")


def write_trace(path: str | Path, samples: Iterable[Sample], device: str = "") -> None:
    """Write samples as a native trace (gzip when the name ends in .gz)."""
    path = Path(path)
    encoder = msgspec.json.Encoder(enc_hook=_numpy_scalar)
    opener = gzip.open if path.suffix == ".gz" else open
    with opener(path, "wb") as f:
        f.write(encoder.encode(Header(FORMAT, VERSION, device)) + b"\n")
        for sample in samples:
            f.write(encoder.encode(sample) + b"\n")
