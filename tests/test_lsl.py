"""Lab Streaming Layer with real liblsl on this machine only: the lsl:// driver against `hmdrt emulate lsl` and against
outlets laid out as real publishers lay theirs out, and the compositor's [lsl] outlets read by plain pylsl inlets.

LSL's discovery is kept to this machine by an lsl_api.cfg that LSLAPICFG names before liblsl reads its configuration
(liblsl src/api_config.cpp @ 64988c6: [ports] IPv6, [multicast] ResolveScope); every stream has a source_id of its
own, so tests never read each other's.
"""

from __future__ import annotations

import json
import math
import os
import sys
import time
import uuid
from pathlib import Path

import numpy as np
import pytest

from hmdrt.bus import messages
from hmdrt.bus.lsl import ClockMap
from hmdrt.bus.messages import Gaze
from hmdrt.cli import main
from hmdrt.clock import MONOTONIC, VirtualClock
from hmdrt.compositor.config import load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.compositor.lsl_outlets import SAMPLE_CHANNELS
from hmdrt.drivers import open_driver
from hmdrt.drivers.base import DeviceLost
from hmdrt.drivers.emulators import make_emulator
from hmdrt.drivers.emulators.feed import GazeFeed
from hmdrt.drivers.emulators.lsl_source import CHANNEL_COUNT, DEPTH_M, LslEmulator, titta_channels
from hmdrt.drivers.lsl import DEFAULT_PROFILE
from hmdrt.drivers.protocols.lsl_gaze import GazeDecoder, MetadataError, gaze_layout, parse_info
from hmdrt.errors import ConfigError
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.spatial import Pose, gaze_direction
from hmdrt.testing import Recording, run_bounded, write_config

from .helpers import gaze_trace

LSL_API_CFG = "[ports]\nIPv6 = disable\n[multicast]\nResolveScope = machine\n[log]\nlevel = -2\n"
STILL_DEPTH = 0.8


@pytest.fixture(scope="module", autouse=True)
def lsl(tmp_path_factory):
    """pylsl with LSL's discovery kept to this machine (set before anything in this process uses liblsl)."""
    config = tmp_path_factory.mktemp("lsl") / "lsl_api.cfg"
    config.write_text(LSL_API_CFG)
    before = os.environ.get("LSLAPICFG")
    os.environ["LSLAPICFG"] = str(config)
    import pylsl

    yield pylsl
    if before is None:
        del os.environ["LSLAPICFG"]
    else:
        os.environ["LSLAPICFG"] = before


def unique() -> str:
    return f"hmdrt-test-{uuid.uuid4().hex[:12]}"


def outlet(lsl, channels: list[dict[str, str]], count: int | None = None, rate: float = 100.0, name: str = "test"):
    """A double outlet of type Gaze describing `channels` (their keys as given); the outlet and its source_id."""
    source_id = unique()
    info = lsl.StreamInfo(name, "Gaze", count or len(channels), rate, lsl.cf_double64, source_id)
    described = info.desc().append_child("channels")
    for channel in channels:
        element = described.append_child("channel")
        for key, value in channel.items():
            element.append_child_value(key, value)
    return lsl.StreamOutlet(info), source_id


def meta_of(lsl, channels: list[dict[str, str]], count: int | None = None):
    """The parsed meta-data of a stream info that pylsl builds for `channels`."""
    info = lsl.StreamInfo("test", "Gaze", count or len(channels), 100.0, lsl.cf_double64, unique())
    described = info.desc().append_child("channels")
    for channel in channels:
        element = described.append_child("channel")
        for key, value in channel.items():
            element.append_child_value(key, value)
    return parse_info(info.as_xml())


def titta(kind: str = "type") -> list[dict[str, str]]:
    return [dict(zip(("label", "eye", kind, "unit"), c, strict=True)) for c in titta_channels()]


