"""Helpers shared by the fuzz tests in this folder: strategies, scratch files, seeds."""

from __future__ import annotations

import tempfile
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hmdrt.bus import messages
from hmdrt.bus.messages import Gaze, Pose

EXTENDED = 20  # the slow run's examples per default-run example


RUNS = [pytest.param(1, id="default"), pytest.param(EXTENDED, id="extended", marks=pytest.mark.slow)]


MESHES = Path(__file__).parent.parent / "data" / "meshes"


_SCRATCH = tempfile.TemporaryDirectory(prefix="hmdrt-fuzz-")


def fuzz(examples: int, **strategies):
    """A property run with `examples` examples by default and EXTENDED times as many under -m slow.

    The decorated function's name and docstring state the property; its arguments are drawn from
    `strategies`.
    """

    def decorate(check):
        @pytest.mark.parametrize("scale", RUNS)
        def test(scale):
            run = given(**strategies)(check)
            settings(
                max_examples=examples * scale,
                deadline=None,
                suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large, HealthCheck.filter_too_much],
            )(run)()

        test.__name__, test.__qualname__, test.__doc__ = check.__name__, check.__qualname__, check.__doc__
        return test

    return decorate


def scratch(name: str, data: bytes | str) -> Path:
    """A file of the given content in this module's scratch folder (overwritten by the next example)."""
    path = Path(_SCRATCH.name) / name
    path.write_bytes(data.encode() if isinstance(data, str) else data)
    return path


def sparse(name: str, size: int) -> Path:
    """A file that claims `size` bytes without taking them on disk: a size check must refuse it unread."""
    path = Path(_SCRATCH.name) / name
    with path.open("wb") as f:
        f.truncate(size)
    return path


def publishable(sample: Gaze | Pose, device: str = "fuzz") -> None:
    """The sample survives the bus decoder unchanged: nothing a driver or importer lets through is refused
    (or crashes the encoder) on the way to the compositor."""
    _, _, back = messages.decode(messages.encode(sample, device))
    assert back == sample


def mutations(data: bytes) -> st.SearchStrategy[bytes]:
    """`data` truncated, with a byte replaced, with bytes inserted, or with a span deleted."""
    n = len(data)
    return st.one_of(
        st.integers(0, max(n - 1, 0)).map(lambda i: data[:i]),
        st.tuples(st.integers(0, max(n - 1, 0)), st.integers(0, 255)).map(
            lambda t: data[: t[0]] + bytes([t[1]]) + data[t[0] + 1 :]
        ),
        st.tuples(st.integers(0, n), st.binary(min_size=1, max_size=16)).map(
            lambda t: data[: t[0]] + t[1] + data[t[0] :]
        ),
        st.tuples(st.integers(0, n), st.integers(1, 16)).map(lambda t: data[: t[0]] + data[t[0] + t[1] :]),
    )


SCALARS = st.one_of(
    st.none(),
    st.booleans(),
    st.integers(-(2**63), 2**64 - 1),
    st.floats(),
    st.text(max_size=12),
    st.binary(max_size=12),
)


MSGPACK_VALUES = st.recursive(
    SCALARS,
    lambda inner: st.lists(inner, max_size=4) | st.dictionaries(st.text(max_size=8), inner, max_size=4),
    max_leaves=12,
)


def error_names_file(exc: Exception, path: Path) -> None:
    assert str(path) in str(exc) or path.name in str(exc), f"{exc} does not name {path}"
