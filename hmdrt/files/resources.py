"""Files installed with hmdrt: the default run config and the trace it replays.

`hmdrt/configs` is a link to the repository's `configs/`, so the sdist and the wheel carry `configs/default.toml`
and `configs/traces/*.jsonl.gz` (pyproject.toml's package data) as one copy. In a checkout the README's
`hmdrt run configs/default.toml` finds the repository's file; after `pip install hmdrt` elsewhere, where there is no
such file, it runs the installed one.
"""

from __future__ import annotations

import logging
from pathlib import Path

log = logging.getLogger(__name__)
INSTALLED = Path(__file__).parents[1] / "configs"


def run_config(path: str | Path) -> Path:
    """PATH, or the installed copy of a missing relative `configs/...` path that hmdrt ships (configs/default.toml)."""
    path = Path(path)
    parts = path.parts
    if path.exists() or path.is_absolute() or parts[:1] != ("configs",):
        return path
    installed = INSTALLED.joinpath(*parts[1:])
    if not installed.is_file():
        return path
    log.info("%s is not here; running the one installed with hmdrt, %s", path, installed)
    return installed
