"""`hmdrt watch` without a browser: the compositor's previews on demand, and the watch server's access rules and
command mapping over plain HTTP and websockets (aiohttp's client), against real sockets and a real compositor
that replays a recorded trace in virtual time at the wall clock's pace."""

from __future__ import annotations

import asyncio
import io
import json
import time

import aiohttp
import msgspec
import numpy as np
import pytest
import zmq
from aiohttp import WSMsgType
from PIL import Image

from hmdrt.bus.security import ClientKeys, write_keypair
from hmdrt.compositor.endpoints import request
from hmdrt.compositor.preview import MAX_HZ
from hmdrt.present.encode import preview_srgb8, side_by_side_srgb8
from hmdrt.testing import Background, write_config
from hmdrt.watch.access import TOKEN_HEADER
from hmdrt.watch.protocol import MAX_GAZE_ERRORS, MAX_MESSAGE_BYTES, frame_point
from hmdrt.watch.server import WatchOptions

from .compositor_helpers import hmdrt, receive
from .helpers import wait_for
from .watching import expected_gaze, paced_compositor, watch_server

EVIL = "http://evil.example"


@pytest.fixture
def running(tmp_path, context):
    """A compositor running in paced virtual time (both eyes at 64x72), stopped after the test."""
    comp = paced_compositor(write_config(tmp_path / "run.toml"), context)
    run = Background(comp)
    try:
        assert wait_for(lambda: len(comp.records) >= 3, timeout_s=60)
        yield comp
    finally:
        comp.stop.set()
        run.thread.join(30)
        comp.close()


def test_previews_are_made_only_while_a_client_subscribes_to_them_by_name(running, context):
    comp = running
    everything = context.socket(zmq.SUB)  # a subscription to every topic does not ask for previews
    everything.setsockopt(zmq.SUBSCRIBE, b"")
    everything.connect(comp.telemetry.address)
    assert len(receive(everything, b"frame", 30, timeout_s=10)) == 30
    assert comp.preview.sent == 0 and not comp.telemetry.subscribed("preview")

    previews = context.socket(zmq.SUB)
    previews.setsockopt(zmq.SUBSCRIBE, b"preview")
    previews.connect(comp.telemetry.address)
    t0 = time.monotonic()
    got = receive(previews, b"preview", 10, timeout_s=20)
    took = time.monotonic() - t0
    assert len(got) == 10 and took > 9 / MAX_HZ * 0.9  # at most MAX_HZ a second (30 frames a second are shown)
    assert len(receive(everything, b"preview", 1)) == 1  # published to every subscriber once someone asks
    for message in got:
        with Image.open(io.BytesIO(message["jpeg"])) as image:
            assert image.format == "JPEG" and image.size == (message["width"], message["height"]) == (128, 72)
        assert [e["eye"] for e in message["eyes"]] == ["left", "right"] and message["method"] == "rrm"
        for eye, want in zip(message["eyes"], expected_gaze(comp, message), strict=True):
            assert eye["gaze"] == pytest.approx(want, abs=1e-6)
        assert message["fovea_deg"] == 10.0 and message["eyes"][0]["fovea"][0] > 1  # rrm's fovea_deg, in pixels
    assert len({tuple(m["eyes"][0]["gaze"]) for m in got}) > 1  # the replayed gaze moves

    previews.close()  # the last subscriber gone: no more previews
    assert wait_for(lambda: (comp.telemetry.publish("probe", {}), not comp.telemetry.subscribed("preview"))[1], 10)
    sent = comp.preview.sent
    receive(everything, b"frame", 15)
    assert comp.preview.sent <= sent + 1  # one that was on its way
    everything.close()


async def _fetch(session: aiohttp.ClientSession, method: str, url: str, **kwargs) -> tuple[int, str]:
    async with session.request(method, url, **kwargs) as response:
        return response.status, await response.text()


async def _replies(ws: aiohttp.ClientWebSocketResponse, count: int) -> list[dict]:
    """The next `count` replies to commands (other messages, and the frames sent as binary ones, skipped)."""
    out = []
    while len(out) < count:
        message = await asyncio.wait_for(ws.receive(), 30)
        if message.type == WSMsgType.BINARY:
            continue
        if message.type != WSMsgType.TEXT:
            raise AssertionError(f"websocket closed: {message}")
        if json.loads(message.data)["type"] == "reply":
            out.append(json.loads(message.data))
    return out


