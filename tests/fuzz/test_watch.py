"""Fuzzing what reaches `hmdrt watch` from outside: page commands (hmdrt.watch.protocol.parse_command), raw HTTP
requests and websocket messages against a real server on a loopback port. Bad input is an error answer or a counted
refusal, never a server error, and the server goes on answering."""

from __future__ import annotations

import asyncio
import json
import re
import socket

import aiohttp
import pytest
from hypothesis import strategies as st

from hmdrt.compositor.commands import COMMANDS as DECLARED
from hmdrt.compositor.commands import to_request
from hmdrt.watch.protocol import MAX_MESSAGE_BYTES, BadMessage, PageCommand, parse_command
from hmdrt.watch.server import WatchOptions, WatchServer
from tests.fuzz.common import MSGPACK_VALUES, fuzz, mutations
from tests.helpers import wait_for
from tests.watching import watch_server

SERVER: WatchServer | None = None  # one server for the module's examples (a fixture per example would be too slow)
NOWHERE = "tcp://127.0.0.1:1"  # no compositor: commands that get through are answered "no compositor answered"


@pytest.fixture(scope="module", autouse=True)
def server():
    global SERVER
    with watch_server(WatchOptions(control=NOWHERE, telemetry=NOWHERE, port=0, control_timeout_s=0.05)) as SERVER:
        yield SERVER


def _outcome(data: str | bytes) -> PageCommand | None:
    try:
        command = parse_command(data)
    except BadMessage:
        return None
    request = to_request(command.command)
    assert request["cmd"] in DECLARED and "id" not in request
    return command


COMMANDS = st.fixed_dictionaries(
    {"cmd": st.sampled_from(["set", "snapshot", "shutdown", "status", "", "SET"])},
    optional={
        "method": MSGPACK_VALUES,
        "params": st.dictionaries(st.text(max_size=70), MSGPACK_VALUES, max_size=40) | MSGPACK_VALUES,
        "path": st.sampled_from(["a.png", "../a.png", "/etc/x.png", ".png", "a.png\n", "a" * 70 + ".png"])
        | st.text(max_size=80),
        "id": st.integers(-(2**63), 2**64) | MSGPACK_VALUES,
        "extra": MSGPACK_VALUES,
    },
)


def _json(value) -> str:
    return json.dumps(value, default=lambda v: v.hex() if isinstance(v, bytes) else str(v))


@fuzz(400, data=st.one_of(st.text(max_size=200), st.binary(max_size=200), COMMANDS.map(_json)))
def test_page_messages_are_a_command_or_refused(data):
    """Any text, bytes or command-shaped JSON parses to a declared control command or raises BadMessage."""
    _outcome(data)


@fuzz(200, command=COMMANDS.map(lambda c: _json(c).encode()).flatmap(mutations))
def test_corrupted_commands_are_a_command_or_refused(command):
    """Commands truncated, overwritten, extended or cut parse or raise BadMessage."""
    _outcome(command)


def test_page_messages_over_the_size_limit_are_refused_unread():
    with pytest.raises(BadMessage, match="at most"):
        parse_command('{"cmd": "shutdown", "method": "' + "x" * MAX_MESSAGE_BYTES + '"}')


def _raw_http(port: int, request: bytes) -> bytes:
    """What the server answers to raw request bytes that ask it to close the connection after its answer."""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as sock:
        sock.sendall(request)
        answer = b""
        while chunk := sock.recv(65536):
            answer += chunk
    return answer


def _request(method: str, path: str, host: str | None, origin: str | None, token: str | None, body: bytes) -> bytes:
    lines = [f"{method} {path}{'' if token is None else ('&' if '?' in path else '?') + 'token=' + token} HTTP/1.1"]
    lines += [f"Host: {host}"] if host is not None else []
    lines += [f"Origin: {origin}"] if origin is not None else []
    lines += [f"Content-Length: {len(body)}", "Connection: close"]
    return ("\r\n".join(lines) + "\r\n\r\n").encode("utf-8", "surrogateescape") + body


def _check_answer(answer: bytes, path: str, before: dict[str, int]) -> None:
    """An HTTP answer that is no server error, and a 403 when (and only when) a refusal of the Host, Origin or token
    was counted; aiohttp's own static files handler may answer 403 to a path that leaves its folder."""
    status_line = re.match(rb"HTTP/\d\.\d (\d{3}) ", answer)  # in the request's version (1.0 when it had none)
    assert status_line, answer[:200]
    status = int(status_line[1])
    assert status < 500, answer[:500]
    after = SERVER.access.counts()
    refused = sum(after[k] - before[k] for k in ("host", "origin", "token"))
    assert refused in (0, 1) and (refused == 1) <= (status == 403), (answer[:300], before, after)
    assert (status == 403) <= (refused == 1 or path.startswith("/static/")), (answer[:300], before, after)


