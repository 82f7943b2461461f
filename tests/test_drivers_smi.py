"""SMI iView X: the line codec against docs/protocols.md, Test vectors, the UDP emulator and the smi:// driver, on
real loopback sockets."""

from __future__ import annotations

import math
import socket
import time
from itertools import islice

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from hmdrt.drivers import open_driver
from hmdrt.drivers.base import DeviceLost, DriverError
from hmdrt.drivers.emulators.feed import GazeFeed
from hmdrt.drivers.emulators.smi_server import SmiEmulator
from hmdrt.drivers.protocols import smi
from hmdrt.errors import ConfigError
from hmdrt.optics import EyeCamera, get_profile
from hmdrt.spatial import Pose, gaze_direction

from .helpers import assert_lost_when_stopped, at_least, collect, gaze_trace

WAIT_S = 5.0  # bound on every wait for a datagram: generous on a loaded machine, never reached when all is well
PERIOD_NS = 4_000_000  # 250 Hz
RED_LINE = (
    "ET_SPL 102172364740 b 855 855 346 346 13.103793 11.830818 13.103793 11.830818 -66.588 -2.985 18.302 11.463 "
    "582.493 574.155 346.478830 623.560946 432.144375 461.448565"
)
RED_LINE_TS = "ET_SPL b 100527788 790 790 255 255 -59.923  3.225 14.816 17.588 587.446 580.656"
FIX_LINE = "ET_FIX l 100527771763 512.0 384.0"
EFX_LINE = "ET_EFX l 100527771763 100527971763 200 512.0 384.0"
TARGET_A = (gaze_direction(10.0, 5.0), gaze_direction(8.0, 5.0))  # left and right eye, converging
TARGET_B = (gaze_direction(-12.0, -8.0), gaze_direction(-14.0, -8.0))


def cameras() -> tuple[EyeCamera, EyeCamera]:
    display = get_profile("dk2")
    return EyeCamera.for_eye(display, Pose(), "left"), EyeCamera.for_eye(display, Pose(), "right")


def angle_deg(a, b) -> float:
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    return math.degrees(math.atan2(np.linalg.norm(np.cross(a, b)), float(a @ b)))


class Client:
    """A UDP client of the emulator on a loopback port of its own."""

    def __init__(self, address: tuple[str, int]):
        self.address = address
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", 0))
        self.sock.settimeout(WAIT_S)

    def send(self, text: str | bytes, to: tuple[str, int] | None = None) -> None:
        self.sock.sendto(text if isinstance(text, bytes) else smi.encode(text), to or self.address)

    def recv(self) -> str:
        return smi.decode(self.sock.recv(smi.MAX_LINE_BYTES + 1))

    def reply(self, text: str) -> str:
        """Send a command and return the next line that is not a sample."""
        self.send(text)
        while (line := self.recv()).startswith("ET_SPL"):
            pass
        return line

    def close(self) -> None:
        self.sock.close()


@pytest.fixture
def emulator():
    with SmiEmulator(feed=GazeFeed(250, seed=3)) as emu:
        yield emu


@pytest.fixture
def client(emulator):
    c = Client(emulator.address)
    yield c
    c.close()


@pytest.fixture(scope="module")
def trace(tmp_path_factory) -> str:
    """One second at 250 Hz: target A for 400 ms, a 100 ms blink, target B for 500 ms."""
    eyes = [(*(TARGET_A if 4 * k < 500 else TARGET_B), not 400 <= 4 * k < 500) for k in range(250)]
    return gaze_trace(tmp_path_factory.mktemp("smi") / "still.jsonl", eyes, PERIOD_NS)


# --- codec: docs/protocols.md, Test vectors -----------------------------------------------------------------


