"""A trace's samples held compactly: numpy columns of 106 bytes a sample, not Python objects of about 600.

Readers append samples as they decode them; every PACK of them is packed into blocks of BLOCK rows, so reading
holds at most PACK sample objects besides the columns. Reading the table back makes Gaze and Pose objects on
demand. A table holds at most MAX_SAMPLES samples (about 1.1 GB of columns): one more is a ConfigError naming the
trace and the cap, so no trace, however it compresses, takes more memory than that.

Columns: kind (gaze or pose), valid, seq (uint64), t_host and t_dev (int64; t_dev None as NO_TIME, outside the
bus's time range), and ten float64 values: a gaze's C, L, R and depth_m (NaN where None), or a pose's position and
orientation.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import NamedTuple, overload

import numpy as np

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.errors import ConfigError

Sample = Gaze | Pose
SHIFT = 16
BLOCK = 1 << SHIFT  # rows per block: sample i is row i & (BLOCK - 1) of block i >> SHIFT
PACK = 4096  # sample objects kept before they are packed
MAX_SAMPLES = 10_000_000  # 2.8 hours of 1000 Hz gaze
GAZE, POSE = 0, 1
NO_TIME = np.iinfo(np.int64).min
SEQ_END = 2**64  # seq is stored as uint64
VALUES = 10
GAZE_FIELDS = {"C": 0, "L": 3, "R": 6, "depth_m": 9}  # a gaze's first value column of each field
DTYPES = {
    "kind": np.uint8,
    "valid": np.bool_,
    "seq": np.uint64,
    "t_host": np.int64,
    "t_dev": np.int64,
    "values": np.float64,  # VALUES of them a row
}
BYTES_PER_SAMPLE = sum(np.dtype(t).itemsize for t in DTYPES.values()) + 8 * (VALUES - 1)
_NAN = float("nan")
_NO_VECTOR = (_NAN,) * 3


class Columns(NamedTuple):
    """Rows of a table's columns (views into one block)."""

    kind: np.ndarray
    valid: np.ndarray
    seq: np.ndarray
    t_host: np.ndarray
    t_dev: np.ndarray
    values: np.ndarray


def _empty(name: str, rows: int) -> np.ndarray:
    return np.empty((rows, VALUES) if name == "values" else rows, DTYPES[name])


def _values(s: Sample) -> tuple[float, ...]:
    if isinstance(s, Pose):
        return (*s.position, *s.orientation, *_NO_VECTOR)
    C, L, R = (_NO_VECTOR if v is None else v for v in (s.C, s.L, s.R))
    return (*C, *L, *R, _NAN if s.depth_m is None else s.depth_m)


def _vector(values: list[float], at: int) -> tuple[float, float, float] | None:
    x = values[at]
    return None if x != x else (x, values[at + 1], values[at + 2])  # NaN: the sample has none


def _objects(rows: Columns) -> list[Sample]:
    """The samples of some rows, made from their columns."""
    out: list[Sample] = []
    columns = (c.tolist() for c in rows)
    for kind, valid, seq, t_host, t_dev, v in zip(*columns, strict=True):
        t_dev = None if t_dev == NO_TIME else t_dev
        if kind == POSE:
            out.append(Pose(seq, t_host, tuple(v[0:3]), tuple(v[3:7]), t_dev, valid))
        else:
            depth = None if v[9] != v[9] else v[9]
            out.append(Gaze(seq, t_host, t_dev, valid, _vector(v, 0), _vector(v, 3), _vector(v, 6), depth))
    return out


class _Block:
    """BLOCK rows of columns, the first `fill` of them in use."""

    def __init__(self):
        self.columns = Columns(*(_empty(name, BLOCK) for name in DTYPES))
        self.fill = 0

    def put(self, samples: list[Sample]) -> None:
        rows = slice(self.fill, self.fill + len(samples))
        kind, valid, seq, t_host, t_dev, values = self.columns
        kind[rows] = [POSE if isinstance(s, Pose) else GAZE for s in samples]
        valid[rows] = [s.valid for s in samples]
        seq[rows] = [s.seq for s in samples]
        t_host[rows] = [s.t_host for s in samples]
        t_dev[rows] = [NO_TIME if s.t_dev is None else s.t_dev for s in samples]
        values[rows] = [_values(s) for s in samples]
        self.fill += len(samples)

    def rows(self, which: slice | np.ndarray) -> Columns:
        return Columns(*(c[which] for c in self.columns))


