"""Access to the bus (docs/runtime.md, Access), over real sockets on loopback: CURVE keys written by `hmdrt keys`, a
compositor with [security] that answers and hears only clients whose keys it lists and counts the others, and
the refusal to bind beyond loopback without it. Waits poll; none sleeps a fixed time."""

from __future__ import annotations

import re
import stat
import threading
import time
from pathlib import Path

import msgspec
import pytest
import zmq
import zmq.auth

from hmdrt.bus.messages import Gaze, encode
from hmdrt.bus.security import ClientKeys, Guard, ServerKeys, is_loopback, write_keypair
from hmdrt.cli import main
from hmdrt.compositor.config import load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.compositor.endpoints import request
from hmdrt.drivers.host import DriverHost
from hmdrt.errors import ConfigError
from hmdrt.testing import ANY_PORT, Background, compositor, write_config

from . import compositor_helpers as runtime
from .helpers import wait_for

NO_ANSWER_S = 0.5  # how long a refused client waits for the answer that never comes


@pytest.fixture(scope="module")
def keys(tmp_path_factory) -> dict[str, tuple[Path, Path]]:
    """{name: (public, secret)}: the compositor's keypair, an allowed client's (alice) and a stranger's (mallory)."""
    folder = tmp_path_factory.mktemp("keys")
    return {name: write_keypair(folder, name) for name in ("server", "alice", "mallory")}


def client(keys: dict, name: str, server: str = "server") -> ClientKeys:
    return ClientKeys.load(keys[server][0], keys[name][1])


def secured_config(tmp_path: Path, keys: dict, **sections) -> Path:
    """A run config (hmdrt.testing.write_config) whose bus, control on tcp:// too, is guarded by CURVE, with
    alice allowed."""
    security = {"server_key": str(keys["server"][1]), "allowed_clients": [str(keys["alice"][0])]}
    sections["bus"] = {"control": ANY_PORT, **sections.get("bus", {})}
    return write_config(tmp_path / "secured.toml", security=security, **sections)


def refused(comp: Compositor) -> int:
    return comp.security()["refused"]


# --- keys ---------------------------------------------------------------------------------------------------------


