"""The bus against other local users and floods (issue 42), over real sockets: the default ingest and telemetry are
ipc:// sockets of this user's alone, which its own clients find; silent devices give up their slots; an abstract
socket is refused in one line; and the control and ingest sockets read within a budget per peer."""

from __future__ import annotations

import json
import os
import stat
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

import msgspec
import pytest
import zmq

from hmdrt.bus import limits
from hmdrt.bus.local import find_endpoint
from hmdrt.bus.messages import Gaze, encode
from hmdrt.cli import main
from hmdrt.compositor.endpoints import RATE_LIMITED
from hmdrt.compositor.samples import MAX_DEVICES
from hmdrt.testing import ANY_PORT, Background, compositor, write_config

from .compositor_helpers import assert_one_line_error, receive, subscribe
from .helpers import wait_for

NOBODY = 65534
AHEAD = (0.0, 0.0, -1.0)
STATUS, STATS = (msgspec.msgpack.encode({"cmd": cmd}) for cmd in ("status", "stats"))


def gaze(seq: int, t_host: int) -> Gaze:
    return Gaze(seq=seq, t_host=t_host, C=AHEAD)


def fork(child: Callable[[dict], dict]) -> tuple[int, int, int]:
    """Fork a child that reads one JSON line of orders, runs child(orders) and writes back its JSON result; forked
    before the test starts any socket, so no thread's state goes with it. (pid, orders fd, result fd)."""
    orders_r, orders_w = os.pipe()
    result_r, result_w = os.pipe()
    pid = os.fork()
    if pid == 0:  # pragma: no cover - the child, which never returns into pytest
        code = 1
        try:
            os.close(orders_w)
            os.close(result_r)
            with os.fdopen(orders_r) as orders:
                result = child(json.loads(orders.readline()))
            os.write(result_w, json.dumps(result).encode())
            code = 0
        finally:
            os._exit(code)
    os.close(orders_r)
    os.close(result_w)
    return pid, orders_w, result_r


def order(orders_fd: int, orders: dict) -> None:
    os.write(orders_fd, (json.dumps(orders) + "\n").encode())
    os.close(orders_fd)


def result_of(pid: int, result_fd: int, timeout_s: float = 30.0) -> dict:
    """The child's result, once it has exited 0."""
    deadline = time.monotonic() + timeout_s
    while (done := os.waitpid(pid, os.WNOHANG))[0] == 0:
        if time.monotonic() > deadline:
            os.kill(pid, 9)
            os.waitpid(pid, 0)
            pytest.fail(f"the forked child ran past {timeout_s} s")
        time.sleep(0.02)
    with os.fdopen(result_fd) as results:
        text = results.read()
    assert os.waitstatus_to_exitcode(done[1]) == 0 and text, "the forked child failed"
    return json.loads(text)


def intruder(orders: dict) -> dict:
    """As another user (nobody): publish gaze to the ingest and to a loopback witness, subscribe to the telemetry and
    ask the control socket for the status, for `seconds`; what got through."""
    os.setgroups([])
    os.setgid(NOBODY)
    os.setuid(NOBODY)
    context = zmq.Context()
    socks = {name: context.socket(kind) for name, kind in (("ingest", zmq.PUB), ("witness", zmq.PUB))}
    socks["telemetry"] = context.socket(zmq.SUB)
    socks["telemetry"].setsockopt(zmq.SUBSCRIBE, b"")
    socks["control"] = context.socket(zmq.REQ)
    errors = []
    for name, sock in socks.items():
        sock.setsockopt(zmq.LINGER, 0)
        try:
            sock.connect(orders[name])
        except zmq.ZMQError as exc:
            errors.append(f"{name}: {exc}")
    received, answered, asked, seq = 0, 0, False, 0
    deadline = time.monotonic() + orders["seconds"]
    while time.monotonic() < deadline:
        for name in ("ingest", "witness"):
            socks[name].send_multipart(encode(gaze(seq, time.monotonic_ns()), "intruder"))
        seq += 1
        while socks["telemetry"].poll(0):
            socks["telemetry"].recv_multipart()
            received += 1
        if not asked:
            try:
                socks["control"].send(STATUS, zmq.NOBLOCK)  # a REQ sends once it has a peer
                asked = True
            except zmq.Again:
                pass
        if socks["control"].poll(10):
            socks["control"].recv()
            answered += 1
    context.destroy(linger=0)
    return {"uid": os.getuid(), "received": received, "answered": answered, "sent": seq, "errors": errors}


