"""The compositor's sinks (hmdrt.compositor.sinks): an output added with one line is started with the run, offered
every VSync's frame as the display showed it, finished when the run ends and closed with the compositor, and its
counters appear in the run report beside those of the sinks built in."""

from __future__ import annotations

from hmdrt.compositor.sinks import Shown, Sink
from hmdrt.testing import compositor, run_bounded, write_config

N = 6


class ToySink(Sink):
    """Counts what it is offered and what happens to it."""

    def __init__(self) -> None:
        self.calls: list[str] = []
        self.offered: list[Shown] = []

    def start(self) -> None:
        self.calls.append("start")

    def offer(self, shown: Shown) -> None:
        self.offered.append(shown)

    def finish(self) -> None:
        self.calls.append("finish")

    def close(self) -> None:
        self.calls.append("close")

    def report(self) -> dict:
        return {"toy_frames": len(self.offered)}


def test_a_sink_added_with_one_line_gets_every_shown_frame_and_reports_into_the_run_report(tmp_path, context):
    toy = ToySink()
    with compositor(write_config(tmp_path / "run.toml", eyes="left"), context, frames=N, virtual_time=True) as comp:
        comp.sinks.append(toy)
        report, _ = run_bounded(comp)
        assert toy.calls == ["start", "finish"]
    assert toy.calls == ["start", "finish", "close"]
    assert report["toy_frames"] == N and report["vsyncs"] == N
    assert [s.record for s in toy.offered] == comp.records  # the same records, in VSync order
    for shown, (_, images) in zip(toy.offered, comp.shown, strict=True):
        assert shown.images is images and shown.frame.timing.frame_id == shown.record.frame_id
        assert shown.fields == shown.record.to_dict()


def test_the_built_in_sinks_report_what_they_could_not_write_under_their_own_keys(tmp_path, context):
    path = write_config(tmp_path / "run.toml", eyes="left", output={"frames_log": "frames.jsonl"})
    with compositor(path, context, frames=2, virtual_time=True) as comp:
        report, _ = run_bounded(comp)
    assert report["frames_not_written"] == report["frames_log_not_written"] == 0 and "lsl_not_pushed" not in report
