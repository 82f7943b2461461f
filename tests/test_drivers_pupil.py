"""pupil://: Pupil Remote and the IPC backbone of the emulator, and the adapter, over real ZeroMQ sockets."""

from __future__ import annotations

import logging
import time

import msgpack
import numpy as np
import pytest
import zmq

from hmdrt.drivers.base import DeviceLost
from hmdrt.drivers.emulators.feed import GazeFeed
from hmdrt.drivers.emulators.pupil_server import EYE_CAMERA_TO_WORLD, PupilEmulator, pupil_datum
from hmdrt.drivers.pupil import TIME_PROBES, MalformedDatum, PupilDriver, decode_gaze
from hmdrt.spatial import gaze_direction
from hmdrt.testing import free_port

from .helpers import SECTION7_GAZE, assert_lost_when_stopped, at_least, collect, gaze_trace

STILL_YAW, STILL_PITCH, STILL_DEPTH = 8.0, -4.0, 0.8
# The keys of a Capture 3.5 3D pupil datum: PupilDetectorPlugin.create_pupil_datum's (pupil-labs/pupil,
# pupil_src/shared_modules/pupil_detector_plugins/detector_base_plugin.py @ v3.5, 4760336) updated with pye3d
# 0.3.0's Detector3D._prepare_result (pupil-labs/pye3d-detector, pye3d/detector_3d.py @ v0.3.0, 552441d).
PYE3D_PUPIL_KEYS = {
    *("id", "topic", "method", "norm_pos", "diameter", "confidence", "timestamp"),
    *("sphere", "projected_sphere", "circle_3d", "diameter_3d", "ellipse", "location", "model_confidence"),
    *("theta", "phi"),
}


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


def capture_26_gaze(datum: dict) -> dict:
    """A binocular gaze datum as Capture 2.6 builds it: Model3D_Binocular._predict_single keys eye_centers_3d and
    gaze_normals_3d by the integers 0 and 1, Gazer3D.predict adds topic, the pupils' mean confidence and timestamp
    and base_data (pupil-labs/pupil, pupil_src/shared_modules/gaze_mapping/gazer_3d/gazer_headset.py @ v2.6,
    a319584; v1.x's calibration_routines/gaze_mappers.py keys them the same way)."""
    base = datum.get("base_data") or []
    return {
        "eye_centers_3d": {0: datum["eye_centers_3d"]["0"], 1: datum["eye_centers_3d"]["1"]},
        "gaze_normals_3d": {0: datum["gaze_normals_3d"]["0"], 1: datum["gaze_normals_3d"]["1"]},
        "gaze_point_3d": datum["gaze_point_3d"],
        "norm_pos": datum["norm_pos"],
        "topic": "gaze.3d.01.",
        "confidence": float(np.mean([p["confidence"] for p in base])) if base else datum["confidence"],
        "timestamp": float(np.mean([p["timestamp"] for p in base])) if base else datum["timestamp"],
        "base_data": base,
    }


def capture_packb(payload: dict) -> bytes:
    """Msgpack bytes as Capture's Msg_Streamer.send packs a payload (zmq_tools.py @ v2.6: use_bin_type=True)."""
    return msgpack.packb(payload, use_bin_type=True)


def psychopy_binocular_sample(gaze: dict) -> dict | None:
    """The pupil values PsychoPy ioHub's Pupil Core plugin records for a binocular eye sample, or None where it
    records none: a paraphrase of eye_sample_from_gaze_3d and _binocular_eye_sample_from_gaze_3d
    (psychopy/psychopy-eyetracker-pupil-labs, psychopy_eyetracker_pupil_labs/pupil_labs/pupil_core/data_parse.py
    @ f848813; GPL-3.0, so paraphrased rather than vendored into this MIT project). EYE_ID_RIGHT is 0."""
    right = left = None
    for p in gaze["base_data"]:
        if p["id"] == 0:
            right = p
        if p["id"] == 1:
            left = p
    if not (right and left):
        return None
    values = {}
    for eye, p in (("right", right), ("left", left)):
        eye_cam_x, eye_cam_y, eye_cam_z = p["sphere"]["center"]
        raw_x, raw_y = p["norm_pos"]
        values[eye] = (eye_cam_x, eye_cam_y, eye_cam_z, p["phi"], p["theta"], raw_x, raw_y, p["diameter"])
        values[eye] += (p.get("diameter_3d", None),)
    return values


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


