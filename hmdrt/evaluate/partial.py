"""The partial results of `hmdrt eval`: each group's rows and crops in OUT/partial/, one file per group written
atomically the moment the group finishes, so a run that is killed (or loses a worker) keeps every finished cell,
and `--resume OUT` renders only the groups it lacks."""

from __future__ import annotations

import io
import json
import logging
import zipfile
from pathlib import Path

import numpy as np

from hmdrt.errors import HmdrtError
from hmdrt.evaluate import validate
from hmdrt.evaluate.config import EvalConfig
from hmdrt.evaluate.groups import Crops, GroupResult, group_id, group_shape, groups
from hmdrt.files.atomic import write_atomic

FOLDER = "partial"
log = logging.getLogger(__name__)


class PartialResults:
    """The finished groups of one eval (done: group_id -> result). resume: read back those of `config` that OUT
    holds (a file that does not read as its group's result is logged and its group rendered again); else start
    afresh, removing any earlier run's files."""

    def __init__(self, out: str | Path, config: EvalConfig, resume: bool = False):
        self.folder = Path(out) / FOLDER
        self.done: dict[str, GroupResult] = {}
        if not resume:
            for stale in self.folder.glob("*.npz"):
                stale.unlink()
            return
        for key in groups(config):
            gid = group_id(config, key)
            path = self.folder / f"{gid}.npz"
            if not path.exists():
                continue
            try:
                self.done[gid] = validate.group_result(str(path), _read(path), group_shape(config, key))
            except HmdrtError as exc:
                log.warning("%s: rendering the group again", exc)
        log.info("resuming: %d of %d groups finished in %s", len(self.done), len(groups(config)), self.folder)

    def add(self, gid: str, result: GroupResult) -> None:
        """Keep a finished group: its file is written whole or not at all."""
        crops = result.crops
        meta = {"rows": result.rows, "scene": crops.scene, "profile": crops.profile, "trace": crops.trace}
        meta |= {"gaze_xy": list(crops.gaze_xy), "labels": list(crops.images)}
        arrays = {f"image_{i}": image for i, image in enumerate(crops.images.values())}
        buffer = io.BytesIO()
        np.savez(buffer, meta=np.frombuffer(json.dumps(meta).encode(), np.uint8), truth=crops.truth, **arrays)
        write_atomic(self.folder / f"{gid}.npz", buffer.getvalue())
        self.done[gid] = result


def _read(path: Path) -> GroupResult:
    """A group's result as add wrote it; HmdrtError where the file does not read as one."""
    try:
        with np.load(path, allow_pickle=False) as data:
            meta = json.loads(data["meta"].tobytes())
            images = {label: data[f"image_{i}"] for i, label in enumerate(meta["labels"])}
            crops = Crops(meta["scene"], meta["profile"], meta["trace"], data["truth"], images, tuple(meta["gaze_xy"]))
            return GroupResult(meta["rows"], crops)
    except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile) as exc:
        raise HmdrtError(f"{path}: not a group's partial results ({type(exc).__name__})") from None