@pytest.mark.skipif(not hasattr(os, "fork") or os.geteuid() != 0, reason="another uid needs root to become one")
def test_the_default_ingest_and_telemetry_are_this_users_alone(tmp_path, runtime_dir, context):
    """Another uid (a forked child as nobody) publishes gaze to the default ingest, subscribes to the telemetry and
    asks the control socket, while the same messages reach a loopback witness of the test's: none of its gaze
    reaches the compositor and nothing reaches it, while this user's own publisher and subscriber are served."""
    runtime_dir.chmod(0o711)  # others may pass through XDG_RUNTIME_DIR: only the hmdrt folder's mode keeps them out
    pid, orders_fd, result_fd = fork(intruder)
    witness = context.socket(zmq.SUB)
    witness.setsockopt(zmq.LINGER, 0)
    witness.setsockopt(zmq.SUBSCRIBE, b"")
    witness_port = witness.bind_to_random_port("tcp://127.0.0.1")
    config = write_config(tmp_path / "run.toml", drivers=[])
    with compositor(config, context, duration_s=60) as comp:
        run = Background(comp)
        bound = comp.status()["endpoints"]
        folder = runtime_dir / "hmdrt"
        assert stat.S_IMODE(os.lstat(folder).st_mode) == 0o700
        for endpoint in bound.values():
            path = Path(endpoint.removeprefix("ipc://"))
            assert endpoint.startswith("ipc://") and path.parent == folder
            assert stat.S_IMODE(os.lstat(path).st_mode) == 0o600
        order(orders_fd, {**bound, "witness": f"tcp://127.0.0.1:{witness_port}", "seconds": 3.0})
        assert wait_for(lambda: witness.poll(0)) and witness.recv_multipart()[0] == b"gaze.intruder"  # it publishes

        own = context.socket(zmq.PUB)
        own.setsockopt(zmq.LINGER, 0)
        own.connect(bound["ingest"])
        seq = 0

        def friend_arrived() -> bool:
            nonlocal seq
            own.send_multipart(encode(gaze(seq, comp.clock.now_ns()), "friend"))
            seq += 1
            return "friend" in comp.store.devices["gaze"]

        assert wait_for(friend_arrived)
        sub = subscribe(context, comp)
        assert receive(sub, b"frame", 3)
        intruders = result_of(pid, result_fd)
        comp.stop.set()
        run.join(30)
    assert intruders["uid"] == NOBODY and intruders["sent"] > 10
    assert intruders["received"] == 0 and intruders["answered"] == 0
    assert "intruder" not in comp.store.counts() and "intruder" not in comp.ingest.status
    assert not list(folder.iterdir())  # the sockets went with the compositor


