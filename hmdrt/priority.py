"""The live view's work yields the cores to the compositor's: a preview late for a person looking is no loss, a frame
late for the display is a deadline miss. The preview thread and the `hmdrt watch` process run at a nice value
BACKGROUND_NICE above the one they started with, so the kernel runs the render and display threads first when they
want a core (Linux keeps a nice value per thread: setpriority(2) on a thread id)."""

from __future__ import annotations

import logging
import os
import threading

log = logging.getLogger(__name__)

BACKGROUND_NICE = 10
MOST_NICE = 19


def yield_cores(whole_process: bool = False) -> None:
    """Raise the calling thread's nice value by BACKGROUND_NICE (threads it starts afterwards inherit it), or with
    whole_process every thread's of this process (/proc/self/task: those a library started at import too); where
    the platform has no per-thread priority, they keep theirs (logged at debug)."""
    try:
        tids = [int(t) for t in os.listdir("/proc/self/task")] if whole_process else [threading.get_native_id()]
    except OSError as exc:
        log.debug("thread priorities left as they are: %s", exc)
        return
    for tid in tids:
        try:
            nice = min(os.getpriority(os.PRIO_PROCESS, tid) + BACKGROUND_NICE, MOST_NICE)
            os.setpriority(os.PRIO_PROCESS, tid, nice)
        except (AttributeError, OSError) as exc:  # no per-thread priority here, or a thread that has ended
            log.debug("priority of thread %d left as it is: %s", tid, exc)
