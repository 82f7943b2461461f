"""pupil://: Pupil Remote and the IPC backbone of the emulator, and the adapter, over real ZeroMQ sockets."""

from __future__ import annotations

import time

import msgpack
import numpy as np
import pytest
import zmq

from drivers.base import DeviceLost
from drivers.emulators.feed import GazeFeed
from drivers.emulators.pupil_server import PupilEmulator
from drivers.pupil import MalformedDatum, PupilDriver, decode_gaze
from hmdrt.spatial import gaze_direction

from .helpers import SECTION7_GAZE, assert_lost_when_stopped, at_least, collect, free_port, gaze_trace

STILL_YAW, STILL_PITCH, STILL_DEPTH = 8.0, -4.0, 0.8


def unit(v) -> np.ndarray:
    return np.asarray(v, dtype=np.float64) / np.linalg.norm(v)


@pytest.fixture
def remote():
    """A REQ socket factory for Pupil Remote; asks one command and returns the reply."""
    sockets = []

    def ask(emulator: PupilEmulator, *frames: bytes | str) -> str:
        if not sockets:
            sock = zmq.Context.instance().socket(zmq.REQ)
            sock.setsockopt(zmq.LINGER, 0)
            sock.setsockopt(zmq.RCVTIMEO, 5000)
            host, port = emulator.address
            sock.connect(f"tcp://{host}:{port}")
            sockets.append(sock)
        sockets[0].send_multipart([f.encode() if isinstance(f, str) else f for f in frames])
        return sockets[0].recv_string()

    yield ask
    for sock in sockets:
        sock.close()


def still_trace(path, blink_share: float = 0.0) -> str:
    """A 100 ms trace of a still gaze (yaw 8, pitch -4, depth 0.8 m), its last blink_share invalid."""
    left, right = still_eyes()
    return gaze_trace(path, [(left, right, k < 10 * (1 - blink_share)) for k in range(10)], 10_000_000, STILL_DEPTH)


def still_eyes() -> tuple[np.ndarray, np.ndarray]:
    """The left and right eye's directions when both look at the still gaze's point."""
    centre = np.array(gaze_direction(STILL_YAW, STILL_PITCH))
    half = np.array([0.0635 / 2, 0.0, 0.0])
    return unit(centre * STILL_DEPTH + half), unit(centre * STILL_DEPTH - half)


def driver_url(emulator: PupilEmulator, timeout: float = 1.0) -> str:
    host, port = emulator.address
    return f"pupil://{host}:{port}?timeout={timeout}"


def backbone(emulator: PupilEmulator, prefix: bytes) -> zmq.Socket:
    sub = zmq.Context.instance().socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.RCVTIMEO, 5000)
    sub.setsockopt(zmq.SUBSCRIBE, prefix)
    sub.connect(f"tcp://127.0.0.1:{emulator.sub_port}")
    return sub


