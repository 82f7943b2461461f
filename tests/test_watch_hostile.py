"""`hmdrt watch` against hostile and broken clients, over real sockets: thousands of slow connections, idle ones, a
page that never answers a ping, a token holder who goes away mid-request, and a process out of files. The page must
keep answering, what it refused and closed must be counted, and its log must stay a few lines without a traceback.
No compositor is needed: the server keeps serving while its control socket does not answer."""

from __future__ import annotations

import base64
import json
import logging
import os
import resource
import selectors
import socket
import struct
import subprocess
import sys
import time
import urllib.parse
import urllib.request
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path

import pytest

from hmdrt.watch.access import TOKEN_HEADER
from hmdrt.watch.limits import MAX_CONNECTIONS
from hmdrt.watch.server import WatchOptions

from .compositor_helpers import readline
from .helpers import wait_for
from .watching import URL, watch_server

NOWHERE = "tcp://127.0.0.1:1"  # no compositor: status requests time out, the telemetry never connects
SLOW = 2000  # slow connections against the default cap
FILES = 1024  # the server's limit of open files, as in the report that 1,030 slow connections locked it out


def _options(**limits: float) -> WatchOptions:
    return WatchOptions(control=NOWHERE, telemetry=NOWHERE, port=0, control_timeout_s=0.5, **limits)


def _connect(port: int) -> socket.socket:
    return socket.create_connection(("127.0.0.1", port), timeout=5)


def _host(port: int) -> bytes:
    return f"Host: 127.0.0.1:{port}\r\n".encode()


def _post_head(port: int, token: str, length: int = 64) -> bytes:
    """A command's headers, with the token, for a body of `length` bytes that is never sent in full."""
    return (
        b"POST /api/command HTTP/1.1\r\n" + _host(port) + f"{TOKEN_HEADER}: {token}\r\n".encode()
        + f"Content-Length: {length}\r\n\r\n".encode() + b'{"cmd"'
    )  # fmt: skip


def _upgrade(port: int, token: str) -> bytes:
    key = base64.b64encode(os.urandom(16)).decode()
    return (
        f"GET /ws?token={token} HTTP/1.1\r\n".encode() + _host(port)
        + f"Upgrade: websocket\r\nConnection: Upgrade\r\nSec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n\r\n"
        .encode()
    )  # fmt: skip


def _head(sock: socket.socket) -> bytes:
    """A response's status line and headers."""
    data = b""
    while b"\r\n\r\n" not in data:
        chunk = sock.recv(4096)
        assert chunk, f"closed after {data!r}"
        data += chunk
    return data


def _open_page(port: int, token: str) -> socket.socket:
    """A websocket that sends nothing, answers nothing (no pong), and is left open."""
    sock = _connect(port)
    sock.sendall(_upgrade(port, token))
    assert _head(sock).startswith(b"HTTP/1.1 101"), "no upgrade"
    return sock


def _until_closed(sock: socket.socket, timeout_s: float) -> bytes:
    """What the server sent until it closed the connection; fails if it is still open after timeout_s."""
    sock.settimeout(timeout_s)
    data = b""
    try:
        while chunk := sock.recv(65536):
            data += chunk
    except ConnectionResetError:
        pass
    except TimeoutError:
        pytest.fail(f"still open after {timeout_s} s, having sent {data[:80]!r}")
    return data


def _is_open(sock: socket.socket) -> bool:
    """Whether the server has not closed the connection (anything it sent is left unread)."""
    timeout = sock.gettimeout()
    sock.setblocking(False)
    try:
        return sock.recv(1, socket.MSG_PEEK) != b""
    except BlockingIOError:
        return True
    except ConnectionResetError:
        return False
    finally:
        sock.settimeout(timeout)


def _opcodes(frames: bytes) -> list[int]:
    """The opcodes of the websocket frames a server sent (unmasked, RFC 6455 section 5.2)."""
    out, at = [], 0
    while at + 2 <= len(frames):
        out.append(frames[at] & 0x0F)
        size, at = frames[at + 1] & 0x7F, at + 2
        if size >= 126:
            width = 2 if size == 126 else 8
            size, at = int.from_bytes(frames[at : at + width], "big"), at + width
        at += size
    return out


def _abort(sock: socket.socket) -> None:
    """Close with a reset, as a client that crashed or lost its network does."""
    sock.setsockopt(socket.SOL_SOCKET, socket.SO_LINGER, struct.pack("ii", 1, 0))
    sock.close()


def _state(port: int) -> tuple[dict, float]:
    """GET /api/state on a connection of its own: the state and how long the answer took."""
    started = time.monotonic()
    with urllib.request.urlopen(f"http://127.0.0.1:{port}/api/state", timeout=5) as response:
        assert response.status == 200
        return json.loads(response.read()), time.monotonic() - started


