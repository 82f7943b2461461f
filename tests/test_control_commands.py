"""The control commands are declared once (hmdrt.compositor.commands): the control socket of a running compositor
and the live page of `hmdrt watch` refuse the same bad commands with the same one line, over real sockets, and a
command the declarations take but the compositor does not (an unknown method) gets the compositor's answer on both."""

from __future__ import annotations

import asyncio
import json

import aiohttp
import pytest

from hmdrt.compositor import commands, control
from hmdrt.compositor.endpoints import request
from hmdrt.testing import compositor, write_config
from hmdrt.watch.access import TOKEN_HEADER
from hmdrt.watch.protocol import BadMessage, parse_command
from hmdrt.watch.server import WatchOptions

from .watching import watch_server

TAKES_SET = 'set takes "method": "name?key=value" and/or "params": {key: value}; '
TAKES_SNAPSHOT = 'snapshot takes "path": a file name such as "shown.png"'

# (what is wrong, the command, the start of the refusal): refused by the declarations, never run
BAD = [
    ("no command", {"command": "status"}, commands.NOT_A_COMMAND),
    ("command not a string", {"cmd": 5}, commands.NOT_A_COMMAND),
    ("unknown command", {"cmd": "explode"}, "unknown command 'explode'; commands: status, stats, set, snapshot"),
    ("missing argument", {"cmd": "set"}, TAKES_SET + "got neither"),
    ("wrong type", {"cmd": "set", "params": "fovea_deg=5"}, TAKES_SET + "params: expected `object`, got `str`"),
    ("wrong type", {"cmd": "set", "method": 5}, TAKES_SET + "method: expected `str`, got `int`"),
    ("wrong type", {"cmd": "snapshot", "path": 42}, TAKES_SNAPSHOT),
    ("wrong value type", {"cmd": "set", "params": {"fovea_deg": [5]}}, TAKES_SET + "a value of params: expected"),
    ("oversized string", {"cmd": "set", "method": "rrm?" + "x" * 200}, TAKES_SET + "method: expected `str` of length"),
    ("oversized value", {"cmd": "set", "params": {"a": "x" * 201}}, TAKES_SET + "a value of params: expected `str` of"),
    ("too many", {"cmd": "set", "params": {f"k{i}": i for i in range(33)}}, TAKES_SET + "params: expected `object` of"),
    ("empty name", {"cmd": "set", "params": {"": 1}}, TAKES_SET + "a key of params: expected `str` of length >= 1"),
    ("out of limits", {"cmd": "snapshot", "path": "../up.png"}, TAKES_SNAPSHOT),
    ("out of limits", {"cmd": "snapshot", "path": "x" * 200 + ".png"}, TAKES_SNAPSHOT),
    ("unknown argument", {"cmd": "status", "verbose": True}, "status takes no arguments; unknown argument 'verbose'"),
    ("unknown argument", {"cmd": "shutdown", "now": 1}, "shutdown takes no arguments; unknown argument 'now'"),
]
# declared right, refused by the compositor: the page forwards them and passes its answer on
ANSWERED = [
    ({"cmd": "set", "method": "nosuch"}, "unknown method 'nosuch'"),
    ({"cmd": "set", "params": {"group_w": 0}}, "group_w"),
    ({"cmd": "set", "params": {"bogus": 1}}, "bogus"),
]


def test_every_declared_command_runs_and_only_those_that_change_the_compositor_need_the_right_to():
    assert set(control.RUN) == set(commands.COMMANDS.values())
    assert control.MUTATING == {"set", "snapshot", "shutdown"}
    for name, command in commands.COMMANDS.items():
        assert commands.parse(commands.to_request(command() if name != "set" else command(method="rrm"))).name() == name


@pytest.mark.parametrize("what, bad, message", BAD, ids=[f"{what}-{i}" for i, (what, *_) in enumerate(BAD)])
def test_a_bad_command_is_one_line_that_names_the_problem(what, bad, message):
    with pytest.raises(commands.BadCommand) as info:
        commands.parse(bad)
    assert str(info.value).startswith(message) and "\n" not in str(info.value) and len(str(info.value)) < 400
    with pytest.raises(BadMessage) as page:
        parse_command(json.dumps({**bad, "id": 7}))  # the page's id is the page's, not the command's
    assert str(page.value) == str(info.value)


async def _through_the_page(url: str, token: str, requests: list[dict]) -> tuple[list[dict], list[dict]]:
    """Each request's reply on the websocket (as sent, with an id) and from POST /api/command."""
    sent, posted = [], []
    async with aiohttp.ClientSession() as session:
        async with session.ws_connect(url + f"ws?token={token}") as ws:
            for number, command in enumerate(requests):
                await ws.send_str(json.dumps({**command, "id": number}))
                while (reply := json.loads((await asyncio.wait_for(ws.receive(), 30)).data))["type"] != "reply":
                    pass
                sent.append(reply)
        for command in requests:
            headers = {TOKEN_HEADER: token}
            async with session.post(url + "api/command", json=command, headers=headers) as response:
                posted.append(await response.json())
    return sent, posted


def test_the_control_socket_and_the_live_page_refuse_the_same_commands_with_the_same_message(tmp_path, context):
    config = write_config(tmp_path / "run.toml", output={"snapshot_dir": "snaps"})
    with compositor(config, context, virtual_time=True) as comp:  # started: its control socket answers
        address = comp.control.address
        direct = [request(address, bad, 10) for _, bad, _ in BAD] + [request(address, bad, 10) for bad, _ in ANSWERED]
        with watch_server(WatchOptions(control=address, port=0, control_timeout_s=10)) as server:
            url, token = server.url(), server.access.token
            sent, posted = asyncio.run(_through_the_page(url, token, [b for _, b, _ in BAD] + [b for b, _ in ANSWERED]))
            refused = server.access.counts()["message"]
        unchanged = request(address, {"cmd": "status"}, 10)

    for reply, (_, _, message) in zip(direct, BAD, strict=False):
        assert reply["ok"] is False and reply["error"].startswith(message), reply
    for reply, (_, message) in zip(direct[len(BAD) :], ANSWERED, strict=True):
        assert reply["ok"] is False and message in reply["error"], reply
    assert not any("\n" in reply["error"] for reply in direct)
    assert [r["error"] for r in sent] == [r["error"] for r in direct]
    assert [r["error"] for r in posted] == [r["error"] for r in direct]
    assert all(r["ok"] is False for r in sent + posted)
    assert [r.get("id") for r in sent[len(BAD) :]] == list(range(len(BAD), len(BAD) + len(ANSWERED)))
    assert refused == 2 * len(BAD)  # the bad ones stopped at the page (websocket and POST), counted
    snapshots = sum(bad.get("cmd") == "snapshot" for _, bad, _ in BAD)
    assert unchanged["security"]["snapshots_refused"] == snapshots  # only those sent to the socket itself
    assert unchanged["method"] == "rrm" and unchanged["params"]["group_w"] == 3
