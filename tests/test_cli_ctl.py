"""`hmdrt ctl COMMAND [ARG=VALUE ...]` against a running compositor's real control socket: it finds the socket as
`hmdrt status` does, types each VALUE by the command's declaration, prints the reply, and refuses a bad command
before sending it with the control socket's own message."""

from __future__ import annotations

import json
import subprocess
import sys

import pytest

from hmdrt.cli import main
from hmdrt.compositor import commands
from hmdrt.compositor.endpoints import request
from hmdrt.testing import compositor, run_bounded, write_config


def ctl(capsys, *args: str) -> tuple[int, str, str]:
    code = main(["ctl", *args])
    out, err = capsys.readouterr()
    return code, out, err


def test_ctl_sends_typed_commands_and_prints_the_replies(tmp_path, context, capsys):
    config = write_config(tmp_path / "ctl.toml", output={"snapshot_dir": "snaps"})
    (tmp_path / "snaps").mkdir()
    with compositor(config, context, frames=3, virtual_time=True) as comp:
        run_bounded(comp)  # a frame shown to snapshot; the control socket answers on
        code, out, err = ctl(capsys, "status")  # found without --control: this user's one compositor
        assert code == 0, err
        assert json.loads(out)["endpoints"]["control"] == comp.control.address

        code, out, err = ctl(capsys, "--control", comp.control.address, "set", "params.group_w=2", "params.bogus=x")
        assert code == 1 and out == "" and "bogus" in err and err.count("\n") == 1, err  # the compositor's answer
        code, out, err = ctl(capsys, "set", "params.group_w=2")  # 2: a number, as JSON reads it
        assert code == 0 and "group_w=2" in json.loads(out)["method"], err
        code, out, err = ctl(capsys, "set", 'params={"group_w": 3}', "method=rrm?fovea_deg=12")
        assert code == 0 and json.loads(out)["method"] == "rrm?fovea_deg=12.0", out  # group_w 3: rrm's default

        code, out, err = ctl(capsys, "snapshot")  # no name: one of the time
        path = json.loads(out)["path"]
        assert code == 0 and path.startswith(str(tmp_path / "snaps" / "snapshot-")) and path.endswith(".png")
        code, out, err = ctl(capsys, "snapshot", "path=shown.png")
        assert code == 0 and json.loads(out) == {"path": str(tmp_path / "snaps" / "shown.png")}
        code, out, err = ctl(capsys, "snapshot", "path=shown.png")  # the compositor's refusal, as it gave it
        shown = tmp_path / "snaps" / "shown.png"  # (the compositor of this process logs its refusal on stderr too)
        assert code == 1 and err.endswith(
            f"\nhmdrt: error: snapshot: {shown} exists; a snapshot never replaces a file\n"
        )

        printed = subprocess.run(
            [sys.executable, "-m", "hmdrt", "ctl", "--control", comp.control.address, "shutdown"],
            capture_output=True,
            text=True,
            timeout=120,
        )
        assert printed.returncode == 0 and printed.stdout == "ok\n", printed.stderr
        assert comp.stop.is_set()


@pytest.mark.parametrize(
    "words, sent",
    [
        (["explode"], {"cmd": "explode"}),
        (["set"], {"cmd": "set"}),
        (["set", "method=5"], None),  # a string argument takes the text: "5", which the compositor would refuse
        (["set", "params=fovea_deg"], "params=fovea_deg: not JSON"),
        (["set", "params.fovea_deg=[5]"], {"cmd": "set", "params": {"fovea_deg": [5]}}),
        (["set", "method=" + "x" * 201], {"cmd": "set", "method": "x" * 201}),
        (["snapshot", "path=../up.png"], {"cmd": "snapshot", "path": "../up.png"}),
        (["snapshot", "path=a.png", "size=2"], {"cmd": "snapshot", "path": "a.png", "size": 2}),
        (["status", "verbose"], "'verbose' is not ARG=VALUE"),
        (["status", "method.x=1"], {"cmd": "status", "method": {"x": 1}}),
        (["set", "method.x=1"], 'set takes "method": "name?key=value" and/or "params": {key: value}; method is not'),
    ],
)
def test_a_bad_command_is_refused_before_it_is_sent_with_the_control_sockets_message(tmp_path, capsys, words, sent):
    nowhere = f"ipc://{tmp_path}/none.sock"  # nothing answers there: the refusal is ctl's own
    code, out, err = ctl(capsys, "--control", nowhere, "--timeout", "0.5", *words)
    if sent is None:
        assert code == 1 and "no hmdrt compositor answered" in err
        return
    assert code == 1 and out == "" and err.count("\n") == 1 and err.startswith("hmdrt: error: "), err
    if isinstance(sent, str):
        assert sent in err
        return
    with pytest.raises(commands.BadCommand) as socket_says:
        commands.parse(sent)  # what the control socket and the live page answer to that request
    assert err == f"hmdrt: error: {socket_says.value}\n"


def test_ctl_without_a_compositor_or_with_a_bad_timeout_is_one_line(tmp_path, capsys):
    code, _, err = ctl(capsys, "status")
    assert code == 1 and "no hmdrt compositor of this user runs" in err and err.count("\n") == 1
    with pytest.raises(SystemExit) as exited:
        main(["ctl", "--timeout", "0", "status"])
    assert exited.value.code == 2 and "argument --timeout: must be positive, got 0" in capsys.readouterr().err


def test_the_same_refusal_from_the_socket_and_from_ctl(tmp_path, context, capsys):
    with compositor(write_config(tmp_path / "same.toml"), context) as comp:
        for words, bad in (([], {"cmd": "set"}), (["params=[1]"], {"cmd": "set", "params": [1]})):
            code, _, err = ctl(capsys, "--control", comp.control.address, "set", *words)
            assert code == 1 and err == f"hmdrt: error: {request(comp.control.address, bad)['error']}\n"
