"""lsl://?type=Gaze&name=STREAM&source_id=ID: gaze from a Lab Streaming Layer stream (docs/protocols.md, LSL).

open() resolves the one stream of the type, name and source_id given (LSL's discovery, as lsl_api.cfg or LSLAPICFG
set it) within `timeout` seconds; when none matches it names the streams it found and raises DeviceLost, so that a
host tries again. It reads the stream's XDF Gaze meta-data (drivers.protocols.lsl_gaze) before any sample and fails
with one error naming the stream and what is wrong when they lie (a string format, too many channels, more channels
described than the stream has, a count or format other than the one announced to discovery) or do not say where the
gaze is; a compositor's driver thread counts that as a crash and tries again with backoff (drivers.host). A sample's
timestamp is the sender's local_clock(); the inlet's time_correction() (liblsl's round-trip probes, refreshed in the
background) maps it to this machine's local_clock(), which is taken for the host clock only where
hmdrt.bus.lsl.ClockMap finds them one clock; otherwise (or in virtual time) the clock sync maps it from receive times,
as for the other network devices. Gaps of under a
second in the timestamps of a stream with a nominal rate count as dropped samples (longer ones are pauses), rows
with infinite or huge values as malformed.
"""

from __future__ import annotations

import logging
import math

import msgspec
import numpy as np

from hmdrt.bus.lsl import ClockMap, load_pylsl
from hmdrt.bus.messages import ClockEstimate, Gaze, Status
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverError, DriverUrl, Sample
from hmdrt.drivers.protocols.lsl_gaze import (
    AXES,
    ORIGINS,
    GazeDecoder,
    MetadataError,
    StreamMeta,
    gaze_layout,
    parse_info,
)
from hmdrt.errors import ConfigError
from hmdrt.optics import get_profile

DEFAULT_PROFILE = "sim-cpu-640"  # the compositor's default display: its screens map ScreenX/Y
BUFFER_S = 10  # seconds of samples the inlet keeps while the driver is not reading (liblsl's max_buflen)
MAX_BATCH = 4096  # samples taken per read()
LIST_WAIT_S = 1.0  # how long the list of streams found takes (not 0.5 s: liblsl 1.18 then waits 5 s more)
MAX_LISTED = 20
MAX_SELECTOR = 256  # characters of a type, name or source_id
MAX_GAP_S = 1.0  # a longer silence of a regular stream is a pause, not dropped samples
MAX_TIME_S = 2**61 / 1e9  # timestamps beyond this leave the bus's time range once mapped

log = logging.getLogger(__name__)