def _good() -> dict:
    port = SERVER.access.port
    return {"host": f"127.0.0.1:{port}", "origin": f"http://127.0.0.1:{port}", "token": SERVER.access.token}


TEXT = st.text(st.characters(codec="utf-8", exclude_characters="\r\n"), max_size=40)


@fuzz(
    300,
    method=st.sampled_from(["GET", "POST", "PUT", "DELETE", "HEAD", "OPTIONS"]) | TEXT,
    path=st.sampled_from(["/", "/ws", "/api/state", "/api/command", "/static/watch.js", "/static/../server.py"])
    | TEXT.map(lambda t: "/" + t),
    host=st.sampled_from(["good", "localhost", "evil.example", "127.0.0.1:1", ""]) | st.none() | TEXT,
    origin=st.sampled_from(["good", "http://evil.example", "null"]) | st.none() | TEXT,
    token=st.sampled_from(["good", "wrong"]) | st.none() | TEXT,
    body=st.binary(max_size=2 * MAX_MESSAGE_BYTES) | COMMANDS.map(lambda c: _json(c).encode()),
)
def test_http_requests_are_answered_or_refused_never_a_server_error(method, path, host, origin, token, body):
    """Requests of any method, path, Host, Origin, token and body get an answer under 500; 403s are counted."""
    good = _good()
    host = good["host"] if host == "good" else f"localhost:{SERVER.access.port}" if host == "localhost" else host
    origin, token = (good["origin"] if origin == "good" else origin), (good["token"] if token == "good" else token)
    before = SERVER.access.counts()
    _check_answer(_raw_http(SERVER.access.port, _request(method, path, host, origin, token, body)), path, before)


def _head(method: str) -> bytes:
    """A request's line and headers with {host} and {token} to fill in, for mutations to corrupt."""
    return f"{method} /api/command?token={{token}} HTTP/1.1\r\nHost: {{host}}\r\nX-Any: value".encode()


@fuzz(200, head=st.sampled_from(["GET", "POST"]).map(_head).flatmap(mutations))
def test_corrupted_http_requests_are_answered_never_a_server_error(head):
    """A request line and headers truncated, overwritten, extended or cut (the framing after them kept, so that the
    server has a whole request to answer) get an answer under 500, and the server answers the next one."""
    good, body = _good(), b'{"cmd": "shutdown"}'
    head = head.replace(b"{host}", good["host"].encode()).replace(b"{token}", good["token"].encode())
    data = head + f"\r\nContent-Length: {len(body)}\r\nConnection: close\r\n\r\n".encode() + body
    before = SERVER.access.counts()
    _check_answer(_raw_http(SERVER.access.port, data), "/api/command", before)
    assert _raw_http(SERVER.access.port, _request("GET", "/", good["host"], None, None, b"")).startswith(
        b"HTTP/1.1 200"
    )


async def _ws_exchange(url: str, message: str | bytes) -> tuple[str, dict | int]:
    """("reply", the reply) to one websocket message, or ("closed", the close code)."""
    async with aiohttp.ClientSession() as session, session.ws_connect(url) as ws:
        await (ws.send_bytes(message) if isinstance(message, bytes) else ws.send_str(message))
        while True:
            answer = await asyncio.wait_for(ws.receive(), 10)
            if answer.type == aiohttp.WSMsgType.TEXT:
                if (reply := json.loads(answer.data))["type"] == "reply":
                    return "reply", reply
            elif answer.type != aiohttp.WSMsgType.BINARY:
                return "closed", ws.close_code


@fuzz(
    150,
    message=st.one_of(
        COMMANDS.map(_json),
        st.text(max_size=100),
        st.binary(max_size=100),
        st.integers(MAX_MESSAGE_BYTES - 8, MAX_MESSAGE_BYTES + 64).map(
            lambda n: '{"cmd": "set", "method": "' + "x" * n + '"}'
        ),
    ),
)
def test_websocket_messages_get_a_reply_or_close_an_oversize_connection(message):
    """A page's message gets a reply: refused (and counted) when it is no command, forwarded when it is one; one
    over the size limit closes the connection (counted)."""
    url = f"ws://127.0.0.1:{SERVER.access.port}/ws?token={SERVER.access.token}"
    before = SERVER.access.refused["message"]
    kind, answer = asyncio.run(_ws_exchange(url, message))
    size = len(message.encode() if isinstance(message, str) else message)
    if size > MAX_MESSAGE_BYTES:
        # 1009 (too big); 1006 when the server closed the connection under the client's write
        assert kind == "closed" and answer in (1009, 1006), (kind, answer)
        assert wait_for(lambda: SERVER.access.refused["message"] == before + 1, 10)
        return
    assert kind == "reply" and answer["ok"] is False, answer
    command = None if isinstance(message, bytes) else _outcome(message)
    if command is None:
        assert SERVER.access.refused["message"] == before + 1
    else:  # forwarded: nobody answers at NOWHERE
        assert "no hmdrt compositor answered" in answer["error"] and answer["id"] == command.id
