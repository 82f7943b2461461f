"""fove://: the TCP framing and records, the emulator and the adapter over real loopback sockets."""

from __future__ import annotations

import socket
import struct
import time

import msgspec
import numpy as np
import pytest

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.drivers.base import DeviceLost
from hmdrt.drivers.emulators.feed import FeedSample, GazeFeed
from hmdrt.drivers.emulators.fove_server import FoveEmulator, eye_record
from hmdrt.drivers.fove import FoveDriver
from hmdrt.drivers.protocols import fove
from hmdrt.errors import ConfigError
from hmdrt.replay.synthetic import SyntheticConfig, SyntheticSource
from hmdrt.spatial import quat_from_yaw_pitch, quat_to_matrix

from .helpers import ScriptedFoveServer, assert_lost_when_stopped, at_least, collect, wait_for

AHEAD = (0.0, 0.0, 1.0)  # FOVE's forward, and its gaze on lost tracking


def eye(frame_id: int, result: int = 0, states=(1, 1), gaze=AHEAD, depth: float | None = 1.5) -> fove.Eye:
    return fove.Eye(
        id=frame_id,
        timestamp=frame_id * 8333,
        gaze_left=gaze,
        gaze_right=gaze,
        state_left=states[0],
        state_right=states[1],
        ray_origin=(0.0, 0.0, 0.0),
        ray_direction=gaze,
        depth=depth,
        result=result,
    )


def pose(pose_id: int) -> fove.Pose:
    return fove.Pose(id=pose_id, timestamp=pose_id * 14286, orientation=(0.0, 0.0, 0.0, 1.0), position=(0.0, 0.0, 0.0))


def url(emulator: FoveEmulator) -> str:
    host, port = emulator.address
    return f"fove://{host}:{port}"


def test_frames_round_trip_in_any_chunking():
    records = [
        fove.Hello(fove.API_VERSION, int(fove.Capability.EYE_TRACKING | fove.Capability.EYE_BLINK)),
        fove.Subscribe(int(fove.Capability.ORIENTATION)),
        eye(7, result=1007, states=(1, 2), gaze=(0.6, 0.0, 0.8), depth=None),
        msgspec.structs.replace(eye(8), id=2**64 - 1, timestamp=2**64 - 1),
        pose(42),
    ]
    stream = b"".join(fove.encode(r) for r in records)
    assert struct.unpack(">I", stream[:4])[0] == len(msgspec.msgpack.encode(records[0]))
    reader = fove.FrameReader()
    payloads = [p for i in range(len(stream)) for p in reader.feed(stream[i : i + 1])]
    assert [fove.decode(p) for p in payloads] == records
    assert fove.Capability.EYE_BLINK == 1 << 18 and fove.Capability.GAZE_DEPTH == 1 << 4


def test_reader_refuses_oversize_frames():
    reader = fove.FrameReader()
    assert reader.feed(struct.pack(">I", fove.MAX_FRAME_BYTES) + bytes(fove.MAX_FRAME_BYTES)) == [
        bytes(fove.MAX_FRAME_BYTES)
    ]
    with pytest.raises(fove.FrameTooLarge):
        fove.FrameReader().feed(struct.pack(">I", fove.MAX_FRAME_BYTES + 1))


@pytest.mark.parametrize(
    "payload",
    [
        b"",
        b"\xc1",  # never valid msgpack
        msgspec.msgpack.encode([1, 2, 3]),
        msgspec.msgpack.encode({"type": "gossip"}),
        msgspec.msgpack.encode({**msgspec.to_builtins(eye(1)), "gaze_left": [float("nan"), 0.0, 1.0]}),
        msgspec.msgpack.encode({**msgspec.to_builtins(eye(1)), "result": 5}),
        msgspec.msgpack.encode({**msgspec.to_builtins(eye(1)), "state_left": 3}),
        msgspec.msgpack.encode({**msgspec.to_builtins(eye(1)), "id": -1}),
        msgspec.msgpack.encode({**msgspec.to_builtins(eye(1)), "extra": 1}),
        msgspec.msgpack.encode({k: v for k, v in msgspec.to_builtins(eye(1)).items() if k != "timestamp"}),
    ],
)
def test_decode_refuses_garbage(payload):
    with pytest.raises(fove.FrameError):
        fove.decode(payload)


def test_quaternion_conversion_rotates_vectors_both_ways():
    """Rotating in FOVE's frame then converting equals converting then rotating in ours."""
    rng = np.random.default_rng(5)
    naive_agrees = 0
    for _ in range(200):
        q_fove = rng.normal(size=4)
        q_fove /= np.linalg.norm(q_fove)  # (w, x, y, z) in FOVE's frame
        v_fove = rng.normal(size=3)
        q_ours = fove.mirror_quaternion(q_fove)
        rotated_then_converted = fove.mirror_vector(quat_to_matrix(q_fove) @ v_fove)
        converted_then_rotated = quat_to_matrix(q_ours) @ fove.mirror_vector(v_fove)
        np.testing.assert_allclose(rotated_then_converted, converted_then_rotated, atol=1e-12)
        np.testing.assert_allclose(fove.mirror_quaternion(q_ours), q_fove, atol=0)  # its own inverse
        naive = quat_to_matrix((q_fove[0], q_fove[1], q_fove[2], -q_fove[3])) @ fove.mirror_vector(v_fove)
        naive_agrees += np.allclose(naive, rotated_then_converted, atol=1e-9)
    assert naive_agrees < 5  # flipping only z of the quaternion is not the conversion


