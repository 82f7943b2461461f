"""Who may control a compositor without keys (README "Access"), over real sockets: the default control
socket is ipc:// in a runtime folder of this user's only, which `hmdrt status` finds; a folder that others could
use is refused; tcp:// without [security] only reads; and a snapshot lands in [output] snapshot_dir by file name,
never elsewhere and never over a file, its refusals counted."""

from __future__ import annotations

import os
import re
import signal
import stat
from pathlib import Path

import pytest
from PIL import Image

from hmdrt.cli import main
from hmdrt.compositor.config import load_config
from hmdrt.compositor.daemon import Compositor
from hmdrt.compositor.endpoints import request
from hmdrt.errors import ConfigError
from hmdrt.testing import ANY_PORT, compositor, run_bounded, write_config

from . import compositor_helpers as runtime
from .helpers import reap

NOBODY = 65534


def socket_file(endpoint: str) -> Path:
    assert endpoint.startswith("ipc://"), endpoint
    return Path(endpoint.removeprefix("ipc://"))


def status_line(capsys) -> tuple[int, str, str]:
    """`hmdrt status` with no --control: its exit code, stdout and stderr."""
    code = main(["status", "--timeout", "10"])
    out, err = capsys.readouterr()
    return code, out.strip(), err.strip()


# --- the default control socket -----------------------------------------------------------------------------------


def test_default_control_is_a_private_ipc_socket_that_status_finds_and_exit_removes(tmp_path, runtime_dir, capsys):
    """`hmdrt run` in its own process binds control-PID.sock, 0600, in RUNTIME/hmdrt, 0700, both this user's;
    `hmdrt status` finds it without --control and may change things through it; SIGTERM removes it."""
    process = runtime.start_run(write_config(tmp_path / "run.toml"), tmp_path / "report.json")
    try:
        line = runtime.readline(process, 60)
        folder = runtime_dir / "hmdrt"
        endpoint = line.rsplit("control ", 1)[1].strip()
        assert endpoint == f"ipc://{folder}/control-{process.pid}.sock", line
        folder_info, socket_info = os.lstat(folder), os.lstat(socket_file(endpoint))
        assert stat.S_ISDIR(folder_info.st_mode) and stat.S_IMODE(folder_info.st_mode) == 0o700
        assert stat.S_ISSOCK(socket_info.st_mode) and stat.S_IMODE(socket_info.st_mode) == 0o600
        assert folder_info.st_uid == socket_info.st_uid == os.geteuid()

        code, out, err = status_line(capsys)
        assert code == 0, err
        assert out.startswith("rrm") and out.endswith("; access: this user")
        reply = request(endpoint, {"cmd": "set", "params": {"group_w": 2}}, 10)
        assert reply["ok"] and "group_w=2" in reply["method"]  # local control, by this user only
        process.send_signal(signal.SIGTERM)
        _, stderr = process.communicate(timeout=60)
    finally:
        reap(process)
    assert process.returncode == 0, stderr
    assert list(folder.iterdir()) == []  # the socket went with the compositor
    code, _, err = status_line(capsys)
    assert code == 1 and "no hmdrt compositor of this user runs" in err


def test_two_compositors_do_not_collide_and_status_asks_which(tmp_path, runtime_dir, context, capsys):
    """Two compositors of one process bind sockets of their own; `hmdrt status` will not guess between them; a
    socket left by a compositor that died without closing is passed over by status and removed by the next start."""
    folder = runtime_dir / "hmdrt"
    folder.mkdir(mode=0o700)
    stale = folder / "control-999999999.sock"  # no process has that PID
    stale.touch()
    config = write_config(tmp_path / "two.toml")
    with compositor(config, context) as first:
        assert not stale.exists()
        with compositor(config, context) as second:
            endpoints = [first.control.address, second.control.address]
            assert len(set(endpoints)) == 2 and all(socket_file(e).parent == folder for e in endpoints)
            assert all(f"/control-{os.getpid()}" in e for e in endpoints)
            code, _, err = status_line(capsys)
            assert code == 1 and "2 hmdrt compositors run; choose one with --control" in err
            assert all(e in err for e in endpoints)
            assert main(["status", "--control", endpoints[1], "--json"]) == 0
            assert '"control": "' + endpoints[1] in capsys.readouterr().out
        assert not socket_file(endpoints[1]).exists()
        stale.touch()  # passed over by status: its PID is not running
        code, out, err = status_line(capsys)
        assert code == 0 and out.endswith("; access: this user"), err