def test_red_capture_parses_in_the_format_of_item_1():
    mnemonic, args = smi.parse_line('ET_FRM "%TU %ET %SX %SY %DX %DY %EX %EY %EZ %PX %PY"')
    fmt = smi.SampleFormat.parse(args[0])
    assert mnemonic == "ET_FRM" and fmt.specifiers == ("TU", "ET", "SX", "SY", "DX", "DY", "EX", "EY", "EZ", "PX", "PY")
    s = fmt.parse_line(RED_LINE)
    assert s.eye == "b" and s.timestamp_us == 102172364740
    v = s.values
    assert v["SX"] == (855, 855) and v["SY"] == (346, 346)
    assert v["DX"] == v["DY"] == (13.103793, 11.830818)
    assert v["EX"] == (-66.588, -2.985) and v["EY"] == (18.302, 11.463) and v["EZ"] == (582.493, 574.155)
    assert v["PX"] == pytest.approx((346.48, 623.56), abs=0.005)
    assert v["PY"] == pytest.approx((432.14, 461.45), abs=0.005)


def test_red_capture_with_a_double_space_and_milliseconds():
    s = smi.SampleFormat.parse("%ET %TS %SX %SY %EX %EY %EZ").parse_line(RED_LINE_TS)
    assert s.eye == "b" and s.values["TS"] == 100527788 and s.timestamp_us == 100527788000
    assert s.values["SX"] == (790, 790) and s.values["SY"] == (255, 255)
    assert s.values["EX"] == (-59.923, 3.225) and s.values["EY"] == (14.816, 17.588)
    assert s.values["EZ"] == (587.446, 580.656)


@pytest.mark.parametrize(
    "fmt, line, eye, values",
    [
        ("%TS: %SX, %SY", "ET_SPL 28437864110: 400, 202", None, {"TS": 28437864110, "SX": (400,), "SY": (202,)}),
        ("%ET %SX %SY", "ET_SPL b 399 398 200 199", "b", {"SX": (399, 398), "SY": (200, 199)}),
    ],
)
def test_documentation_examples(fmt, line, eye, values):
    s = smi.SampleFormat.parse(fmt).parse_line(line)
    assert s == smi.SplSample(eye, values)
    assert smi.SampleFormat.parse(fmt).format_line(s) == line  # binocular doubling on the way out too


def test_fixation_events_of_item_6():
    start, end = smi.parse_event(FIX_LINE), smi.parse_event(EFX_LINE)
    assert start == smi.FixationStart("l", 100527771763, 512.0, 384.0)
    assert end == smi.FixationEnd("l", 100527771763, 100527971763, 200, 512.0, 384.0)
    assert smi.parse_event(start.line()) == start and smi.parse_event(end.line()) == end


def test_validation_reply_of_item_5_survives_the_wire():
    v = smi.Validation.parse("ET_VLS l 640 512 0.5 0.3\u00b0 0.4\u00b0")
    assert v == smi.Validation("l", 640, 512, 0.5, 0.3, 0.4)
    assert smi.Validation.parse(smi.decode(smi.encode(v.line()))) == v


@pytest.mark.parametrize(
    "text, expected",
    [
        ('ET_FRM "%ET  %SX %SY"\n', ("ET_FRM", ("%ET  %SX %SY",))),
        ("ET_CAL   5 \t\n", ("ET_CAL", ("5",))),  # runs of whitespace; the serial variant's TAB+LF end
        ('ET_SAV "C:\\data\\run 1.idf"\r\n', ("ET_SAV", ("C:\\data\\run 1.idf",))),
        ('ET_CNT ""', ("ET_CNT", ("",))),
    ],
)
def test_lines_split_on_whitespace_and_keep_quoted_strings(text, expected):
    assert smi.parse_line(smi.decode(text.encode())) == expected


def test_commands_quote_string_arguments():
    assert smi.command("ET_FRM", smi.GAZE_FORMAT) == 'ET_FRM "%TU %ET %SX %SY"'
    assert smi.command("ET_STR", 120) == "ET_STR 120"
    assert smi.parse_line(smi.command("ET_SAV", "run 1.idf")) == ("ET_SAV", ("run 1.idf",))