def test_this_users_driver_finds_the_default_ingest(tmp_path, context):
    """`hmdrt driver URL` without --bus publishes to the one compositor of this user running."""
    config = write_config(tmp_path / "run.toml", drivers=[])
    with compositor(config, context, duration_s=60) as comp:
        run = Background(comp)
        assert find_endpoint("ingest") == comp.ingest.address
        assert find_endpoint("telemetry") == comp.telemetry.address
        driver = subprocess.run(
            [sys.executable, "-m", "hmdrt", "driver", "synthetic://?seed=1&rate=250&name=own", "--duration", "1.5"],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert driver.returncode == 0, driver.stderr
        assert wait_for(lambda: comp.store.counts().get("own") is not None and comp.store.counts()["own"].stored > 100)
        comp.stop.set()
        run.join(30)


def test_silent_devices_give_up_their_slots_and_a_full_live_table_refuses(tmp_path, context):
    """MAX_DEVICES - 1 made-up device names (and the config's replay) fill the table: a new device is refused and
    counted while they publish; once they have been silent for [fallback] centre_after_ms, it gets a slot."""
    # in real time: in virtual time a loaded machine's ingest can take so long that the made-up samples arrive over
    # the store's 1 s of history behind the clock, are dropped as too old, and leave slots that never held a sample
    # (free at once, by design)
    config = write_config(tmp_path / "run.toml", fallback={"stale_ms": 100, "centre_after_ms": 2000})
    with compositor(config, context, frames=100_000) as comp:
        run = Background(comp)
        pub = context.socket(zmq.PUB)
        pub.setsockopt(zmq.LINGER, 0)
        pub.connect(comp.ingest.address)
        names = [f"bogus{i}" for i in range(MAX_DEVICES - 1)]

        def publish(devices: list[str]) -> None:
            for device in devices:
                pub.send_multipart(encode(gaze(int(comp.clock.now_ns()), comp.clock.now_ns()), device))

        assert wait_for(lambda: (publish(names[:1]), "bogus0" in comp.store.counts())[1])  # subscribed
        publish([*names, "real"])  # all within a few frames, well within the 2 s a slot waits
        assert wait_for(lambda: comp.store.devices_refused > 0)
        assert len(comp.store.counts()) == MAX_DEVICES
        assert "real" not in comp.store.counts() and comp.store.devices_expired == 0
        silent_since = comp.clock.now_ns()
        assert wait_for(lambda: comp.clock.now_ns() > silent_since + 2_100_000_000, timeout_s=60)
        assert wait_for(lambda: (publish(["real"]), "real" in comp.store.counts())[1])
        counts = comp.store.counts()
        assert "replay" in counts and not any(name in counts for name in names)  # live replay kept its slot
        assert comp.store.devices_expired == len(names)
        comp.stop.set()
        report, _ = run.join(30)
    assert report["devices_expired"] == len(names) and report["devices_refused"] >= 1


@pytest.mark.parametrize(
    "args",
    [
        ["run", "{config}", "--frames", "1", "--virtual-time"],
        ["status", "--control", "ipc://@hmdrt"],
        ["driver", "synthetic://", "--bus", "ipc://@hmdrt", "--duration", "1"],
        ["record", "--out", "x.jsonl", "--bus", "ipc://@hmdrt", "--duration", "1"],
    ],
    ids=["run", "status", "driver", "record"],
)
def test_an_abstract_socket_is_refused_in_one_line(tmp_path, capsys, own_signals, args):
    config = write_config(tmp_path / "abstract.toml", bus={"control": "ipc://@hmdrt"})
    assert main([arg.format(config=config) for arg in args]) == 1
    assert_one_line_error(capsys.readouterr().err, "an abstract Unix socket has no file permissions")


def control_flood(orders: dict) -> dict:
    """Another process: send stats requests on a DEALER as fast as they go (2,000 unanswered at most) for `seconds`;
    the replies."""
    context = zmq.Context()
    flood = context.socket(zmq.DEALER)
    flood.setsockopt(zmq.LINGER, 0)
    flood.connect(orders["control"])
    replies, sent = [], 0
    started = time.monotonic()
    while time.monotonic() - started < orders["seconds"]:
        while sent - len(replies) < 2000 and flood.poll(0, zmq.POLLOUT):
            flood.send_multipart([b"", STATS], zmq.NOBLOCK)
            sent += 1
        while flood.poll(1):
            replies.append(flood.recv_multipart()[-1])
    context.destroy(linger=0)
    return {
        "seconds": time.monotonic() - started,
        "limited": sum(reply == RATE_LIMITED for reply in replies),
        "served": sum(reply != RATE_LIMITED for reply in replies),
    }


def test_a_control_flood_is_refused_beyond_its_budget_and_frames_go_on(tmp_path, context):
    """Another process floods a loopback tcp:// control socket (every local user's, as far as TCP says) with stats
    requests: beyond the peer's budget they are answered "rate limited" and counted, reading waits on the socket's
    budget, and the compositor keeps rendering at its rate."""
    pid, orders_fd, result_fd = fork(control_flood)
    config = write_config(tmp_path / "flood.toml", bus={"control": ANY_PORT})
    with compositor(config, context, duration_s=60) as comp:
        run = Background(comp)
        assert wait_for(lambda: len(comp.records) >= 3, timeout_s=30)
        rendered = lambda: sum(record.shown != "repeat" for record in comp.records)  # noqa: E731
        before, started = rendered(), time.monotonic()
        order(orders_fd, {"control": comp.control.address, "seconds": 2.0})
        flood = result_of(pid, result_fd)
        during, elapsed = rendered() - before, time.monotonic() - started
        limited = comp.control.limiter.counts()
        report = comp.summary()
        comp.stop.set()
        run.join(30)
    budget = limits.CONTROL
    assert 0 < flood["limited"] <= limited["refused"]  # the replies still on their way when it stopped, too
    assert flood["served"] <= budget.burst + budget.per_peer_hz * flood["seconds"] + 1
    assert flood["served"] + flood["limited"] <= budget.socket_hz * (flood["seconds"] + 1) and limited["paused_s"] > 0
    assert report["rate_limited"]["control"]["refused"] > 0  # in the stats
    assert during >= 0.3 * 30 * elapsed  # new frames all along (30 Hz on a quiet machine)


def ingest_flood(orders: dict) -> dict:
    """Another process of this user: publish `count` gaze messages to the ingest as fast as they go."""
    context = zmq.Context()
    pub = context.socket(zmq.PUB)
    pub.setsockopt(zmq.SNDHWM, 0)
    pub.connect(orders["ingest"])
    time.sleep(0.3)  # the ingest's subscription arrives
    now = time.monotonic_ns()
    for seq in range(orders["count"]):
        pub.send_multipart(encode(gaze(seq, now), "flood"))
    pub.close(linger=5000)
    context.term()
    return {"sent": orders["count"]}


def test_an_ingest_flood_is_refused_beyond_its_peers_budget_while_another_driver_gets_through(
    tmp_path, context, monkeypatch
):
    """One process floods the ingest; another publishes at a tracker's rate: the flood beyond its budget is refused
    and counted, and every sample of the other arrives. The budget is lowered to 400 a second (the steady one's
    250 fits), so that the ingest thread outruns it however loaded the machine is."""
    monkeypatch.setattr(limits, "INGEST", limits.Budget(per_peer_hz=400, burst=400, socket_hz=20_000))
    pid, orders_fd, result_fd = fork(ingest_flood)
    config = write_config(tmp_path / "flood.toml", drivers=[])
    with compositor(config, context, duration_s=60) as comp:
        run = Background(comp)
        steady = context.socket(zmq.PUB)
        steady.setsockopt(zmq.LINGER, 0)
        steady.connect(comp.ingest.address)
        sent = 0

        def publish() -> None:
            nonlocal sent
            steady.send_multipart(encode(gaze(sent, time.monotonic_ns()), "steady"))
            sent += 1

        assert wait_for(lambda: (publish(), "steady" in comp.store.counts())[1])
        time.sleep(0.1)
        before = comp.store.counts()["steady"].samples  # those sent before the subscription arrived are lost
        order(orders_fd, {"ingest": comp.ingest.address, "count": 30_000})
        for _ in range(300):  # 1.2 s at 250 Hz, during the flood
            publish()
            time.sleep(0.004)
        assert result_of(pid, result_fd)["sent"] == 30_000
        assert wait_for(lambda: comp.store.counts()["steady"].samples >= before + 300, timeout_s=30)
        refused = comp.ingest.limiter.refused
        flood = comp.store.counts()["flood"].samples
        comp.stop.set()
        run.join(30)
    assert refused > 0 and flood <= 30_000 - refused
    assert comp.store.counts()["steady"].samples == before + 300
