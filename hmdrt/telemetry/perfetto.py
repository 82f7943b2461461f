"""A frames log as a timeline: `hmdrt export perfetto FRAMES.jsonl --out run.json` writes the Chrome trace-event
JSON that Perfetto (ui.perfetto.dev) and chrome://tracing open.

One process, four tracks: `render` has a span per rendered frame from its wake-up to its hand-over, with the
method's stages nested in it (a frame's stage times are sums, so each is laid out once, in the order it ended,
from the render start); `display` has each VSync as an instant and the latch (a new or late frame) or timewarp
(a repeat) as a span from it, and marks each deadline miss; `gaze` and `pose` have each sample a frame used as
an instant at its host capture time. In virtual time the clock does not move during a frame's work, so a frame's
span lasts the work's wall time instead, at most the period, its stages shrunk in proportion to fit
(`stages_scaled`). A span never outlasts its parent: a child that would is cut and says so (`cut`: true; its
measured ms are in its args). Times are microseconds of the run's clock.
"""

from __future__ import annotations

import json
from pathlib import Path

import msgspec

from hmdrt.files.atomic import write_atomic
from hmdrt.telemetry.frames_log import FramesLogReading
from hmdrt.telemetry.report import FrameRecord, SampleUse

PID = 1
RENDER, DISPLAY, GAZE, POSE = 1, 2, 3, 4
TRACKS = {RENDER: "render", DISPLAY: "display", GAZE: "gaze samples", POSE: "pose samples"}


def _us(ns: float) -> float:
    return round(ns / 1000.0, 3)


def _span(name: str, tid: int, start_ns: int, dur_ns: int, cat: str, **args) -> dict:
    return {
        "name": name,
        "cat": cat,
        "ph": "X",
        "ts": _us(start_ns),
        "dur": _us(dur_ns),
        "pid": PID,
        "tid": tid,
        "args": args,
    }


def _instant(name: str, tid: int, t_ns: int, cat: str, scope: str = "t", **args) -> dict:
    return {"name": name, "cat": cat, "ph": "i", "s": scope, "ts": _us(t_ns), "pid": PID, "tid": tid, "args": args}


def _stage_tree(stages_ms: dict[str, float]) -> dict[str, list[str]]:
    """Children per stage key ("" for the top), in the order the stages ended; a key whose parent is missing
    hangs from its nearest recorded ancestor."""
    tree: dict[str, list[str]] = {"": []}
    for key in stages_ms:
        parts = key.split("/")
        parent = next(
            ("/".join(parts[:i]) for i in range(len(parts) - 1, 0, -1) if "/".join(parts[:i]) in stages_ms), ""
        )
        tree.setdefault(parent, []).append(key)
    return tree


def _stages(
    record: FrameRecord, parent: str, start_ns: int, end_ns: int, tree: dict[str, list[str]], scale: float
) -> list[dict]:
    """The stages under `parent`, one after another from start_ns, each `scale` times as long as measured and cut
    at end_ns; a stage left with no time is not drawn."""
    events, at = [], start_ns
    for key in tree.get(parent, []):
        ms = record.stages_ms[key]
        want = int(ms * 1e6 * scale)  # rounded down: stages that fit together still fit
        dur = max(0, min(want, end_ns - at))
        if dur:
            events.append(_span(key.rsplit("/", 1)[-1], RENDER, at, dur, "stage", stage=key, ms=ms, cut=dur < want))
            events += _stages(record, key, at, at + dur, tree, scale)
        at += dur
    return events


def _render(record: FrameRecord, virtual: bool, period_ns: int) -> list[dict]:
    """A rendered frame's span on the render track, its stages nested in it."""
    start = record.actual_wake_ns
    if virtual:  # the clock stood still: the wall time of the work, at most a period
        dur = min(round(record.frame_ms * 1e6), period_ns)
    else:
        dur = max(0, record.render_end_ns - start)
    late = " (late)" if record.missed else ""
    args = {
        "frame_id": record.frame_id,
        "missed": record.missed,
        "frame_ms": record.frame_ms,
        "render_ms": record.render_ms,
        "rays": record.rays,
        "method": record.method,
        "params": record.params,
        "level": record.level,
        "predicted_wake_ns": record.predicted_wake_ns,
        "actual_wake_ns": record.actual_wake_ns,
        "render_start_ns": record.render_start_ns,
        "render_end_ns": record.render_end_ns,
        "predicted_present_ns": record.predicted_present_ns,
        "predicted_display_ns": record.predicted_display_ns,
        "margin_ns": record.margin_ns,
    }
    frame = _span(f"frame {record.frame_id}{late}", RENDER, start, dur, "frame", **args)
    if record.missed:
        frame["cname"] = "terrible"  # chrome://tracing's red
    stages_start = min(max(record.render_start_ns, start), start + dur)
    tree = _stage_tree(record.stages_ms)
    measured_ns = sum(record.stages_ms[key] for key in tree[""]) * 1e6
    scale = 1.0
    if virtual and measured_ns > start + dur - stages_start:  # shown in proportion within the period
        scale = frame["args"]["stages_scaled"] = (start + dur - stages_start) / measured_ns
    return [frame, *_stages(record, "", stages_start, start + dur, tree, scale)]