def _clean_log(caplog: pytest.LogCaptureFixture) -> None:
    """No record of the server's carries a traceback."""
    assert not [r for r in caplog.records if r.exc_info or r.exc_text], "a traceback in the log"


def test_a_slow_or_idle_connection_and_a_page_without_pong_are_closed_after_their_timeouts(caplog):
    caplog.set_level(logging.DEBUG, logger="hmdrt.watch")
    with watch_server(_options(request_timeout_s=0.5, idle_timeout_s=1.5)) as server:
        port, token = server.access.port, server.access.token
        kept = _connect(port)  # one request, then kept alive
        kept.sendall(b"GET /api/state HTTP/1.1\r\n" + _host(port) + b"\r\n")
        assert _head(kept).startswith(b"HTTP/1.1 200")
        page = _open_page(port, token)
        silent = _connect(port)  # connects and sends nothing
        partial = _connect(port)
        partial.sendall(b"GET /api/state HTTP/1.1\r\n" + _host(port))  # never the blank line
        body = _connect(port)
        body.sendall(_post_head(port, token))  # the body never comes in full
        assert all(map(_is_open, (silent, partial, body, kept, page)))

        assert _until_closed(silent, 3) == b"" and _until_closed(partial, 3) == b""
        assert _until_closed(body, 3).startswith(b"HTTP/1.1 408")
        assert _is_open(kept) and _is_open(page)  # their idle timeout has not passed
        _until_closed(kept, 5)
        assert _opcodes(_until_closed(page, 5))[-1] == 0x9  # the hello and status, a ping (unanswered), closed
        assert wait_for(lambda: server.counts()["timed_out"] == {"request": 3, "idle": 2}, 5), server.counts()
        assert server.counts()["connections"] == 0
    _clean_log(caplog)
    assert len([r for r in caplog.records if "no pong" in r.getMessage()]) == 1


def test_over_the_caps_the_longest_waiting_connection_makes_room_and_refusals_are_counted(caplog):
    caplog.set_level(logging.DEBUG, logger="hmdrt.watch")
    with watch_server(_options(max_connections=4, max_pages=2)) as server:
        port, token = server.access.port, server.access.token

        def refused() -> dict:
            return server.counts()["refused"]

        pages = [_open_page(port, token) for _ in range(2)]
        third = _connect(port)
        third.sendall(_upgrade(port, token))
        assert _head(third).startswith(b"HTTP/1.1 503")  # over max_pages; the connection waits for its next request
        first_post = _connect(port)
        first_post.sendall(_post_head(port, token))
        time.sleep(0.2)  # its handler starts reading the body: busy
        newcomer = _connect(port)  # at max_connections: the longest-waiting one (third) is closed for it
        _until_closed(third, 3)
        assert refused()["connections"] == 1
        second_post = _connect(port)
        second_post.sendall(_post_head(port, token))
        assert _until_closed(newcomer, 3) == b""  # waited longest now
        time.sleep(0.2)
        busy = _connect(port)  # all four busy: refused
        assert _until_closed(busy, 3).startswith(b"HTTP/1.1 503") and refused()["connections"] == 3

        _abort(first_post)  # a token holder goes away mid-request
        assert wait_for(lambda: server.connections.count == 3, 5)
        idle = [_connect(port) for _ in range(20)]  # the first takes the free place, each next one's its
        state, took = _state(port)
        assert took < 1.0
        assert state["watch"]["refused"]["connections"] == 3 + 19 + 1 and state["watch"]["refused"]["pages"] == 1
        assert state["watch"]["pages"] == 2 and state["watch"]["connections"] == 4
        assert sum(map(_is_open, idle)) == 0
    for sock in (*pages, second_post):  # after the server stopped: it logs nothing of them
        sock.close()
    _clean_log(caplog)
    gone = [r for r in caplog.records if "went away mid-request" in r.getMessage()]
    assert len(gone) == 1 and gone[0].levelno == logging.DEBUG


@contextmanager
def _watch(log: Path, *options: str) -> Iterator[tuple[subprocess.Popen, int, str]]:
    """`hmdrt [OPTIONS] watch` with no compositor, its log in `log` and at most FILES open files:
    (process, port, token)."""
    with log.open("w") as stderr:
        process = subprocess.Popen(
            [
                sys.executable,
                "-m",
                "hmdrt",
                *options,
                "watch",
                "--port",
                "0",
                "--control",
                NOWHERE,
                "--telemetry",
                NOWHERE,
            ],
            stdout=subprocess.PIPE,
            stderr=stderr,
            text=True,
        )
    try:
        resource.prlimit(process.pid, resource.RLIMIT_NOFILE, (FILES, FILES))
        line = readline(process, 60)
        match = URL.fullmatch(line.strip())
        assert match, f"hmdrt watch printed {line!r}; its log: {log.read_text()}"
        yield process, urllib.parse.urlsplit(match.group(3)).port, match.group(2)
    finally:
        process.terminate()
        process.wait(10)


