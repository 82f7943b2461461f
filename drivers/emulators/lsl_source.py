"""`hmdrt emulate lsl`: an LSL gaze stream laid out as TittaLSL publishes a Tobii eye tracker's, fed by a GazeFeed
(docs/protocols.md, LSL).

The stream copies TittaLSL's "Gaze" outlet channel for channel (dcnieho/Titta, LSL_streamer/src/TittaLSL.cpp @ 0610aaf,
Sender::create and Sender::pushSample): type Gaze, 37 double channels, for the left and then the right eye the gaze
point on the display area (ScreenX/Y, normalized, origin top left), the gaze point in user coordinates
(IntersectionX/Y/Z, mm), the pupil diameter (mm) and the gaze origin (PupilX/Y/Z, mm), each with a ValidFlag and an
AvailableFlag, the eye openness (unavailable here, as on trackers without it), and last the device time stamp in
seconds, a channel TittaLSL does not describe. Tobii's user coordinate system (x right, y up, z towards the user) has
the axes of the head frame, so the gaze points and origins are head-frame points: each eye at its camera of the HMD
profile, looking along the feed's direction to the feed's depth (else DEPTH_M). The display area is each eye's
screen of that profile. A sample the feed marks untracked has NaN positions and ValidFlag 0, as the Tobii SDK
reports a lost eye. Each sample is pushed when due, stamped with its capture time on the LSL clock (TittaLSL stamps
Tobii's system time, which it checks to be LSL's clock).
"""

from __future__ import annotations

import itertools
import os

from hmdrt.bus.lsl import ClockMap, load_pylsl
from hmdrt.clock import MONOTONIC, Clock
from hmdrt.drivers.emulators.base import Emulated, Emulator, EmulatorOptions
from hmdrt.drivers.emulators.feed import FeedSample, GazeFeed
from hmdrt.drivers.lsl import DEFAULT_PROFILE
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.spatial import Pose

NAME = "Tobii_gaze"  # TittaLSL's stream name for the gaze stream
RATE_HZ = 120.0  # the emulated gaze rate by default
DEPTH_M = 0.65  # how far the gaze point lies when the feed gives no depth: a typical eye to screen distance
PUPIL_MM = 4.0
NAN = float("nan")
_instances = itertools.count()


def _flags(thing: str, eye: str) -> list[tuple[str, str, str, str]]:
    return [
        (f"valid.{thing}.{eye}_eye", eye, "ValidFlag", "bool"),
        (f"available.{thing}.{eye}_eye", eye, "AvailableFlag", "bool"),
    ]


def titta_channels() -> list[tuple[str, str, str, str]]:
    """(label, eye, type, unit) of each described channel, in TittaLSL's order."""
    channels = []
    for eye in ("left", "right"):
        display, user = f"position_on_display_area.gaze_point.{eye}_eye", "position_in_user_coordinates"
        channels += [(f"{a}.{display}", eye, f"Screen{a.upper()}", "normalized") for a in "xy"]
        channels += [(f"{a}.{user}.gaze_point.{eye}_eye", eye, f"Intersection{a.upper()}", "mm") for a in "xyz"]
        channels += _flags("gaze_point", eye)
        channels += [(f"diameter.pupil.{eye}_eye", eye, "Diameter", "mm"), *_flags("pupil", eye)]
        channels += [(f"{a}.{user}.gaze_origin.{eye}_eye", eye, f"Pupil{a.upper()}", "mm") for a in "xyz"]
        channels += _flags("gaze_origin", eye)
        channels += [(f"diameter.eye_openness.{eye}_eye", eye, "EyeLidDistance", "mm"), *_flags("eye_openness", eye)]
    return channels


CHANNEL_COUNT = len(titta_channels()) + 1  # and the undescribed device time stamp


class LslEmulator(Emulator):
    """An LSL outlet of emulated Tobii gaze (TittaLSL's layout), found by LSL's discovery under `source_id`."""

    name = "lsl"
    emulates = (Emulated("lsl", rate_hz=RATE_HZ, latency_ms=0.0, reached="is found by LSL's discovery, not at a port"),)

    def __init__(self, feed: GazeFeed | None = None, rate_hz: float = RATE_HZ, clock: Clock = MONOTONIC):
        """feed: the gaze source (default: synthetic gaze at rate_hz; a given feed brings its own rate)."""
        super().__init__(clock)
        self.feed = feed if feed is not None else GazeFeed(rate_hz, clock=clock)
        self.source_id = f"hmdrt-emulator-{os.getpid()}-{next(_instances)}"
        profile = get_profile(DEFAULT_PROFILE)
        self._cameras = [EyeCamera.for_eye(profile, Pose(), eye) for eye in ("left", "right")]
        self._outlet = None

    @classmethod
    def emulate(cls, device: Emulated, options: EmulatorOptions) -> LslEmulator:
        return cls(feed=options.feed(device), clock=options.clock)

    @property
    def url(self) -> str:
        return f"lsl://?source_id={self.source_id}"

    def _bind(self) -> None:
        lsl = load_pylsl()
        info = lsl.StreamInfo(NAME, "Gaze", CHANNEL_COUNT, self.feed.rate_hz, lsl.cf_double64, self.source_id)
        acquisition = info.desc().append_child("acquisition")
        for key, value in (
            ("manufacturer", "hmdrt"),
            ("model", "TittaLSL emulator"),
            ("serial_number", self.source_id),
        ):
            acquisition.append_child_value(key, value)
        channels = info.desc().append_child("channels")
        for label, eye, kind, unit in titta_channels():
            channel = channels.append_child("channel")
            for key, value in (("label", label), ("eye", eye), ("type", kind), ("unit", unit)):
                channel.append_child_value(key, value)
        self._outlet = lsl.StreamOutlet(info)
        self._map = ClockMap.measure(self.clock)
        self._samples = self.feed.samples()
        self._sample = next(self._samples)

    def _release(self) -> None:
        self._outlet = None  # pylsl destroys the outlet with its last reference

    def values(self, sample: FeedSample) -> list[float]:
        """The 37 channel values of one feed sample."""
        values: list[float] = []
        depth_mm = (sample.depth_m or DEPTH_M) * 1000.0
        for camera, direction in zip(self._cameras, (sample.left, sample.right), strict=True):
            if sample.valid:
                origin = camera.position * 1000.0
                screen = camera.project((camera.position + direction)[None])[0][0] / (camera.width, camera.height)
                values += [*screen, *(origin + direction * depth_mm), 1.0, 1.0, PUPIL_MM, 1.0, 1.0, *origin, 1.0, 1.0]
            else:
                values += [NAN] * 5 + [0.0, 1.0, NAN, 0.0, 1.0] + [NAN] * 3 + [0.0, 1.0]
            values += [NAN, 0.0, 0.0]  # no eye openness
        return [float(v) for v in values] + [(sample.capture_ns - self.epoch_ns) / 1e9]

    def _tick(self, now_ns: int) -> int:
        while self._sample.due_ns <= now_ns:
            self._outlet.push_sample(self.values(self._sample), self._map.to_lsl(self._sample.capture_ns))
            self._log_sent(self._sample.capture_ns - self.epoch_ns)
            self._sample = next(self._samples)
        return self._sample.due_ns

    def _poll(self, timeout_s: float) -> None:
        self._stop.wait(timeout_s)  # nothing to answer: LSL serves the outlet from threads of its own
