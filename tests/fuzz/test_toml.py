"""Fuzzing bytes and text from outside, TOML configs, profiles and scene descriptions:
bad input never gets in, never crashes."""

from __future__ import annotations

import json
import math
from pathlib import Path

import msgspec
import pytest
from hypothesis import strategies as st

from hmdrt.compositor.config import RunConfig, load_config
from hmdrt.errors import ConfigError, SceneError
from hmdrt.evaluate.config import EvalConfig, load_eval_config
from hmdrt.files.configfile import MAX_TOML_BYTES, read_toml
from hmdrt.optics.profiles import HmdProfile, get_profile
from hmdrt.scene.files import SceneFile, load_scene_file
from hmdrt.scene.model import Scene
from tests.fuzz.common import (
    error_names_file,
    fuzz,
    mutations,
    scratch,
    sparse,
)


def toml_value(v) -> str:
    """A TOML value (inline tables and arrays) for a Python value."""
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
    if isinstance(v, str):
        return json.dumps(v, ensure_ascii=False)
    if isinstance(v, list):
        return "[" + ", ".join(map(toml_value, v)) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{json.dumps(k, ensure_ascii=False)} = {toml_value(x)}" for k, x in v.items()) + "}"
    return v.isoformat()


def toml_document(doc: dict) -> str:
    return "".join(f"{json.dumps(k, ensure_ascii=False)} = {toml_value(v)}\n" for k, v in doc.items())


def struct_keys(*types) -> list[str]:
    """Every field name of msgspec structs and the structs they hold, with tag names and values."""
    keys, todo = set(), list(types)
    while todo:
        t = todo.pop()
        info = msgspec.inspect.type_info(t)
        stack = [info]
        while stack:
            i = stack.pop()
            if isinstance(i, msgspec.inspect.StructType):
                if i.tag_field:
                    keys |= {i.tag_field, str(i.tag)}
                keys |= {f.name for f in i.fields}
                stack += [f.type for f in i.fields]
            elif isinstance(i, msgspec.inspect.UnionType):
                stack += list(i.types)
            elif isinstance(i, msgspec.inspect.ListType | msgspec.inspect.DictType):
                stack += [i.item_type] if hasattr(i, "item_type") else [i.key_type, i.value_type]
            elif isinstance(i, msgspec.inspect.TupleType | msgspec.inspect.VarTupleType):
                stack += list(getattr(i, "item_types", [getattr(i, "item_type", None)]))
    return sorted(k for k in keys if k)


TOML_SCALARS = st.one_of(
    st.booleans(),
    st.integers(-(2**70), 2**70),
    st.floats(),
    st.floats(-100, 100),
    st.text(max_size=10),
    st.sampled_from(["", "left", "rrm", "full", "sim-cpu", "whitted", "0,0", "640x720", "synthetic://?seed=1"]),
    st.dates(),
)


def toml_docs(*types) -> st.SearchStrategy[dict]:
    """TOML documents whose keys are the config types' own field and tag names (and a stray one), holding
    arbitrary values, nested tables and arrays of tables."""
    keys = st.sampled_from([*struct_keys(*types), "stray"])
    values = st.recursive(
        TOML_SCALARS,
        lambda inner: st.lists(inner, max_size=3) | st.dictionaries(keys, inner, max_size=5),
        max_leaves=16,
    )
    return st.dictionaries(keys, values, max_size=8)


@fuzz(150, doc=toml_docs(RunConfig))
def test_run_config_of_any_toml_is_a_run_config_or_config_error(doc):
    """load_config of any document with the config's own keys is a RunConfig or a ConfigError naming the file."""
    path = scratch("run.toml", toml_document(doc))
    try:
        assert isinstance(load_config(path), RunConfig)
    except ConfigError as exc:
        error_names_file(exc, path)


@pytest.mark.parametrize("value", ["[]", "1", '"x"'])
def test_run_config_whose_run_is_not_a_table_is_a_config_error(value):
    """A config whose `run` is an array, a number or a string is a ConfigError naming the file."""
    path = scratch("run-not-table.toml", f"run = {value}\n")
    with pytest.raises(ConfigError, match="run-not-table.toml"):
        load_config(path)


