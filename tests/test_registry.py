"""Methods register themselves, and the checklists come from the registry: a method registered in a test is in the
golden, allocation, method-test and bench lists, and the golden check says which images it lacks."""

from __future__ import annotations

import importlib.util
import pkgutil
import sys
from pathlib import Path

import msgspec
import pytest

import hmdrt.foveation
from hmdrt.foveation import METHODS, MethodChoice
from hmdrt.foveation.base import Checks
from hmdrt.foveation.reference import Full
from hmdrt.foveation.registry import (
    allocation_cases,
    bench_methods,
    golden_cases,
    register,
    temporal_methods,
    unregister,
)
from tests.test_golden import missing_golden

BENCH = Path(__file__).parent.parent / "bench"


def bench_module(name: str):
    """A bench script as a module (bench/ is no package: its scripts import references.py beside them)."""
    spec = importlib.util.spec_from_file_location(f"bench_{name}", BENCH / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.path.insert(0, str(BENCH))
    try:
        spec.loader.exec_module(module)
    finally:
        sys.path.remove(str(BENCH))
    return module


class ToyParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    gain: float = 1.0  # not read: an option for a variant


@pytest.fixture
def toy():
    """A toy method, the full reference under a new name with an option and a variant, registered for one test."""

    @register
    class Toy(Full):
        name = "toy"
        Params = ToyParams
        checks = Checks(golden=("whitted",), variants=("", "gain=2"), temporal=True)

    try:
        yield Toy
    finally:
        unregister("toy")
    assert "toy" not in METHODS


def test_a_registered_method_is_in_every_checklist(toy):
    assert METHODS["toy"] is toy and MethodChoice.parse("toy").make(None).name == "toy"
    assert {("whitted", "toy"), ("whitted", "toy?gain=2")} <= set(golden_cases())
    assert {("whitted", "toy"), ("whitted", "toy?gain=2")} <= set(allocation_cases())
    assert "toy" in temporal_methods()
    for bench in ("stage_budget", "foveation_speedup", "own_rays"):
        assert bench_module(bench).default_methods() == bench_methods(), bench
    assert {"toy", "toy?gain=2"} <= set(bench_methods())


def test_the_golden_check_names_the_images_a_registered_method_lacks(toy):
    missing = missing_golden()
    assert any(line.startswith("no golden image for method toy on whitted") for line in missing), missing
    assert any(line.startswith("no golden image for method toy?gain=2 on whitted") for line in missing), missing
    assert all("toy" in line for line in missing), missing  # the built-in methods' images are all there


def test_every_method_module_is_loaded_and_registers_a_method():
    """A module of hmdrt.foveation that hmdrt/foveation/__init__.py does not load registers nothing: named here."""
    shared = {"base", "registry", "stages"}
    modules = {m.name for m in pkgutil.iter_modules(hmdrt.foveation.__path__)} - shared
    registered = {cls.__module__.split(".")[2] for cls in METHODS.values()}
    assert modules <= registered, f"method modules that register nothing: {sorted(modules - registered)}"
    assert {"full", "regular", "rrm", "kim21", "weier16", "weier18"} <= set(METHODS)


def test_every_declared_variant_is_a_valid_choice():
    for name, cls in METHODS.items():
        for spec in cls.checks.specs(name):
            assert MethodChoice.parse(spec).name == name


@pytest.mark.parametrize(
    "declared, error, message",
    [
        ({}, TypeError, "must declare its own name"),  # a subclass under its parent's name
        ({"name": "two words"}, TypeError, "lower-case"),
        ({"name": "full"}, ValueError, "'full' is taken by hmdrt.foveation.reference.Full"),
        ({"name": "unchecked", "checks": ("whitted",)}, TypeError, "checks must be a Checks"),
        ({"name": "unparamed", "Params": dict}, TypeError, "Params must be a msgspec.Struct"),
    ],
)
def test_registration_refuses_what_the_checklists_cannot_read(declared, error, message):
    with pytest.raises(error, match=message):
        register(type("Bad", (Full,), declared))
    assert METHODS["full"] is Full and "unchecked" not in METHODS and "unparamed" not in METHODS


def test_registering_again_is_harmless_and_unregistering_needs_a_method():
    assert register(Full) is Full and METHODS["full"] is Full
    with pytest.raises(KeyError, match="no method 'unchecked'"):
        unregister("unchecked")
