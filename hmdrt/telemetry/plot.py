"""Plots of a run: `hmdrt report plot FRAMES.jsonl|REPORT.json --out DIR` writes PNGs (matplotlib on Agg, in the
eval's style: hmdrt.files.figures).

From a frames log (`[output] frames_log`; a `.jsonl` file): `timeline.png`, each rendered frame's work against
the period and the deadline (the period less the pacing margin), late frames and VSyncs without a new frame
marked, the controller's level below; `latency.png`, histograms of gaze- and pose-to-photon latency. A run
report keeps percentiles only, so from one: `summary.png`, the frame time and latency percentiles against the
period and the controller's trajectory, with a note that the rest needs a frames log.
"""

from __future__ import annotations

import re
from pathlib import Path
from typing import Annotated

import msgspec
import numpy as np

from hmdrt.errors import HmdrtError
from hmdrt.files.atomic import check_writable
from hmdrt.files.figures import plt, save
from hmdrt.telemetry.frames_log import MAX_MS, FramesLogReading, read_frames_log

MAX_REPORT_BYTES = 64 * 1024**2
NEWLINE = b"\n"
NEEDS_LOG = (
    "a run report keeps percentiles only: per-frame times, misses, repeats and latency histograms need a frames "
    "log ([output] frames_log)"
)
OptionalMs = Annotated[float, msgspec.Meta(ge=0.0, le=MAX_MS)] | None


class _Percentiles(msgspec.Struct, frozen=True):
    p50: OptionalMs = None
    p95: OptionalMs = None
    p99: OptionalMs = None
    max: OptionalMs = None


class _Latency(msgspec.Struct, frozen=True):
    gaze_to_photon: _Percentiles = _Percentiles()
    pose_to_photon: _Percentiles = _Percentiles()


class _Change(msgspec.Struct, frozen=True):
    level: Annotated[float, msgspec.Meta(ge=0.0, le=1.0)]
    frame: Annotated[int, msgspec.Meta(ge=0)] | None = None  # None: the start


class _Controller(msgspec.Struct, frozen=True):
    kind: str = ""
    trajectory: list[_Change] = []


class _Pacing(msgspec.Struct, frozen=True):
    margin_ns: Annotated[int, msgspec.Meta(ge=0)] = 0


class ReportSummary(msgspec.Struct, frozen=True):
    """The parts of a run report (hmdrt.telemetry.report) these plots use."""

    vsync_hz: Annotated[float, msgspec.Meta(gt=0.0, le=1000.0)]
    vsyncs: int = 0
    presented: int = 0
    re_presented: int = 0
    deadline_misses: int = 0
    method_spec: str = ""
    profile: str = ""
    virtual_time: bool = False
    frame_ms: _Percentiles = _Percentiles()
    latency_ms: _Latency = _Latency()
    pacing: _Pacing = _Pacing()
    controller: _Controller | None = None


def read_report(path: str | Path) -> ReportSummary:
    """A run report's summary; HmdrtError naming the file (and line, for bad JSON) when it is not one."""
    path = Path(path)
    try:
        if path.stat().st_size > MAX_REPORT_BYTES:
            raise HmdrtError(f"run report {path} is larger than {MAX_REPORT_BYTES} bytes")
        data = path.read_bytes()
    except (OSError, ValueError) as exc:
        raise HmdrtError(f"cannot read run report {path}: {getattr(exc, 'strerror', None) or exc}") from None
    try:
        return msgspec.json.decode(data, type=ReportSummary)
    except (msgspec.DecodeError, RecursionError) as exc:
        reason = "nested too deeply" if isinstance(exc, RecursionError) else str(exc)
        at = re.search(r"\(byte (\d+)\)", reason)  # msgspec names the byte of a JSON syntax error
        where = f"{path}:{data.count(NEWLINE, 0, int(at.group(1))) + 1}" if at else str(path)
        raise HmdrtError(f"{where}: not a run report: {reason}") from None


def plot_run(path: str | Path, out: str | Path) -> tuple[list[Path], str | None]:
    """Plot a frames log (.jsonl) or a run report (any other file) into the folder `out`: the PNGs written, and a
    note of what the input could not show (None for a frames log)."""
    path, out = Path(path), Path(out)
    if path.suffix == ".jsonl":
        reading = read_frames_log(path)
        check_writable(out)
        return [timeline(reading, out / "timeline.png"), latency(reading, out / "latency.png")], None
    report = read_report(path)
    check_writable(out)
    return [summary(report, out / "summary.png")], NEEDS_LOG


def _budget_lines(ax, period_ms: float, margin_ms: float) -> None:
    ax.axhline(period_ms, color="k", lw=1, label=f"period {period_ms:.1f} ms")
    ax.axhline(period_ms - margin_ms, color="C3", ls="--", lw=1, label=f"deadline: period less {margin_ms:g} ms margin")