def test_capture_26_integer_keyed_gaze_decodes_as_capture_3_string_keyed():
    """Capture 1.x-2.6 key gaze_normals_3d by the msgpack integers 0 and 1 (capture_26_gaze); the driver took
    every such binocular datum for malformed."""
    payload = capture_packb(capture_26_gaze(SECTION7_GAZE))
    assert set(msgpack.unpackb(payload, strict_map_key=False)["gaze_normals_3d"]) == {0, 1}  # integer keys on the wire
    old = decode_gaze(b"gaze.3d.01.", payload)
    assert old == decode_gaze(b"gaze.3d.01.", msgpack.packb(SECTION7_GAZE))
    np.testing.assert_allclose(old.R, unit([0.06, 0.0, -0.998]), atol=1e-12)  # eye 0 is still the right eye


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
        (
            b"gaze.3d.01.",
            msgpack.packb({**SECTION7_GAZE, "gaze_normals_3d": {0: [0, 0, 1], "0": [0, 0, 1], 1: [0, 0, 1]}}),
        ),
        (b"gaze.3d.01.", msgpack.packb({**SECTION7_GAZE, "gaze_normals_3d": {0: [0, 0, 1], 2: [0, 0, 1]}})),
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
    assert all(g.depth_m == pytest.approx(0.5) for g in invalid)  # Pupil's initial gaze distance, 500 mm
    assert {d["confidence"] for d in datums} == {0.0, 0.95}
    assert all("gaze_point_3d" in d for d in datums)  # Pupil sends it with every 3D gaze datum, blinks too


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


def test_capture_26_gaze_over_the_backbone(tmp_path, sockets):
    """Binocular gaze built as Capture 2.6 builds it (capture_26_gaze) and sent as its Msg_Streamer.send sends it
    (topic frame, then msgpack with integer keys) reaches the driver through the backbone as gaze, not as a
    malformed datum."""
    with PupilEmulator(feed=GazeFeed(20.0, trace=still_trace(tmp_path / "still.jsonl"))) as emulator:
        sub = backbone(emulator, b"gaze.3d.01.")
        template = msgpack.unpackb(sub.recv_multipart()[1])  # a datum of the emulator's, for realistic base_data
        sub.close()
        driver = PupilDriver(driver_url(emulator))
        driver.open()
        pub = sockets(zmq.PUB)
        pub.connect(f"tcp://127.0.0.1:{emulator.pub_port}")
        try:
            datum = capture_26_gaze(template)
            datum["base_data"] = [{**p, "timestamp": 4321.0 + 0.004 * p["id"]} for p in datum["base_data"]]
            datum["timestamp"] = float(np.mean([p["timestamp"] for p in datum["base_data"]]))  # Gazer3D.predict
            target = round(datum["timestamp"] * 1e9)

            def send(samples: list) -> bool:
                pub.send_string(datum["topic"], flags=zmq.SNDMORE)
                pub.send(capture_packb(datum))
                return any(g.t_dev == target for g in samples)

            match = next(g for g in collect(driver, send) if g.t_dev == target)
        finally:
            pub.close()
            driver.close()
    left, right = still_eyes()
    np.testing.assert_allclose(match.R, right, atol=1e-9)
    np.testing.assert_allclose(match.L, left, atol=1e-9)
    assert match.valid and match.depth_m == pytest.approx(STILL_DEPTH)
    assert driver.counters.malformed == 0