async def _check_access(url: str, token: str, port: int) -> dict:
    """Every kind of refusal once or more, a read-only page, and a command with the token; what came back."""
    out = {}
    bad_host = {"Host": f"evil.example:{port}"}
    async with aiohttp.ClientSession() as session:
        out["page"] = await _fetch(session, "GET", url)
        async with session.get(url) as response:
            out["headers"] = dict(response.headers)
        out["rebound host"] = await _fetch(session, "GET", url, headers=bad_host)
        out["other port"] = await _fetch(session, "GET", url, headers={"Host": f"127.0.0.1:{port + 1}"})
        out["foreign origin"] = await _fetch(session, "GET", url + "api/state", headers={"Origin": EVIL})
        out["no token"] = await _fetch(session, "POST", url + "api/command", data=b'{"cmd": "shutdown"}')
        out["wrong token"] = await _fetch(
            session, "POST", url + "api/command", data=b'{"cmd": "shutdown"}', headers={TOKEN_HEADER: "x" + token}
        )
        try:
            await session.ws_connect(url + "ws", headers={"Origin": EVIL})
        except aiohttp.WSServerHandshakeError as exc:
            out["websocket from a foreign origin"] = exc.status
        async with session.ws_connect(url + "ws", headers={"Origin": url.rstrip("/")}) as ws:  # read-only
            hello = json.loads((await ws.receive()).data)
            await ws.send_str('{"cmd": "shutdown"}')
            await ws.send_str('{"cmd": "set", "params": "fovea_deg=5"}')  # not a command
            await ws.send_bytes(b"\x00")
            out["read-only"] = (hello, await _replies(ws, 3))
        async with session.ws_connect(url + f"ws?token={token}") as ws:
            await ws.send_str("x" * (MAX_MESSAGE_BYTES + 1))
            while (message := await asyncio.wait_for(ws.receive(), 30)).type in (WSMsgType.TEXT, WSMsgType.BINARY):
                pass  # the hello, the status, frames: then the close
            out["oversize"] = (message.type, ws.close_code)
        out["set"] = await _fetch(
            session,
            "POST",
            url + "api/command",
            json={"cmd": "set", "params": {"fovea_deg": 5}},
            headers={TOKEN_HEADER: token},
        )
        out["state"] = await _fetch(session, "GET", url + "api/state")
    return out


def test_the_watch_server_refuses_foreign_hosts_origins_and_commands_without_the_token(running):
    comp = running
    options = WatchOptions(control=comp.control.address, port=0, control_timeout_s=5.0)
    with watch_server(options) as server:
        url, token, port = server.url(), server.access.token, server.access.port
        out = asyncio.run(_check_access(url, token, port))
        wait_for(lambda: server.access.total_refused >= 10, 10)  # the oversize message may be counted after the close
        counts = server.access.counts()

    status, text = out["page"]
    assert status == 200 and "<title>hmdrt watch</title>" in text
    assert (
        out["headers"]["X-Frame-Options"] == "DENY"
        and "frame-ancestors 'none'" in out["headers"]["Content-Security-Policy"]
    )
    for case in ("rebound host", "other port", "foreign origin", "no token", "wrong token"):
        assert out[case][0] == 403, (case, out[case])
    assert out["websocket from a foreign origin"] == 403
    hello, replies = out["read-only"]
    assert hello["type"] == "hello" and hello["privileged"] is False
    assert [r["ok"] for r in replies] == [False, False, False]
    assert "read-only" in replies[0]["error"] and replies[1]["error"].startswith("set takes")
    assert out["oversize"][1] in (1009, 1006)  # too big; 1006 when the server closed under the client's write
    # refused and counted: host 2, origin 2 (a request and a websocket), token 3 (two requests, one read-only
    # page's command), message 3 (not a command, binary, over the size)
    assert counts == {"host": 2, "origin": 2, "token": 3, "message": 3, "total": 10}

    # with the token, a command reaches the compositor
    status, text = out["set"]
    assert status == 200 and json.loads(text) == {"ok": True, "method": "rrm?fovea_deg=5.0"}
    assert wait_for(lambda: request(comp.control.address, {"cmd": "status"})["params"]["fovea_deg"] == 5.0, 30)
    assert not comp.stop.is_set()  # no refused shutdown got through
    state = msgspec.json.decode(out["state"][1])
    assert state["connected"] and state["status"]["method"].startswith("rrm") and state["watch"]["refused"]["total"]
    assert state["control_allows"] is True  # ipc:// control without [security]: this user's


def test_hmdrt_watch_beyond_loopback_without_keys_or_without_a_compositor_is_a_one_line_error(tmp_path):
    beyond = hmdrt("watch", "--control", f"ipc://{tmp_path}/none.sock", "--bind", "0.0.0.0", timeout_s=60)
    assert beyond.returncode == 1 and beyond.stderr.count("\n") == 1, beyond.stderr
    assert "--bind 0.0.0.0 is not loopback" in beyond.stderr and "--server-key" in beyond.stderr
    alone = hmdrt("watch", "--control", f"ipc://{tmp_path}/none.sock", "--port", "0", timeout_s=60)
    assert alone.returncode == 1 and alone.stderr.count("\n") == 1, alone.stderr
    assert "no hmdrt compositor answered" in alone.stderr and "Traceback" not in alone.stderr