class SampleTable(Sequence[Sample]):
    """Gaze and pose samples in the order appended, stored as columns (see the module docstring). `source` names
    the trace in the error for one sample past MAX_SAMPLES."""

    def __init__(self, source: str = "the trace"):
        self.source = source
        self._blocks: list[_Block] = []
        self._pending: list[Sample] = []
        self._packed = 0

    @classmethod
    def of(cls, samples: Iterable[Sample]) -> SampleTable:
        """`samples` as a table: itself when it is one."""
        if isinstance(samples, SampleTable):
            return samples
        table = cls()
        table.extend(samples)
        return table

    def append(self, sample: Sample) -> None:
        """Add a sample; a ValueError for a seq that does not fit 64 bits, a ConfigError past MAX_SAMPLES."""
        if self._packed + len(self._pending) >= MAX_SAMPLES:
            raise ConfigError(
                f"{self.source} holds more than {MAX_SAMPLES} samples, the most hmdrt keeps of a trace "
                f"(about {MAX_SAMPLES * BYTES_PER_SAMPLE / 1e9:.1f} GB in memory)"
            )
        if sample.seq >= SEQ_END:
            raise ValueError(f"seq {sample.seq} does not fit 64 bits")
        self._pending.append(sample)
        if len(self._pending) >= PACK:
            self._pack()

    def extend(self, samples: Iterable[Sample]) -> None:
        for sample in samples:
            self.append(sample)

    def _pack(self) -> None:
        pending, self._pending = self._pending, []
        start = 0
        while start < len(pending):
            if not self._blocks or self._blocks[-1].fill == BLOCK:
                self._blocks.append(_Block())
            block = self._blocks[-1]
            stop = start + min(BLOCK - block.fill, len(pending) - start)
            block.put(pending[start:stop])
            start = stop
        self._packed += len(pending)

    def _filled(self) -> list[_Block]:
        if self._pending:
            self._pack()
        return self._blocks

    def __len__(self) -> int:
        return self._packed + len(self._pending)

    @overload
    def __getitem__(self, index: int) -> Sample: ...

    @overload
    def __getitem__(self, index: slice) -> list[Sample]: ...

    def __getitem__(self, index: int | slice) -> Sample | list[Sample]:
        if isinstance(index, slice):
            return self.take(np.arange(*index.indices(len(self))))
        n = len(self)
        if not -n <= index < n:
            raise IndexError(f"sample {index} of {n}")
        i = index % n
        block = self._filled()[i >> SHIFT]
        return _objects(block.rows(slice(i & (BLOCK - 1), (i & (BLOCK - 1)) + 1)))[0]

    def __iter__(self) -> Iterator[Sample]:
        for block in self._filled():
            for start in range(0, block.fill, PACK):
                yield from _objects(block.rows(slice(start, min(start + PACK, block.fill))))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, str | bytes):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"SampleTable({len(self)} samples of {self.source})"

    def take(self, indices: np.ndarray) -> list[Sample]:
        """The samples at `indices` (non-negative), in that order."""
        indices = np.asarray(indices, dtype=np.int64)
        blocks = self._filled()
        out: list[Sample | None] = [None] * len(indices)
        which = indices >> SHIFT
        for b in np.unique(which).tolist():
            at = np.flatnonzero(which == b)
            for k, sample in zip(at.tolist(), _objects(blocks[b].rows(indices[at] & (BLOCK - 1))), strict=True):
                out[k] = sample
        return out  # type: ignore[return-value]

    def columns(self) -> Iterator[Columns]:
        """The rows in use, a block at a time."""
        for block in self._filled():
            yield block.rows(slice(0, block.fill))

    def column(self, name: str) -> np.ndarray:
        """One column over all samples (a copy)."""
        return np.concatenate([getattr(rows, name) for rows in self.columns()] or [_empty(name, 0)])

    def present(self, field: str) -> bool:
        """Whether some gaze sample has `field` (C, L, R or depth_m)."""
        at = GAZE_FIELDS[field]
        return any(np.isfinite(rows.values[rows.kind == GAZE, at]).any() for rows in self.columns())

    @property
    def gaze_count(self) -> int:
        """How many of the samples are gaze."""
        return sum(int((rows.kind == GAZE).sum()) for rows in self.columns())

    @property
    def nbytes(self) -> int:
        """The bytes the columns take."""
        return sum(sum(c.nbytes for c in block.columns) for block in self._blocks)
