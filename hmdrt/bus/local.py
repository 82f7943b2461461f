"""Where the compositor's sockets bind by default (docs/runtime.md, Access): Unix sockets in a runtime folder that
only its user may enter, as Monado's $XDG_RUNTIME_DIR/monado_comp_ipc, so that without keys the whole bus is that
user's alone: no other user can publish gaze to the ingest, read the telemetry or send control commands.

The folder is $XDG_RUNTIME_DIR/hmdrt, or /tmp/hmdrt-UID without XDG_RUNTIME_DIR, created 0700; one that exists
must be a real folder of this user that group and others cannot use, or nothing binds or connects there. Each
compositor binds control-PID.sock, ingest-PID.sock and telemetry-PID.sock in it (the Nth of one process
KIND-PID-N.sock), mode 0600, removed when it closes; a client given no endpoint (`hmdrt status`, `hmdrt driver`)
connects to the one compositor running, or is told to choose. An abstract socket (ipc://@NAME) has no file, so no
permissions guard it: it is refused.
"""

from __future__ import annotations

import itertools
import logging
import os
import re
import stat
import tempfile
from pathlib import Path

from hmdrt.errors import ConfigError

log = logging.getLogger(__name__)

KINDS = {"control": "--control", "ingest": "--bus", "telemetry": "--telemetry"}  # the client option naming each
SOCKET_NAME = re.compile(r"(control|ingest|telemetry)-(\d+)(?:-\d+)?\.sock")
_started = itertools.count(1)  # sets of default sockets bound by this process


def runtime_dir() -> Path:
    """$XDG_RUNTIME_DIR/hmdrt when XDG_RUNTIME_DIR is an absolute path (as the XDG spec asks), else /tmp/hmdrt-UID."""
    xdg = os.environ.get("XDG_RUNTIME_DIR", "")
    if os.path.isabs(xdg):
        return Path(xdg) / "hmdrt"
    return Path(tempfile.gettempdir()) / f"hmdrt-{os.geteuid()}"


def check_private(folder: Path) -> None:
    """ConfigError unless `folder` is a folder (not a link to one) of this user with no permission for others: a
    Unix socket in it can then be reached by this user (and root) alone."""
    try:
        info = os.lstat(folder)
    except OSError as exc:
        raise ConfigError(f"socket folder {folder}: {exc.strerror}") from None
    if not stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"socket folder {folder} is not a folder but a link or a file; remove it")
    if info.st_uid != os.geteuid():
        raise ConfigError(
            f"socket folder {folder} belongs to uid {info.st_uid}, not to this user (uid {os.geteuid()}); "
            "remove it or set XDG_RUNTIME_DIR"
        )
    mode = stat.S_IMODE(info.st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"socket folder {folder} has mode {mode:04o}, open to other users; it must be 0700 (chmod 700 {folder})"
        )


def private_runtime_dir() -> Path:
    """The runtime folder, created 0700 if need be and checked private (ConfigError otherwise)."""
    folder = runtime_dir()
    try:
        folder.mkdir(mode=0o700)
        folder.chmod(0o700)  # the umask may have narrowed it
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot create the socket folder {folder}: {exc.strerror}") from None
    check_private(folder)
    return folder


def check_endpoint(endpoint: str, what: str) -> None:
    """ConfigError for an abstract Unix socket (ipc://@NAME), to bind or to connect to: it has no file, so no
    permissions; any local user could reach it, or bind it first and pose as the compositor. `what` names the
    setting in the message ("bus.control = ipc://@x")."""
    if endpoint.startswith("ipc://@"):
        raise ConfigError(
            f"{what}: an abstract Unix socket has no file permissions, so any local user could reach it; give an "
            "ipc:// path in a folder of yours (mode 0700), or none for the private default"
        )


def ipc_path(endpoint: str) -> Path | None:
    """The socket file of an ipc:// endpoint; None for other transports."""
    transport, _, address = endpoint.partition("://")
    return Path(address) if transport == "ipc" else None


def _sockets(folder: Path) -> list[tuple[str, int, Path]]:
    """(kind, PID, path) of the sockets in the runtime folder."""
    found = ((SOCKET_NAME.fullmatch(path.name), path) for path in folder.iterdir())
    return sorted((match[1], int(match[2]), path) for match, path in found if match)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process now has that PID
        return True
    return True


def bind_endpoints(configured: dict[str, str]) -> dict[str, str]:
    """The endpoints to bind, by kind (control, ingest, telemetry): each configured one as it is (the folder of an
    ipc:// one must be private), and for "" a new socket in the runtime folder, created if need be, numbered alike
    for one compositor. Sockets left there by compositors that died without closing (SIGKILL) are removed."""
    for kind, endpoint in configured.items():
        check_endpoint(endpoint, f"bus.{kind} = {endpoint}")
        path = ipc_path(endpoint)
        if path is not None:
            check_private(path.parent.resolve())
    if all(configured.values()):
        return dict(configured)
    folder = private_runtime_dir()
    for _, pid, path in _sockets(folder):
        if not _alive(pid):
            log.info("removing %s, left by a process that is gone", path)
            path.unlink(missing_ok=True)
    n = next(_started)
    name = f"{os.getpid()}{'' if n == 1 else f'-{n}'}.sock"
    return {kind: endpoint or f"ipc://{folder}/{kind}-{name}" for kind, endpoint in configured.items()}


def find_endpoint(kind: str) -> str:
    """The `kind` endpoint (control, ingest, telemetry) of this user's one running compositor, for a client given
    none; ConfigError when none or several run."""
    option = KINDS[kind]
    folder, running = runtime_dir(), []
    if os.path.lexists(folder):
        check_private(folder)
        running = [f"ipc://{path}" for found, pid, path in _sockets(folder) if found == kind and _alive(pid)]
    if not running:
        raise ConfigError(
            f"no hmdrt compositor of this user runs (no {kind} socket in {folder}); "
            f"give {option} ENDPOINT for one bound elsewhere"
        )
    if len(running) > 1:
        raise ConfigError(f"{len(running)} hmdrt compositors run; choose one with {option}: {', '.join(running)}")
    return running[0]
