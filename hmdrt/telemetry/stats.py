"""Per-frame stage timings and ray counts (the render stats keys of docs/architecture.md, "Command line").

A stage appears in stages_ms only once it has run, so stages_run lists exactly what ran. A stage
entered inside another is recorded as "outer/inner" (inclusive times), so a method's own stages sum
to its frame time and the tracer's breakdown stays visible under them. A stage may say how many bytes of
memory it must read and write at the least (`touches`), so that bench/stage_budget.py can set its time
against a plain copy of those bytes.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

RAY_KINDS = ("primary", "shadow", "secondary", "ao", "area")


@dataclass
class FrameStats:
    stages_ms: dict[str, float] = field(default_factory=dict)
    rays: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0))
    metrics: dict[str, float] = field(default_factory=dict)  # method-specific figures, e.g. sample_fraction
    touched: dict[str, int] = field(default_factory=dict)  # bytes each stage must read and write, where it says
    _open: list[str] = field(default_factory=list, repr=False)

    @contextmanager
    def stage(self, name: str, touches: int = 0) -> Iterator[None]:
        """Time the enclosed work into stages_ms[name], prefixed by any enclosing stages; `touches`: the bytes
        the work must read and write at the least (summed into touched[name])."""
        key = "/".join([*self._open, name])
        if touches:
            self.touched[key] = self.touched.get(key, 0) + touches
        self._open.append(name)
        start = time.perf_counter_ns()
        try:
            yield
        finally:
            self._open.pop()
            self.stages_ms[key] = self.stages_ms.get(key, 0.0) + (time.perf_counter_ns() - start) / 1e6

    def count(self, kind: str, n: int) -> None:
        self.rays[kind] += int(n)

    def to_dict(self) -> dict:
        return {
            "stages_ms": {k: round(v, 3) for k, v in self.stages_ms.items()},
            "rays": {**self.rays, "total": sum(self.rays.values())},
            "stages_run": list(self.stages_ms),
            "metrics": dict(self.metrics),
        }


def nbytes(*arrays: np.ndarray) -> int:
    """The bytes of these arrays together: what a pass that reads or writes each of them once must touch."""
    return sum(a.nbytes for a in arrays)
