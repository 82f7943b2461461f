"""hid://: a Rift DK2-class tracker IMU over HID, fused into head orientation (docs/protocols.md, DK2 HID).

    hid://2833:0021          the real device, found with hid.enumerate and opened through hidapi
    hid://stub?device=dk2    drivers.emulators.dk2_stub: hidapi's device methods speaking the DK2's bytes

hidapi sits behind HidAdapter (CONTRIBUTING.md, adapters): bytes in and out, -1 and hidapi's exceptions raised as
DeviceLost, and a device factory so the stub plugs in where hid.device would. The driver sends the
keep-alive feature report 0x11 on open and again 0.2 s before it expires (as OpenHMD does), decodes
each 0x0B report, counts IMU samples lost between reports from the u16 sample count (counters.dropped
counts IMU samples), maps the u32 microsecond timestamp to the host clock through a ClockSync that
unwraps its 2**32 us wrap, and fuses every sample (drivers.fusion). It publishes one Pose per report:
the orientation after the report's last sample, stamped with that sample's device time (t_dev keeps
the raw wrapping timestamp in ns), position (0, 0, 0); valid once the first accelerometer reading has
levelled the filter. The report's magnetometer reading holds yaw (mag=0 leaves it to drift, for a
device whose magnetometer is disturbed).

Axes (section 10 leaves the IMU axes unconfirmed): the DK2 sensor frame is taken to be the head frame,
as OpenHMD does (+X right, +Y up, +Z back), so samples enter the filter unchanged. Only this module
would change if hardware showed otherwise.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Protocol

from hmdrt.bus.messages import Pose
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.base import DeviceLost, Driver, DriverUrl, Sample, SequenceGaps
from hmdrt.drivers.emulators.dk2_stub import Dk2Stub, HeadMotion
from hmdrt.drivers.fusion import OrientationFusion
from hmdrt.drivers.protocols.dk2 import (
    DK2_SENSOR_SIZE,
    PRODUCT_DK2,
    SAMPLE_COUNT_WRAP,
    SAMPLE_PERIOD_US,
    TIMESTAMP_WRAP_US,
    VENDOR_ID,
    Dk2FormatError,
    KeepAlive,
    decode_dk2_report,
    encode_keep_alive,
)
from hmdrt.errors import ConfigError

KEEP_ALIVE_MARGIN_NS = 200_000_000
MAX_REPORTS_PER_READ = 256


class HidDeviceApi(Protocol):
    """The methods of hidapi's hid.device that the adapter uses (the stub has the same)."""

    def open(self, vendor_id: int = 0, product_id: int = 0, serial_number: str | None = None) -> None: ...
    def open_path(self, path: bytes) -> None: ...
    def set_nonblocking(self, v: int) -> int: ...
    def read(self, max_length: int, timeout_ms: int = 0) -> list[int]: ...
    def send_feature_report(self, data) -> int: ...
    def get_feature_report(self, report_num: int, max_length: int) -> list[int]: ...
    def close(self) -> None: ...


