"""Latency-budget testing of the hmdrt compositor: run configs, compositors under test and checks on their reports.

The pytest plugin (hmdrt.testing.pytest_plugin, entry point "hmdrt") builds its fixtures from these; docs/testing.md
shows them in use. Importing this package is cheap: the compositor parts (Recording, compositor, Background,
run_bounded) are loaded from hmdrt.testing.runs on first use.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hmdrt.telemetry.view import Report
from hmdrt.testing.checks import (
    as_report,
    assert_every_vsync_shown,
    assert_gaze_error_within,
    assert_latency_within,
    assert_miss_rate_at_most,
)
from hmdrt.testing.config import ANY_PORT, TRACE, free_port, write_config

if TYPE_CHECKING:
    from hmdrt.testing.runs import Background, Recording, compositor, run_bounded

_RUNS = ("Background", "Recording", "compositor", "run_bounded")

__all__ = [
    "ANY_PORT",
    "TRACE",
    "Background",
    "Recording",
    "Report",
    "as_report",
    "assert_every_vsync_shown",
    "assert_gaze_error_within",
    "assert_latency_within",
    "assert_miss_rate_at_most",
    "compositor",
    "free_port",
    "run_bounded",
    "write_config",
]


def __getattr__(name: str) -> Any:
    if name in _RUNS:
        return getattr(importlib.import_module("hmdrt.testing.runs"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
