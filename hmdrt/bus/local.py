"""Where the control socket binds by default (docs/runtime.md, Access): a Unix socket in a runtime folder that only its
user may enter, as Monado's $XDG_RUNTIME_DIR/monado_comp_ipc, so control without keys is control by that user.

The folder is $XDG_RUNTIME_DIR/hmdrt, or /tmp/hmdrt-UID without XDG_RUNTIME_DIR, created 0700; one that exists
must be a real folder of this user that group and others cannot use, or nothing binds or connects there. Each
compositor binds control-PID.sock in it (the Nth of one process control-PID-N.sock), mode 0600, removed when it
closes; a client given no endpoint (`hmdrt status`) connects to the one compositor running, or is told to choose.
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

SOCKET_NAME = re.compile(r"control-(\d+)(?:-\d+)?\.sock")
_started = itertools.count(1)  # default control sockets bound by this process


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
        raise ConfigError(f"control socket folder {folder}: {exc.strerror}") from None
    if not stat.S_ISDIR(info.st_mode):
        raise ConfigError(f"control socket folder {folder} is not a folder but a link or a file; remove it")
    if info.st_uid != os.geteuid():
        raise ConfigError(
            f"control socket folder {folder} belongs to uid {info.st_uid}, not to this user (uid {os.geteuid()}); "
            "remove it or set XDG_RUNTIME_DIR"
        )
    mode = stat.S_IMODE(info.st_mode)
    if mode & 0o077:
        raise ConfigError(
            f"control socket folder {folder} has mode {mode:04o}, open to other users; it must be 0700 "
            f"(chmod 700 {folder})"
        )


def ipc_path(endpoint: str) -> Path | None:
    """The socket file of an ipc:// endpoint; None for other transports."""
    transport, _, address = endpoint.partition("://")
    return Path(address) if transport == "ipc" else None


def _sockets(folder: Path) -> list[tuple[int, Path]]:
    """(PID, path) of the control sockets in the runtime folder."""
    found = ((SOCKET_NAME.fullmatch(path.name), path) for path in folder.iterdir())
    return sorted((int(match[1]), path) for match, path in found if match)


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # another user's process now has that PID
        return True
    return True


def bind_endpoint(configured: str) -> str:
    """The compositor's control endpoint: `configured` ([bus] control; the folder of an ipc:// one must be private),
    or for "" a new socket in the runtime folder, created if need be. Sockets left there by compositors that died
    without closing (SIGKILL) are removed."""
    if configured:
        path = ipc_path(configured)
        if path is not None:
            check_private(path.parent.resolve())
        return configured
    folder = runtime_dir()
    try:
        folder.mkdir(mode=0o700)
        folder.chmod(0o700)  # the umask may have narrowed it
    except FileExistsError:
        pass
    except OSError as exc:
        raise ConfigError(f"cannot create the control socket folder {folder}: {exc.strerror}") from None
    check_private(folder)
    for pid, path in _sockets(folder):
        if not _alive(pid):
            log.info("removing %s, left by a compositor that is gone", path)
            path.unlink(missing_ok=True)
    n = next(_started)
    return f"ipc://{folder}/control-{os.getpid()}{'' if n == 1 else f'-{n}'}.sock"


def find_control() -> str:
    """The control endpoint of this user's one running compositor, for a client given none; ConfigError when none
    or several run."""
    folder, running = runtime_dir(), []
    if os.path.lexists(folder):
        check_private(folder)
        running = [f"ipc://{path}" for pid, path in _sockets(folder) if _alive(pid)]
    if not running:
        raise ConfigError(
            f"no hmdrt compositor of this user runs (no control socket in {folder}); "
            "give --control ENDPOINT for one bound elsewhere"
        )
    if len(running) > 1:
        raise ConfigError(f"{len(running)} hmdrt compositors run; choose one with --control: {', '.join(running)}")
    return running[0]