class HidAdapter:
    """A hidapi device as bytes: reads return bytes, a -1 or a hidapi exception raises DeviceLost."""

    def __init__(self, factory: Callable[[], HidDeviceApi]):
        self._factory = factory
        self._device: HidDeviceApi | None = None

    def _call(self, what: str, fn, *args):
        try:
            result = fn(*args)
        except (OSError, ValueError, RuntimeError) as exc:
            raise DeviceLost(f"HID {what} failed: {exc}") from None
        if result == -1:
            raise DeviceLost(f"HID {what} failed (hidapi returned -1)")
        return result

    def _open(self, what: str, open_device: Callable[[HidDeviceApi], object]) -> None:
        self.close()
        device = self._factory()
        self._call(what, open_device, device)
        self._call("set_nonblocking", device.set_nonblocking, 1)  # so that read(size, 0) polls
        self._device = device

    def open(self, vendor_id: int, product_id: int) -> None:
        self._open(f"open {vendor_id:04x}:{product_id:04x}", lambda d: d.open(vendor_id, product_id))

    def open_path(self, path: bytes) -> None:
        self._open(f"open {path!r}", lambda d: d.open_path(path))

    def _dev(self) -> HidDeviceApi:
        if self._device is None:
            raise DeviceLost("HID device is not open")
        return self._device

    def _bytes(self, what: str, size: int, fn, *args) -> bytes:
        data = self._call(what, fn, *args)
        try:
            return bytes(data[:size])
        except (TypeError, ValueError) as exc:
            raise DeviceLost(f"HID {what} returned something other than bytes: {exc}") from None

    @property
    def device(self) -> HidDeviceApi | None:
        """The open hidapi device object (a Dk2Stub for hid://stub)."""
        return self._device

    def read(self, size: int, timeout_ms: int) -> bytes:
        """One input report (at most size bytes), or b"" when none arrived within timeout_ms (0 polls)."""
        return self._bytes("read", size, self._dev().read, size, max(0, timeout_ms))

    def send_feature(self, data: bytes) -> None:
        self._call(f"feature report 0x{data[0]:02x}", self._dev().send_feature_report, data)

    def get_feature(self, report_id: int, size: int) -> bytes:
        what = f"get feature report 0x{report_id:02x}"
        return self._bytes(what, size, self._dev().get_feature_report, report_id, size)

    def close(self) -> None:
        if self._device is not None:
            device, self._device = self._device, None
            try:
                device.close()
            except (OSError, ValueError, RuntimeError):
                pass  # closing a device that already went away


