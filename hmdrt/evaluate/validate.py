"""Checks of what comes back from elsewhere: a Dask worker's group result or truth, or a partial results file read
back on resume. A value that is not what was asked for is an HmdrtError of one line naming the task, never a
traceback from deep in the tables or plots."""

from __future__ import annotations

import math
import re

import numpy as np

from hmdrt.errors import HmdrtError
from hmdrt.evaluate import provenance
from hmdrt.evaluate.groups import Crops, GroupResult, GroupShape
from hmdrt.evaluate.quality import BANDS

SCALARS = (type(None), bool, int, float, str)
NUMBER = (int, float)
MAYBE_NUMBER = (type(None), int, float)
MAX_METRICS = 64  # a row's metrics (a method's per-frame figures, averaged)
METRIC_NAME = re.compile(r"[a-z][a-z0-9_]{0,63}")
# the columns every row has, by type; the rest (rays by kind, jod) need only be scalars, or tables of them
COLUMNS: dict[str, tuple[type, ...]] = {
    "scene": (str,),
    "profile": (str,),
    "trace": (str,),
    "trace_group": (str,),
    "method": (str,),
    "params": (str,),
    "label": (str,),
    "width": (int,),
    "height": (int,),
    "frames": (int,),
    "warmup_frames": (int,),
    "timing_rounds": (int,),
    "ms_per_frame": NUMBER,
    "cpu_ms_per_frame": NUMBER,
    "speedup_spread": MAYBE_NUMBER,
    "timing_noisy": (bool,),
    "rays_per_frame": (int,),
    "sample_fraction": NUMBER,
    "metrics": (dict,),
    "score_space": (str,),
    "stages_ms": (dict,),
    "options": (dict,),
    "speedup_vs_full": MAYBE_NUMBER,
    "baseline": (type(None), str),
    "speedup_vs_baseline": MAYBE_NUMBER,
    "psnr_fovea_vs_baseline": MAYBE_NUMBER,
    "pareto": (bool,),
    "worker": (type(None), str),
    "group_seconds": NUMBER,
    "date": (str,),
    "commit": (str,),
    "machine": (str,),
    "latency_ms": NUMBER,
    "tracker": (str,),
    "prediction": (str,),
    "gaze_error_p50_deg": NUMBER,
    "gaze_error_p95_deg": NUMBER,
    "gaze_outside_fovea": MAYBE_NUMBER,
    "pose_latency_ms": NUMBER,
    "pose_tracker": (str,),
    "pose_error_p50_deg": NUMBER,
    "pose_error_p95_deg": NUMBER,
    **{f"{score}_{band}": MAYBE_NUMBER for score in ("psnr", "ssim", "flicker") for band in (*BANDS, "image")},
}


def _fail(task: str, why: str) -> HmdrtError:
    return HmdrtError(f"task {task}: {why}".replace("\n", " "))


def _kind(value: object) -> str:
    return type(value).__name__


def truth_image(task: str, value: object, shape: tuple[int, int]) -> np.ndarray:
    """`value` as a truth of (height, width) = shape: a finite float32 array (height, width, 3)."""
    _check_image(task, "the truth", value, shape)
    return value  # type: ignore[return-value]


def group_result(task: str, value: object, expected: GroupShape) -> GroupResult:
    """`value` as the result of a group of that shape (group_shape); an HmdrtError naming `task` where it is
    anything else."""
    ids, labels, shape = expected
    if not isinstance(value, GroupResult):
        raise _fail(task, f"returned a {_kind(value)}, not a group result")
    if not isinstance(value.rows, list) or [_label(task, row) for row in value.rows] != labels:
        raise _fail(task, f"its rows are not one per cell of the group ({len(labels)}: {', '.join(labels)[:200]})")
    for row in value.rows:
        _check_row(task, row, ids)
    crops = value.crops
    if not isinstance(crops, Crops):
        raise _fail(task, f"its crops are a {_kind(crops)}, not Crops")
    if not _same(ids, {"scene": crops.scene, "profile": crops.profile, "trace": crops.trace}):
        raise _fail(task, "its crops are of another group")
    _check_image(task, "the crops' truth", crops.truth, shape)
    if not isinstance(crops.images, dict) or list(crops.images) != labels:
        raise _fail(task, "its crops are not one image per cell of the group")
    for label, image in crops.images.items():
        _check_image(task, f"the crop of {label!r}", image, shape)
    gaze = crops.gaze_xy
    if not (isinstance(gaze, tuple) and len(gaze) == 2 and all(_finite(v) for v in gaze)):
        raise _fail(task, "its crops' gaze pixel is not two finite numbers")
    return value


