"""Progress on a terminal: a status line rewritten in place on a real pseudo-terminal, nothing on a pipe or a file;
`hmdrt run` shows its live status and `hmdrt render --frames` its progress only when stderr is a terminal."""

import fcntl
import io
import os
import pty
import select
import struct
import termios
import time

import pytest

from hmdrt.cli import main
from hmdrt.console.progress import CLEAR_LINE, StatusLine
from hmdrt.testing import write_config


@pytest.fixture
def terminal():
    """A real pseudo-terminal: the slave end as a text stream (isatty() is True) and a reader of the master end."""
    master, slave = pty.openpty()
    fcntl.ioctl(slave, termios.TIOCSWINSZ, struct.pack("HHHH", 24, 120, 0, 0))  # a new pty is 0 columns wide
    stream = os.fdopen(slave, "w", buffering=1)
    seen = bytearray()

    def read() -> str:
        while select.select([master], [], [], 0.2)[0]:
            try:
                chunk = os.read(master, 65536)
            except OSError:  # the slave end closed
                break
            if not chunk:
                break
            seen.extend(chunk)
        return seen.decode(errors="replace")

    yield stream, read
    stream.close()
    os.close(master)


def test_status_line_rewrites_one_line_on_a_terminal_and_clears_it(terminal):
    stream, read = terminal
    calls = []
    with StatusLine(lambda s: calls.append(s) or f"tick {len(calls)}", stream, interval_s=0.05):
        time.sleep(0.4)
    out = read()
    assert len(calls) >= 3 and calls == sorted(calls)
    assert f"{CLEAR_LINE}tick 1" in out and f"{CLEAR_LINE}tick 3" in out
    assert "\n" not in out  # one line, rewritten in place
    assert out.endswith(CLEAR_LINE)


def test_status_line_writes_nothing_where_output_is_not_a_terminal():
    stream, calls = io.StringIO(), []
    with StatusLine(lambda s: calls.append(s) or "tick", stream, interval_s=0.01):
        time.sleep(0.05)
    assert stream.getvalue() == "" and calls == []


@pytest.mark.usefixtures("own_signals")
def test_run_shows_a_live_status_on_a_terminal_only(tmp_path, monkeypatch, terminal, capsys):
    stream, read = terminal
    config = write_config(tmp_path / "run.toml", method="full", eyes="left")
    monkeypatch.setattr("sys.stderr", stream)
    assert main(["run", str(config), "--duration", "1.5"]) == 0
    out = read()
    assert "VSyncs" in out and "Hz" in out and "misses" in out and "gaze-to-photon p99" in out
    assert out.count(CLEAR_LINE) >= 2  # updated in place, then cleared
    monkeypatch.undo()
    assert main(["run", str(config), "--frames", "3", "--virtual-time"]) == 0
    assert CLEAR_LINE not in "".join(capsys.readouterr())


def test_render_frames_shows_progress_on_a_terminal(tmp_path, monkeypatch, terminal):
    stream, read = terminal
    monkeypatch.setattr("sys.stderr", stream)
    args = "render --scene whitted --profile sim-cpu --method full --resolution 32x24 --frames 3 --out"
    assert main([*args.split(), str(tmp_path)]) == 0
    out = read()
    assert "3/3" in out, repr(out)