def timeline(reading: FramesLogReading, path: Path) -> Path:
    """Frame time per VSync against the period and deadline, misses and repeats marked; the level below."""
    header, records = reading.header, reading.records
    rendered = [r for r in records if r.shown != "repeat"]
    late = [r for r in rendered if r.missed]
    repeats = [r.vsync for r in records if r.shown == "repeat"]
    fig, (ax, ax_level) = plt.subplots(2, 1, sharex=True, figsize=(10, 6), gridspec_kw={"height_ratios": [3, 1]})
    x = [r.vsync for r in rendered]
    ax.plot(x, [r.frame_ms for r in rendered], ".-", ms=3, lw=0.8, label="frame: wake-up to hand-over")
    ax.plot(x, [r.render_ms for r in rendered], lw=0.8, alpha=0.6, label="of it the method's render")
    _budget_lines(ax, header.period_ns / 1e6, header.margin_ns / 1e6)
    if late:
        ax.plot([r.vsync for r in late], [r.frame_ms for r in late], "x", color="C3", ms=7, label="late (a miss)")
    if repeats:
        ax.plot(
            repeats,
            [0.02] * len(repeats),
            "|",
            color="0.4",
            ms=10,
            transform=ax.get_xaxis_transform(),
            label="repeat (no new frame)",
        )
    ax.set_ylim(bottom=0)
    ax.set_ylabel("ms (wall clock)")
    clock = "; virtual time: the work's wall time" if header.virtual_time else ""
    ax.set_title(
        f"{header.method} at {header.profile}, {header.vsync_hz:g} Hz: {len(records)} VSyncs, {len(rendered)} "
        f"frames ({len(late)} late), {len(repeats)} repeats{clock}",
        fontsize=9,
    )
    ax.legend(fontsize=7, loc="upper right")
    ax.grid(True, alpha=0.3)
    levels = [(r.vsync, r.level) for r in records if r.level is not None]
    if levels:
        ax_level.step(*zip(*levels, strict=True), where="post", color="C2")
    else:
        ax_level.text(
            0.5, 0.5, "no controller level in this log", ha="center", va="center", transform=ax_level.transAxes
        )
    ax_level.set_ylim(-0.05, 1.05)
    ax_level.set_ylabel(f"level\n({header.controller})")
    ax_level.set_xlabel("VSync")
    ax_level.grid(True, alpha=0.3)
    return save(fig, path)


def _latencies(reading: FramesLogReading) -> dict[str, list[float]]:
    """Gaze- and pose-to-photon per VSync, leaving out samples held through a blink or lost tracking."""
    out: dict[str, list[float]] = {"gaze-to-photon": [], "pose-to-photon": []}
    for r in reading.records:
        pose = r.warp_pose or r.pose
        if r.gaze is not None and not r.gaze.held:
            out["gaze-to-photon"].append(r.gaze_to_photon_ms())
        if pose is not None and not pose.held:
            out["pose-to-photon"].append(r.pose_to_photon_ms())
    return out


def latency(reading: FramesLogReading, path: Path) -> Path:
    """Histograms of gaze- and pose-to-photon latency with their p50 and p99 and the period's multiples."""
    period_ms = reading.header.period_ns / 1e6
    fig, axes = plt.subplots(1, 2, figsize=(10, 4))
    for ax, (name, values) in zip(axes, _latencies(reading).items(), strict=True):
        ax.set_title(f"{name} ({len(values)} VSyncs)", fontsize=9)
        ax.set_xlabel("ms from capture to the VSync shown")
        if not values:
            ax.text(0.5, 0.5, "no samples", ha="center", va="center", transform=ax.transAxes)
            continue
        ax.hist(values, bins=min(50, max(5, len(values) // 4)), color="C0", alpha=0.8)
        for q, style in ((50, "-"), (99, "--")):
            at = float(np.percentile(values, q, method="inverted_cdf"))
            ax.axvline(at, color="C3", ls=style, lw=1, label=f"p{q} {at:.1f} ms")
        for k in range(1, int(max(values) // period_ms) + 1):
            ax.axvline(k * period_ms, color="0.6", lw=0.8, ls=":", label="periods" if k == 1 else None)
        ax.set_ylabel("VSyncs")
        ax.legend(fontsize=7)
    return save(fig, path)


def summary(report: ReportSummary, path: Path) -> Path:
    """What a run report can show: frame time and latency percentiles, and the controller's trajectory."""
    keys = ("p50", "p95", "p99", "max")
    period_ms = 1e3 / report.vsync_hz
    controller = report.controller is not None and report.controller.kind != "none" and report.controller.trajectory
    fig, axes = plt.subplots(1, 3 if controller else 2, figsize=(12 if controller else 9, 4.2))
    ax = axes[0]
    ax.bar(keys, [_value(getattr(report.frame_ms, k)) for k in keys], color="C0")
    _budget_lines(ax, period_ms, report.pacing.margin_ns / 1e6)
    ax.set_ylabel("frame ms (wall clock)")
    ax.set_title(f"frame time: {report.presented} frames, {report.deadline_misses} misses", fontsize=9)
    ax.legend(fontsize=7)
    ax = axes[1]
    at = np.arange(len(keys))
    for i, (name, values) in enumerate(
        (("gaze-to-photon", report.latency_ms.gaze_to_photon), ("pose-to-photon", report.latency_ms.pose_to_photon))
    ):
        ax.bar(at + (i - 0.5) * 0.4, [_value(getattr(values, k)) for k in keys], 0.4, label=name)
    ax.axhline(period_ms, color="k", lw=1, label=f"period {period_ms:.1f} ms")
    ax.set_xticks(at, keys)
    ax.set_ylabel("ms")
    ax.set_title(f"latency: {report.vsyncs} VSyncs, {report.re_presented} repeats", fontsize=9)
    ax.legend(fontsize=7)
    if controller:
        changes = report.controller.trajectory
        ax = axes[2]
        frames, levels = [c.frame or 0 for c in changes], [c.level for c in changes]
        frames.append(max(report.presented, frames[-1]))  # the last level holds to the end of the run
        levels.append(levels[-1])
        ax.step(frames, levels, where="post", color="C2")
        ax.set_ylim(-0.05, 1.05)
        ax.set_xlabel("frame")
        ax.set_ylabel("level")
        ax.set_title(f"{report.controller.kind}: level changes (the start and the newest 100)", fontsize=9)
    fig.suptitle(f"{report.method_spec} at {report.profile}, {report.vsync_hz:g} Hz\n({NEEDS_LOG})", fontsize=8)
    return save(fig, path)


def _value(ms: float | None) -> float:
    return np.nan if ms is None else ms
