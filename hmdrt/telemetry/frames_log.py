"""The per-frame log of `hmdrt run` (`[output] frames_log`): a header line naming the run, then every VSync's frame
record (the `frame` telemetry: predicted and actual times, new/late/repeat, method and parameters, stage times,
rays, the gaze and pose samples used, latencies) as one line of JSON.

A VSync's gaze error at photon time is known only once samples captured after its photon time have arrived, so it
is not on its own line, written at the VSync: it is on the line of the later VSync at which it became known, in
`gaze_errors`, naming its VSync (FramesLogReading.gaze_errors joins them back). A VSync without one was not resolved
(the run report counts why: hmdrt.compositor.gaze_error).

The log is written append-only on a thread of its own (hmdrt.files.background), each line straight to the file (no
buffer in between), so a run killed with SIGKILL keeps every frame up to its last line. In real time a full
queue drops the record and counts it; in virtual time the display waits, so every frame is logged. A record that
cannot be written (a full disk) is counted and leaves no part of its line: the log goes on with whole lines once
there is room. The reader is for `hmdrt export` and `hmdrt report plot`: it refuses oversized files and lines and
names the file and line of anything that is not a frame record. It leaves out a last line cut short (a run killed
mid-write), and skips and counts lines that are not JSON at all (the torn lines an older writer left on a disk that
filled up), with one warning.
"""

from __future__ import annotations

import contextlib
import logging
import os
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated

import msgspec

from hmdrt.errors import ConfigError, HmdrtError
from hmdrt.files.atomic import open_replacing
from hmdrt.files.background import BackgroundWriter
from hmdrt.telemetry.report import SHOWN, FrameRecord, GazeError

log = logging.getLogger(__name__)

FORMAT = "hmdrt-frames"
VERSION = 1
QUEUE = 1024  # records waiting to be written; in real time more are dropped and counted
MAX_LINE_BYTES = 64 * 1024
MAX_FILE_BYTES = 1024**3  # about six hours at 30 Hz
MAX_MS = 1e7  # a time in ms beyond this (about 2.8 hours) is no frame's
MAX_INT = 2**62  # times in ns, counts and ids: past this, no run's


class FramesHeader(msgspec.Struct, frozen=True, kw_only=True):
    """The first line: what the run was, and the display period and margin its frames are measured against."""

    format: str = FORMAT
    v: int = VERSION
    vsync_hz: Annotated[float, msgspec.Meta(gt=0.0, le=1000.0)]
    period_ns: Annotated[int, msgspec.Meta(gt=0)]
    margin_ns: Annotated[int, msgspec.Meta(ge=0)] = 0
    virtual_time: bool = False  # times are of the simulated clock; frame, stage and present ms are wall time
    method: str = ""
    profile: str = ""
    scene: str = ""
    controller: str = "none"
    seed: int = 0
    config: str = ""
    hmdrt: str = ""


_encoder = msgspec.json.Encoder()
_header_decoder = msgspec.json.Decoder(FramesHeader)
_record_decoder = msgspec.json.Decoder(FrameRecord)


class FramesLog(BackgroundWriter[dict]):
    """Writes the header at once (ConfigError when the file cannot be written), then each offered record.

    The file is made new (hmdrt.files.atomic.open_replacing: a link at the name is replaced, never written through)
    and holds whole lines only: a line that fails part-way (a full disk) is cut off again and counted, and the next
    one is tried in its place, so once there is room again the log goes on whole."""

    def __init__(self, path: str | Path, header: FramesHeader, block: bool = False):
        super().__init__("frames-log", QUEUE, block)
        self.path = Path(path)
        first = _encoder.encode(header) + b"\n"
        try:
            self._file = open_replacing(self.path, first)  # a run's log starts afresh, then only grows
        except OSError as exc:
            raise ConfigError(f"output.frames_log: cannot write {self.path}: {exc.strerror or exc}") from None
        self._end = len(first)  # where the next line goes: the end of the last whole line
        self._torn = False  # a failed write may have left part of a line after _end
        self._failing = False

    def offer(self, record: dict) -> None:
        """Queue a frame record (FrameRecord.to_dict()); called on the display thread."""
        self._put(record)

    def _line(self, data: bytes) -> None:
        """Write one line after the last whole one, all of it, with no buffer in between: a short write goes on
        from where it stopped; one that fails leaves the file ending on the last whole line (or cut back to it
        before the next line, when even that failed)."""
        fd, line, done = self._file.fileno(), memoryview(data + b"\n"), 0
        try:
            self._trim()
            while done < len(line):
                done += os.pwrite(fd, line[done:], self._end + done)
        except OSError:
            self._torn = self._torn or done > 0
            with contextlib.suppress(OSError):
                self._trim()
            raise
        self._end += len(line)

    def _trim(self) -> None:
        """Cut off what a failed write left after the last whole line."""
        if self._torn:
            os.ftruncate(self._file.fileno(), self._end)
            self._torn = False

    def _write(self, record: dict) -> None:
        try:
            self._line(_encoder.encode(record))
        except OSError as exc:
            self._failing = True
            raise HmdrtError(f"cannot write {self.path}: {exc.strerror or exc}") from None
        if self._failing:
            self._failing = False
            log.warning("%s: writing again; %d records could not be written (in the report)", self.path, self.failed)

    def close(self) -> None:
        """Write what is queued and close the file; safe to call more than once."""
        super().close()
        self._file.close()