def unit(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


def still_eyes() -> tuple[np.ndarray, np.ndarray]:
    """Each eye's direction to a point 0.8 m away at yaw 8, pitch -4 degrees (eyes 63.5 mm apart, sim-cpu-640)."""
    point = np.array(gaze_direction(8.0, -4.0)) * STILL_DEPTH
    half = np.array([0.0635 / 2, 0.0, 0.0])
    return unit(point + half), unit(point - half)


def still_trace(path: Path) -> str:
    """100 ms of the still gaze, its last 3 of 10 samples a blink."""
    left, right = still_eyes()
    return gaze_trace(path, [(left, right, k < 7) for k in range(10)], 10_000_000, STILL_DEPTH)


def collect(driver, count: int, timeout_s: float = 10.0) -> list:
    samples, deadline = [], time.monotonic() + timeout_s
    while len(samples) < count and time.monotonic() < deadline:
        samples += driver.read(0.05)
    return samples


# --- the clocks ---------------------------------------------------------------------------------------------------


def test_local_clock_and_the_host_monotonic_clock_are_one_clock_here(lsl):
    """liblsl's local_clock() is steady_clock, CLOCK_MONOTONIC on Linux: the clock of time.monotonic_ns. Read between
    two monotonic readings it lies within them; ClockMap relies on that only where it measures it so."""
    for _ in range(20):
        before = time.monotonic_ns()
        lsl_ns = lsl.local_clock() * 1e9
        after = time.monotonic_ns()
        if sys.platform == "linux":
            assert before - 1000 <= lsl_ns <= after + 1000  # within a microsecond: the double's rounding
    host = ClockMap.measure(MONOTONIC)
    assert host.shared is (sys.platform == "linux") and host.to_clock(host.to_lsl(123_456_789)) == 123_456_789
    virtual = ClockMap.measure(VirtualClock(5_000_000_000))
    assert not virtual.shared and abs(virtual.to_lsl(5_000_000_000) - lsl.local_clock()) < 0.01


# --- the meta-data of real publishers -----------------------------------------------------------------------------


def test_tittalsl_layout_is_read_from_its_intersections_and_gaze_origins_under_their_valid_flags(lsl):
    """The emulator's channels are TittaLSL's Gaze stream, transcribed from dcnieho/Titta LSL_streamer/src/TittaLSL.cpp
    @ 0610aaf (Sender::create, the Gaze case: 36 described channels of 37, the device time stamp undescribed). The
    driver reads each eye's gaze point less its gaze origin, each valid only with its own ValidFlag."""
    left = [
        ("x.position_on_display_area.gaze_point.left_eye", "left", "ScreenX", "normalized"),
        ("y.position_on_display_area.gaze_point.left_eye", "left", "ScreenY", "normalized"),
        ("x.position_in_user_coordinates.gaze_point.left_eye", "left", "IntersectionX", "mm"),
        ("y.position_in_user_coordinates.gaze_point.left_eye", "left", "IntersectionY", "mm"),
        ("z.position_in_user_coordinates.gaze_point.left_eye", "left", "IntersectionZ", "mm"),
        ("valid.gaze_point.left_eye", "left", "ValidFlag", "bool"),
        ("available.gaze_point.left_eye", "left", "AvailableFlag", "bool"),
        ("diameter.pupil.left_eye", "left", "Diameter", "mm"),
        ("valid.pupil.left_eye", "left", "ValidFlag", "bool"),
        ("available.pupil.left_eye", "left", "AvailableFlag", "bool"),
        ("x.position_in_user_coordinates.gaze_origin.left_eye", "left", "PupilX", "mm"),
        ("y.position_in_user_coordinates.gaze_origin.left_eye", "left", "PupilY", "mm"),
        ("z.position_in_user_coordinates.gaze_origin.left_eye", "left", "PupilZ", "mm"),
        ("valid.gaze_origin.left_eye", "left", "ValidFlag", "bool"),
        ("available.gaze_origin.left_eye", "left", "AvailableFlag", "bool"),
        ("diameter.eye_openness.left_eye", "left", "EyeLidDistance", "mm"),
        ("valid.eye_openness.left_eye", "left", "ValidFlag", "bool"),
        ("available.eye_openness.left_eye", "left", "AvailableFlag", "bool"),
    ]
    right = [(label.replace("left", "right"), "right", kind, u) for label, _, kind, u in left]
    assert titta_channels() == left + right and CHANNEL_COUNT == 37

    layout = gaze_layout(meta_of(lsl, titta(), CHANNEL_COUNT))
    assert [(s.eye, s.kind) for s in layout.sources] == [
        ("left", "Intersection"), ("left", "Screen"), ("right", "Intersection"), ("right", "Screen"),
    ]  # fmt: skip
    # valid.gaze_point vouches for the screen position and the gaze point, valid.pupil for the diameter,
    # valid.gaze_origin for the origin; no confidence channel
    assert [layout.flags[c] for c in (0, 1, 2, 3, 4, 7, 10, 11, 12)] == [5] * 5 + [8] + [13] * 3
    assert not layout.confidence
    emulator = LslEmulator(GazeFeed(120.0))
    sample = next(s for s in emulator.feed.samples() if s.valid)
    depth = sample.depth_m or DEPTH_M
    row = np.array(emulator.values(sample))
    decoder = GazeDecoder(layout, "head", get_profile(DEFAULT_PROFILE))
    good = decoder.decode(row)[0]
    assert np.allclose(good.L, sample.left, atol=1e-12) and np.allclose(good.R, sample.right, atol=1e-12)
    assert good.depth_m == pytest.approx(depth) and good.valid
    no_left_point = row.copy()
    no_left_point[2:5] = np.nan  # no gaze point in user coordinates: the left eye from its display-area position
    fallback = decoder.decode(no_left_point)[0]
    assert np.allclose(fallback.L, sample.left, atol=1e-6) and fallback.depth_m == pytest.approx(depth)  # the right's
    unvouched = row.copy()
    unvouched[5] = 0.0  # valid.gaze_point.left_eye = 0: neither of the left eye's gaze positions counts
    assert decoder.decode(unvouched)[0].L is None and decoder.decode(unvouched)[0].valid


def test_pupil_capture_relay_layout_gives_the_combined_gaze_and_its_depth(lsl):
    """The Pupil Capture LSL relay's gaze outlet (labstreaminglayer/App-PupilLabs,
    pupil_capture/pupil_capture_lsl_relay/channel.py and gaze_scene_camera.py @ 37dedd6): gaze_point_3d is typed
    Direction (eye both, mm, Pupil's OpenCV world camera), eye centres and then gaze normals both PositionX/Y/Z, the
    other eye NaN in a monocular datum. axes=opencv turns y down and z forward into the head frame."""

    def channel(label: str, eye: str, kind: str, unit: str, system: str = "world") -> dict[str, str]:
        return {"label": label, "eye": eye, "type": kind, "unit": unit, "coordinate_system": system}

    eyes = ("right", "left")  # Pupil's eye 0 is the right eye
    channels = [{"label": "confidence", "eye": "both", "type": "Confidence", "unit": "normalized"}]
    channels += [channel(f"norm_pos_{a}", "both", f"Screen{a.upper()}", "normalized") for a in "xy"]
    channels += [channel(f"gaze_point_3d_{a}", "both", f"Direction{a.upper()}", "mm") for a in "xyz"]
    for prefix in ("eye_center{}_3d_", "gaze_normal{}_"):
        channels += [
            channel(prefix.format(e) + a, eyes[e], f"Position{a.upper()}", "mm") for e in range(2) for a in "xyz"
        ]
    for size, u in (("2d", "pixels"), ("3d", "mm")):
        channels += [channel(f"diameter{e}_{size}", eyes[e], "Diameter", u, f"eye{e}") for e in range(2)]
    layout = gaze_layout(meta_of(lsl, channels))
    assert [(s.eye, s.kind) for s in layout.sources] == [("both", "Direction"), ("both", "Screen")]
    decoder = GazeDecoder(layout, "opencv", get_profile(DEFAULT_PROFILE), origin="bottom-left")
    row = np.full(len(channels), np.nan)
    row[:6] = [0.9, 0.5, 0.5, 100.0, -50.0, 500.0]
    gaze = decoder.decode(row)[0]
    assert np.allclose(gaze.C, unit([100.0, 50.0, -500.0]), atol=1e-12) and gaze.L is None and gaze.R is None
    assert gaze.depth_m == pytest.approx(math.sqrt(100**2 + 50**2 + 500**2) / 1000)
    row[0] = 0.3  # below the confidence threshold
    assert not decoder.decode(row)[0].valid and decoder.decode(row)[0].C is None
    row[[0, 3, 4, 5]] = [0.9, np.nan, np.nan, np.nan]  # a 2D-mapped datum: no gaze_point_3d, norm_pos up and right
    row[[1, 2]] = [0.75, 0.75]
    gaze = decoder.decode(row)[0]
    assert gaze.valid and gaze.C[0] > 0.1 and gaze.C[1] > 0.1 and gaze.C[2] < 0 and gaze.depth_m is None


def test_neon_relay_metatype_and_screen_pixels(lsl):
    """Pupil Labs' Neon relay writes the type as `metatype` and the gaze in pixels, eye both (pupil-labs/lsl-relay,
    src/pupil_labs/lsl_relay/channels.py @ da699cf). Pixels map through both eyes of the profile, origin top left."""
    channels = [
        {"label": a, "eye": "both", "metatype": f"Screen{a.upper()}", "unit": "pixels", "coordinate_system": "world"}
        for a in "xy"
    ]
    layout = gaze_layout(meta_of(lsl, channels))
    profile = get_profile(DEFAULT_PROFILE)
    decoder = GazeDecoder(layout, profile=profile)
    top_left, bottom_right = decoder.decode(np.array([[0.0, 0.0], [profile.width, profile.height]]))
    assert top_left.C[0] < -0.3 and top_left.C[1] > 0.3 and bottom_right.C[0] > 0.3 and bottom_right.C[1] < -0.3
    cameras = [EyeCamera.for_eye(profile, Pose(), eye) for eye in ("left", "right")]
    both = sum(c.directions(np.array([[0.0, 0.0]]))[0].astype(np.float64) for c in cameras)
    assert np.allclose(top_left.C, unit(both), atol=1e-12)


def test_metadata_that_does_not_say_where_the_gaze_is_is_one_error_naming_the_channels(lsl, capsys, tmp_path):
    """labstreaminglayer/PicoNeo2Eye Scripts/GazeLSLOutlet.cs @ bac9805 describes its 12 channels by label only: no
    eye, type or unit. The driver refuses it in one line naming what it found, and so does `hmdrt driver`."""
    labels = ["Timestamp", "ConvergenceDistance", "ConvergenceDistanceIsValid"]
    labels += [f"GazeRay{what}{a}" for what in ("Origin", "Direction") for a in "XYZ"]
    labels += ["GazeRayIsValid", "IsLeftEyeBlinking", "IsRightEyeBlinking"]
    source, source_id = outlet(lsl, [{"label": label} for label in labels], name="Unity.TobiiGaze")
    driver = open_driver(f"lsl://?source_id={source_id}&timeout=5")
    with pytest.raises(MetadataError) as error:
        driver.open()
    message = str(error.value)
    assert "Unity.TobiiGaze" in message and "GazeRayDirectionX [no type, both, no unit]" in message
    assert "IsRightEyeBlinking" in message and "DirectionX/Y/Z" in message
    bus = f"ipc://{tmp_path}/ingest"  # nobody listens: the driver fails before it publishes
    assert main(["driver", f"lsl://?source_id={source_id}", "--bus", bus, "--duration", "5"]) == 1
    lines = capsys.readouterr().err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("hmdrt: error: LSL stream 'Unity.TobiiGaze'")
    del source


def test_driver_errors_name_what_is_wrong(lsl):
    """A stream LSL cannot find is named with the streams it did find; a string stream, a Screen without a unit and
    an eye other than left, right or both are one line each."""
    name = f"EEG-{unique()}"
    eeg = lsl.StreamOutlet(lsl.StreamInfo(name, "EEG", 2, 100.0, lsl.cf_float32, unique()))
    with pytest.raises(DeviceLost, match=f"name='absent'.*streams found: .*{name}"):
        open_driver("lsl://?name=absent&timeout=0.3").open()
    screen = [{"label": a, "eye": "left", "type": f"Screen{a.upper()}"} for a in "xy"]
    for channels, message in (
        (screen, r"x \[ScreenX, left, no unit\], y \[ScreenY, left, no unit\] need unit pixels or normalized"),
        ([{**c, "unit": "px", "eye": "middle"} for c in screen], "eye other than"),
    ):
        with pytest.raises(MetadataError, match=message):
            gaze_layout(meta_of(lsl, channels))
    text = lsl.StreamInfo("markers", "Gaze", 1, 0.0, lsl.cf_string, unique())
    with pytest.raises(MetadataError, match="channel format 'string'"):
        gaze_layout(parse_info(text.as_xml()))
    with pytest.raises(ConfigError, match="no --port"):
        make_emulator("lsl", port=4000)
    for url, message in (("lsl://host", "no host"), ("lsl://?axes=zup", "axes="), ("lsl://?name=it's", "quotes")):
        with pytest.raises(ConfigError, match=message):
            open_driver(url)
    del eeg


def test_without_pylsl_each_part_names_the_extra(tmp_path, monkeypatch):
    """Where pylsl cannot be imported, the driver, the emulator and the compositor's outlets say how to install it."""
    monkeypatch.setitem(sys.modules, "pylsl", None)  # what a missing package does to import
    hint = r"pip install 'hmdrt\[lsl\]'"
    with pytest.raises(ConfigError, match=hint):
        open_driver("lsl://").open()
    with pytest.raises(ConfigError, match=hint):
        make_emulator("lsl").start()
    config = write_config(tmp_path / "run.toml", lsl={"outlets": ["frames"]})
    with pytest.raises(ConfigError, match=hint):
        Compositor(load_config(config, virtual_time=True))


# --- samples ------------------------------------------------------------------------------------------------------


def test_emulated_gaze_arrives_exactly_with_capture_times_on_the_host_clock(lsl, tmp_path):
    """Through `hmdrt emulate lsl`'s emulator and the lsl:// driver in real time: the trace's directions and depth to
    1e-12, the blinks invalid, each t_dev the emulator's capture time and t_host that time on the host clock
    (time_correction() on one machine is off by microseconds), never after receipt."""
    left, right = still_eyes()
    with LslEmulator(GazeFeed(200.0, trace=still_trace(tmp_path / "still.jsonl"))) as emulator:
        driver = open_driver(emulator.url)
        driver.open()
        try:
            samples = collect(driver, 100)
        finally:
            driver.close()
    assert len(samples) >= 100 and driver.counters.malformed == 0 and driver.counters.dropped == 0
    valid = [s for s in samples if s.valid]
    assert 0 < len(samples) - len(valid) == driver.counters.invalid
    for s in valid:
        assert np.allclose(s.L, left, atol=1e-12) and np.allclose(s.R, right, atol=1e-12)
        assert s.depth_m == pytest.approx(STILL_DEPTH, abs=1e-9)
    assert all(s.L is None and s.R is None and s.C is None for s in samples if not s.valid)
    captured = np.array([t for t, _ in emulator.sent])
    for s in samples:
        nearest = captured[np.argmin(np.abs(captured - s.t_dev))]
        assert abs(s.t_dev - nearest) < 1000 and abs(s.t_host - nearest) < 1_000_000
    assert [s.seq for s in samples] == list(range(len(samples)))
    status = driver.status()  # the clock estimate is the inlet's time correction, and the status is bus-ready
    assert status.clock.pairs == len(samples) and abs(status.clock.offset_ns) < 1_000_000
    assert messages.decode(messages.encode(status, "lsl"))[2] == status


def test_malformed_rows_and_gaps_are_counted_and_a_stream_that_ends_is_lost(lsl):
    """Infinite values make a row malformed, NaN is a missing value, a gap in a regular stream's timestamps counts
    its missing samples as dropped, and an outlet that goes away makes reads raise DeviceLost."""
    source, source_id = outlet(lsl, titta(), CHANNEL_COUNT, rate=100.0)
    emulator = LslEmulator(GazeFeed(100.0))
    row = emulator.values(next(emulator.feed.samples()))
    driver = open_driver(f"lsl://?source_id={source_id}")
    driver.open()
    try:
        t0 = lsl.local_clock() - 1.0
        bad = list(row)
        bad[2] = math.inf
        missing = [math.nan] * len(row)
        for k, values in enumerate([row, row, bad, missing, row]):
            source.push_sample(values, t0 + (k if k < 4 else 9) * 0.01)  # the last one after 5 missing samples
        samples = collect(driver, 4)
        assert [s.valid for s in samples] == [True, True, False, True]
        assert driver.counters.malformed == 1 and driver.counters.dropped == 5 and driver.counters.samples == 4
        assert all(isinstance(s, Gaze) for s in samples)
        del source
        with pytest.raises(DeviceLost, match="went away"):
            collect(driver, 1, timeout_s=5.0)
    finally:
        driver.close()


# --- the compositor -----------------------------------------------------------------------------------------------


class Watching(Recording):
    """The compositor, keeping also the gaze each shown frame was rendered for."""

    def __init__(self, *args, **kwargs):
        self.gazes: list = []
        super().__init__(*args, **kwargs)

    def _shown(self, record, images) -> None:
        self.gazes.append(self.display.last.gaze_dirs)
        super()._shown(record, images)


def test_a_trace_through_emulate_lsl_drives_a_compositor_in_virtual_time(lsl, tmp_path, context):
    """The trace replayed by the emulator, read through lsl:// by a virtual-time compositor: its frames render the
    trace's gaze from the lsl device, and the report counts the blinks and nothing malformed or dropped."""
    left, right = still_eyes()
    with LslEmulator(GazeFeed(120.0, trace=still_trace(tmp_path / "still.jsonl"))) as emulator:
        path = write_config(tmp_path / "run.toml", drivers=[{"url": emulator.url}])
        comp = Watching(load_config(path, frames=20, virtual_time=True), context=context)
        try:
            report, _ = run_bounded(comp)
        finally:
            comp.close()
    counts = report["drivers"]["lsl"]
    assert counts["samples"] > 0 and counts["invalid"] > 0 and counts["malformed"] == counts["dropped"] == 0
    used = [(r, g) for r, g in zip(comp.records, comp.gazes, strict=True) if r.gaze is not None]
    assert len(used) >= 15 and all(r.gaze.device == "lsl" for r, _ in used)
    for _, gaze in used:
        assert np.allclose(gaze["left"], left, atol=1e-9) and np.allclose(gaze["right"], right, atol=1e-9)


def test_compositor_outlets_carry_every_vsync_and_each_frames_gaze_pose_and_latency(lsl, tmp_path, context):
    """[lsl] outlets frames and samples read by plain pylsl inlets: a marker per VSync at its present time (frame id,
    new/late/repeat, method), and per frame the gaze and pose it was rendered for with the report's latencies."""
    path = write_config(tmp_path / "run.toml", lsl={"outlets": ["frames", "samples"]})
    comp = Recording(load_config(path, frames=20, virtual_time=True), context=context)
    try:
        inlets = {}
        for kind, source_id in comp.lsl.source_ids.items():
            (info,) = lsl.resolve_byprop("source_id", source_id, 1, 5.0)
            inlets[kind] = lsl.StreamInlet(info, recover=False)
            inlets[kind].open_stream(5.0)
        labels = inlets["samples"].info(5.0).desc().child("channels").first_child()
        described = []
        while not labels.empty():
            described.append(labels.child_value("label"))
            labels = labels.next_sibling()
        report, _ = run_bounded(comp)
        markers, marker_times = pull(inlets["frames"], 20)
        values, value_times = pull(inlets["samples"], 20)
    finally:
        comp.close()
    assert described == [c[0] for c in SAMPLE_CHANNELS] and report["vsyncs"] == 20
    records = comp.records
    assert [json.loads(m[0]) for m in markers] == [
        {"frame_id": r.frame_id, "vsync": r.vsync, "shown": r.shown, "missed": r.missed, "method": "rrm"}
        for r in records
    ]
    offset = marker_times[0] - records[0].actual_present_ns / 1e9  # virtual time from 0, offset to LSL time at start
    assert abs(offset - lsl.local_clock()) < 120.0
    presents = np.array([r.actual_present_ns / 1e9 + offset for r in records])
    assert np.allclose(marker_times, presents, atol=1e-6) and value_times == marker_times
    column = {label: i for i, label in enumerate(described)}
    for record, row in zip(records, values, strict=True):
        assert row[column["frame_id"]] == record.frame_id
        assert row[column["gaze_to_photon_ms"]] == pytest.approx(record.gaze_to_photon_ms(), abs=1e-6)
        assert row[column["pose_to_photon_ms"]] == pytest.approx(record.pose_to_photon_ms(), abs=1e-6)
        capture = record.gaze.t_host / 1e9 + offset
        assert row[column["gaze_capture_time"]] == pytest.approx(capture, abs=1e-6)
        for eye in ("left", "right"):
            direction = [row[column[f"gaze_{eye}_{a}"]] for a in "xyz"]
            assert abs(np.linalg.norm(direction) - 1.0) < 1e-9
        quaternion = [row[column[f"head_orientation_{a}"]] for a in "wxyz"]
        assert abs(np.linalg.norm(quaternion) - 1.0) < 1e-9
    assert report["lsl_not_pushed"] == 0


def pull(inlet, count: int, timeout_s: float = 10.0) -> tuple[list, list[float]]:
    """Up to `count` samples of an inlet and their timestamps; what arrived by timeout_s."""
    values, times, deadline = [], [], time.monotonic() + timeout_s
    while len(values) < count and time.monotonic() < deadline:
        chunk, stamps = inlet.pull_chunk(timeout=0.2)
        values += chunk
        times += stamps
    return values, times
