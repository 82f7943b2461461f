"""bench/kernel_times.py: its spies time the calls a method's frames make, each under its label, and leave the
functions as they were."""

from __future__ import annotations

import sys
from collections import defaultdict

import numpy as np
import pytest

from hmdrt.foveation.stages import pyramid
from tests.test_registry import bench_module


@pytest.fixture(scope="module")
def kernel_times():
    return bench_module("kernel_times")


def test_a_target_names_a_module_attribute_a_class_method_and_a_splitting_argument(kernel_times):
    plain = kernel_times.parse_target("hmdrt.foveation.stages.pyramid:pull_push")
    assert (plain.owner, plain.name, plain.label, plain.split) == (pyramid, "pull_push", "pyramid.pull_push", None)
    split = kernel_times.parse_target("hmdrt.foveation.stages.pyramid:_pull_level[1]")
    assert split.split == 1
    method = kernel_times.parse_target("hmdrt.foveation.stages.pyramid:Pyramid.level")
    assert (method.owner, method.name) == (pyramid.Pyramid, "level")
    for bad in ("pyramid", "hmdrt.foveation.stages.pyramid:", "hmdrt.foveation.stages.pyramid:CHANNELS", "a:b[x]"):
        with pytest.raises(ValueError):
            kernel_times.parse_target(bad)


def test_a_spy_counts_each_call_under_its_label_and_puts_the_original_back(kernel_times):
    original = pyramid.pull_push
    calls: dict[str, list[float]] = defaultdict(list)
    undo = kernel_times.spy(kernel_times.parse_target("hmdrt.foveation.stages.pyramid:pull_push[1]"), calls)
    assert pyramid.pull_push is not original
    pyr = pyramid.Pyramid.empty(8, 6)
    pyr.data[:, pyramid.WEIGHT] = 1.0
    pyramid.pull_push(pyr, None)
    pyramid.pull_push(pyr, None)
    undo()
    assert pyramid.pull_push is original
    assert list(calls) == ["pyramid.pull_push[None]"] and len(calls["pyramid.pull_push[None]"]) == 2
    assert all(ms > 0 for ms in calls["pyramid.pull_push[None]"])


def test_the_bench_prints_each_kernels_calls_and_time_per_frame(kernel_times, monkeypatch, capsys):
    argv = ["kernel_times.py", "full", "hmdrt.trace.integrator:trace", "--profile", "sim-cpu", "--frames", "3"]
    monkeypatch.setattr(sys, "argv", [*argv, "--warmup", "1"])
    kernel_times.main()
    lines = capsys.readouterr().out.splitlines()
    assert lines[0].startswith("full on whitted at sim-cpu, still view, 2 frames after 1")
    label, per_frame, median, ms = lines[2].split()
    assert label == "integrator.trace" and float(per_frame) == 1.0
    assert float(median) > 0 and np.isclose(float(ms), float(median), rtol=1.0)