def test_a_preview_is_shrunk_by_block_means_in_linear_light():
    """preview_srgb8: each block's mean of linear values, then sRGB within one code value of the exact encoding;
    the remainder of rows and columns left out; NaN black and infinity white, as the exact encoding has them."""
    rng = np.random.default_rng(1)
    left = rng.uniform(-0.1, 1.2, (9, 8, 3)).astype(np.float32)
    left[0:2, 0:2] = [[0.0], [1.0]]  # rows of black and white: mid grey in linear light, not (0 + 255) / 2
    left[2, 2, 0], left[2, 3, 1] = np.nan, np.inf
    right = rng.uniform(0.0, 1.0, (9, 6, 3)).astype(np.float32)
    small = preview_srgb8([left, right], 2)
    assert small.shape == (4, 4 + 3, 3)
    means = [image[:8, : image.shape[1] // 2 * 2].reshape(4, 2, -1, 2, 3).mean(axis=(1, 3)) for image in (left, right)]
    exact = side_by_side_srgb8(means).astype(int)
    assert np.abs(small.astype(int) - exact).max() <= 1
    assert small[0, 0, 0] in (187, 188, 189) and small[1, 1, 0] == 0 and small[1, 1, 1] == 255
    assert np.abs(preview_srgb8([left], 1).astype(int) - side_by_side_srgb8([left]).astype(int)).max() <= 1


async def _beyond_loopback(port: int, token: str) -> dict:
    """What a server bound beyond loopback answers with and without the token, and its state once it has frames."""
    base, host = f"http://127.0.0.1:{port}/", {"Host": f"watch.test:{port}"}
    async with aiohttp.ClientSession() as session:
        out = {
            "page": (await _fetch(session, "GET", base, headers=host))[0],
            "script": (await _fetch(session, "GET", base + "static/watch.js", headers=host))[0],
            "page with the token": (await _fetch(session, "GET", base + f"?token={token}", headers=host))[0],
        }
        for _ in range(100):
            status, text = await _fetch(session, "GET", base + "api/state", headers={**host, TOKEN_HEADER: token})
            out["state"] = msgspec.json.decode(text)
            if out["state"]["report"].get("vsyncs") and out["state"]["connected"]:
                break
            await asyncio.sleep(0.1)
    return out


def test_a_watch_server_beyond_loopback_takes_curve_keys_and_needs_the_token_for_all_but_its_static_files(
    tmp_path, context
):
    keys = {name: write_keypair(tmp_path / "keys", name) for name in ("server", "watcher")}
    security = {"server_key": str(keys["server"][1]), "allowed_clients": [str(keys["watcher"][0])]}
    comp = paced_compositor(write_config(tmp_path / "secured.toml", security=security), context)
    run = Background(comp)
    try:
        watcher = ClientKeys.load(keys["server"][0], keys["watcher"][1])
        options = WatchOptions(comp.control.address, bind="0.0.0.0", port=0, allow_hosts=("watch.test",), keys=watcher)
        with watch_server(options) as server:
            assert server.url() == f"http://watch.test:{server.access.port}/"
            out = asyncio.run(_beyond_loopback(server.access.port, server.access.token))
    finally:
        comp.stop.set()
        run.thread.join(30)
        comp.close()
    assert (out["page"], out["script"], out["page with the token"]) == (403, 200, 200)
    state = out["state"]
    assert state["connected"] and state["report"]["vsyncs"] > 0  # telemetry and control, both over CURVE
    assert state["status"]["security"]["curve"] and state["control_allows"] is True


def test_a_frame_point_carries_the_gaze_errors_its_record_settled_and_refuses_a_malformed_list():
    error = {"vsync": 7, "left_deg": 1.5, "right_deg": None, "fovea_deg": 10.0}
    point = frame_point({"vsync": 9, "shown": "new", "gaze_errors": [{**error, "extra": "x"}] * 40})
    assert point["gaze_errors"] == [error] * MAX_GAZE_ERRORS  # the page puts each at its own VSync's point
    assert frame_point({"vsync": 9})["gaze_errors"] == []
    for bad in (5, [5], {"vsync": 7}, "text"):  # the hub counts these as malformed and skips them
        with pytest.raises((TypeError, AttributeError)):
            frame_point({"vsync": 9, "gaze_errors": bad})
