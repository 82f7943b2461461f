"""Files written whole or not at all: the bytes go to a temporary file in the same folder, then replace the
target by rename, so a crash never leaves a half-written file where a good one was."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

from hmdrt.errors import HmdrtError


def write_atomic(path: str | Path, data: bytes, mode: int | None = None, replace: bool = True) -> None:
    """Write `data` to `path` atomically, creating its folder; a failure is an HmdrtError naming the path.

    mode: the file's permission bits, exactly (the umask does not narrow them; the temporary file is 0600 until
    then). replace=False: never overwrite; FileExistsError when the file is there, checked and created in one
    step (a hard link of the written temporary file)."""
    path = Path(path)
    tmp = None
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
        with os.fdopen(fd, "wb") as f:
            if mode is not None:
                os.fchmod(f.fileno(), mode)
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
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
            Path(tmp).unlink(missing_ok=True)


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