def _label(task: str, row: object) -> str:
    if not isinstance(row, dict) or not isinstance(row.get("label"), str):
        raise _fail(task, f"a row is a {_kind(row)} without a label, not a row")
    return row["label"]


def _same(ids: dict[str, str], found: dict[str, object]) -> bool:
    """Whether `found` names the group `ids` does (compared as text only: a value may be anything)."""
    return all(isinstance(found[k], str) and found[k] == v for k, v in ids.items())


def _check_row(task: str, row: dict, ids: dict[str, str]) -> None:
    where = f"row {str(row['label'])[:80]!r}"
    for name, kinds in COLUMNS.items():
        if name not in row:
            raise _fail(task, f"{where} has no {name}")
        if not isinstance(row[name], kinds):
            raise _fail(task, f"{where}: {name} is a {_kind(row[name])}")
    for name, value in row.items():
        table = isinstance(value, dict) and all(isinstance(k, str) and _plain(v) for k, v in value.items())
        if not isinstance(name, str) or not (isinstance(value, SCALARS) or table):
            raise _fail(task, f"{where}: column {str(name)[:80]!r} is a {_kind(value)}, not a value")
    if not _same(ids, {k: row[k] for k in ids}):
        raise _fail(task, f"{where} is of another group")
    _check_metrics(task, where, row["metrics"])
    _check_provenance(task, where, row)


def _check_metrics(task: str, where: str, metrics: dict) -> None:
    """At most MAX_METRICS metrics, each a lower-case name (a CSV column metric_NAME) and a finite number."""
    if len(metrics) > MAX_METRICS:
        raise _fail(task, f"{where} has {len(metrics)} metrics, more than {MAX_METRICS}")
    for name, value in metrics.items():
        if not METRIC_NAME.fullmatch(name):
            raise _fail(task, f"{where}: metric {name[:80]!r} is not a lower-case name of at most 64 characters")
        if not _finite(value):
            raise _fail(task, f"{where}: metric {name!r} is not a finite number")


def _check_provenance(task: str, where: str, row: dict) -> None:
    """The date (YYYY-MM-DD), commit (a short hash, "-dirty" or not, or "unknown") and machine (one printable
    line of at most provenance.MAX_TEXT characters) that the tables print."""
    machine = row["machine"]
    if not provenance.DATE.fullmatch(row["date"]):
        raise _fail(task, f"{where}: date {row['date'][:40]!r} is not YYYY-MM-DD")
    if not provenance.COMMIT.fullmatch(row["commit"]):
        raise _fail(task, f"{where}: commit {row['commit'][:60]!r} is not a short hash or 'unknown'")
    if not machine or len(machine) > provenance.MAX_TEXT or not machine.isprintable():
        raise _fail(task, f"{where}: machine is not one printable line of at most {provenance.MAX_TEXT} characters")


def _plain(value: object) -> bool:
    """A scalar or a sequence of scalars (a method option such as kim21's alpha)."""
    return isinstance(value, SCALARS) or (
        isinstance(value, list | tuple) and all(isinstance(v, SCALARS) for v in value)
    )


def _check_image(task: str, what: str, value: object, shape: tuple[int, int]) -> None:
    if not isinstance(value, np.ndarray) or value.dtype != np.float32 or value.shape != (*shape, 3):
        found = f"{value.dtype} {value.shape}" if isinstance(value, np.ndarray) else _kind(value)
        raise _fail(task, f"{what} is {found}, not float32 {(*shape, 3)}")
    if not np.isfinite(value).all():
        raise _fail(task, f"{what} is not finite")


def _finite(value: object) -> bool:
    """A number, not a bool, that a float holds finitely (an int past float's range is not one)."""
    if not isinstance(value, NUMBER) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:
        return False
