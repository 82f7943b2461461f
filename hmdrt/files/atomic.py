"""Files written whole or not at all, and never through what someone else placed at their name: the bytes go to a new
temporary file in the same folder, one this process created (O_EXCL, O_NOFOLLOW: never a file or link that was
there), then replace the target by rename. A crash never leaves a half-written file where a good one was, a failed
write leaves no file, and a link at the name is replaced, its target untouched."""

from __future__ import annotations

import os
import secrets
import tempfile
from collections.abc import Iterable
from pathlib import Path
from typing import BinaryIO

from hmdrt.errors import HmdrtError

NEW_FILE = os.O_WRONLY | os.O_CREAT | os.O_EXCL | os.O_NOFOLLOW | os.O_CLOEXEC
TRIES = 100  # random temporary names tried before giving up (tempfile's TMP_MAX is 10000; 2^32 names each)


def temporary_beside(path: Path, suffix: str = ".tmp", mode: int = 0o666) -> tuple[int, Path]:
    """A new hidden file in `path`'s folder (created if need be), named after it and ending in `suffix`, open for
    writing: its descriptor and path. Its permission bits are `mode` less the umask, as open() would make them."""
    path.parent.mkdir(parents=True, exist_ok=True)
    for _ in range(TRIES):
        tmp = path.with_name(f".{path.name}.{secrets.token_hex(4)}{suffix}")
        try:
            return os.open(tmp, NEW_FILE, mode), tmp
        except FileExistsError:
            continue
    raise FileExistsError(f"no free temporary name beside {path} in {TRIES} tries")


def _write_all(fd: int, data: bytes) -> None:
    view = memoryview(data)
    while view:
        view = view[os.write(fd, view) :]


def write_atomic(
    path: str | Path, data: bytes | Iterable[bytes], mode: int | None = None, replace: bool = True, sync: bool = True
) -> None:
    """Write `data` to `path` atomically, creating its folder; a failure is an HmdrtError naming the path, and
    leaves no file behind.

    mode: the file's permission bits, exactly (the umask does not narrow them; the temporary file is 0600 until
    then); None: 0666 less the umask. replace=False: never overwrite; FileExistsError when the name is taken (also
    by a link), checked and created in one step (a hard link of the written temporary file). sync=False: no fsync,
    for files as many as the frames, which a crash may leave empty but never half written."""
    path = Path(path)
    tmp = None
    try:
        fd, tmp = temporary_beside(path, mode=0o666 if mode is None else 0o600)
        try:
            if mode is not None:
                os.fchmod(fd, mode)
            for chunk in (data,) if isinstance(data, bytes) else data:  # chunks: a large file is never held whole
                _write_all(fd, chunk)
            if sync:
                os.fsync(fd)
        finally:
            os.close(fd)
        if replace:
            os.replace(tmp, path)
            tmp = None
        else:
            os.link(tmp, path)
    except OSError as exc:
        if isinstance(exc, FileExistsError) and exc.filename2 is not None:  # os.link's target, not the folder
            raise
        raise HmdrtError(f"cannot write {path}: {exc.strerror or exc}") from None
    finally:
        if tmp is not None:
            tmp.unlink(missing_ok=True)


def open_replacing(path: str | Path, first: bytes = b"", buffering: int = 0) -> BinaryIO:
    """A new file at `path` holding `first`, open to write on (with buffering as open()'s; 0: every write goes
    straight to the file): made beside it and renamed over whatever had the name, so a link there is replaced, not
    followed, and no file that was there is written into. OSError when it cannot be made."""
    path = Path(path)
    fd, tmp = temporary_beside(path)
    try:
        _write_all(fd, first)
        os.replace(tmp, path)
    except OSError:
        os.close(fd)
        tmp.unlink(missing_ok=True)
        raise
    return os.fdopen(fd, "wb", buffering=buffering)


def check_writable(folder: str | Path) -> None:
    """Create `folder` and write and remove a file in it: an output that cannot be written fails at start, not
    after a run. HmdrtError naming the folder."""
    folder = Path(folder)
    try:
        folder.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError as exc:
        raise HmdrtError(f"cannot write {folder}: {exc.strerror or exc}") from None
