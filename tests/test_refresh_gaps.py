"""bench/refresh_gaps.py: how long rrm's peripheral pixels wait between refreshes, from a run's frames log."""

import re
import subprocess
import sys
from pathlib import Path

from hmdrt.testing import run_bounded

BENCH = Path(__file__).resolve().parent.parent / "bench" / "refresh_gaps.py"


def waits(log: Path) -> tuple[int, tuple[int, int, int]]:
    run = subprocess.run([sys.executable, str(BENCH), str(log)], capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    found = re.search(r"N changed (\d+) times; .* p50 (\d+), p99 (\d+), max (\d+) frames; 0 pixels", run.stdout)
    assert found, run.stdout
    changed, *spread = map(int, found.groups())
    return changed, tuple(spread)


def test_a_held_cycle_refreshes_every_peripheral_pixel_once_a_cycle(hmdrt_config, hmdrt_compositor, tmp_path):
    log = tmp_path / "frames.jsonl"
    rrm = {"name": "rrm", "options": {"group_w": 2, "group_h": 3}}
    config = hmdrt_config(method=rrm, output={"frames_log": str(log)})
    run_bounded(hmdrt_compositor(config, frames=30, virtual_time=True))
    assert waits(log) == (0, (6, 6, 6))  # N = 2 x 3


def test_a_moved_cycle_makes_some_pixels_wait_longer(hmdrt_config, hmdrt_compositor, tmp_path):
    """A controller over a renderer slower than the period moves group_w from 2 toward MAX_CYCLE // 3 = 6."""
    log = tmp_path / "frames.jsonl"
    config = hmdrt_config(
        method={"name": "rrm", "options": {"group_w": 2, "group_h": 3}},
        output={"frames_log": str(log)},
        pacing={"render_delay_ms": 40},
        controller={"kind": "hold-budget", "foresight": False},
    )
    run_bounded(hmdrt_compositor(config, frames=60))
    changed, (p50, p99, longest) = waits(log)
    assert changed >= 1 and longest > 6


def test_a_log_of_another_method_or_a_bad_file_is_a_clear_error(tmp_path):
    bad = tmp_path / "bad.jsonl"
    bad.write_text("{not json\n")
    run = subprocess.run([sys.executable, str(BENCH), str(bad)], capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and "not a frames log header" in run.stderr and "Traceback" not in run.stderr