def test_keys_writes_a_loadable_keypair_with_a_private_secret_and_refuses_to_overwrite(tmp_path, capsys):
    folder = tmp_path / "keys"
    assert main(["keys", "station", "--dir", str(folder)]) == 0
    public, secret = folder / "station.key", folder / "station.key_secret"
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert stat.S_IMODE(public.stat().st_mode) & 0o077 == 0o044  # readable by others, writable by none
    public_key, no_secret = zmq.auth.load_certificate(public)
    same_public, secret_key = zmq.auth.load_certificate(secret)
    assert no_secret is None and same_public == public_key and len(public_key) == len(secret_key) == 40
    assert zmq.curve_public(secret_key) == public_key
    capsys.readouterr()

    assert main(["keys", "station", "--dir", str(folder)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "exists; pass --force" in err[0]
    assert zmq.auth.load_certificate(secret) == (public_key, secret_key)  # untouched

    assert main(["keys", "station", "--dir", str(folder), "--force"]) == 0
    new_public, new_secret = zmq.auth.load_certificate(secret)
    assert new_public != public_key and zmq.auth.load_certificate(public)[0] == new_public
    assert stat.S_IMODE(secret.stat().st_mode) == 0o600
    assert sorted(p.name for p in folder.iterdir()) == ["station.key", "station.key_secret"]  # no temporary left


def test_loopback_is_127_0_0_0_8_ipv6_loopback_localhost_and_local_transports():
    for endpoint in ("tcp://127.0.0.1:5560", "tcp://127.3.2.1:*", "tcp://[::1]:5560", "tcp://localhost:1", "ipc://x"):
        assert is_loopback(endpoint), endpoint
    for endpoint in ("tcp://*:5560", "tcp://0.0.0.0:5560", "tcp://[::]:1", "tcp://10.0.0.2:1", "tcp://eth0:1"):
        assert not is_loopback(endpoint), endpoint


# --- refusing to start --------------------------------------------------------------------------------------------


def test_a_non_loopback_bind_without_security_is_a_one_line_error(tmp_path):
    config = write_config(tmp_path / "open.toml", bus={"telemetry": "tcp://0.0.0.0:*"})
    r = runtime.hmdrt("run", str(config), "--frames", "1")
    assert r.returncode == 1
    runtime.assert_one_line_error(r.stderr, "bus.telemetry = tcp://0.0.0.0:* is not loopback: binding it needs CURVE")


@pytest.mark.parametrize(
    "security, message",
    [
        ({"allowed_clients": ["alice.key"]}, "missing required field `server_key`"),
        ({"server_key": "server.key_secret", "allowed_clients": []}, "allowed_clients"),
        ({"server_key": "server.key", "allowed_clients": ["alice.key"]}, "holds no secret key"),
        ({"server_key": "server.key_secret", "allowed_clients": ["nobody.key"]}, "nobody.key: not found"),
    ],
)
def test_an_incomplete_security_section_is_an_error_at_start(tmp_path, keys, context, security, message):
    folder = keys["server"][0].parent  # the key paths are relative to the config file
    config = write_config(folder / f"{tmp_path.name}.toml", bus={"ingest": "tcp://*:*"}, security=security)
    with pytest.raises(ConfigError, match=message):
        Compositor(load_config(config), context=context)


# --- a compositor with [security] -------------------------------------------------------------------------------


def test_control_answers_only_allowed_keys_and_counts_the_refused(tmp_path, keys, context, capsys):
    with compositor(secured_config(tmp_path, keys), context) as comp:
        control, alice = comp.control.address, client(keys, "alice")
        status = request(control, {"cmd": "status"}, keys=alice)
        assert status["ok"] and status["security"]["curve"] and status["security"]["admitted"] >= 1

        strangers = {
            "no keys": None,
            "a key not on the list": client(keys, "mallory"),
            "the wrong server key": client(keys, "alice", server="mallory"),
        }
        for who, stranger in strangers.items():
            before = refused(comp)
            for command in ({"cmd": "shutdown"}, {"cmd": "set", "params": {"group_w": 2}}):
                with pytest.raises(ConfigError, match="no hmdrt compositor answered"):
                    request(control, command, NO_ANSWER_S, keys=stranger)
            assert wait_for(lambda b=before: refused(comp) > b), who
        assert not comp.stop.is_set() and "group_w=2" not in comp.session.spec  # nothing the strangers asked for

        assert request(control, {"cmd": "set", "params": {"group_w": 2}}, keys=alice)["ok"]
        assert main(["status", "--control", control, *key_options(keys, "alice")]) == 0
        assert re.search(r"; access: CURVE, \d+ handshakes admitted, \d+ refused$", capsys.readouterr().out.strip())
        report = comp.summary()["security"]
        assert report["curve"] and report["refused"] >= 3 and report["admitted"] >= 2
        assert request(control, {"cmd": "shutdown"}, keys=alice) == {"ok": True} and comp.stop.is_set()


def hears_telemetry(context: zmq.Context, comp: Compositor, keys: ClientKeys | None) -> bool:
    """Whether a SUB with these keys hears the compositor's telemetry: yes once a probe arrives, no once its
    handshake has been refused (after which nothing can arrive on it)."""
    sub = context.socket(zmq.SUB)
    sub.setsockopt(zmq.LINGER, 0)
    sub.setsockopt(zmq.SUBSCRIBE, b"")
    if keys is not None:
        keys.apply(sub)
    before = refused(comp)
    sub.connect(comp.telemetry.address)
    try:
        deadline = time.monotonic() + 10
        while time.monotonic() < deadline:
            comp.telemetry.publish("probe", {})
            if sub.poll(50):
                return True
            if refused(comp) > before:
                return False
        pytest.fail("the subscriber was neither admitted nor refused")
    finally:
        sub.close()


def test_telemetry_reaches_only_allowed_keys(tmp_path, keys, context):
    with compositor(secured_config(tmp_path, keys), context) as comp:
        assert not hears_telemetry(context, comp, None)
        assert not hears_telemetry(context, comp, client(keys, "mallory"))
        assert hears_telemetry(context, comp, client(keys, "alice"))


def test_a_mutating_command_without_a_client_identity_is_refused_and_counted(tmp_path, keys, context):
    """Under CURVE no such request can arrive; the control server still checks, in case one ever did."""
    with compositor(secured_config(tmp_path, keys), context) as comp:
        anonymous = [zmq.Frame(msgspec.msgpack.encode({"cmd": "shutdown"}))]
        reply = comp.control._reply(anonymous)
        assert not reply["ok"] and "needs an authenticated (CURVE) client" in reply["error"]
        assert not comp.stop.is_set() and comp.security()["commands_refused"] == 1
        assert comp.control._reply([zmq.Frame(msgspec.msgpack.encode({"cmd": "stats"}))])["ok"]  # reading is not


def key_options(keys: dict, name: str) -> list[str]:
    return ["--server-key", str(keys["server"][0]), "--client-key", str(keys[name][1])]


def test_only_the_keyed_drivers_samples_reach_the_ingest(tmp_path, keys, context, own_signals):
    """Three drivers publish: the config's own (keys of the compositor's making), `hmdrt driver` with alice's
    keys, and one without keys. The third is refused at the handshake, counted, and none of its samples arrive;
    the run report counts it too."""
    with compositor(secured_config(tmp_path, keys), context, frames=30) as comp:
        stop = threading.Event()
        plain = DriverHost("synthetic://?seed=2&rate=250&name=plain", comp.ingest.address, subscriber_wait_s=0.2)
        thread = threading.Thread(target=plain.run, args=(stop,))
        thread.start()
        try:
            assert wait_for(lambda: refused(comp) >= 1)
            running = Background(comp)
            url = "synthetic://?seed=1&rate=250&name=keyed"
            code = main(["driver", url, "--bus", comp.ingest.address, *key_options(keys, "alice"), "--duration", "1"])
            assert code == 0
            heard = comp.store.counts
            assert wait_for(lambda: len(heard()) == 2 and "keyed" in heard() and heard()["keyed"].samples > 100)
        finally:
            stop.set()
            thread.join(10)
        counts = comp.store.counts()
        assert "plain" not in counts and "plain" not in comp.ingest.status
        assert plain.counters.samples > 100  # it did publish, into a connection that never opened
        assert len(counts) == 2  # the keyed driver and the config's replay
        assert refused(comp) >= 1 and comp.security()["admitted"] >= 2
        report, _ = running.join(60)
        assert report["security"]["curve"] and report["security"]["refused"] >= 1


def test_record_connects_with_keys_to_a_curve_publisher(tmp_path, keys, context, own_signals):
    """`hmdrt record --connect` with keys hears a CURVE publisher that admits alice only."""
    guard = Guard(context, ServerKeys.load(keys["server"][1], [str(keys["alice"][0])]))
    pub = context.socket(zmq.PUB)
    pub.setsockopt(zmq.LINGER, 0)
    guard.serve(pub)
    port = pub.bind_to_random_port("tcp://127.0.0.1")
    stop = threading.Event()

    def publish() -> None:
        seq = 0
        while not stop.wait(0.004):
            pub.send_multipart(encode(Gaze(seq=seq, t_host=seq * 4_000_000, valid=True, C=(0.0, 0.0, -1.0)), "eye"))
            seq += 1

    thread = threading.Thread(target=publish)
    thread.start()
    out = tmp_path / "rec.jsonl"
    try:
        args = ["record", "--out", str(out), "--bus", f"tcp://127.0.0.1:{port}", "--connect", "--duration", "1"]
        assert main([*args, *key_options(keys, "alice")]) == 0
    finally:
        stop.set()
        thread.join(10)
        pub.close()
        guard.close()
    assert len(out.read_text().splitlines()) > 50 and guard.admitted >= 1
    assert main(["record", "--out", str(out), *key_options(keys, "alice")]) == 1  # keys without --connect