@pytest.mark.parametrize(
    "rebase",
    [
        pytest.param(lambda now: "T 0.0", id="T-0.0"),  # pupil-helpers python/pupil_remote_control.py
        pytest.param(lambda now: f"T {now + 1.0}", id="T-forward-1s"),  # PsychoPy's PupilRemote.set_pupil_time
    ],
)
def test_a_rebase_by_another_client_is_measured_again(tmp_path, remote, caplog, rebase):
    """Another client rebases Pupil time as pupil-helpers' python/pupil_remote_control.py does (send_string("T 0.0"),
    pupil-labs/pupil-helpers @ 21dee56) or as PsychoPy's Pupil Core plugin does (f"T {pupil_time}",
    psychopy/psychopy-eyetracker-pupil-labs, .../pupil_core/pupil_remote.py @ f848813). The emulated capture is
    60 ms before receipt: t_host must stay the capture time, not slip to the receipt time, and the rebase is counted
    and logged. A forward jump of 1 s is within what the clock sync takes for a host stall, so only the driver's
    check of the offset sees it."""
    latency_ns = 60_000_000
    feed = GazeFeed(200.0, trace=still_trace(tmp_path / "still.jsonl"), latency_ms=latency_ns / 1e6)
    with PupilEmulator(feed=feed) as emulator:
        assert remote(emulator, "T 1000.0") == "Timesync successful."
        driver = PupilDriver(driver_url(emulator))
        driver.open()
        before = collect(driver, at_least(60))
        epoch_before = emulator.epoch_ns
        command = rebase(emulator.pupil_time())
        with caplog.at_level(logging.WARNING, logger="hmdrt.drivers.pupil"):
            assert remote(emulator, command) == "Timesync successful."
            target_ns = round(float(command[2:]) * 1e9)
            epoch_after = emulator.epoch_ns

            def new_timebase(g) -> bool:
                return target_ns <= g.t_dev < target_ns + 10**10

            after = collect(driver, lambda s: sum(map(new_timebase, s)) >= 150)
        driver.close()
    rebased = [g for g in after if new_timebase(g)]
    assert len(rebased) >= 150
    for samples, epoch in ((before, epoch_before), (rebased, epoch_after)):
        errors = [g.t_host - (g.t_dev + epoch) for g in samples]  # the emulator's capture time on the host clock
        assert max(abs(e) for e in errors) <= 20_000_000, errors  # the receipt time would be 60 ms late
    assert driver.rebases == 1
    assert abs(driver.offset_ns + epoch_after) <= driver.rtt_ns + 1_000_000
    assert any("Pupil time jumped" in r.getMessage() for r in caplog.records if r.levelno == logging.WARNING)


def test_a_stalled_reader_is_not_a_rebase(tmp_path, caplog):
    """A reader that stalls for 1 s finds datums up to 1 s late, past MAX_LAG_NS: one `t` measurement finds the
    offset unchanged, so no rebase is counted or logged, and the queued datums behind it are not measured again
    one by one."""

    class CountingDriver(PupilDriver):
        probes = 0

        def _probe(self) -> tuple[int, int, int]:
            self.probes += 1
            return super()._probe()

    with PupilEmulator(feed=GazeFeed(200.0, trace=still_trace(tmp_path / "still.jsonl"))) as emulator:
        driver = CountingDriver(driver_url(emulator))
        driver.open()
        collect(driver, at_least(400))
        probes = driver.probes
        time.sleep(1.0)
        with caplog.at_level(logging.WARNING, logger="hmdrt.drivers.pupil"):
            late = collect(driver, at_least(400))
        driver.close()
        epoch = emulator.epoch_ns
    assert driver.rebases == 0 and not caplog.records
    assert TIME_PROBES <= driver.probes - probes <= 2 * TIME_PROBES  # measured again, not once per queued datum
    assert abs(driver.offset_ns + epoch) <= driver.rtt_ns + 1_000_000 and len(late) >= 400


