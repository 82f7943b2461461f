"""Fuzzing what comes back from a Dask worker: a group result of any shape is either accepted, and then
the results, tables and summary take it, or refused as one HmdrtError line naming the task; never a traceback."""

from __future__ import annotations

import json
import math

import numpy as np
from hypothesis import strategies as st

from hmdrt.errors import HmdrtError
from hmdrt.evaluate import validate
from hmdrt.evaluate.groups import Crops, GroupResult, GroupShape
from hmdrt.evaluate.results import flat, table
from hmdrt.evaluate.runner import Evaluation, summarise
from tests.fuzz.common import MSGPACK_VALUES, fuzz

TASK = "group-0123abcd-run"
IDS = {"scene": "whitted", "profile": "sim-cpu", "trace": "gaze 0,0"}
SHAPE = GroupShape(IDS, ["full", "rrm a"], (3, 4))
TEXT_VALUES = {"trace_group": "gaze 0,0", "params": "full", "score_space": "srgb", "baseline": "full"}
TEXT_VALUES |= {"date": "2026-12-06", "commit": "08396c0-dirty", "machine": "Intel(R) Xeon(R) Processor, 2 CPUs"}


def _row(label: str) -> dict:
    """A row with every column the validator asks for, as the runner writes it."""
    row: dict = {**IDS, "label": label, "method": label.split()[0], "options": {"fovea_deg": 5.0, "alpha": (1.0, 2.0)}}
    for name, kinds in validate.COLUMNS.items():
        if name not in row:
            kind = kinds[-1]
            row[name] = TEXT_VALUES.get(name, "") if kind is str else {"trace": 1.5} if kind is dict else kind(1)
    return {**row, "rays_primary": 12, "worker": "tcp://127.0.0.1:1", "jod": 9.5}


def _valid() -> GroupResult:
    image = np.full((3, 4, 3), 0.5, np.float32)
    crops = Crops(**IDS, truth=image, images={label: image.copy() for label in SHAPE.labels}, gaze_xy=(1.5, 2.0))
    return GroupResult([_row(label) for label in SHAPE.labels], crops)


ARRAYS = st.sampled_from(
    [
        np.zeros((3, 4, 3), np.float64),
        np.zeros((4, 3, 3), np.float32),
        np.full((3, 4, 3), np.nan, np.float32),
        np.zeros((3, 4), np.float32),
        np.zeros(0, np.float32),
    ]
)
JUNK = st.one_of(MSGPACK_VALUES, ARRAYS, st.just(object()), st.just(GroupResult([], None)))  # type: ignore[arg-type]
COLUMN = st.sampled_from([*validate.COLUMNS, "label", "rays_primary", "options", "nonsense"])
METRICS = st.dictionaries(  # of names valid and not, values finite and not
    st.one_of(st.sampled_from(["sample_fraction", "reuse_fraction"]), st.text(max_size=70)),
    st.one_of(MSGPACK_VALUES, st.floats(), st.integers(), st.just(2**1100)),
    max_size=70,
)


def _set_column(result: GroupResult, index: int, column: str, value: object) -> GroupResult:
    result.rows[index % len(result.rows)][column] = value
    return result


def _drop_column(result: GroupResult, index: int, column: str) -> GroupResult:
    result.rows[index % len(result.rows)].pop(column, None)
    return result


def _set_crops(result: GroupResult, field: str, value: object) -> GroupResult:
    setattr(result.crops, field, value)
    return result


EDITS = st.one_of(  # of a result whose rows and crops are still the runner's
    st.builds(lambda i, c, v: lambda r: _set_column(r, i, c, v), st.integers(0, 3), COLUMN, JUNK),
    st.builds(lambda i, c: lambda r: _drop_column(r, i, c), st.integers(0, 3), COLUMN),
    st.builds(lambda i, m: lambda r: _set_column(r, i, "metrics", m), st.integers(0, 3), METRICS),
    st.builds(
        lambda f, v: lambda r: _set_crops(r, f, v),
        st.sampled_from(["scene", "truth", "images", "gaze_xy"]),
        st.one_of(JUNK, st.just({"full": np.zeros((3, 4, 3), np.float32)}), st.just((np.inf, 0.0))),
    ),
)
REPLACEMENTS = st.one_of(  # of the whole, the rows or the crops
    st.just(lambda r: r),
    st.builds(lambda junk: lambda r: junk, JUNK),
    st.builds(lambda rows: lambda r: GroupResult(rows, r.crops), st.lists(JUNK, max_size=3)),
    st.builds(lambda crops: lambda r: GroupResult(r.rows, crops), JUNK),
)


@fuzz(150, edits=st.lists(EDITS, max_size=3), replace=REPLACEMENTS)
def test_a_group_result_is_accepted_whole_or_refused_as_one_line_naming_the_task(edits, replace):
    """validate.group_result of a valid result mutated in any way returns it, and then its rows go into the CSV,
    the JSON, the summary and the table, with one row and one crop per cell of the right shape; or it raises an
    HmdrtError of one line that names the task."""
    value = _valid()
    for edit in edits:
        value = edit(value)
    value = replace(value)
    try:
        result = validate.group_result(TASK, value, SHAPE)
    except HmdrtError as exc:
        assert str(exc).startswith(f"task {TASK}: ") and "\n" not in str(exc)
        return
    assert [r["label"] for r in result.rows] == SHAPE.labels
    assert all(image.shape == (3, 4, 3) for image in [result.crops.truth, *result.crops.images.values()])
    for row in result.rows:
        assert len(row["metrics"]) <= validate.MAX_METRICS
        assert all(math.isfinite(v) and not isinstance(v, bool) for v in row["metrics"].values())
        flat(row)
    json.dumps(result.rows)
    table(Evaluation(result.rows, summarise(result.rows), [result.crops], 0, 0, 1.0, "srgb"))


@fuzz(50, value=st.one_of(JUNK, ARRAYS))
def test_a_truth_is_a_finite_float32_image_or_refused_naming_the_task(value):
    """validate.truth_image accepts exactly a finite float32 (3, 4, 3) array."""
    try:
        image = validate.truth_image("truth-abc", value, (3, 4))
    except HmdrtError as exc:
        assert str(exc).startswith("task truth-abc: ") and "\n" not in str(exc)
        return
    assert image.dtype == np.float32 and image.shape == (3, 4, 3) and np.isfinite(image).all()
