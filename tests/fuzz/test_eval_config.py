"""Fuzzing the eval config's method entries (labels, compare_to and scenes in any combination load into a config
whose every baseline names one cell) and its traces' latency and tracker settings, or fail as one ConfigError
line."""

from __future__ import annotations

import collections
from pathlib import Path

import msgspec
from hypothesis import strategies as st

from hmdrt.errors import ConfigError
from hmdrt.evaluate.config import EvalConfig, load_eval_config
from hmdrt.tracking.model import Tracker
from hmdrt.tracking.presets import PRESETS
from tests.fuzz.common import fuzz, scratch
from tests.fuzz.test_toml import toml_value

SCENES = ["whitted", "tunnel_maps"]
LABELS = st.sampled_from(["", "full", "rrm", "a", "a fovea_deg=5.0", "A", "a\nb", "rrm?fovea_deg=5.0"])

COMMON = {"label": LABELS, "compare_to": LABELS, "scenes": st.lists(st.sampled_from(SCENES), max_size=2, unique=True)}
ENTRIES = st.one_of(
    st.fixed_dictionaries({"name": st.just("full")}, optional=COMMON),
    st.fixed_dictionaries({"name": st.just("rrm")}, optional={**COMMON, "sweep": st.just({"fovea_deg": [5.0, 10.0]})}),
    st.fixed_dictionaries({"name": st.just("regular")}, optional={**COMMON, "options": st.just({"spp": 2})}),
)


def _document(methods: list[dict], space: str) -> str:
    lines = [f"scenes = {toml_value(SCENES)}", f"score_space = {toml_value(space)}"]
    for m in methods:
        lines += ["[[methods]]", *(f"{k} = {toml_value(v)}" for k, v in m.items())]
    return "\n".join(lines) + "\n"


@fuzz(100, methods=st.lists(ENTRIES, min_size=1, max_size=5), space=st.sampled_from(["srgb", "linear", "sRGB"]))
def test_eval_config_baselines_each_name_one_cell_or_the_config_is_a_one_line_error(methods, space):
    """load_eval_config of method entries with any labels, compare_to and scenes is an EvalConfig whose every
    compare_to names exactly one cell on each scene the entry runs on, or a ConfigError of one line."""
    path = scratch("eval-methods.toml", _document(methods, space))
    try:
        config = load_eval_config(path)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    assert isinstance(config, EvalConfig) and config.score_space in ("srgb", "linear")
    for scene in config.scenes:
        cells = config.cells(scene)
        labels = collections.Counter(c.label for c in cells)
        assert all(labels[c.compare_to] == 1 for c in cells if c.compare_to)


RECORDING = Path(__file__).parent.parent / "data" / "traces" / "raccoons.asc"  # EyeLink at 1000 Hz
NUMBERS = st.one_of(
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**6), 10**6), st.sampled_from([0.0, 1000.0])
)
TRACKER_TABLES = st.dictionaries(
    st.sampled_from(["accuracy_deg", "precision_deg", "rate_hz", "loss_rate", "loss_ms", "noise"]), NUMBERS, max_size=5
)
TRACE_SETTINGS = st.fixed_dictionaries(
    {},
    optional={
        "latency_ms": NUMBERS,
        "tracker": st.one_of(st.sampled_from([*PRESETS, "tobii", ""]), TRACKER_TABLES, st.integers()),
        "prediction": st.sampled_from(["off", "default", "kalman", ""]),
    },
)


@fuzz(100, settings=st.lists(TRACE_SETTINGS, min_size=1, max_size=3), recorded=st.booleans())
def test_eval_trace_latency_and_tracker_load_in_range_or_fail_as_one_line(settings, recorded):
    """load_eval_config of traces with any latency, tracker (preset, table, anything) and prediction is an
    EvalConfig whose every trace's latency lies in [0, 1000] ms and whose tracker is a valid one no faster than
    its recording, or a ConfigError of one line."""
    source = f"path = {toml_value(str(RECORDING))}" if recorded else "builtin = true"
    lines = []
    for entry in settings:
        lines += ["[[traces]]", source, *(f"{k} = {toml_value(v)}" for k, v in entry.items())]
    path = scratch("eval-traces.toml", "\n".join(lines) + "\n")
    try:
        config = load_eval_config(path)
    except ConfigError as exc:
        assert "\n" not in str(exc)
        return
    for trace in config.traces:
        tracker = trace.tracker_model
        assert 0.0 <= trace.latency_ms <= 1000.0 and trace.prediction in ("off", "default")
        assert isinstance(tracker, Tracker) and msgspec.convert(msgspec.to_builtins(tracker), Tracker) == tracker
        assert not recorded or tracker.period_ns is None or tracker.rate_hz <= 1000.0 * 1.01  # inf: every sample
