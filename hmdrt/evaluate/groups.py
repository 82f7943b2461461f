"""The eval's unit of work: a scene, profile and trace that some method cell runs on, the digest that names a
group's rows, what its result holds, and the crops of its last scored frame; and the check, when the config loads,
that the work it plans fits the size limits (hmdrt.ranges)."""

from __future__ import annotations

import hashlib
import itertools
import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, NamedTuple

import msgspec
import numpy as np

from hmdrt.optics import HmdProfile, get_profile
from hmdrt.ranges import MAX_EVAL_FRAMES, refuse_large
from hmdrt.scene import check_scene
from hmdrt.version import __version__

if TYPE_CHECKING:  # hmdrt.evaluate.config checks a config with check_work as it loads
    from hmdrt.evaluate.config import EvalConfig, Trace


@dataclass
class Crops:
    """The last scored frame of one scene, profile and trace: the truth, each method's image, the gaze pixel."""

    scene: str
    profile: str
    trace: str
    truth: np.ndarray
    images: dict[str, np.ndarray]
    gaze_xy: tuple[float, float]


def profile_of(name: str, resolution: str) -> HmdProfile:
    """The profile `name`, at the eval's per-eye `resolution` where one is given."""
    profile = get_profile(name)
    return profile.with_resolution_text(resolution, "resolution") if resolution else profile


class GroupKey(NamedTuple):
    """A scene, profile and trace of the config that some method cell runs on: the unit of the eval's work."""

    scene: str
    profile: str  # as the config names it
    trace: Trace


@dataclass
class GroupResult:
    """What a group yields: one row per cell (with the worker that rendered it and the group's wall time) and the
    crops of its last scored frame."""

    rows: list[dict]
    crops: Crops


def groups(config: EvalConfig) -> list[GroupKey]:
    """Every scene, profile and trace that some cell runs on, in the order of the results."""
    return [
        GroupKey(scene, profile, trace)
        for scene in config.scenes
        for profile, trace in itertools.product(config.profiles, config.traces)
        if config.cells(scene, trace)
    ]


def group_id(config: EvalConfig, key: GroupKey) -> str:
    """A digest of everything that decides a group's rows: its names, its cells and the config's settings that
    reach its images, so that a finished group of an edited config is reused only where it is the same."""
    settings = (
        "resolution",
        "eye",
        "frames",
        "warmup_frames",
        "timing_rounds",
        "truth_spp",
        "seed",
        "score_space",
        "jod",
    )
    what = {
        "version": __version__,
        "group": [key.scene, key.profile, msgspec.to_builtins(key.trace)],
        "cells": [[str(c.choice), c.label, c.compare_to] for c in config.cells(key.scene, key.trace)],
        "settings": {name: getattr(config, name) for name in settings},
    }
    return hashlib.sha256(msgspec.json.encode(what)).hexdigest()[:24]


class GroupShape(NamedTuple):
    """What a group's result holds: the columns that name it in every row, its cells' labels in the order of its
    rows, and its images' (height, width)."""

    ids: dict[str, str]
    labels: list[str]
    shape: tuple[int, int]


def group_shape(config: EvalConfig, key: GroupKey) -> GroupShape:
    profile = profile_of(key.profile, config.resolution)
    ids = {"scene": key.scene, "profile": profile.name, "trace": key.trace.label}
    return GroupShape(ids, [c.label for c in config.cells(key.scene, key.trace)], (profile.height, profile.width))


def planned_frames(config: EvalConfig) -> int:
    """The frames the eval renders: per method entry, its cells x the scenes and traces (a sweep's each) it runs on,
    all x profiles x frames per cell x timing rounds (a choice that two entries repeat counted twice)."""
    per_profile = 0
    for m in config.methods:
        chosen = set(m.scenes)
        scenes = sum(scene in chosen for scene in config.scenes) if chosen else len(config.scenes)
        traces = sum(trace.named(m.traces) for trace in config.traces)
        per_profile += math.prod(len(values) for values in m.sweep.values()) * scenes * traces
    return per_profile * len(config.profiles) * config.frames * config.timing_rounds


def check_work(config: EvalConfig) -> None:
    """A ConfigError (SceneError) of one line, before anything is rendered, for an eval past the size limits: its
    frames in all (planned_frames), a profile's pixels at its resolution, or a built-in scene's triangles."""
    unit = "frames (scenes x profiles x traces x method cells x frames x timing rounds)"
    refuse_large("the eval renders", float(planned_frames(config)), MAX_EVAL_FRAMES, unit)
    for name in dict.fromkeys(config.profiles):
        profile_of(name, config.resolution)
    for spec in dict.fromkeys(config.scenes):
        check_scene(spec)