class HidDriver(Driver):
    scheme = "hid"
    grammar = (
        "hid://stub?device=dk2&trace=PATH&seed=N&start_us=US&bias=RAD_S&noise=X&gain=G&mag=0|1&keepalive_ms=MS"
        "&name=DEVICE or hid://2833:0021?gain=G&mag=0|1&keepalive_ms=MS&name=DEVICE (defaults: device=dk2, "
        "synthetic head motion, seed=0 start_us=0 bias=0.003 noise=1 gain=1 mag=1 (magnetometer yaw correction) "
        "keepalive_ms=10000)"
    )
    options = {
        "device": (str, "dk2", None, None),
        "trace": (str, "", None, None),
        "seed": (int, 0, 0, 2**31 - 1),
        "start_us": (int, 0, 0, TIMESTAMP_WRAP_US - 1),
        "bias": (float, 0.003, 0.0, 0.1),
        "noise": (float, 1.0, 0.0, 10.0),
        "gain": (float, 1.0, 0.0, 20.0),
        "keepalive_ms": (int, 10_000, 1_000, 65_535),
        "mag": (bool, True, None, None),
    }
    STUB_ONLY = ("trace", "seed", "start_us", "bias", "noise")
    path_options = ("trace",)
    clock_wrap_ns = TIMESTAMP_WRAP_US * 1000

    def __init__(self, url: DriverUrl | str, clock: Clock = MONOTONIC):
        super().__init__(url, clock)
        if self.opt["device"] != "dk2":
            raise ConfigError(f"hid:// supports device=dk2 only, got {self.opt['device']!r}; expected {self.grammar}")
        target = self.url.netloc
        self.stub = target == "stub"
        if not self.stub:
            self.vid, self.pid = self._parse_ids(target)
            given = [name for name in self.STUB_ONLY if name in self.url.options]
            if given:
                raise ConfigError(f"hid:// option {given[0]} applies to hid://stub only; expected {self.grammar}")
        self._adapter: HidAdapter | None = None

    def _parse_ids(self, target: str) -> tuple[int, int]:
        vid, sep, pid = target.partition(":")
        try:
            ids = int(vid, 16), int(pid, 16)
        except ValueError:
            ids = None
        if not sep or ids is None:
            raise ConfigError(f"hid:// needs stub or VID:PID in hex (e.g. 2833:0021), got {target!r}")
        if ids[0] != VENDOR_ID or ids[1] not in PRODUCT_DK2:
            raise ConfigError(f"hid://{target} is not a DK2-class tracker (2833:0021 or 2833:2021)")
        return ids

    def _open_adapter(self) -> HidAdapter:
        o = self.opt
        if self.stub:
            motion = HeadMotion.from_trace(o["trace"]) if o["trace"] else HeadMotion.synthetic(o["seed"])
            adapter = HidAdapter(lambda: Dk2Stub(motion, self.clock, o["seed"], o["start_us"], o["bias"], o["noise"]))
            adapter.open(VENDOR_ID, PRODUCT_DK2[0])
            return adapter
        try:
            import hid
        except ImportError as exc:
            raise ConfigError(f"hid://{self.vid:04x}:{self.pid:04x} needs hidapi (pip install hidapi): {exc}") from None
        found = hid.enumerate(self.vid, self.pid)
        if not found:
            raise DeviceLost(
                f"no HID device {self.vid:04x}:{self.pid:04x} (hid.enumerate found none: is it plugged in, and may "
                "this user open it, e.g. through a udev rule?)"
            )
        adapter = HidAdapter(hid.device)
        adapter.open_path(found[0]["path"])
        return adapter

    def open(self) -> None:
        self.close()
        self._fusion = OrientationFusion(gain=self.opt["gain"])
        self._gaps = SequenceGaps(modulus=SAMPLE_COUNT_WRAP)
        self._last_us: int | None = None
        self._seq = 0
        self._adapter = self._open_adapter()
        self._keep_alive()
        self.state = "connected"

    def _keep_alive(self) -> None:
        timeout_ms = self.opt["keepalive_ms"]
        self._adapter.send_feature(encode_keep_alive(KeepAlive(timeout_ms)))
        self._keep_alive_due = self.clock.now_ns() + timeout_ms * 1_000_000 - KEEP_ALIVE_MARGIN_NS

    def read(self, timeout_s: float) -> list[Sample]:
        if self._adapter is None:
            raise DeviceLost("hid:// is not open")
        now = self.clock.now_ns()
        if now >= self._keep_alive_due:
            self._keep_alive()
        wait_ns = min(int(timeout_s * 1e9), self._keep_alive_due - now)
        out: list[Sample] = []
        data = self._adapter.read(DK2_SENSOR_SIZE, math.ceil(max(wait_ns, 0) / 1e6))
        for _ in range(MAX_REPORTS_PER_READ):
            if not data:
                break
            pose = self._pose(data, self.clock.now_ns())
            if pose is not None:
                out.append(pose)
            data = self._adapter.read(DK2_SENSOR_SIZE, 0)
        return self.count(out)

    def _pose(self, data: bytes, t_recv: int) -> Pose | None:
        """Fuse one report's samples; the Pose after its last sample, or None (malformed or empty)."""
        try:
            report = decode_dk2_report(data)
        except Dk2FormatError:
            self.counters.malformed += 1
            return None
        if not report.samples:
            return None
        mag = report.mag if self.opt["mag"] else None
        for i, sample in enumerate(report.samples):
            self.counters.dropped += self._gaps.see((report.sample_count + i) % SAMPLE_COUNT_WRAP)
            t_us = (report.timestamp_us + i * SAMPLE_PERIOD_US) % TIMESTAMP_WRAP_US
            step_us = 0 if self._last_us is None else (t_us - self._last_us) % TIMESTAMP_WRAP_US
            self._last_us = t_us
            dt_ns = step_us * 1000 if step_us < TIMESTAMP_WRAP_US // 2 else 0  # a step back is no step
            orientation = self._fusion.update(sample.gyro_radps, sample.accel_mps2, dt_ns, mag)
        t_dev = t_us * 1000
        pose = Pose(
            seq=self._seq,
            t_host=self.sync.add(t_dev, t_recv),
            position=(0.0, 0.0, 0.0),
            orientation=orientation,
            t_dev=t_dev,
            valid=self._fusion.aligned,
        )
        self._seq += 1
        return pose

    @property
    def hid(self) -> HidDeviceApi | None:
        """The open hidapi device object (a Dk2Stub for hid://stub), or None when closed."""
        return self._adapter.device if self._adapter is not None else None

    def close(self) -> None:
        if self._adapter is not None:
            self._adapter.close()
            self._adapter = None
        self.state = "closed"
