"""hmdrt: a simulated head-mounted-display runtime with foveated ray tracing.

The library API (hmdrt.api, docs/api.md) is reachable from here too, as hmdrt.render_frame and so on; it is
imported on first use, so that `import hmdrt` loads no numba, scene or compositor module.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from hmdrt.version import __version__

if TYPE_CHECKING:
    from hmdrt.api import (
        GBufferImage,
        RenderedFrame,
        Report,
        load_trace,
        render_frame,
        run_compositor,
        trace_gbuffer,
        write_trace,
    )

__all__ = [
    "GBufferImage",
    "RenderedFrame",
    "Report",
    "__version__",
    "load_trace",
    "render_frame",
    "run_compositor",
    "trace_gbuffer",
    "write_trace",
]
_API = frozenset(__all__) - {"__version__"}


def __getattr__(name: str) -> Any:
    if name in _API:
        return getattr(importlib.import_module("hmdrt.api"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