class LslDriver(Driver):
    scheme = "lsl"
    grammar = (
        "lsl://?type=Gaze&name=STREAM&source_id=ID&timeout=S&axes=head|opencv|unity&profile=NAME"
        "&origin=top-left|bottom-left&confidence=C (name= picks the stream by its LSL name and names the bus device; "
        f"defaults type Gaze, timeout 5 s, axes head, profile {DEFAULT_PROFILE}, origin top-left, confidence 0.6)"
    )
    options = {
        "type": (str, "Gaze", None, None),
        "source_id": (str, "", None, None),
        "timeout": (float, 5.0, 0.1, 60.0),
        "axes": (str, "head", None, None),
        "profile": (str, DEFAULT_PROFILE, None, None),
        "origin": (str, "top-left", None, None),
        "confidence": (float, 0.6, 0.0, 1.0),
    }

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        if self.url.netloc or self.url.path:
            raise ConfigError(f"lsl:// takes no host or path (LSL finds streams itself); expected {self.grammar}")
        if self.opt["axes"] not in AXES or self.opt["origin"] not in ORIGINS:
            raise ConfigError(f"lsl:// axes= is one of {', '.join(AXES)} and origin= one of {', '.join(ORIGINS)}")
        self.profile = get_profile(self.opt["profile"])
        selectors = {
            "type": self.opt["type"],
            "name": self.url.options.get("name", ""),
            "source_id": self.opt["source_id"],
        }
        for key, value in selectors.items():
            if "'" in value or not value.isprintable() or len(value) > MAX_SELECTOR:
                raise ConfigError(f"lsl:// {key}= must be printable, without quotes, at most {MAX_SELECTOR} characters")
        if not selectors["type"]:
            raise ConfigError("lsl:// type= must name the stream type (default Gaze)")
        self.predicate = " and ".join(f"{key}='{value}'" for key, value in selectors.items() if value)
        self.decoder: GazeDecoder | None = None
        self._inlet = None
        self._lsl = None
        self._map: ClockMap | None = None
        self._correction = 0.0  # seconds to add to the sender's timestamps for this machine's local_clock()
        self._last_stamp: float | None = None
        self._seq = 0

    def open(self) -> None:
        lsl = self._lsl = load_pylsl()
        timeout = self.opt["timeout"]
        found = lsl.resolve_bypred(self.predicate, 1, timeout)
        if not found:
            message = f"no LSL stream matches {self.predicate} within {timeout:g} s; {self._streams()}"
            log.warning(message)
            raise DeviceLost(message)
        if len(found) > 1:
            raise DriverError(
                f"{len(found)} LSL streams match {self.predicate}: {_listing(found)}; "
                "choose one with name= or source_id="
            )
        inlet = lsl.StreamInlet(found[0], max_buflen=BUFFER_S, recover=False)
        try:
            layout = gaze_layout(_checked_meta(found[0], inlet.info(timeout)))
            self.decoder = GazeDecoder(
                layout, self.opt["axes"], self.profile, self.opt["origin"], self.opt["confidence"]
            )
            inlet.open_stream(timeout)
            self._correction = inlet.time_correction(timeout)
        except MetadataError:
            inlet.close_stream()
            raise
        except RuntimeError as exc:  # pylsl's errors: timed out, lost, liblsl failed
            inlet.close_stream()
            raise DeviceLost(f"LSL stream {found[0].name()!r} did not answer within {timeout:g} s: {exc}") from None
        self._inlet, self._map, self._last_stamp = inlet, ClockMap.measure(self.clock), None
        log.info("lsl://: reading %s: %s", layout.meta.title(), layout.describe())
        self.state = "connected"

    def _streams(self) -> str:
        """The streams LSL finds now, for a message saying that none matched."""
        streams = self._lsl.resolve_streams(LIST_WAIT_S)
        if not streams:
            return "LSL found no stream at all (is the source running, and within lsl_api.cfg's ResolveScope?)"
        return f"streams found: {_listing(streams)}"

    def read(self, timeout_s: float) -> list[Sample]:
        if self._inlet is None:
            raise DeviceLost("lsl:// is not connected")
        util = self._lsl.util
        try:
            first, stamp = self._inlet.pull_sample(timeout=max(timeout_s, 0.0))
            if first is None:
                return []
            rows, stamps = self._inlet.pull_chunk(timeout=0.0, max_samples=MAX_BATCH)
            try:
                self._correction = self._inlet.time_correction(0.0)
            except util.TimeoutError:
                pass  # no new estimate yet: the last one holds
        except RuntimeError as exc:  # pylsl's LostError, or liblsl failing
            self.close()
            self.state = "lost"
            raise DeviceLost(f"the LSL stream of {self.predicate} went away ({exc})") from None
        return self.count(self._samples([first, *rows], [stamp, *stamps], self.clock.now_ns()))

    def _samples(self, rows: list, stamps: list[float], t_recv: int) -> list[Sample]:
        out: list[Sample] = []
        for row, stamp in zip(self.decoder.decode(np.array(rows, dtype=np.float64)), stamps, strict=True):
            if not (math.isfinite(stamp) and abs(stamp) < MAX_TIME_S):
                self.counters.malformed += 1
                continue
            self._count_gap(stamp)  # a malformed row was sent all the same: no gap
            if row is None:
                self.counters.malformed += 1
                continue
            local = stamp + self._correction
            if self._map.shared:
                t_host = min(self._map.to_clock(local), t_recv)
            else:
                t_host = self.sync.add(round(local * 1e9), t_recv)
            out.append(
                Gaze(
                    seq=self._seq,
                    t_host=t_host,
                    t_dev=round(stamp * 1e9),
                    valid=row.valid,
                    C=row.C,
                    L=row.L,
                    R=row.R,
                    depth_m=row.depth_m,
                )
            )
            self._seq += 1
        return out

    def _count_gap(self, stamp: float) -> None:
        """Count the samples a regular stream skipped before this one (gaps of 1.5 periods to MAX_GAP_S)."""
        rate, last = self.decoder.layout.meta.nominal_srate, self._last_stamp
        self._last_stamp = stamp
        if rate > 0 and last is not None and 1.5 / rate < stamp - last <= MAX_GAP_S:
            self.counters.dropped += round((stamp - last) * rate) - 1

    def status(self) -> Status:
        """The driver's status; with one clock for LSL and the host, its estimate is the inlet's time correction."""
        status = super().status()
        if self._map is not None and self._map.shared and self._seq:
            estimate = ClockEstimate(offset_ns=self._correction * 1e9, drift_ppm=0.0, residual_ns=0.0, pairs=self._seq)
            status = msgspec.structs.replace(status, clock=estimate)
        return status

    def close(self) -> None:
        if self._inlet is not None:
            self._inlet.close_stream()
        self._inlet = None
        self.state = "closed"


def _named(stream) -> str:
    """A stream info as "'name' (type T, source_id S, N channels)", its texts cut short."""
    name, kind, source_id = (text[:MAX_SELECTOR] for text in (stream.name(), stream.type(), stream.source_id()))
    return f"{name!r} (type {kind!r}, source_id {source_id!r}, {stream.channel_count()} channels)"


def _listing(streams: list) -> str:
    """Stream infos as _named says, the first MAX_LISTED of them."""
    more = len(streams) - MAX_LISTED
    return ", ".join(_named(s) for s in streams[:MAX_LISTED]) + (f" and {more} more" if more > 0 else "")


def _checked_meta(announced, full) -> StreamMeta:
    """The meta-data of a stream's full info, checked before any sample is read: parse_info's limits, and the
    channel count and format the stream announced to discovery (what the inlet reads samples by) must be the full
    info's. MetadataError naming the stream and what is wrong."""
    try:
        first, meta = parse_info(announced.as_xml()), parse_info(full.as_xml())
    except MetadataError as exc:
        raise MetadataError(f"LSL stream {_named(announced)}: {exc}") from None
    said, says = (first.channel_count, first.channel_format), (meta.channel_count, meta.channel_format)
    if said != says:
        raise MetadataError(
            f"{meta.title()} announced {said[0]} channels of {said[1]!r} but its stream info says {says[0]} of "
            f"{says[1]!r}"
        )
    return meta
