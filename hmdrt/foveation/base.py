"""What every rendering method receives and returns, and how a method plans which stages to run.

Methods register by name (registry.register). Each declares its stages and what each needs; the
plan of a frame keeps only the stages whose needs the scene, the configuration and the method's own
state (a previous frame to reproject) meet, so stages that cannot change the image never run. Each also
declares its Checks: what the golden, allocation and method tests and the benches run of it.

Parameters can change between frames (Method.set_params): a method derives everything that depends on
its parameters in one _configure(params), which its constructor calls too, and keeps its temporal state
(caches, history, persistent buffers, fixation filters) wherever the new parameters leave it meaningful.
A method also declares its cost knobs (Method.knobs): the parameters the compositor's budget controller
may trade for time, each with a floor from its paper, so that the controller knows no method by name, and
the history it needs before its images are steady (Method.warmup_frames), which the eval renders unscored.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any, ClassVar, Literal, Protocol

import msgspec
import numpy as np

from hmdrt.optics.camera import EyeCamera
from hmdrt.telemetry.stats import FrameStats
from hmdrt.trace.integrator import Whitted

EYES = ("left", "right")


@dataclass(frozen=True)
class FrameRequest:
    """One eye's frame: its camera, that eye's unit gaze (head frame), frame number, seed and eye.

    gaze_depth_m is the vergence depth of the two eyes' gaze when the source knows it. A gaze that is not a
    finite, non-zero 3-vector (NaN from a tracker, say) is refused with ValueError: every method would
    otherwise turn it into NaN eccentricities and render without a fovea.
    """

    camera: EyeCamera
    gaze: np.ndarray
    frame: int = 0
    seed: int = 0
    eye: str = "left"
    gaze_depth_m: float | None = None

    def __post_init__(self) -> None:
        g = self.gaze
        if np.shape(g) != (3,) or not all(map(math.isfinite, g)) or not any(g):  # per frame: no array temporaries
            raise ValueError(f"gaze must be a finite, non-zero 3-vector (head frame), got {self.gaze!r}")


@dataclass(frozen=True)
class Stage:
    """A named step of a method and the features it needs to be able to change the image. A stage that `touches`
    is an image-space pass that reports the bytes it must read and write (FrameStats.stage(touches=)), which
    bench/stage_budget.py sets against a copy of as many bytes; tests/test_foveation.py checks that it does."""

    name: str
    needs: frozenset[str] = frozenset()
    touches: bool = False


@dataclass(frozen=True)
class Checks:
    """What the project's checklists run of a method, so that none keeps a list of methods by hand: registry.py
    derives the golden, allocation, method-test and bench lists from the registered classes' Checks. The defaults
    check a new method as fully as the others until it declares less (hmdrt/foveation/README.md)."""

    golden: tuple[str, ...] = ("whitted",)  # scenes its golden images are pinned on (tests/test_golden.py); the
    # steady-state allocation test (tests/test_allocations.py) runs the same cases
    variants: tuple[str, ...] = ("",)  # the option strings its golden, allocation and bench cases run: "" is the
    # defaults, "dof=none" is "name?dof=none"
    bench: bool = True  # timed by bench/stage_budget.py and bench/foveation_speedup.py
    temporal: bool = True  # keeps history across frames: tests/test_foveation.py checks that a still view converges
    # and that a sequence reproduces bit for bit (how many frames it needs is Method.warmup_frames)

    def specs(self, name: str) -> list[str]:
        """The method's specs as the lists run them, "name" or "name?options" per variant."""
        return [f"{name}?{v}" if v else name for v in self.variants]


# features a stage may need
HISTORY = "history"  # a previous frame of this eye to reproject or blend
SECONDARY = "secondary"  # the scene has reflective or refractive materials (and depth > 0)
STOCHASTIC = "stochastic"  # the scene has area lights or ambient occlusion
DOF = "dof"  # a depth-of-field preset other than none


def scene_features(tracer: Whitted) -> frozenset[str]:
    """What the scene offers the stages: secondary rays, stochastic lighting."""
    features = set()
    if tracer.max_depth > 0 and tracer.secondary:
        features.add(SECONDARY)
    if tracer.plan.area_total or tracer.plan.ao_samples:
        features.add(STOCHASTIC)
    return frozenset(features)