def until_received(sub: zmq.Socket, send, timeout_s: float = 5.0) -> list[bytes] | None:
    """Repeat `send()` until `sub` receives a message (PUB/SUB drops what is sent before it joins)."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        send()
        if sub.poll(100):
            return sub.recv_multipart()
    return None


def test_pupil_remote_answers_every_command(remote):
    with PupilEmulator() as emulator:
        sub_port = remote(emulator, "SUB_PORT")
        assert sub_port.isdigit() and int(sub_port) == emulator.sub_port
        pub_port = remote(emulator, "PUB_PORT")
        assert pub_port.isdigit() and int(pub_port) == emulator.pub_port != emulator.sub_port
        before = emulator.pupil_time()
        assert before <= float(remote(emulator, "t")) <= emulator.pupil_time()
        assert remote(emulator, "T 0.0") == "Timesync successful."
        assert 0.0 <= float(remote(emulator, "t")) < 5.0  # the clock was rebased to 0
        assert remote(emulator, "T 1234.5") == "Timesync successful."
        assert 1234.5 <= float(remote(emulator, "t")) < 1239.5
        assert remote(emulator, "T abc") == "'abc' cannot be converted to float."
        assert remote(emulator, "T nan") == "'nan' cannot be converted to float."
        assert 1234.5 <= float(remote(emulator, "t")) < 1239.5  # a failed T leaves the clock alone
        assert remote(emulator, "R") == "OK"
        assert remote(emulator, "r") == "OK"
        assert remote(emulator, "C") == "OK"
        assert remote(emulator, "c") == "OK"
        assert remote(emulator, "v")
        assert remote(emulator, "x") == "Unknown command."
        assert remote(emulator, "") == "Unknown command."


def test_notifications_and_forwarded_messages_reach_the_backbone(remote):
    with PupilEmulator() as emulator:
        sub = backbone(emulator, b"notify.")
        try:
            replies = []
            got = until_received(sub, lambda: replies.append(remote(emulator, "R session_7")))
            assert set(replies) == {"OK"}
            assert got[0] == b"notify.recording.should_start"
            assert msgpack.unpackb(got[1]) == {"subject": "recording.should_start", "session_name": "session_7"}
            while sub.poll(200):  # drain the repeats
                sub.recv_multipart()
            note = msgpack.packb({"subject": "custom.thing", "value": 3})
            assert remote(emulator, "notify.custom.thing", note) == "Message forwarded."
            assert sub.poll(5000) and sub.recv_multipart() == [b"notify.custom.thing", note]
        finally:
            sub.close()


def test_pupil_remote_survives_malformed_requests(remote):
    with PupilEmulator() as emulator:
        assert remote(emulator, b"\xff\xfe") == "Unknown command."
        assert remote(emulator, "notify.x", b"\xc1") == "Unknown command."
        assert remote(emulator, "notify.x", msgpack.packb([1, 2])) == "Unknown command."
        assert remote(emulator, b"\xff", msgpack.packb({"subject": "x"})) == "Unknown command."
        assert emulator.malformed == 4
        assert remote(emulator, "SUB_PORT") == str(emulator.sub_port)


def test_section7_gaze_converts_to_head_frame_directions():
    gaze = decode_gaze(b"gaze.3d.01.", msgpack.packb(SECTION7_GAZE))
    np.testing.assert_allclose(gaze.R, unit([0.06, 0.0, -0.998]), atol=1e-12)  # eye 0 is the right eye
    np.testing.assert_allclose(gaze.L, unit([-0.06, 0.0, -0.998]), atol=1e-12)
    np.testing.assert_allclose(gaze.C, [0.0, 0.0, -1.0], atol=1e-12)
    assert gaze.depth_m == pytest.approx(0.5)
    assert gaze.valid and gaze.t_dev == round(535741.7153e9)


def test_camera_y_down_becomes_head_y_up():
    datum = {**SECTION7_GAZE, "gaze_normals_3d": {"0": [0.0, 0.5, 0.866], "1": [0.0, 0.5, 0.866]}}
    gaze = decode_gaze(b"gaze.3d.01.", msgpack.packb(datum))
    np.testing.assert_allclose(gaze.C, unit([0.0, -0.5, -0.866]), atol=1e-12)  # looking down
    assert gaze.C[1] < 0


def test_monocular_gaze_fills_its_own_eye():
    datum = {k: v for k, v in SECTION7_GAZE.items() if k not in ("gaze_normals_3d", "gaze_point_3d")}
    datum["gaze_normal_3d"] = [0.1, 0.0, 0.995]
    right = decode_gaze(b"gaze.3d.0.", msgpack.packb(datum))
    left = decode_gaze(b"gaze.3d.1.", msgpack.packb(datum))
    assert right.L is None and left.R is None and right.depth_m is None
    np.testing.assert_allclose(right.R, unit([0.1, 0.0, -0.995]), atol=1e-12)
    assert right.C == right.R and left.C == left.L == right.R


@pytest.mark.parametrize("confidence, valid", [(0.0, False), (0.59, False), (0.6, True), (1.0, True)])
def test_validity_follows_the_pairing_threshold(confidence, valid):
    datum = {**SECTION7_GAZE, "confidence": confidence}
    assert decode_gaze(b"gaze.3d.01.", msgpack.packb(datum)).valid is valid


@pytest.mark.parametrize(
    "topic, payload",
    [
        (b"gaze.3d.01.", b"\xc1"),
        (b"gaze.3d.01.", msgpack.packb([1, 2, 3])),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "confidence": 1.5})),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "timestamp": "soon"})),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "gaze_normals_3d": {"0": [0.0, 0.0, 1.0]}})),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "gaze_normals_3d": {"0": [0, 0, 1], "1": [0, 0, -1]}})),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "gaze_normals_3d": {"0": [0, 0, 0], "1": [0, 0, 1]}})),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "gaze_point_3d": [float("nan"), 0.0, 1.0]})),
        (b"gaze.3d.0.", msgpack.packb(SECTION7_GAZE)),  # monocular without gaze_normal_3d
        (b"gaze.3d.2.", msgpack.packb(SECTION7_GAZE)),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "base_data": [b"x" * 70_000]})),
    ],
)
def test_malformed_datums_are_refused(topic, payload):
    with pytest.raises(MalformedDatum):
        decode_gaze(topic, payload)


def test_streams_gaze_at_200_hz(tmp_path, remote):
    feed = GazeFeed(200.0, trace=still_trace(tmp_path / "still.jsonl"))
    with PupilEmulator(feed=feed) as emulator:
        assert remote(emulator, "T 1234.5") == "Timesync successful."  # an arbitrary Pupil epoch
        driver = PupilDriver(driver_url(emulator))
        t_open = time.monotonic_ns()
        driver.open()
        offset_ns = -emulator.epoch_ns  # Pupil time minus host time, as the emulator keeps it
        gaze = collect(driver, lambda s: time.monotonic_ns() - t_open >= 1e9)
        t_end = time.monotonic_ns()
        driver.close()
    assert abs(driver.offset_ns - offset_ns) <= driver.rtt_ns + 1_000_000
    assert 100 <= len(gaze) <= 300
    assert driver.counters.samples == len(gaze) and driver.counters.malformed == 0
    left, right = still_eyes()
    for g in gaze:
        assert g.valid
        np.testing.assert_allclose(g.L, left, atol=1e-9)
        np.testing.assert_allclose(g.R, right, atol=1e-9)
        np.testing.assert_allclose(g.C, unit(left + right))
        for v in (g.L, g.R, g.C):
            assert abs(np.linalg.norm(v) - 1.0) < 1e-9
        assert g.depth_m == pytest.approx(STILL_DEPTH)
        assert abs(g.t_host - (g.t_dev - offset_ns)) <= driver.rtt_ns + 2e6  # the capture time, on the host clock
        assert t_open + offset_ns - 100e6 <= g.t_dev <= t_end + offset_ns  # Pupil time, in ns
    steps = [b.t_dev - a.t_dev for a, b in zip(gaze, gaze[1:], strict=False)]
    assert all(step > 0 and abs(step / 5e6 - round(step / 5e6)) < 1e-3 for step in steps)  # 200 Hz device clock
    assert [g.seq for g in gaze] == list(range(len(gaze)))


def test_blinks_have_zero_confidence_and_are_invalid(tmp_path):
    feed = GazeFeed(200.0, trace=still_trace(tmp_path / "blinks.jsonl", blink_share=0.5))
    with PupilEmulator(feed=feed) as emulator:
        sub = backbone(emulator, b"gaze.3d.01.")
        driver = PupilDriver(driver_url(emulator))
        driver.open()
        gaze = collect(driver, at_least(60))
        datums = [msgpack.unpackb(sub.recv_multipart()[1]) for _ in range(40)]
        sub.close()
        driver.close()
    invalid = [g for g in gaze if not g.valid]
    assert invalid and len(invalid) < len(gaze)
    assert driver.counters.invalid == len(invalid)
    assert all(g.depth_m is None for g in invalid)
    assert {d["confidence"] for d in datums} == {0.0, 0.95}
    assert all("gaze_point_3d" not in d for d in datums if d["confidence"] == 0.0)


def test_relayed_datums_and_malformed_messages(tmp_path, sockets):
    """Messages published to PUB_PORT reach the driver through the backbone, malformed ones are counted."""
    with PupilEmulator(feed=GazeFeed(20.0, trace=still_trace(tmp_path / "still.jsonl"))) as emulator:
        driver = PupilDriver(driver_url(emulator))
        driver.open()
        pub = sockets(zmq.PUB)
        pub.connect(f"tcp://127.0.0.1:{emulator.pub_port}")
        try:
            target = round(SECTION7_GAZE["timestamp"] * 1e9)
            section7 = [b"gaze.3d.01.", msgpack.packb(SECTION7_GAZE)]
            relayed = collect(driver, lambda s: pub.send_multipart(section7) or any(g.t_dev == target for g in s))
            match = next(g for g in relayed if g.t_dev == target)
            np.testing.assert_allclose(match.R, unit([0.06, 0.0, -0.998]), atol=1e-12)
            for bad in ([b"gaze.3d.01.", b"\xc1"], [b"gaze.3d.01."], [b"gaze.3d.0.", msgpack.packb(SECTION7_GAZE)]):
                before = driver.counters.malformed
                collect(driver, lambda s, bad=bad, n=before: pub.send_multipart(bad) or driver.counters.malformed > n)
                assert driver.counters.malformed > before
            assert collect(driver, lambda s: any(g.valid for g in s))  # the stream goes on
        finally:
            pub.close()
            driver.close()


def test_device_lost_when_pupil_remote_does_not_answer(sockets):
    mute = sockets(zmq.REP)  # bound, never answers
    port = mute.bind_to_random_port("tcp://127.0.0.1")
    try:
        driver = PupilDriver(f"pupil://127.0.0.1:{port}?timeout=0.3")
        started = time.monotonic()
        with pytest.raises(DeviceLost, match="did not answer 'SUB_PORT'"):
            driver.open()
        assert time.monotonic() - started < 3.0
    finally:
        mute.close()
    with pytest.raises(DeviceLost):  # a port nobody listens on
        PupilDriver(f"pupil://127.0.0.1:{free_port()}?timeout=0.3").open()


def test_device_lost_when_the_emulator_stops():
    emulator = PupilEmulator().start()
    driver = PupilDriver(driver_url(emulator, timeout=0.3))
    assert_lost_when_stopped(emulator, driver)
    driver.close()


def test_default_port_is_pupil_remotes():
    assert PupilDriver("pupil://127.0.0.1").address == ("127.0.0.1", 50020)
