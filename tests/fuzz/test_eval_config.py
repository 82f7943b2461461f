"""Fuzzing the eval config's method entries: labels, compare_to and scenes in any combination load
into a config whose every baseline names one cell, or fail as one ConfigError line."""

from __future__ import annotations

import collections

from hypothesis import strategies as st

from hmdrt.errors import ConfigError
from hmdrt.evaluate.config import EvalConfig, load_eval_config
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