@pytest.mark.parametrize(
    "data", [b"", b"hello", b"et_png", b'"ET_PNG"', b'ET_FRM "%TU', b'ET_SAV a"b"', b"ET_PNG\x00", b"ET_A\nET_B"]
)
def test_bad_lines_are_rejected(data):
    with pytest.raises(smi.SmiError):
        smi.parse_line(smi.decode(data))


@pytest.mark.parametrize(
    "fmt, message",
    [
        ("%SX%SY", "need a separator"),
        ("%SX.%SY", "need a separator"),
        ("%XX %SX", "unknown specifier"),
        ("50% %SX", "unknown specifier"),
        ("%SX %SX", "repeats"),
        ("gaze", "no specifier"),
        ("%TU " * 300, "at most"),
    ],
)
def test_bad_formats_are_rejected(fmt, message):
    with pytest.raises(smi.SmiError, match=message):
        smi.SampleFormat.parse(fmt)


@pytest.mark.parametrize(
    "fmt, line",
    [
        ("%ET %TS %SX %SY %EX %EY %EZ", RED_LINE),  # another format's line
        ("%ET %SX %SY", "ET_SPL l 399 398 200 199"),  # eye l with two values per eye
        ("%ET %SX %SY", "ET_SPL b 399 200"),  # eye b with one
        ("%ET %SX %SY", "ET_SPL b 399 398 200 nan"),
        ("%ET %SX %SY", "ET_SPL b 399 398 200 1e999"),
        ("%TU %SX", "ET_SPL -5 3"),
        ("%TU %SX", "ET_SPL 5 3 extra"),
        ("%TU %SX", "ET_SPLX 5 3"),
        ("%TU %SX", "ET_FIX 5 3"),
        ("%TU %SX", f"ET_SPL {2**64 + 1} 3"),
    ],
)
def test_lines_that_do_not_match_the_format_are_rejected(fmt, line):
    with pytest.raises(smi.SmiError):
        smi.SampleFormat.parse(fmt).parse_line(line)


@st.composite
def formats_and_samples(draw):
    names = draw(st.lists(st.sampled_from(sorted(smi.SPECIFIERS)), min_size=1, max_size=9, unique=True))
    seps = [draw(st.sampled_from([" ", "  ", "\t", ": ", ", ", " ; ", " | "])) for _ in names[1:]]
    text = (
        draw(st.sampled_from(["", "gaze "]))
        + "%"
        + names[0]
        + "".join(s + "%" + n for s, n in zip(seps, names[1:], strict=True))
    )
    if "ET" in names:
        eye = draw(st.sampled_from("lrb"))
    else:
        eye = draw(st.sampled_from(["b", None])) if smi.PER_EYE.intersection(names) else None
    finite = st.floats(allow_nan=False, allow_infinity=False)
    values = {n: draw(st.integers(0, 2**64)) for n in names if n in smi.COUNTERS}
    values.update({n: tuple(draw(finite) for _ in range(2 if eye == "b" else 1)) for n in names if n in smi.PER_EYE})
    return smi.SampleFormat.parse(text), smi.SplSample(eye, values)


@settings(max_examples=300, deadline=None)
@given(formats_and_samples())
def test_formatted_lines_parse_back_to_the_sample(case):
    fmt, sample = case
    data = smi.encode(fmt.format_line(sample))
    assert len(data) <= smi.MAX_LINE_BYTES
    assert fmt.parse_line(smi.decode(data)) == sample


# --- emulator ------------------------------------------------------------------------------------


def test_emulator_answers_ping_and_rate_and_keeps_the_format(emulator, client):
    assert client.reply("ET_PNG") == "ET_PNG"
    assert client.reply("ET_SRT") == "ET_SRT 250"
    client.send(smi.command("ET_FRM", "%TS: %SX, %SY"))
    client.send("ET_STR")
    fmt = smi.SampleFormat.parse("%TS: %SX, %SY")
    lines = [client.recv() for _ in range(5)]
    samples = [fmt.parse_line(line) for line in lines]
    assert all(s.eye == "b" and len(s.values["SX"]) == 2 for s in samples)  # binocular tracker: two values per eye
    with pytest.raises(smi.SmiError):
        smi.SampleFormat.parse(smi.GAZE_FORMAT).parse_line(lines[0])
    client.send("ET_EST")
    assert client.reply("ET_PNG") == "ET_PNG"
    assert not emulator.streaming