def give_away(folder: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Make folder another user's: really as root, else by making this process believe it is someone else."""
    if os.geteuid() == 0:
        os.chown(folder, NOBODY, NOBODY)
    else:
        owner = os.geteuid() + 1
        monkeypatch.setattr(os, "geteuid", lambda: owner)


@pytest.mark.parametrize(
    "spoil, message",
    [
        (lambda folder, _: folder.chmod(0o755), "has mode 0755, open to other users; it must be 0700 (chmod 700"),
        (lambda folder, _: folder.chmod(0o770), "has mode 0770, open to other users"),
        (give_away, "not to this user"),
        (lambda folder, _: (folder.rmdir(), folder.symlink_to(folder.parent)), "is not a folder but a link"),
    ],
    ids=["world-readable", "group-writable", "another-owner", "a-link"],
)
def test_a_runtime_folder_others_could_use_is_refused(
    tmp_path, runtime_dir, context, capsys, monkeypatch, spoil, message
):
    folder = runtime_dir / "hmdrt"
    folder.mkdir(mode=0o700)
    spoil(folder, monkeypatch)
    with pytest.raises(ConfigError, match=re.escape(message)):
        Compositor(load_config(write_config(tmp_path / "r.toml")), context=context)
    assert not list(runtime_dir.glob("hmdrt/*.sock"))  # nothing bound there
    code, _, err = status_line(capsys)  # nor does a client trust a socket in it
    assert code == 1 and err.startswith(f"hmdrt: error: socket folder {folder}") and message in err


def test_an_ipc_endpoint_in_a_folder_others_can_use_is_refused(tmp_path, context):
    open_folder = tmp_path / "open"
    open_folder.mkdir(mode=0o777)
    open_folder.chmod(0o777)
    config = write_config(tmp_path / "ipc.toml", bus={"control": f"ipc://{open_folder}/c.sock"})
    with pytest.raises(ConfigError, match="has mode 0777, open to other users"):
        Compositor(load_config(config), context=context)


# --- tcp:// -------------------------------------------------------------------------------------------------------


def test_tcp_control_without_security_answers_reads_and_refuses_changes(tmp_path, context, capsys):
    """Any local user can reach loopback tcp: without [security] it answers status and stats, and refuses and
    counts set, snapshot and shutdown (with [security], tests/test_security.py)."""
    config = write_config(tmp_path / "tcp.toml", bus={"control": ANY_PORT})
    with compositor(config, context) as comp:  # started, not running: the control socket answers
        control = comp.control.address
        assert control.startswith("tcp://127.0.0.1:")
        assert request(control, {"cmd": "status"})["ok"] and request(control, {"cmd": "stats"})["ok"]
        for command in (
            {"cmd": "set", "params": {"group_w": 2}},
            {"cmd": "snapshot", "path": "a.png"},
            {"cmd": "shutdown"},
        ):
            reply = request(control, command)
            assert not reply["ok"] and "refused on a tcp:// control socket without [security]" in reply["error"]
        assert comp.security() == {
            "curve": False,
            "open_to_local_users": ["control"],
            "commands_refused": 3,
            "snapshots_refused": 0,
        }
        assert not comp.stop.is_set() and "group_w=2" not in comp.session.spec and not (tmp_path / "a.png").exists()
        assert main(["status", "--control", control]) == 0
        assert (
            capsys.readouterr()
            .out.strip()
            .endswith("; access: any local user on control (loopback tcp://), control read-only")
        )


# --- snapshots ----------------------------------------------------------------------------------------------------


def test_snapshots_land_in_the_snapshot_folder_by_name_only_and_refusals_are_counted(tmp_path, context):
    config = write_config(tmp_path / "snap.toml", output={"snapshot_dir": "snaps"})
    folder, outside = tmp_path / "snaps", tmp_path / "outside"
    folder.mkdir()
    outside.mkdir()
    (folder / "taken.png").write_bytes(b"keep")
    (folder / "link.png").symlink_to(outside / "target.png")  # dangling: writing through it would land outside
    with compositor(config, context, frames=3, virtual_time=True) as comp:
        run_bounded(comp)
        control = comp.control.address

        def snapshot(path: object) -> dict:
            return request(control, {"cmd": "snapshot", "path": path})

        reply = snapshot("shown.png")
        assert reply == {"ok": True, "path": str(folder / "shown.png")}
        with Image.open(folder / "shown.png") as image:
            assert image.format == "PNG" and image.size == (2 * 64, 72)

        bad_names = [
            "../../../anywhere.png",
            "../outside/up.png",
            "sub/x.png",
            "a\\b.png",
            str(outside / "absolute.png"),
            "/tmp/absolute.png",
            "..png",
            ".hidden.png",
            "shown.jpg",
            "x.png\n",
            "",
            42,
            "x" * 200 + ".png",
        ]
        for name in bad_names:
            reply = snapshot(name)
            assert not reply["ok"] and reply["error"].startswith('snapshot takes "path": a file name'), (name, reply)
        for name in ("shown.png", "taken.png", "link.png"):
            reply = snapshot(name)
            assert not reply["ok"] and f"{folder / name} exists; a snapshot never replaces a file" in reply["error"]
        refused = len(bad_names) + 3
        assert request(control, {"cmd": "status"})["security"]["snapshots_refused"] == refused
        assert comp.summary()["security"] == {
            "curve": False,
            "open_to_local_users": [],
            "commands_refused": 0,
            "snapshots_refused": refused,
        }
    assert (folder / "taken.png").read_bytes() == b"keep"
    assert sorted(p.name for p in folder.iterdir()) == ["link.png", "shown.png", "taken.png"]
    assert list(outside.iterdir()) == [] and not Path("/tmp/absolute.png").exists()
    assert not (folder / "../../../anywhere.png").resolve().exists()


def test_the_snapshot_folder_is_relative_to_the_config_and_defaults_to_where_the_run_started(tmp_path, monkeypatch):
    config = write_config(tmp_path / "c.toml", output={"snapshot_dir": "snaps"})
    assert load_config(config).output.snapshot_dir == str(tmp_path / "snaps")
    started = tmp_path / "started"
    started.mkdir()
    monkeypatch.chdir(started)
    assert load_config(write_config(tmp_path / "d.toml")).output.snapshot_dir == str(started)
