"""Writes configs/eval/traces/kim21_*.jsonl: kim2021 section 4.4's slow cases (Figure 6), 0.6 s at 250 Hz.

python bench/kim21_traces.py
"""

from __future__ import annotations

from pathlib import Path

from hmdrt.replay.trace import Gaze, Pose, write_trace
from hmdrt.spatial import gaze_direction, quat_from_yaw_pitch

RATE, SECONDS = 250, 0.6
N = int(RATE * SECONDS) + 1
STEP_NS = 1_000_000_000 // RATE
FOLDER = Path(__file__).resolve().parents[1] / "configs" / "eval" / "traces"


def _rounded(values) -> list[float]:
    return [round(float(x), 7) + 0.0 for x in values]


def pursuit() -> list:
    """The gaze pursues a target at 4 deg/s, from 1.2 deg left to 1.2 deg right; the head still."""
    out: list = [Pose(seq=0, t_host=0, position=[0.0, 0.0, 0.0], orientation=[1.0, 0.0, 0.0, 0.0])]
    for k in range(N):
        out.append(Gaze(seq=k, t_host=k * STEP_NS, C=_rounded(gaze_direction(-1.2 + 4.0 * k / RATE, 0.0))))
    return out


def head() -> list:
    """The head turns right at 2 deg/s while the eyes stay on the point ahead where they started (the
    vestibulo-ocular reflex turns the gaze left in the head as fast)."""
    out: list = []
    for k in range(N):
        yaw = 2.0 * k / RATE
        orientation = _rounded(quat_from_yaw_pitch(yaw, 0.0))
        out.append(Pose(seq=k, t_host=k * STEP_NS, position=[0.0, 0.0, 0.0], orientation=orientation))
        out.append(Gaze(seq=k, t_host=k * STEP_NS, C=_rounded(gaze_direction(-yaw, 0.0))))
    return out


if __name__ == "__main__":
    write_trace(
        str(FOLDER / "kim21_slow_pursuit.jsonl"),
        pursuit(),
        "synthetic: gaze pursuit 4 deg/s, head still (kim2021 Figure 6)",
    )
    write_trace(
        str(FOLDER / "kim21_slow_head.jsonl"),
        head(),
        "synthetic: head yaw 2 deg/s, eyes on a point in the scene (kim2021 section 4.4)",
    )