@dataclass
class FramesLogReading:
    """A frames log read back: its header and records in file order."""

    path: Path
    header: FramesHeader
    records: list[FrameRecord]
    cut: bool = False  # its last line was cut short (a run killed mid-write) and left out
    corrupt: int = 0  # lines in the middle that are not JSON (torn by a full disk), left out

    def gaze_errors(self) -> dict[int, GazeError]:
        """Each resolved VSync's gaze error at photon time, by VSync (each is on the line of a later VSync)."""
        return {error.vsync: error for record in self.records for error in record.gaze_errors}


def _fault(record: FrameRecord) -> str | None:
    """What makes a decoded record one no run writes, or None."""
    if record.shown not in SHOWN:
        return f"shown is {record.shown!r}, not one of {', '.join(SHOWN)}"
    if record.vsync < 0 or record.frame_id < 0:
        return "a negative vsync or frame_id"
    uses = [vars(use) for use in (record.gaze, record.pose, record.warp_pose) if use is not None]
    if any(type(v) is int and not -MAX_INT < v < MAX_INT for fields in (vars(record), *uses) for v in fields.values()):
        return f"an integer beyond +-{MAX_INT}"
    times = {"frame_ms": record.frame_ms, "render_ms": record.render_ms, "present_ms": record.present_ms}
    times.update({f"stages_ms.{k}": v for k, v in record.stages_ms.items()})
    for name, ms in times.items():
        if not 0.0 <= ms <= MAX_MS:
            return f"{name} = {ms} is not a time in ms"
    if record.level is not None and not 0.0 <= record.level <= 1.0:
        return f"level = {record.level} is not in [0, 1]"
    for error in record.gaze_errors:
        if not 0 <= error.vsync <= record.vsync:
            return f"a gaze error of vsync {error.vsync}, neither this VSync nor an earlier one"
        for name in ("left_deg", "right_deg", "fovea_deg"):
            degrees = getattr(error, name)
            if degrees is not None and not 0.0 <= degrees <= 180.0:
                return f"gaze_errors: {name} = {degrees} is not an angle in degrees"
    return None


def _is_json(line: bytes) -> bool:
    """Whether a line is JSON of any shape; a line that a full disk cut off, joined to the next one, is not."""
    try:
        msgspec.json.decode(line)
    except (msgspec.ValidationError, RecursionError):  # a number out of range, nesting too deep: JSON all the same
        return True
    except msgspec.DecodeError:
        return False
    return True


def read_frames_log(path: str | Path) -> FramesLogReading:
    """Read a frames log; HmdrtError naming the file (and line) when it is too large or not a frames log."""
    path = Path(path)
    try:
        size = path.stat().st_size
        stream = path.open("rb")
    except OSError as exc:
        raise HmdrtError(f"cannot read frames log {path}: {exc.strerror or exc}") from None
    except ValueError as exc:  # a NUL in the path
        raise HmdrtError(f"cannot read frames log {path}: {exc}") from None
    if size > MAX_FILE_BYTES:
        stream.close()
        raise HmdrtError(f"frames log {path} is {size} bytes; the limit is {MAX_FILE_BYTES}")
    with stream:
        return _read(path, stream)


def _read(path: Path, stream) -> FramesLogReading:
    header, records, total, number, cut = None, [], 0, 0, False
    corrupt, first_corrupt = 0, 0
    while line := stream.readline(MAX_LINE_BYTES + 1):
        number += 1
        total += len(line)
        where = f"{path}:{number}"
        if len(line) > MAX_LINE_BYTES:
            raise HmdrtError(f"{where}: a line longer than {MAX_LINE_BYTES} bytes")
        if total > MAX_FILE_BYTES:
            raise HmdrtError(f"{path}: more than {MAX_FILE_BYTES} bytes")
        try:
            decoded = (_header_decoder if header is None else _record_decoder).decode(line)
        except (msgspec.DecodeError, RecursionError) as exc:
            if not line.endswith(b"\n") and header is not None:  # the last line, cut by a kill: the rest stands
                log.warning("%s: the last line is cut short (a run killed mid-write?); left out", where)
                cut = True
                break
            if header is not None and not _is_json(line):  # torn by a full disk: the lines around it stand
                corrupt += 1
                first_corrupt = first_corrupt or number
                continue
            what = "a frames log header" if header is None else "a frame record"
            reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
            reason = "an empty line" if not line.strip() else reason
            raise HmdrtError(f"{where}: not {what}: {reason}") from None
        if header is None:
            if decoded.format != FORMAT or decoded.v != VERSION:
                raise HmdrtError(
                    f"{where}: not a {FORMAT} log of version {VERSION} (format {decoded.format!r}, v {decoded.v})"
                )
            header = decoded
            continue
        fault = _fault(decoded)
        if fault is None and records and decoded.vsync <= records[-1].vsync:
            fault = f"vsync {decoded.vsync} after vsync {records[-1].vsync}: out of order"
        if fault is not None:
            raise HmdrtError(f"{where}: not a frame record: {fault}")
        records.append(decoded)
    if header is None:
        raise HmdrtError(f"{path}: empty, not a frames log")
    if corrupt:
        lines = "a line" if corrupt == 1 else f"{corrupt} lines"
        log.warning("%s: %s not JSON (torn by a full disk?) left out, the first at line %d", path, lines, first_corrupt)
    return FramesLogReading(path, header, records, cut, corrupt)