def _slow_connections(port: int, count: int) -> list[socket.socket]:
    """`count` connections, every other one having sent part of a request, opened 100 at a time."""
    socks = []
    partial = b"GET / HTTP/1.1\r\n" + _host(port)
    with selectors.DefaultSelector() as sel:
        for start in range(0, count, 100):
            batch = [socket.socket() for _ in range(min(100, count - start))]
            for sock in batch:
                sock.setblocking(False)
                sock.connect_ex(("127.0.0.1", port))
                sel.register(sock, selectors.EVENT_WRITE)
            connected = set()
            deadline = time.monotonic() + 10
            while len(connected) < len(batch) and time.monotonic() < deadline:
                connected |= {key.fileobj for key, _ in sel.select(1)}
            for i, sock in enumerate(batch):
                sel.unregister(sock)
                if i % 2:
                    sock.send(partial)
            assert len(connected) == len(batch), f"{len(batch) - len(connected)} connections did not connect"
            socks += batch
    return socks


def _poll(condition: Callable[[], bool], timeout_s: float) -> bool:
    """wait_for at a tenth of a second, for a condition costly enough to slow the server down."""
    deadline = time.monotonic() + timeout_s
    while not condition() and time.monotonic() < deadline:
        time.sleep(0.1)
    return condition()


def _at_least_files(count: int) -> None:
    soft, hard = resource.getrlimit(resource.RLIMIT_NOFILE)
    if soft < count:
        if hard != resource.RLIM_INFINITY and hard < count:
            pytest.skip(f"needs {count} open files; this process may open {hard}")
        resource.setrlimit(resource.RLIMIT_NOFILE, (count, hard))


def test_two_thousand_slow_connections_leave_the_page_answering_and_the_log_short(tmp_path):
    _at_least_files(SLOW + 200)
    log = tmp_path / "watch.log"
    with _watch(log, "--log-level", "debug") as (process, port, token):
        post = _connect(port)  # a token holder goes away with its command half sent
        post.sendall(_post_head(port, token))
        time.sleep(0.1)
        post.close()
        _abort(_open_page(port, token))  # and with a page open
        assert wait_for(lambda: "closed (code 1006)" in log.read_text(), 5)

        socks = _slow_connections(port, SLOW)
        assert _poll(lambda: SLOW - sum(map(_is_open, socks)) >= SLOW - MAX_CONNECTIONS, 15)  # the cap holds
        state, took = _state(port)
        assert took < 1.0
        refused = state["watch"]["refused"]["connections"]
        assert refused >= SLOW - MAX_CONNECTIONS + 1 and state["watch"]["connections"] <= MAX_CONNECTIONS
        assert len(os.listdir(f"/proc/{process.pid}/fd")) < MAX_CONNECTIONS + 64
        assert SLOW - sum(map(_is_open, socks)) == refused  # each refusal closed one, the last for the state
        for sock in socks:
            sock.close()
    text = log.read_text()
    lines = text.splitlines()
    assert "Traceback" not in text and len(lines) < 30 and len(text) < 6000, text
    assert sum("went away mid-request" in line for line in lines) == 1
    assert sum("closed (code 1006)" in line for line in lines) == 1
    assert 10 <= sum("max_connections" in line and "suppressed" not in line for line in lines) <= 20  # LOG_BURST
    assert any(line.startswith("hmdrt: WARNING: hmdrt.watch.limits: suppressed ") for line in lines), text


def test_a_process_out_of_files_logs_a_few_lines_and_answers_once_it_has_them_again(tmp_path):
    log = tmp_path / "watch.log"
    with _watch(log) as (process, port, _):
        open_files = len(os.listdir(f"/proc/{process.pid}/fd"))
        limits = resource.prlimit(process.pid, resource.RLIMIT_NOFILE, (open_files + 1, FILES))
        socks = [_connect(port) for _ in range(50)]  # asyncio cannot accept them: EMFILE, over and over
        assert wait_for(lambda: "Too many open files" in log.read_text(), 5)
        time.sleep(1.5)  # asyncio retries each second
        resource.prlimit(process.pid, resource.RLIMIT_NOFILE, limits)
        _, took = _state(port)
        assert took < 2.5  # the next retry accepts
        for sock in socks:
            sock.close()
    text = log.read_text()
    assert "Traceback" not in text and len(text.splitlines()) < 40, text
    assert "socket.accept() out of system resource: Too many open files; retrying" in text