def _display(record: FrameRecord, period_ns: int) -> list[dict]:
    """A VSync on the display track: its instant, the latch or timewarp span, and a miss when it was one."""
    t = record.actual_present_ns
    events = [_instant("vsync", DISPLAY, t, "vsync", vsync=record.vsync, shown=record.shown, frame_id=record.frame_id)]
    if record.shown == "repeat":
        name = "repeat (warp skipped)" if record.warp_skipped else "timewarp"
    else:
        name = f"latch frame {record.frame_id}" + (" (late)" if record.missed else "")
    work = round(record.present_ms * 1e6)
    events.append(
        _span(
            name,
            DISPLAY,
            t,
            min(work, period_ns),
            "display",
            shown=record.shown,
            present_ms=record.present_ms,
            cut=work > period_ns,
        )
    )
    if record.missed:
        late_ms = (t - record.predicted_present_ns) / 1e6
        events.append(_instant(f"miss: frame {record.frame_id}", DISPLAY, t, "miss", "p", late_ms=late_ms))
    return events


def _samples(records: list[FrameRecord]) -> list[dict]:
    """Each gaze and pose sample the frames used, once, at its capture time on the host clock."""
    events, seen = [], set()
    for record in records:
        uses: list[tuple[int, str, SampleUse | None]] = [
            (GAZE, "gaze", record.gaze),
            (POSE, "pose", record.pose),
            (POSE, "pose", record.warp_pose),
        ]
        for tid, kind, use in uses:
            if use is None or (tid, use.device, use.seq) in seen:
                continue
            seen.add((tid, use.device, use.seq))
            events.append(
                _instant(
                    f"{kind} {use.device} #{use.seq}",
                    tid,
                    use.t_host,
                    kind,
                    device=use.device,
                    seq=use.seq,
                    held=use.held,
                    predicted_ms=use.predicted_ns / 1e6,
                    first_vsync=record.vsync,
                )
            )
    return events


def trace_events(reading: FramesLogReading) -> dict:
    """The trace-event JSON object of a frames log: metadata, then every event by time (a parent before its
    children)."""
    header = reading.header
    events: list[dict] = []
    for record in reading.records:
        if record.shown != "repeat":
            events += _render(record, header.virtual_time, header.period_ns)
        events += _display(record, header.period_ns)
    events += _samples(reading.records)
    events.sort(key=lambda e: (e["tid"], e["ts"], -e.get("dur", 0.0)))
    clock = ", virtual time" if header.virtual_time else ""
    name = f"hmdrt {header.method} at {header.profile} ({header.vsync_hz:g} Hz{clock})"
    meta = [{"name": "process_name", "ph": "M", "pid": PID, "tid": 0, "args": {"name": name}}]
    for tid, track in TRACKS.items():
        meta.append({"name": "thread_name", "ph": "M", "pid": PID, "tid": tid, "args": {"name": track}})
        meta.append({"name": "thread_sort_index", "ph": "M", "pid": PID, "tid": tid, "args": {"sort_index": tid}})
    return {
        "traceEvents": meta + events,
        "displayTimeUnit": "ms",
        "otherData": {
            "source": str(reading.path),
            "frames": str(len(reading.records)),
            **{k: str(v) for k, v in msgspec.structs.asdict(header).items()},  # chrome://tracing shows strings
        },
    }


def write_trace(reading: FramesLogReading, out: str | Path) -> int:
    """Write the trace of a frames log to `out` (whole or not at all); returns the number of events."""
    trace = trace_events(reading)
    write_atomic(out, json.dumps(trace, separators=(",", ":")).encode())
    return len(trace["traceEvents"])