def test_emulated_datums_carry_what_pupil_sends(tmp_path):
    """Gaze datums carry gaze_point_3d, blinks too (gazer_headset.py always sets it), and in base_data the two 3D
    pupil datums they were mapped from, each also published on its pupil.<id>.3d topic. Checked against
    Capture 3.5's Gazer3D.predict and Model3D_Binocular._predict_single (pupil-labs/pupil,
    pupil_src/shared_modules/gaze_mapping/gazer_3d/gazer_headset.py @ v3.5, 4760336), the pye3d plugin's datum
    (PYE3D_PUPIL_KEYS), pye3d 0.3.0's cart2sph (pye3d/geometry/utilities.py) and the values PsychoPy's ioHub
    plugin reads (psychopy_binocular_sample): with empty base_data it recorded no eye samples at all."""
    feed = GazeFeed(200.0, trace=still_trace(tmp_path / "blinks.jsonl", blink_share=0.5))
    with PupilEmulator(feed=feed) as emulator:
        sub = backbone(emulator, b"gaze.3d.01.")
        sub.setsockopt(zmq.SUBSCRIBE, b"pupil.")
        messages = [sub.recv_multipart() for _ in range(120)]
        sub.close()
    gaze = [msgpack.unpackb(payload) for topic, payload in messages if topic == b"gaze.3d.01."]
    pupils = {}  # (topic, timestamp) -> pupil datum
    for topic, payload in messages:
        if topic != b"gaze.3d.01.":
            pupils[topic, msgpack.unpackb(payload)["timestamp"]] = msgpack.unpackb(payload)
    assert {d["confidence"] for d in gaze} == {0.0, 0.95}
    assert {topic for topic, _ in pupils} == {b"pupil.0.3d", b"pupil.1.3d"}
    for d in gaze:
        assert len(d["gaze_point_3d"]) == 3
        base = d["base_data"]
        assert [p["id"] for p in base] == [0, 1]  # Gazer3D: pupil_match[0] is the right eye, eye 0
        assert d["confidence"] == pytest.approx(np.mean([p["confidence"] for p in base]))
        assert d["timestamp"] == pytest.approx(np.mean([p["timestamp"] for p in base]))
        features = np.array([[p["id"], *p["sphere"]["center"], *p["circle_3d"]["normal"]] for p in base])
        assert features.shape == (2, 7) and np.isfinite(features).all()  # Gazer3D._extract_pupil_features
        for p in base:
            assert set(p) == PYE3D_PUPIL_KEYS and p["topic"] == f"pupil.{p['id']}.3d" and "3d" in p["method"]
            normal = np.array(p["circle_3d"]["normal"])
            world = EYE_CAMERA_TO_WORLD @ normal  # s<id>_normal = rotation_matrix[id] @ pupil normal
            np.testing.assert_allclose(d["gaze_normals_3d"][str(p["id"])], world, atol=1e-12)
            assert p["phi"] == pytest.approx(np.arctan2(normal[2], normal[0]))  # pye3d's cart2sph
            assert p["theta"] == pytest.approx(np.arccos(normal[1] / np.linalg.norm(normal)))
            assert p["model_confidence"] == 1.0 and p["location"] == p["ellipse"]["center"]
            assert 0.0 < p["norm_pos"][0] < 1.0 and 0.0 < p["norm_pos"][1] < 1.0
            published = pupils.get((f"pupil.{p['id']}.3d".encode(), p["timestamp"]))
            assert published is None or published == p
        values = psychopy_binocular_sample(d)
        assert values is not None and all(np.isfinite(v) for eye in values.values() for v in eye)
    assert any(
        (f"pupil.{p['id']}.3d".encode(), p["timestamp"]) in pupils for d in gaze for p in d["base_data"]
    )  # the same datums went out on the pupil topics


def test_pupil_datum_follows_the_eye():
    """Looking right, up or straight moves the pupil ellipse in the eye image as the eye camera, facing the eye,
    sees it, and tilts the pupil away from the camera (a narrower minor axis)."""
    straight = pupil_datum(0, np.array([0.0, 0.0, 1.0]), 0.95, 1.0)
    right = pupil_datum(0, unit([0.3, 0.0, 1.0]), 0.95, 1.0)
    up = pupil_datum(0, unit([0.0, -0.3, 1.0]), 0.95, 1.0)  # OpenCV: y down
    assert straight["norm_pos"] == pytest.approx([0.5, 0.5])
    assert straight["ellipse"]["axes"][0] == pytest.approx(straight["ellipse"]["axes"][1])
    assert right["norm_pos"][0] < 0.5  # the camera faces the eye: its image is mirrored left to right
    assert up["norm_pos"][1] > 0.5  # norm_pos origin is bottom-left
    assert right["ellipse"]["axes"][0] < right["ellipse"]["axes"][1]
    assert right["diameter"] == pytest.approx(right["ellipse"]["axes"][1])
