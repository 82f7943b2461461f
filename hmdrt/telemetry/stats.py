"""Per-frame stage timings and ray counts (the render stats keys of DESIGN.md).

A stage appears in stages_ms only once it has run, so stages_run lists exactly what ran.
"""

from __future__ import annotations

import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field

RAY_KINDS = ("primary", "shadow", "secondary", "ao", "area")


@dataclass
class FrameStats:
    stages_ms: dict[str, float] = field(default_factory=dict)
    rays: dict[str, int] = field(default_factory=lambda: dict.fromkeys(RAY_KINDS, 0))

    @contextmanager
    def stage(self, name: str) -> Iterator[None]:
        """Time the enclosed work into stages_ms[name] (accumulating over repeated entries)."""
        start = time.perf_counter_ns()
        try:
            yield
        finally:
            self.stages_ms[name] = self.stages_ms.get(name, 0.0) + (time.perf_counter_ns() - start) / 1e6

    def count(self, kind: str, n: int) -> None:
        self.rays[kind] += int(n)

    def to_dict(self) -> dict:
        return {
            "stages_ms": {k: round(v, 3) for k, v in self.stages_ms.items()},
            "rays": {**self.rays, "total": sum(self.rays.values())},
            "stages_run": list(self.stages_ms),
        }