def test_a_fove_right_turn_is_our_right_turn():
    """A turn taking FOVE's forward (+Z) towards +X takes our forward (-Z) towards +X too."""
    half = np.radians(30.0) / 2
    turn_fove = (np.cos(half), 0.0, np.sin(half), 0.0)  # about +Y: +Z turns towards +X
    assert (quat_to_matrix(turn_fove) @ np.array(AHEAD))[0] > 0.49
    turned = quat_to_matrix(fove.mirror_quaternion(turn_fove)) @ np.array([0.0, 0.0, -1.0])
    np.testing.assert_allclose(turned, fove.mirror_vector(quat_to_matrix(turn_fove) @ np.array(AHEAD)), atol=1e-12)
    assert turned[0] > 0.49
    # the section 7 identity pose: orientation (x, y, z, w) = (0, 0, 0, 1)
    assert fove.from_fove_quaternion((0.0, 0.0, 0.0, 1.0)) == (1.0, 0.0, 0.0, 0.0)


def test_emulator_reports_lost_tracking_as_fove_does():
    sample = FeedSample(3, 0, 0, np.array([0.1, 0.0, -0.99]), np.array([0.1, 0.0, -0.99]), False, 1.0)
    record = eye_record(sample, 25)
    assert (record.gaze_left, record.gaze_right, record.ray_direction) == (AHEAD, AHEAD, AHEAD)
    assert (record.state_left, record.state_right, record.result) == (2, 2, fove.Result.DATA_UNRELIABLE)
    assert record.depth is None and record.id == 3 and record.timestamp == 25


def test_streams_gaze_and_pose_from_the_emulator():
    """About a second of eye frames (120 Hz) and poses (70 Hz), matching the emulator's seeded feed."""
    seed = 7
    with FoveEmulator(feed=GazeFeed(120.0, seed=seed, latency_ms=20.0), seed=seed) as emulator:
        driver = FoveDriver(url(emulator))
        t_open = time.monotonic_ns()
        driver.open()
        samples = collect(driver, lambda s: time.monotonic_ns() - t_open >= 1e9)
        t_end = time.monotonic_ns()
        driver.close()
    gaze = [s for s in samples if isinstance(s, Gaze)]
    poses = [s for s in samples if isinstance(s, Pose)]
    assert 60 <= len(gaze) <= 180 and 35 <= len(poses) <= 110
    assert driver.counters.dropped == 0 and driver.counters.malformed == 0
    assert driver.counters.samples == len(samples)
    assert driver.hello.eye_rate_hz == 120.0 and driver.hello.display_rate_hz == 70.0

    reference = {}
    for sample in GazeFeed(120.0, seed=seed).samples():
        reference[sample.index] = sample
        if sample.index >= gaze[-1].seq:
            break
    for g in gaze:
        expected = reference[g.seq]
        assert g.valid == expected.valid
        if g.valid:
            for got, want in ((g.L, expected.left), (g.R, expected.right)):
                assert abs(np.linalg.norm(got) - 1.0) < 1e-9
                np.testing.assert_allclose(got, want, atol=1e-9)
            centre = (expected.left + expected.right) / np.linalg.norm(expected.left + expected.right)
            np.testing.assert_allclose(g.C, centre, atol=1e-9)
            assert g.depth_m == pytest.approx(expected.depth_m)
        else:
            assert g.C == g.L == g.R == (0.0, 0.0, -1.0)
    steps = [(b.t_dev - a.t_dev, b.seq - a.seq) for a, b in zip(gaze, gaze[1:], strict=False)]
    assert all(abs(dt - n * 1e9 / 120.0) <= 1000 for dt, n in steps)  # device clock: 1/120 s per frame id
    # device time mapped onto the host clock: the capture time, with the eye frames' 20 ms latency taken out
    assert all(t_open - 100e6 <= s.t_host <= t_end for s in samples)
    settled = [s for s in samples if s.t_dev - samples[0].t_dev > 200e6]  # the estimate's first windows are done
    assert all(abs(s.t_host - (emulator.epoch_ns + s.t_dev)) < 3e6 for s in settled)

    head = SyntheticSource(SyntheticConfig(seed=seed, head=True))
    expected_q = [quat_from_yaw_pitch(*head.head_pose(k / 70.0)) for k in range(poses[-1].seq + 1)]
    for p in poses:
        np.testing.assert_allclose(p.orientation, expected_q[p.seq], atol=1e-12)
        assert p.position == (0.0, 0.0, 0.0) and p.valid
    assert any(abs(p.orientation[2]) > 1e-3 for p in poses)  # the head did turn


