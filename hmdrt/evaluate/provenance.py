"""When, from which commit and on which machine eval rows were measured: each of the papers' tables states
its date, commit and machine. The process that renders a group stamps its rows (a Dask worker its own machine and
checkout), and the papers' tables state what their rows say under each heading."""

from __future__ import annotations

import datetime
import functools
import os
import platform
import re
import subprocess
from pathlib import Path

GIT_TIMEOUT_S = 10.0
MAX_TEXT = 200  # characters of a machine's description (validate.py holds rows to it)
MAX_LISTED = 3  # distinct commits or machines a table's line names
COMMIT = re.compile(r"[0-9a-f]{4,40}(-dirty)?|unknown")
DATE = re.compile(r"[0-9]{4}-[0-9]{2}-[0-9]{2}")


def _git(root: Path, *args: str) -> subprocess.CompletedProcess:
    """A read-only git command in `root` (--no-optional-locks: it never rewrites the index)."""
    return subprocess.run(
        ["git", "--no-optional-locks", "-C", str(root), *args], capture_output=True, text=True, timeout=GIT_TIMEOUT_S
    )


@functools.cache
def commit() -> str:
    """The short hash of the git checkout hmdrt runs from, "-dirty" added where tracked files differ from it;
    "unknown" where hmdrt is not run from its own checkout (an installed wheel, even inside another repository)
    or git is missing."""
    root = Path(__file__).resolve().parents[2]
    try:
        found = _git(root, "rev-parse", "--show-toplevel", "--short", "HEAD")
        lines = found.stdout.split()
        if found.returncode != 0 or len(lines) != 2 or Path(lines[0]).resolve() != root:
            return "unknown"
        dirty = _git(root, "diff", "--quiet", "HEAD", "--").returncode == 1
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    text = lines[1] + ("-dirty" if dirty else "")
    return text if COMMIT.fullmatch(text) else "unknown"


@functools.cache
def machine() -> str:
    """The CPU model (/proc/cpuinfo's model name, else platform.processor(), else the architecture), the CPUs this
    process may use and the system, e.g. "Intel(R) Xeon(R) Processor, 2 CPUs, Linux x86_64"."""
    model = ""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as f:
            model = next((line.split(":", 1)[1] for line in f if line.startswith("model name")), "")
    except OSError:
        pass
    model = " ".join(model.split()) or platform.processor() or platform.machine() or "unknown CPU"
    cpus = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 0
    text = f"{model}, {cpus} CPUs, {platform.system()} {platform.machine()}"
    return "".join(c if c.isprintable() else "?" for c in text)[:MAX_TEXT]


def stamp() -> dict[str, str]:
    """The columns a group's rows carry: today's date (UTC), the commit and the machine."""
    return {"date": datetime.datetime.now(datetime.UTC).date().isoformat(), "commit": commit(), "machine": machine()}


def line(rows: list[dict]) -> str:
    """The rows' dates, commits and machines in one sentence (a range of dates; a few commits and machines, then
    how many more)."""
    if not rows:
        return "No rows."
    dates = sorted({r["date"] for r in rows})
    when = dates[0] if len(dates) == 1 else f"{dates[0]} to {dates[-1]}"
    commits, machines = _distinct([r["commit"] for r in rows]), _distinct([r["machine"] for r in rows])
    return (
        f"Measured {when} (UTC) at commit{'s' if len(commits) > 1 else ''} {_listed(commits, ', ')} "
        f"on {'machines ' if len(machines) > 1 else ''}{_listed(machines, '; ')}."
    )


def _distinct(values: list[str]) -> list[str]:
    return list(dict.fromkeys(values))


def _listed(distinct: list[str], sep: str) -> str:
    more = len(distinct) - MAX_LISTED
    return sep.join(distinct[:MAX_LISTED]) + (f"{sep}and {more} more" if more > 0 else "")
