"""How much slower the compositor's per-frame Python runs when it last ran a frame ago (overhead).

    python bench/cold_start.py [--repeats 100]

The render thread runs its sampling and prediction once per frame, 11-33 ms after it last did. This times a
frame's gaze and pose lookup (the sample store at 250 Hz, predicting 30 ms ahead), a numpy array from a
3-tuple and an empty call, each right after the thread spun in a Python loop for a gap of 0.1-30 ms and again
at once (warm), and prints the medians and their ratio, measured in one run. The thread never sleeps and the
loop touches little memory, so what makes the first call slower is time passing on the machine (other work
on the same cores and caches), not the compositor's own work in between.
"""

from __future__ import annotations

import argparse
import statistics
import time
from collections.abc import Callable

import numpy as np

from hmdrt.bus.messages import Gaze, Pose
from hmdrt.compositor.samples import SampleStore
from hmdrt.spatial import gaze_direction, quat_from_yaw_pitch

GAPS_MS = (0.1, 1.0, 3.0, 10.0, 30.0)
RATE_NS = 4_000_000  # 250 Hz


def filled_store(seconds: float = 1.0) -> tuple[SampleStore, int]:
    """A store with a second of a turning head and a drifting gaze, as the replay driver sends them."""
    store = SampleStore()
    for i in range(int(seconds * 1e9 / RATE_NS)):
        t = i * RATE_NS
        store.add("trk", Gaze(seq=i, t_host=t, C=tuple(gaze_direction(5 * np.sin(i / 25), 0.0))), t)
        orientation = tuple(quat_from_yaw_pitch(0.2 * i, 0.0))
        store.add("trk", Pose(seq=i, t_host=t, position=(0.0, 0.0, 0.0), orientation=orientation), t)
    return store, t


def spin(gap_s: float) -> None:
    end = time.perf_counter() + gap_s
    while time.perf_counter() < end:
        pass


def first_and_again(work: Callable[[], object], gap_s: float, repeats: int) -> tuple[float, float]:
    """Median microseconds of work right after a gap of spinning, and of the same work at once after it."""
    cold, warm = [], []
    for _ in range(repeats):
        spin(gap_s)
        t0 = time.perf_counter_ns()
        work()
        t1 = time.perf_counter_ns()
        work()
        t2 = time.perf_counter_ns()
        cold.append(t1 - t0)
        warm.append(t2 - t1)
    return statistics.median(cold) / 1e3, statistics.median(warm) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=100, help="timings per gap and call (default 100)")
    args = parser.parse_args()
    store, now = filled_store()
    ahead = now + 30_000_000
    works = {
        "gaze + pose lookup": lambda: (store.gaze_at(ahead, now), store.pose_at(ahead, now)),
        "np.array(3-tuple)": lambda: np.array((0.0, 0.0, -1.0)),
        "empty call": lambda: None,
    }
    print(f"median us of the first call after a gap / at once after it, {args.repeats} each")
    print(f"{'gap ms':>8} " + " ".join(f"{name:>28}" for name in works))
    for gap_ms in GAPS_MS:
        cells = []
        for work in works.values():
            cold, warm = first_and_again(work, gap_ms / 1e3, args.repeats)
            cells.append(f"{cold:7.1f} / {warm:5.1f} = {cold / warm:4.1f}x")
        print(f"{gap_ms:8g} " + " ".join(f"{c:>28}" for c in cells))


if __name__ == "__main__":
    main()