def test_emulator_serves_several_clients_and_survives_bad_ones():
    with FoveEmulator(head=False) as emulator:
        host, port = emulator.address
        rude = socket.create_connection((host, port))
        rude.close()  # gone before reading its hello
        garbage = socket.create_connection((host, port), timeout=5.0)
        garbage.sendall(struct.pack(">I", 1) + b"\xc1")  # undecodable
        garbage.sendall(fove.encode(pose(1)))  # a record only the server sends
        first, second = (FoveDriver(f"fove://{host}:{port}") for _ in range(2))
        first.open()
        second.open()
        for driver in (first, second):
            samples = collect(driver, lambda s: sum(isinstance(x, Pose) for x in s) >= 5)
            assert sum(isinstance(x, Gaze) for x in samples) >= 5
            poses = [x for x in samples if isinstance(x, Pose)]
            assert len(poses) >= 5 and all(p.orientation == (1.0, 0.0, 0.0, 0.0) for p in poses)
        assert wait_for(lambda: emulator.malformed >= 2) and emulator.malformed == 2
        garbage.sendall(struct.pack(">I", fove.MAX_FRAME_BYTES + 1))  # oversize: the server hangs up
        garbage.settimeout(5.0)
        while garbage.recv(65536):
            pass
        assert emulator.malformed == 3
        garbage.close()
        assert len(first.read(1.0)) > 0  # still serving the others
        assert wait_for(lambda: emulator.clients == 2)
        first.close()
        second.close()


def test_result_codes_and_eye_states_set_validity():
    cases = [
        (eye(1), True),
        (eye(2, result=1007), True),  # Data_LowAccuracy: usable
        (eye(3, result=1003), False),  # Data_NoUpdate
        (eye(4, result=1006, states=(2, 2)), False),  # Data_Unreliable: lost tracking
        (eye(5, states=(2, 1)), False),  # one eye closed
        (eye(6, states=(0, 1)), False),  # one eye not detected
        (eye(7, gaze=(0.0, 0.0, 0.5)), False),  # not a unit vector
    ]
    with ScriptedFoveServer([fove.encode(record) for record, _ in cases]) as server:
        driver = FoveDriver(server.url)
        driver.open()
        gaze = collect(driver, at_least(len(cases)))
        driver.close()
    assert server.subscribe.capabilities & fove.Capability.EYE_TRACKING
    assert [g.valid for g in gaze] == [valid for _, valid in cases]
    assert driver.counters.invalid == sum(not valid for _, valid in cases)
    lost = gaze[3]
    assert lost.C == lost.L == lost.R == (0.0, 0.0, -1.0)  # FOVE's (0, 0, 1) in our frame
    assert gaze[0].t_dev == 8333 * 1000 and gaze[0].depth_m == 1.5


def test_frame_id_gaps_count_as_dropped():
    script = [fove.encode(r) for r in (eye(10), eye(11), pose(0), eye(14), pose(3), eye(15))]
    with ScriptedFoveServer(script) as server:
        driver = FoveDriver(server.url)
        driver.open()
        samples = collect(driver, at_least(6))
        driver.close()
    assert [s.seq for s in samples] == [10, 11, 0, 14, 3, 15]
    assert driver.counters.dropped == 2 + 2


def test_malformed_frames_are_counted_and_skipped():
    script = [
        fove.encode(eye(1)),
        struct.pack(">I", 3) + b"\xc1\xc1\xc1",
        fove.encode(eye(2)),
        fove.encode(fove.Hello(fove.API_VERSION, 8)),  # not expected mid-stream
        struct.pack(">I", 0),
        fove.encode(eye(3)),
    ]
    with ScriptedFoveServer(script) as server:
        driver = FoveDriver(server.url)
        driver.open()
        samples = collect(driver, at_least(3))
        assert driver.read(0.2) == []
        driver.close()
    assert [s.seq for s in samples] == [1, 2, 3]
    assert driver.counters.malformed == 3


def test_oversize_frame_closes_the_connection():
    script = [fove.encode(eye(1)), struct.pack(">I", 1 << 20) + bytes(100)]
    with ScriptedFoveServer(script) as server:
        driver = FoveDriver(server.url)
        driver.open()
        samples = []
        with pytest.raises(DeviceLost, match="exceeds"):
            for _ in range(100):
                samples += driver.read(0.05)
    assert [s.seq for s in samples] == [1]
    assert driver.counters.malformed == 1 and driver.state == "lost"


def test_device_lost_when_the_emulator_stops():
    emulator = FoveEmulator(head=False).start()
    driver = FoveDriver(url(emulator))
    assert_lost_when_stopped(emulator, driver)
    driver.close()
    with pytest.raises(DeviceLost, match="cannot connect"):
        driver.open()  # nothing listens there any more


def test_url_needs_a_port_and_known_options():
    with pytest.raises(ConfigError, match="HOST:PORT"):
        FoveDriver("fove://127.0.0.1")
    with pytest.raises(ConfigError, match="no option"):
        FoveDriver("fove://127.0.0.1:1?rate=5")
