"""Which peripheral pixels a frame of refresh rate modulation refreshes (smith2013 section 3.2.1).

The periphery is split into blocks of `block` pixels, grouped into cycle groups of group_w x group_h blocks, N
cells in all; a frame refreshes one cell of every group, the cells taken in a visit order that sets the
fragmentation style. smith2013 changes the group size and the order on the fly; the budget controller changes
group_w as often as every few frames. RefreshSchedule keeps each pixel's wait near N across those changes.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import numpy as np

if TYPE_CHECKING:
    from hmdrt.foveation.rrm import RrmParams

Order = Literal["horizontal", "serpentine", "scattered"]


def visit_order(group_w: int, group_h: int, order: Order) -> np.ndarray:
    """The cells of a cycle group (row-major indices) in the order they are refreshed.

    horizontal: row by row, left to right. serpentine: row by row, alternating direction. scattered:
    a stride through the cells coprime to N and near N / golden ratio, so consecutive refreshes are far apart.
    """
    n = group_w * group_h
    if order == "horizontal":
        return np.arange(n)
    if order == "serpentine":
        rows = [np.arange(r * group_w, (r + 1) * group_w) for r in range(group_h)]
        return np.concatenate([row if r % 2 == 0 else row[::-1] for r, row in enumerate(rows)])
    target = n / 1.618033988749895
    stride = min((s for s in range(1, n + 1) if math.gcd(s, n) == 1), key=lambda s: (abs(s - target), s))
    return (np.arange(n) * stride) % n


def refresh_phase(width: int, height: int, params: RrmParams) -> np.ndarray:
    """(height, width) int: each peripheral pixel's phase, the rank in the visit order (0 .. N-1) of its cell.
    While N holds, phase frame mod N is refreshed (RefreshSchedule, which Rrm follows cell by cell without
    building this map)."""
    rank = np.empty(params.cycle, dtype=np.int32)
    rank[visit_order(params.group_w, params.group_h, params.order)] = np.arange(params.cycle)
    bx = (np.arange(width) // params.block) % params.group_w
    by = np.arange(height) % params.group_h
    return rank[by[:, None] * params.group_w + bx[None, :]]


class RefreshSchedule:
    """The phase each frame of one eye refreshes: frame mod N while N holds, as smith2013 schedules it.

    When group_w changes, a new cell holds blocks last refreshed at different frames, and frame mod N would leave
    some of them waiting for the sum of the cycles they crossed (up to 66 frames in 60 s runs whose controller moved
    N between 12 and 20). So the schedule keeps the frame each block column of each of the group's rows was last
    refreshed, and takes the cell holding the stalest block first, ties to the nearest phase from frame mod N: every
    block is refreshed within the N frames after a change, and a frame still refreshes one cell. A new block, group_h
    or width starts afresh, as does a frame that goes back.
    """

    def __init__(self) -> None:
        self._layout: tuple[int, int, int] | None = None  # (width, block, group_h): what a block column is
        self._last = np.zeros((0, 0), np.int64)  # (group_h, block columns): the frame each was last refreshed
        self._cycle: tuple[int, str] | None = None  # (group_w, order): what the cells are
        self._order = np.zeros(0, np.int64)  # the cells by phase (visit_order)
        self._cells = np.zeros(0, np.int64)  # by phase: when the cell's stalest block was last refreshed
        self._frame, self._phase = -1, 0

    def cell(self, frame: int, width: int, params: RrmParams) -> tuple[int, int]:
        """The (row, column) in the cycle group of the cell `frame` refreshes (its phase's, phase())."""
        phase = self.phase(frame, width, params)
        return divmod(int(self._order[phase]), params.group_w)

    def phase(self, frame: int, width: int, params: RrmParams) -> int:
        """The phase (rank in the visit order) that `frame` refreshes; the same again for the same frame."""
        layout = (width, params.block, params.group_h)
        if (frame, layout, self._cycle) == (self._frame, self._layout, (params.group_w, params.order)):
            return self._phase
        if layout != self._layout or frame < self._frame:
            self._layout, self._cycle = layout, None
            self._last = np.full((params.group_h, -(-width // params.block)), frame - 1, np.int64)
        gw, n = params.group_w, params.cycle
        if self._cycle != (gw, params.order):
            self._cycle = (gw, params.order)
            self._order = visit_order(gw, params.group_h, params.order)
            # each cell's stalest block: the block columns padded to whole groups (frame - 1 stands for none)
            padded = np.pad(self._last, ((0, 0), (0, -self._last.shape[1] % gw)), constant_values=frame - 1)
            self._cells = padded.reshape(params.group_h, -1, gw).min(axis=1).reshape(-1)[self._order]
        stalest = np.flatnonzero(self._cells == self._cells.min())
        phase = int(stalest[np.argmin((stalest - frame) % n)])
        cell = int(self._order[phase])
        self._last[cell // gw, cell % gw :: gw] = frame
        self._cells[phase] = frame
        self._frame, self._phase = frame, phase
        return phase
