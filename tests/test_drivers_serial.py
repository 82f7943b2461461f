"""Razor AHRS and HATIRE: codecs against docs/protocols.md, Test vectors, framers on garbage, and serial:// through a
real pseudo-terminal (the emulator) and pyserial's loop://."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
import serial

from drivers import open_driver
from drivers.base import DeviceLost
from drivers.emulators.serial_emulator import SerialTrackerEmulator
from drivers.protocols import hatire, razor
from drivers.protocols.hatire import HatireFrame, HatireFramer, HatireInfo
from drivers.protocols.razor import ErrorLine, RazorFramer, Synch, Ypr
from drivers.serial_port import SerialDriver
from hmdrt.bus.messages import Pose
from hmdrt.errors import ConfigError
from hmdrt.spatial import quat_from_yaw_pitch, quat_multiply, quat_to_matrix
from replay.synthetic import SyntheticConfig, SyntheticSource

from .helpers import assert_lost_when_stopped, at_least, collect

RAZOR_LINE = b"#YPR=-142.28,-5.38,33.52\r\n"
HATIRE_FRAME = bytes.fromhex("aaaa0700000020410000a0c000002040") + bytes(12) + bytes.fromhex("5555")
TIMEOUT_S = 10.0  # generous bound for anything that waits on the pty


def angle_between_deg(a, b) -> float:
    """The rotation angle between two orientations (accurate near zero, unlike acos of the dot product)."""
    d = quat_multiply(np.asarray(a) * (1.0, -1.0, -1.0, -1.0), np.asarray(b))
    return math.degrees(2 * math.atan2(float(np.linalg.norm(d[1:])), abs(float(d[0]))))


def read_until(port: serial.SerialBase, marker: bytes) -> bytes:
    data = b""
    deadline = time.monotonic() + TIMEOUT_S
    while marker not in data and time.monotonic() < deadline:
        data += port.read(max(1, port.in_waiting))
    assert marker in data, f"no {marker!r} within {TIMEOUT_S} s"
    return data


def read_at_least(port: serial.SerialBase, n: int) -> bytes:
    data = b""
    deadline = time.monotonic() + TIMEOUT_S
    while len(data) < n and time.monotonic() < deadline:
        data += port.read(max(1, port.in_waiting))
    return data


def quiet(port: serial.SerialBase, seconds: float = 0.3) -> bool:
    """Whether nothing arrives for `seconds` (many frame periods)."""
    port.timeout = seconds
    data = port.read(1000)
    port.timeout = 0.05
    return data == b""


# --- Razor codec ------------------------------------------------------------------------------------------------


def test_razor_vector_decodes_and_encodes():
    assert razor.decode_line(RAZOR_LINE) == Ypr(-142.28, -5.38, 33.52)
    assert razor.encode_ypr(-142.28, -5.38, 33.52) == RAZOR_LINE
    assert razor.parse_commands(b"#s12") == (["s12"], b"")
    assert razor.encode_synch("12") == b"#SYNCH12\r\n"


def test_razor_command_parser_splits_concatenated_commands_and_keeps_a_partial_tail():
    assert razor.parse_commands(b"#ob#o1#s12") == (["ob", "o1", "s12"], b"")
    assert razor.parse_commands(b"xx#ot#oe0#s") == (["ot", "oe0"], b"#s")
    assert razor.parse_commands(b"#zzzzz#f") == (["f"], b"")


@pytest.mark.parametrize(
    "line",
    [b"#YPR=1,2\r\n", b"#YPR=nan,0,0\r\n", b"#YPR=0,91,0\r\n", b"#YPR=1_0,0,0\r\n", b"#XYZ=1,2,3\r\n", b"#YPR=1,2,3"],
)
def test_razor_rejects_malformed_lines(line):
    with pytest.raises(razor.RazorFormatError):
        razor.decode_line(line)


def test_razor_framer_resynchronises_on_garbage_across_chunks():
    stream = b"\x00\xffjunk" + RAZOR_LINE + b"#YPR=12,3" + b"!ERR: reading mag\r\n" + b"#SYNCH07\r\n" + RAZOR_LINE
    garbage = len(b"\x00\xffjunk") + len(b"#YPR=12,3")
    framer = RazorFramer()
    frames = []
    for i in range(0, len(stream), 5):  # arbitrary chunk boundaries
        frames += framer.feed(stream[i : i + 5])
    assert frames == [Ypr(-142.28, -5.38, 33.52), ErrorLine("reading mag"), Synch("07"), Ypr(-142.28, -5.38, 33.52)]
    assert framer.discarded == garbage


def test_razor_framer_caps_a_line_that_never_ends():
    framer = RazorFramer()
    assert framer.feed(b"#" + b"1" * 1000) == []
    assert framer.discarded == 1001
    assert framer.feed(RAZOR_LINE) == [Ypr(-142.28, -5.38, 33.52)]


# --- HATIRE codec -----------------------------------------------------------------------------------------------


def test_hatire_vector_decodes_and_encodes():
    frame = HatireFrame(cpt=7, yaw=10.0, pitch=-5.0, roll=2.5)
    assert hatire.decode_frame(HATIRE_FRAME) == frame
    assert hatire.encode_frame(frame) == HATIRE_FRAME


def test_hatire_info_frame_round_trips():
    data = hatire.encode_info(2000, "HAT V 1.10")
    assert len(data) == hatire.FRAME_SIZE and data[-3:] == b"\n\x55\x55"
    assert hatire.decode_frame(data) == HatireInfo(2000, "HAT V 1.10")


def test_hatire_rejects_bad_frames():
    with pytest.raises(hatire.HatireFormatError, match="30-byte"):
        hatire.decode_frame(HATIRE_FRAME[:29])
    nan_yaw = hatire.encode_frame(HatireFrame(1, math.nan, 0.0, 0.0))
    with pytest.raises(hatire.HatireFormatError, match="not finite"):
        hatire.decode_frame(nan_yaw)


def test_hatire_framer_resynchronises_and_counts_discarded_bytes():
    bad_values = hatire.encode_frame(HatireFrame(8, 1e9, 0.0, 0.0))
    garbage = b"\xaa\x01\x55\x55\xaa"  # false starts and stray end markers
    stream = garbage + HATIRE_FRAME + b"\xaa\xaa" + bad_values + hatire.encode_info(5001, "HAT START") + HATIRE_FRAME
    framer = HatireFramer()
    frames = []
    for i in range(0, len(stream), 7):
        frames += framer.feed(stream[i : i + 7])
    assert frames == [
        hatire.decode_frame(HATIRE_FRAME),
        HatireInfo(5001, "HAT START"),
        hatire.decode_frame(HATIRE_FRAME),
    ]
    assert framer.discarded == len(garbage) + 2 + len(bad_values)


# --- angle conventions ------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "ypr, expected",
    [
        ((30.0, 0.0, 0.0), quat_from_yaw_pitch(30.0, 0.0)),  # yaw right
        ((0.0, 20.0, 0.0), quat_from_yaw_pitch(0.0, 20.0)),  # pitch up
        ((-45.0, -10.0, 0.0), quat_from_yaw_pitch(-45.0, -10.0)),  # yaw then pitch
    ],
)
def test_device_angles_match_the_head_frame_yaw_and_pitch(ypr, expected):
    assert angle_between_deg(razor.ypr_to_quat(*ypr), expected) < 1e-9


def test_roll_right_lowers_the_right_side():
    q = razor.ypr_to_quat(0.0, 0.0, 30.0)
    right = quat_to_matrix(q) @ np.array([1.0, 0.0, 0.0])
    forward = quat_to_matrix(q) @ np.array([0.0, 0.0, -1.0])
    assert right[1] == pytest.approx(-math.sin(math.radians(30.0)))
    assert forward == pytest.approx([0.0, 0.0, -1.0])


def test_yaw_pitch_roll_round_trip():
    rng = np.random.default_rng(0)
    angles = np.column_stack([rng.uniform(-179, 179, 50), rng.uniform(-89, 89, 50), rng.uniform(-179, 179, 50)])
    for yaw, pitch, roll in angles:
        assert razor.quat_to_ypr(razor.ypr_to_quat(yaw, pitch, roll)) == pytest.approx((yaw, pitch, roll), abs=1e-9)


# --- serial:// over a real pty ----------------------------------------------------------------------------------


def expected_razor_orientations(seed: int, count: int) -> list[tuple[float, ...]]:
    """What the emulator sends: synthetic head poses as two-decimal Razor angles, back in the head frame."""
    source = SyntheticSource(SyntheticConfig(seed=seed, rate_hz=razor.RATE_HZ, head=True, blink_rate_hz=0.0))
    poses = (s for s in source.samples() if isinstance(s, Pose))
    out = []
    for pose, _ in zip(poses, range(count), strict=False):
        ypr = (round(v, 2) for v in razor.quat_to_ypr(pose.orientation))
        out.append(razor.ypr_to_quat(*ypr))
    return out


def read_through_pty(protocol: str, seed: int, n: int) -> tuple[SerialTrackerEmulator, SerialDriver, list[Pose]]:
    """At least n poses (or what arrives within TIMEOUT_S) of serial:// on an emulated tracker's pty; the
    emulator and driver, both closed, with them."""
    with SerialTrackerEmulator(protocol, seed=seed) as emu:
        driver = open_driver(f"serial://{emu.device_path}?protocol={protocol}")
        driver.open()
        poses = collect(driver, at_least(n), TIMEOUT_S)
        driver.close()
    return emu, driver, poses


def test_razor_frames_through_a_pty_arrive_and_convert():
    _, driver, poses = read_through_pty("razor", 4, 25)
    assert len(poses) >= 25
    expected = expected_razor_orientations(4, 2000)
    first = min(range(len(expected)), key=lambda i: angle_between_deg(expected[i], poses[0].orientation))
    errors = [angle_between_deg(expected[first + j], p.orientation) for j, p in enumerate(poses)]
    assert max(errors) < 1e-3  # consecutive frames, each converted exactly
    assert [p.seq for p in poses] == list(range(len(poses)))
    assert all(p.t_dev is None for p in poses)
    assert all(b.t_host >= a.t_host for a, b in zip(poses, poses[1:], strict=False))
    assert driver.counters.malformed == 0 and driver.counters.samples == len(poses)


def test_razor_emulator_answers_commands():
    with SerialTrackerEmulator("razor", seed=0) as emu, serial.Serial(emu.device_path, 57600, timeout=0.05) as port:
        port.write(b"#s12")
        read_until(port, b"#SYNCH12\r\n")
        port.write(b"#o0#s34")
        read_until(port, b"#SYNCH34\r\n")
        assert quiet(port)  # streaming off
        port.write(b"#f")
        line = read_until(port, b"\r\n")
        assert isinstance(razor.decode_line(line), Ypr)
        assert quiet(port)  # #f sends exactly one frame


def test_hatire_frames_through_a_pty_arrive_and_count_no_drops():
    emu, driver, poses = read_through_pty("hatire", 2, 30)
    assert len(poses) >= 30 and emu.frames_sent >= len(poses) and emu.overflows == 0
    assert all(abs(np.linalg.norm(p.orientation) - 1.0) < 1e-9 for p in poses)
    assert driver.counters.dropped == 0 and driver.counters.malformed == 0
    assert driver.baud == 115200


def test_hatire_emulator_start_stop_and_version():
    with SerialTrackerEmulator("hatire") as emu, serial.Serial(emu.device_path, 115200, timeout=0.05) as port:
        port.write(b"V")
        framer = HatireFramer()
        frames: list = []
        deadline = time.monotonic() + TIMEOUT_S
        while HatireInfo(2000, "HAT V 1.10") not in frames and time.monotonic() < deadline:
            frames += framer.feed(port.read(max(1, port.in_waiting)))
        assert HatireInfo(2000, "HAT V 1.10") in frames
        port.write(b"s")
        read_until(port, hatire.encode_info(hatire.CODE_STOP, "HAT STOP"))
        assert quiet(port)
        port.write(b"S")
        data = read_until(port, hatire.encode_info(hatire.CODE_START, "HAT START"))
        data += read_at_least(port, hatire.FRAME_SIZE * 2)
        counters = [f.cpt for f in HatireFramer().feed(data) if isinstance(f, HatireFrame)]
        assert counters[:2] == [0, 1]  # S restarts the frame counter


def test_adapter_raises_device_lost_when_the_emulator_stops():
    emu = SerialTrackerEmulator("razor").start()
    driver = SerialDriver(f"serial://{emu.device_path}?protocol=razor")
    assert_lost_when_stopped(emu, driver, match="serial port")
    driver.close()
    with pytest.raises(DeviceLost, match="cannot open"):
        driver.open()  # the pty is gone


# --- serial:// over loop:// -------------------------------------------------------------------------------------


def frame(cpt: int, yaw: float = 10.0) -> bytes:
    return hatire.encode_frame(HatireFrame(cpt, yaw, -5.0, 2.5))


def test_hatire_over_loop_counts_a_skipped_counter_across_the_wrap():
    driver = open_driver("serial://?port=loop://&protocol=hatire")
    driver.open()
    garbage = b"\x13\x37garbage\xaa"
    driver.port.write(frame(997) + frame(998) + garbage + frame(999) + frame(0) + frame(1) + frame(3))
    poses = collect(driver, at_least(6), TIMEOUT_S)
    driver.close()
    assert len(poses) == 6
    assert driver.counters.dropped == 1  # counter 2 is missing; 999 -> 0 is the wrap, not a loss
    assert driver.counters.malformed == len(b"S") + len(garbage)  # loop:// echoes the start command
    assert angle_between_deg(poses[0].orientation, razor.ypr_to_quat(10.0, -5.0, 2.5)) < 1e-5


def test_razor_over_loop_with_partial_writes():
    driver = open_driver("serial://?port=loop://&protocol=razor&baud=9600")
    driver.open()
    for i in range(0, len(RAZOR_LINE), 4):
        driver.port.write(RAZOR_LINE[i : i + 4])
    poses = collect(driver, at_least(1), TIMEOUT_S)
    driver.close()
    assert len(poses) == 1
    assert angle_between_deg(poses[0].orientation, razor.ypr_to_quat(-142.28, -5.38, 33.52)) < 1e-9
    assert driver.counters.malformed == len(b"#ot#o1")


@pytest.mark.parametrize(
    "url, message",
    [
        ("serial:///dev/ttyUSB0", "protocol=razor or protocol=hatire"),
        ("serial:///dev/ttyUSB0?protocol=nmea", "protocol=razor or protocol=hatire"),
        ("serial://?protocol=razor", "not both or neither"),
        ("serial:///dev/ttyUSB0?protocol=razor&port=loop://", "not both or neither"),
        ("serial://dev/ttyUSB0?protocol=razor", "URL path"),
        ("serial:///dev/ttyUSB0?protocol=razor&baud=0", "outside"),
    ],
)
def test_bad_serial_urls_are_clear_errors(url, message):
    with pytest.raises(ConfigError, match=message):
        open_driver(url)


def test_unknown_pyserial_scheme_is_a_config_error_and_missing_device_is_device_lost(tmp_path):
    with pytest.raises(ConfigError, match="cannot use port"):
        open_driver("serial://?port=bogus://x&protocol=razor").open()
    with pytest.raises(DeviceLost, match="cannot open serial port"):
        open_driver(f"serial://{tmp_path}/ttyNONE?protocol=hatire").open()
