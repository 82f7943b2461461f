"""The run report read by attribute: `report.latency_ms.gaze_to_photon.p99` for `report["latency_ms"]["gaze_to_photon"]
["p99"]`, so that tests and scripts read the keys docs/architecture.md ("Run report") lists as fields.

Only the standard library is imported here: the pytest plugin (hmdrt.testing) reads reports without loading the
compositor.
"""

from __future__ import annotations

import copy
from collections.abc import Iterator, Mapping
from typing import Any


def _view(value: Any) -> Any:
    """Tables as Reports and lists of them as lists of Reports; other values as they are."""
    if isinstance(value, Mapping):
        return Report(value)
    if isinstance(value, list):
        return [_view(v) for v in value]
    return value


class Report(Mapping[str, Any]):
    """A run report (Compositor.run()'s dict, the JSON of `hmdrt run --report`), read-only, by key or attribute.

    Nested tables are Reports too; keys that are not identifiers (stages such as "outer/inner") stay reachable by
    key. `period_ms` is the display period the report's `vsync_hz` gives. Equal to a dict of the same content.
    """

    __slots__ = ("_data",)

    def __init__(self, data: Mapping[str, Any]):
        self._data = data

    def __getitem__(self, key: str) -> Any:
        return _view(self._data[key])

    def __iter__(self) -> Iterator[str]:
        return iter(self._data)

    def __len__(self) -> int:
        return len(self._data)

    def __getattr__(self, name: str) -> Any:
        if name.startswith("_"):
            raise AttributeError(name)
        try:
            return self[name]
        except KeyError:
            raise AttributeError(f"the report has no {name!r}; it has {', '.join(self._data) or 'nothing'}") from None

    @property
    def period_ms(self) -> float:
        """The display period in milliseconds (1000 / vsync_hz); only the top of a run report has one."""
        if "vsync_hz" not in self._data:
            raise AttributeError("period_ms")  # __getattr__ then names the keys there are
        return 1000.0 / self._data["vsync_hz"]

    def to_dict(self) -> dict[str, Any]:
        """A deep copy of the report as plain dicts and lists (for JSON)."""
        return copy.deepcopy(dict(self._data))

    def __repr__(self) -> str:
        return f"Report({dict(self._data)!r})"