def plan(stages: tuple[Stage, ...], features: frozenset[str]) -> tuple[str, ...]:
    """The names of the stages whose needs `features` meet, in order."""
    return tuple(s.name for s in stages if s.needs <= features)


Floor = float | Callable[[dict[str, Any]], float] | None


@dataclass(frozen=True)
class Knob:
    """A Params field the budget controller moves: from its configured value (level 1) to `floor` (level 0), a
    number or a function of the configured values (Method.knob_values); None leaves it to the foveal widening."""

    field: str
    floor: Floor
    cheaper: Literal["lower", "higher"] = "lower"
    foveal: bool = False  # a foveal radius, widened for gaze speed and tracker accuracy


class Method(Protocol):
    name: ClassVar[str]
    Params: ClassVar[type[msgspec.Struct]]
    stages: ClassVar[tuple[Stage, ...]]
    knobs: ClassVar[tuple[Knob, ...]]  # the cost knobs the budget controller may move; () for none
    checks: ClassVar[Checks]  # what the checklists run of it
    params: msgspec.Struct  # the parameters the next frame is rendered with

    @classmethod
    def knob_values(cls, params: msgspec.Struct) -> dict[str, Any]:
        """Every field's configured value as the knobs read it (level 1)."""
        ...

    @property
    def warmup_frames(self) -> int:
        """Frames to render from a fresh start before the images are steady: the temporal history the current
        parameters need (RRM: its refresh cycle); 0 for a method that keeps none."""
        ...

    def render(self, request: FrameRequest, stats: FrameStats, out: np.ndarray | None = None) -> np.ndarray:
        """Linear RGB image (height, width, 3) float32 of this eye's frame, written into `out` when given (a
        C-contiguous buffer of that shape) and returned; the caller's to keep: the method never writes to an
        image it has returned (the compositor shows and saves them without a copy). In steady state a method
        allocates nothing of the image's size: its buffers persist across frames (tests/test_allocations.py)."""
        ...

    def set_params(self, params: msgspec.Struct) -> None:
        """Render with `params` (a validated Params) from the next frame on, keeping the temporal state
        they leave meaningful; each method's _configure says what a change resets. Raises TypeError for
        another method's Params and ConfigError for values only the method can refuse, unchanged then."""
        ...


class Configurable(ABC):
    """Method.set_params for a method whose parameter-derived state all comes from _configure."""

    name: ClassVar[str]
    Params: ClassVar[type[msgspec.Struct]]
    knobs: ClassVar[tuple[Knob, ...]] = ()
    checks: ClassVar[Checks] = Checks()
    params: msgspec.Struct

    @classmethod
    def knob_values(cls, params: msgspec.Struct) -> dict[str, Any]:
        return msgspec.structs.asdict(params)

    @property
    def warmup_frames(self) -> int:
        """One previous frame, unless the method declares the history it needs (Method.warmup_frames)."""
        return 1

    def set_params(self, params: msgspec.Struct) -> None:
        if not isinstance(params, self.Params):
            raise TypeError(f"{self.name} takes {self.Params.__name__}, not {type(params).__name__}")
        self._configure(params)

    @abstractmethod
    def _configure(self, params: msgspec.Struct) -> None:
        """Derive everything that depends on `params` and adopt them; raise before changing anything."""


class NoParams(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """A method without options."""


def sample_keys(first_sample: int, count: int, seed: int) -> np.ndarray:
    """Random-stream keys of consecutive samples, distinct per seed."""
    return np.arange(first_sample, first_sample + count, dtype=np.int64) + (np.int64(seed) << np.int64(32))


def pixel_keys(pixels: np.ndarray, seed: int, frame: int = 0, stream: int = 0) -> np.ndarray:
    """Keys of samples at pixel indices, distinct per frame and stream; frame 0, stream 0 equals sample_keys."""
    return pixels.astype(np.int64) + (np.int64(seed) << 32) + np.int64(frame) * (1 << 22) + np.int64(stream) * (1 << 40)