@fuzz(100, doc=toml_docs(EvalConfig))
def test_eval_config_of_any_toml_is_an_eval_config_or_config_error(doc):
    """load_eval_config of any document with the config's own keys is an EvalConfig, a ConfigError, or for a scene
    it cannot make (scenes = [""], a built-in past its size limit) the SceneError hmdrt run and eval report in one
    line."""
    path = scratch("eval.toml", toml_document(doc))
    try:
        assert isinstance(load_eval_config(path), EvalConfig)
    except (ConfigError, SceneError):
        pass


@fuzz(150, doc=toml_docs(HmdProfile))
def test_profile_of_any_toml_is_a_profile_or_config_error(doc):
    """A .toml profile of any document with the profile's keys is an HmdProfile or a ConfigError naming the file."""
    path = scratch("profile.toml", toml_document(doc))
    try:
        assert isinstance(get_profile(str(path)), HmdProfile)
    except ConfigError as exc:
        error_names_file(exc, path)


@fuzz(100, doc=toml_docs(SceneFile))
def test_scene_description_of_any_toml_is_a_scene_or_scene_error(doc):
    """A TOML scene description of any document with the scene's keys (objects, materials, textures, lights) is a
    Scene or a SceneError naming the file."""
    path = scratch("scene.toml", toml_document(doc))
    try:
        assert isinstance(load_scene_file(path), Scene)
    except SceneError as exc:
        error_names_file(exc, path)


TOML_LOADERS = {
    "config": (lambda p: read_toml(p), ConfigError),
    "run": (lambda p: load_config(p), ConfigError),
    "eval": (lambda p: load_eval_config(p), ConfigError),
    "profile": (lambda p: get_profile(str(p)), ConfigError),
    "scene": (lambda p: load_scene_file(p), SceneError),
}
TOML_SEED = (Path(__file__).parents[2] / "configs" / "default.toml").read_bytes()


@fuzz(
    200,
    loader=st.sampled_from(sorted(TOML_LOADERS)),
    data=st.one_of(st.binary(max_size=300), mutations(TOML_SEED), st.text(max_size=200).map(str.encode)),
)
def test_any_bytes_as_toml_load_or_raise_the_loaders_error_naming_the_file(loader, data):
    """Arbitrary bytes, non-UTF-8 and mutations of configs/default.toml given to every TOML loader give a value
    or the loader's error (ConfigError, SceneError); a syntax error names the file and the line."""
    load, error = TOML_LOADERS[loader]
    path = scratch(f"{loader}.toml", data)
    try:
        load(path)
    except error as exc:
        if "not valid TOML" in str(exc) and "nested" not in str(exc) and "codec" not in str(exc):
            error_names_file(exc, path)
            assert "line" in str(exc) or "end of document" in str(exc)


@pytest.mark.parametrize("loader", sorted(TOML_LOADERS))
@pytest.mark.parametrize("nesting", ["[" * 600 + "]" * 600, "{a = " * 600 + "1" + "}" * 600])
def test_toml_nested_deeper_than_the_parser_follows_is_the_loaders_error(loader, nesting):
    """Regression: a value nested a few hundred arrays or inline tables deep (1 KB) raised RecursionError out
    of every TOML loader; now it is their own error, naming the file."""
    load, error = TOML_LOADERS[loader]
    path = scratch(f"deep-{loader}.toml", f"name = {nesting}\n")
    with pytest.raises(error, match="nested too deeply") as info:
        load(path)
    error_names_file(info.value, path)


@pytest.mark.parametrize("loader", sorted(TOML_LOADERS))
def test_toml_files_are_size_capped_before_reading(loader):
    """A TOML file over MAX_TOML_BYTES (sparse: nothing to read) is refused by size. Regression: configs and
    profiles were read whole whatever their size, and /dev/zero (size 0) was read without end."""
    load, error = TOML_LOADERS[loader]
    path = sparse(f"big-{loader}.toml", MAX_TOML_BYTES + 1)
    with pytest.raises(error, match="larger than") as info:
        load(path)
    error_names_file(info.value, path)
    with pytest.raises(ConfigError, match="larger than"):
        read_toml("/dev/zero")


def test_non_utf8_and_unreadable_profiles_are_config_errors():
    """Regression: a .toml profile that is not UTF-8 raised UnicodeDecodeError out of get_profile; a NUL in a
    profile path (a string in a config) raised ValueError. Both are ConfigErrors naming the file now."""
    path = scratch("latin1.toml", b"name = '\xe9'\n")
    with pytest.raises(ConfigError, match="latin1.toml"):
        get_profile(str(path))
    with pytest.raises(ConfigError, match="profile"):
        get_profile("bad\x00name.toml")