def test_emulator_streams_the_default_format_and_every_specifier(client):
    client.send("ET_STR")
    default = [smi.SampleFormat.parse(smi.GAZE_FORMAT).parse_line(client.recv()) for _ in range(5)]
    steps = {b.timestamp_us - a.timestamp_us for a, b in zip(default, default[1:], strict=False)}
    assert steps == {4000}  # 250 Hz on the tracker's microsecond clock
    everything = "%TU %TS %SC %ET %SX %SY %DX %DY %PX %PY %CX %CY %EX %EY %EZ"
    client.send("ET_EST")
    client.send(smi.command("ET_FRM", everything))
    assert client.reply("ET_PNG") == "ET_PNG"  # skips the samples sent before ET_EST
    client.send("ET_STR")
    fmt = smi.SampleFormat.parse(everything)
    s = fmt.parse_line(client.recv())
    assert s.values["TS"] == s.values["TU"] // 1000 and s.values["SC"] >= 0
    assert set(s.values) == set(fmt.specifiers) - {"ET"} and all(len(s.values[n]) == 2 for n in smi.PER_EYE)


def test_emulator_streams_at_a_lower_rate_on_request(client):
    client.send("ET_STR 50")
    times = [smi.SampleFormat.parse(smi.GAZE_FORMAT).parse_line(client.recv()).timestamp_us for _ in range(8)]
    assert {b - a for a, b in zip(times, times[1:], strict=False)} == {20_000}


def test_calibration_dialogue_in_order(client):
    client.send("ET_CAL 5")
    assert client.recv() == "ET_CAL 5"
    mnemonic, area = smi.parse_line(client.recv())
    assert mnemonic == "ET_CSZ" and tuple(map(int, area)) == (get_profile("dk2").width, get_profile("dk2").height)
    points = [smi.parse_line(client.recv()) for _ in range(5)]
    assert [p[0] for p in points] == ["ET_PNT"] * 5 and [int(p[1][0]) for p in points] == [1, 2, 3, 4, 5]
    xy = {(int(p[1][1]), int(p[1][2])) for p in points}
    assert len(xy) == 5 and all(0 <= x < int(area[0]) and 0 <= y < int(area[1]) for x, y in xy)
    assert client.recv() == "ET_CHG 1"
    for i in range(2, 6):
        assert client.reply("ET_ACC") == f"ET_CHG {i}"
    assert client.reply("ET_ACC") == "ET_FIN"


def test_calibration_abort_and_custom_area(emulator, client):
    assert client.reply("ET_CSZ 1280 1024") == "ET_CSZ 1280 1024"
    client.send("ET_CAL 9")
    assert client.recv() == "ET_CAL 9"
    assert client.recv() == "ET_CSZ 1280 1024"
    assert client.recv() == "ET_PNT 1 640 512"  # the centre first, as in docs/protocols.md, Test vectors (SMI)
    for _ in range(9):
        client.recv()
    assert client.reply("ET_BRK") == "ET_BRK"
    malformed = emulator.malformed
    client.send("ET_ACC")
    assert client.reply("ET_PNG") == "ET_PNG"  # no ET_CHG came before the ping's reply
    assert emulator.malformed == malformed + 1  # ET_ACC outside a calibration is counted


def test_client_calibration_points_until_reset(client):
    client.send("ET_PNT 2 100 200")
    client.send("ET_CAL 2")
    w, h = get_profile("dk2").width, get_profile("dk2").height
    assert [client.recv() for _ in range(4)][2:] == [f"ET_PNT 1 {w // 2} {h // 2}", "ET_PNT 2 100 200"]
    assert client.recv() == "ET_CHG 1"
    client.send("ET_DEF")
    client.send("ET_CAL 2")
    assert [client.recv() for _ in range(4)][3] != "ET_PNT 2 100 200"


