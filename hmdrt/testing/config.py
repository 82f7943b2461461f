"""Small run configs for tests, and free loopback ports. Nothing heavy is imported: the pytest plugin imports this
at start-up (hmdrt.testing.pytest_plugin)."""

from __future__ import annotations

import json
import socket
from pathlib import Path

from hmdrt.files.resources import INSTALLED

ANY_PORT = "tcp://127.0.0.1:*"  # a loopback port the socket picks free when it binds (open to every local user)
TRACE = INSTALLED / "traces" / "synthetic_250hz.jsonl.gz"  # the recorded synthetic gaze and head trace hmdrt ships


def _toml_value(value: object) -> str:
    if isinstance(value, dict):
        return "{" + ", ".join(f"{k} = {_toml_value(v)}" for k, v in value.items()) + "}"
    return json.dumps(value)  # str, int, float, bool and lists of them read the same in TOML


def write_config(
    path: Path,
    method: str | dict = "rrm",
    eyes: str = "both",
    trace: str | Path = TRACE,
    **sections: dict | list,
) -> Path:
    """Write a run config to `path` and return it: 64x72 per eye on sim-cpu (30 Hz), fed by `trace` replayed in a
    loop (device "replay"), its sockets the default private ipc:// ones (in XDG_RUNTIME_DIR: the hmdrt_runtime_dir
    fixture gives each test its own; bus={"ingest": ANY_PORT} puts one on a free loopback port).

    A str `method` names the method ("weier16?frc=small"); a dict adds keys to [method] (name rrm), as in
    {"options": {"group_w": 2}}. `sections` add keys to a section, as in pacing={"render_delay_ms": 45}, or
    replace the drivers list, as in drivers=[{"url": "synthetic://?seed=2"}].
    """
    config: dict[str, dict | list] = {
        "display": {"profile": "sim-cpu", "resolution": "64x72", "eyes": eyes},
        "method": {"name": "rrm", **method} if isinstance(method, dict) else {"name": method},
        "drivers": [{"url": f"replay://{Path(trace).resolve()}?loop=1"}],
    }
    for name, keys in sections.items():
        config[name] = keys if isinstance(keys, list) else {**config.get(name, {}), **keys}
    lines = []
    for name, keys in config.items():
        for table in keys if isinstance(keys, list) else [keys]:
            lines.append(f"[[{name}]]" if isinstance(keys, list) else f"[{name}]")
            lines += [f"{k} = {_toml_value(v)}" for k, v in table.items()]
    path.write_text("\n".join(lines) + "\n")
    return path


def free_port() -> int:
    """A loopback TCP port nobody listens on now (for URLs handed to other processes; a socket of this process
    binds ANY_PORT instead, which cannot race)."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