def test_calibration_start_is_answered_as_pyviewx_and_winkorblush_expect(client):
    """iView X answers ET_CAL n with ET_CAL n (the number of points) before ET_CSZ, the ET_PNT lines and ET_CHG 1:
    the order of the iView X stand-in in gesztesigabor/winkorblush (experiment/test_smi.py, commit
    ea7a525398efe78810889bd6d406e6452dc60ac3). PyViewX's calibrator (RyanHope/PyViewX,
    pyviewx.pygame/pyviewx/pygame/calibrator.py, commit 1934f168186540bedbfa5b81cf42012ddeca2b32) sizes its
    list from that reply (`calibrationPoints = [None] * int(inResponse[0])` on ET_CAL, after `_reset` left it
    `[]`) and stores each ET_PNT at index i - 1, so without the reply its first ET_PNT raises IndexError.
    Its handlers are replayed here, on the emulator's datagrams as they arrive."""
    points: list = []  # PyViewX's calibrator after _reset()
    current = -1
    client.send("ET_CAL 9 2")  # PyViewX's startCalibration(9, eye=2): ET_CAL <points> <eye>
    while current < 0:
        mnemonic, args = smi.parse_line(client.recv())
        if mnemonic == "ET_CAL":
            points = [None] * int(args[0])
        elif mnemonic == "ET_PNT":
            points[int(args[0]) - 1] = (int(args[1]), int(args[2]))
        elif mnemonic == "ET_CHG":
            current = int(args[0]) - 1
    display = get_profile("dk2")
    assert len(points) == 9 and None not in points and current == 0
    assert points[current] == (round(display.width / 2), round(display.height / 2))  # the centre first


def test_validation_reports_the_feed_accuracy_per_eye():
    with SmiEmulator(feed=GazeFeed(250, offset_deg=0.3, noise_deg=0.4)) as emu:
        c = Client(emu.address)
        c.send("ET_VLS")
        reports = [smi.Validation.parse(c.recv()), smi.Validation.parse(c.recv())]
        c.close()
    display = get_profile("dk2")
    assert [r.eye for r in reports] == ["l", "r"]
    for r in reports:
        assert (r.x, r.y) == (display.width // 2, display.height // 2)  # a target at the area's centre
        # RMS error of a constant offset (along x) plus Gaussian noise of the stated deviation (on both axes)
        assert r.x_deg == pytest.approx(math.hypot(0.3, 0.4), abs=1e-3) and r.y_deg == pytest.approx(0.4)
        assert r.deviation_deg == pytest.approx(math.hypot(r.x_deg, r.y_deg), abs=1e-3)


def test_fixation_events_for_a_steady_gaze(trace):
    cams = cameras()
    targets = {eye: [cams[i].gaze_pixel(t[i]) for t in (TARGET_A, TARGET_B)] for i, eye in enumerate("lr")}
    events: dict[str, list] = {"l": [], "r": []}
    with SmiEmulator(feed=GazeFeed(250, trace=trace)) as emu:
        c = Client(emu.address)
        c.send("ET_FIX 75 45")
        while len(events["l"]) < 3 or not events["r"]:
            event = smi.parse_event(c.recv())
            events[event.eye].append(event)
        c.close()
    first, end, second = events["l"][:3]
    assert (
        isinstance(first, smi.FixationStart)
        and isinstance(end, smi.FixationEnd)
        and isinstance(second, smi.FixationStart)
    )
    assert (end.start_us, end.x, end.y) == (first.start_us, first.x, first.y)
    assert end.duration_ms == round((end.end_us - end.start_us) / 1000) and 75 <= end.duration_ms <= 500
    seen = [nearest(e, targets["l"]) for e in (first, second)]
    assert all(distance < 0.02 for _, distance in seen)  # at a target's pixel, to rounding
    assert seen[0][0] != seen[1][0]  # the gaze moved to the other target
    assert nearest(events["r"][0], targets["r"])[1] < 0.02


def nearest(event: smi.FixationStart, pixels: list[np.ndarray]) -> tuple[int, float]:
    """Index of the pixel nearest an event's position, and its distance."""
    distances = [math.hypot(event.x - p[0], event.y - p[1]) for p in pixels]
    return int(np.argmin(distances)), min(distances)


def test_emulator_counts_bad_commands_and_keeps_serving(emulator, client):
    bad = [b"hello", b"ET_XYZ", b"ET_STR abc", b"ET_STR 251", b"ET_CAL 4", b"ET_ACC", b"\xff\xfe", b'ET_FRM "%QQ"']
    for data in bad:
        client.send(data)
    client.send(b"ET_PNG" + b" " * 5000)
    client.send(b"x" * 60_000)
    assert client.reply("ET_PNG") == "ET_PNG"
    assert (emulator.malformed, emulator.oversized) == (len(bad), 2)
    client.send("ET_STR")  # the rejected ET_FRM left the default format in place
    smi.SampleFormat.parse(smi.GAZE_FORMAT).parse_line(client.recv())


def test_record_commands_are_acknowledged(client):
    for text in ("ET_REC", "ET_PSE", "ET_CNT trial 2", "ET_STP", 'ET_SAV "run.idf"', "ET_CLR"):
        assert client.reply(text) == text.split()[0]


# --- driver --------------------------------------------------------------------------------------


def smi_url(address: tuple[str, int], **options) -> str:
    query = "&".join(f"{k}={v}" for k, v in {"listen": 0, **options}.items())
    return f"smi://{address[0]}:{address[1]}?{query}"


def test_driver_streams_the_feed_as_unit_head_frame_directions(trace):
    with SmiEmulator(feed=GazeFeed(250, trace=trace)) as emu:
        driver = open_driver(smi_url(emu.address))
        opened = time.monotonic_ns()
        driver.open()
        start = time.monotonic()
        samples = collect(driver, timeout_s=1.0)
        elapsed = time.monotonic() - start
        driver.close()
        closed = time.monotonic_ns()
    assert 0.6 * 250 * elapsed <= len(samples) <= 1.2 * 250 * elapsed + 10
    assert [s.seq for s in samples] == list(range(len(samples)))
    steps = np.diff([s.t_dev for s in samples])
    assert np.all(steps > 0) and np.mean(steps == PERIOD_NS) > 0.9  # every tracker sample, in order
    sent = dict(emu.sent)  # device time -> when the emulator wrote it, never before it was due
    assert all(emu.epoch_ns + s.t_dev <= sent[s.t_dev] <= closed for s in samples)
    assert all(opened - 100e6 <= s.t_host <= sent[s.t_dev] + 100e6 for s in samples)
    settled = [s for s in samples if s.t_dev - samples[0].t_dev > 300e6]  # the estimate's first windows are done
    assert settled and all(abs(s.t_host - (emu.epoch_ns + s.t_dev)) < 5e6 for s in settled)  # capture, host clock
    expected = list(islice(GazeFeed(250, trace=trace).samples(), samples[-1].t_dev // PERIOD_NS + 1))
    blinks = 0
    for s in samples:
        ref = expected[s.t_dev // PERIOD_NS]  # the tracker clock counts periods from its start
        assert s.valid == ref.valid
        if not s.valid:
            assert s.L is None and s.R is None
            blinks += 1
            continue
        for got, want in ((s.L, ref.left), (s.R, ref.right)):
            assert abs(np.linalg.norm(got) - 1.0) < 1e-6 and angle_deg(got, want) < 0.01
        assert abs(np.linalg.norm(s.C) - 1.0) < 1e-9
    assert 0 < blinks < len(samples)
    assert driver.counters.samples == len(samples) and driver.counters.invalid == blinks
    assert driver.counters.malformed == 0


def test_driver_reads_monocular_red_and_skips_bad_datagrams(emulator, client):
    driver = open_driver(smi_url(emulator.address))
    driver.open()
    client.send("ET_EST")
    assert client.reply("ET_PNG") == "ET_PNG"  # the emulator has stopped streaming
    driver.read(0.0)
    bad = [b"garbage", b"\xff\xfe", b"ET_SPL 5001 l 591", b"ET_SPL 5001 l 591 inf", b"ET_SPL " + b"1 " * 3000]
    good = [
        "ET_SPL 1001 l 591 732",
        "ET_SPL 2001 r 700 500",
        "ET_SPL 3001 b 0 700 0 500",
        "ET_SPL 4001 b 0 0 0 0",
        FIX_LINE,  # a fixation event is not a sample, and not malformed either
        RED_LINE,
        RED_LINE_TS,
    ]
    for data in [*bad, b"x" * 60_000, *good]:
        client.send(data, to=driver.local_address)
    samples = collect(driver, at_least(6))
    driver.close()
    assert driver.counters.malformed == len(bad) + 1
    assert [s.t_dev for s in samples] == [1001_000, 2001_000, 3001_000, 4001_000, 102172364740_000, 100527788_000_000]
    left, right, right_only, lost, red, red_ts = samples
    assert left.valid and left.R is None and left.C is None
    assert right.valid and right.L is None
    assert right_only.valid and right_only.L is None and right_only.R == right.R
    assert not lost.valid and lost.L is None and lost.R is None
    cams = cameras()
    np.testing.assert_allclose(cams[0].gaze_pixel(left.L), (591, 732), atol=0.01)
    np.testing.assert_allclose(cams[1].gaze_pixel(right.R), (700, 500), atol=0.01)
    for sample, xy in ((red, (855, 346)), (red_ts, (790, 255))):
        np.testing.assert_allclose(cams[0].gaze_pixel(sample.L), xy, atol=0.01)
        np.testing.assert_allclose(cams[1].gaze_pixel(sample.R), xy, atol=0.01)
    assert red.L[0] > left.L[0] and red.L[1] > left.L[1]  # right of and above the centre pixel: +X right, +Y up


def test_driver_close_stops_the_stream(emulator, client):
    driver = open_driver(smi_url(emulator.address))
    driver.open()
    assert collect(driver, at_least(1)) and emulator.streaming
    driver.close()
    driver.close()
    assert client.reply("ET_PNG") == "ET_PNG"  # the emulator handled the ET_EST sent before
    assert not emulator.streaming


def test_driver_loses_a_stopped_tracker_and_reopens_when_it_is_back():
    emu = SmiEmulator(feed=GazeFeed(250, seed=1))
    emu.start()
    address = emu.address
    driver = open_driver(smi_url(address))
    try:
        assert_lost_when_stopped(emu, driver, match="sent nothing")
        driver.close()
        with pytest.raises(DeviceLost, match="no ET_PNG reply"):  # nobody answers the ping within 3 s
            driver.open()
        with SmiEmulator(port=address[1], feed=GazeFeed(250, seed=1)):
            driver.open()
            assert len(collect(driver, at_least(5))) >= 5
    finally:
        driver.close()
        emu.stop()


def test_driver_refuses_a_rate_above_the_tracker_rate():
    with SmiEmulator(rate_hz=60) as emu:
        driver = open_driver(smi_url(emu.address, rate=250))
        with pytest.raises(DriverError, match="exceeds the tracker's 60 Hz"):
            driver.open()
        driver.close()


@pytest.mark.parametrize(
    "url, message",
    [
        ("smi://127.0.0.1:4444?profile=nope", "unknown profile"),
        ("smi://127.0.0.1:4444?rate=0", "outside"),
        ("smi://127.0.0.1:4444?listen=70000", "outside"),
        ("smi://127.0.0.1:4444?port=5", "no option 'port'"),
    ],
)
def test_bad_driver_urls_are_clear_errors(url, message):
    with pytest.raises(ConfigError, match=message):
        open_driver(url)


def test_emulator_rejects_a_feed_at_another_rate():
    with pytest.raises(ConfigError, match="120 Hz"):
        SmiEmulator(feed=GazeFeed(120), rate_hz=250)
